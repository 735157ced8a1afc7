"""Config: YAML groups, overrides, errors with suggestions, the CLI's handling of them, the reference page."""

import re
from pathlib import Path

import pytest
import yaml

from rgs_warp.app.cli import help_text, main
from rgs_warp.config import (
    CONSTRAINTS,
    Config,
    ConfigError,
    config_from_dict,
    group_options,
    leaves,
    load_config,
    load_saved_config,
    parse_yaml,
    save_config,
)


def test_defaults_and_overrides():
    cfg = load_config()
    assert cfg.dataset.type == "synthetic" and cfg.dataset.name == "room0" and cfg.method == "rgs"
    cfg = load_config(
        [
            "dataset=replica/office0",
            "tracking.iters=40",
            "device=cpu",
            "render.background=[1,1,1]",
            "dataset.max_frames=10",
            "mapping.lr_color=1e-3",
        ]
    )
    assert (cfg.dataset.type, cfg.dataset.path, cfg.tracking.iters, cfg.device) == (
        "replica",
        "Replica/office0",
        40,
        "cpu",
    )
    assert cfg.render.background == (1.0, 1.0, 1.0) and cfg.dataset.max_frames == 10
    assert cfg.mapping.lr_color == pytest.approx(1e-3)
    assert cfg.tracking.lr == Config().tracking.lr  # untouched keys keep their defaults


def test_baseline_method_has_the_table_2_values():
    rgs, cfg = load_config(), load_config(["method=baseline", "mapping.iters_per_frame=40"])
    assert cfg.method == "baseline" and rgs.method == "rgs"
    assert cfg.render.sh_degree == 3  # Table 2
    d = cfg.densify
    assert (d.grad_threshold, d.start, d.stop, d.interval) == (2e-4, 500, 15000, 100)
    assert d.opacity_reset_interval == 3000  # Table 1
    assert d.opacity_reset_value > cfg.mapping.opacity_cull == 0.05  # a reset must not wipe the map
    m = cfg.mapping
    assert (m.lr_color, m.lr_opacity, m.lr_scale, m.lr_rotation) == (2.5e-3, 2.5e-2, 5e-3, 1e-3)
    assert m.lr_position == pytest.approx(1.6e-4 * d.scene_extent_m)  # 3DGS's spatial_lr_scale
    assert m.lr_final_factor == pytest.approx(1.6e-6 / 1.6e-4)  # the decay to 1.6e-6
    assert m.iters_per_frame == 40  # overrides apply after the method
    # everything else is rgs's: tracking, keyframes, window, loss, initialization
    for section in ("tracking", "keyframes", "seeding", "matching"):
        assert getattr(cfg, section) == getattr(rgs, section), section
    same = ("window", "init_iters", "init_window", "lambda_dssim", "depth_weight", "robust_scale", "opacity_cull")
    assert all(getattr(m, k) == getattr(rgs.mapping, k) for k in same)
    with pytest.raises(ConfigError, match="unknown method 'baselin'. Did you mean 'baseline'"):
        load_config(["method=baselin"])
    with pytest.raises(ConfigError, match="method: 'x' is not one of rgs, baseline"):
        config_from_dict({"method": "x"})  # e.g. a saved config.yaml


def test_group_option_replaces_section_and_keys_apply_after():
    cfg = load_config(["dataset.stride=3", "dataset=7scenes/redkitchen"])
    assert cfg.dataset.type == "7scenes" and cfg.dataset.stride == 3


@pytest.mark.parametrize(
    "args, message",
    [
        (
            ["tracking.iter=3"],
            r"unknown key 'tracking.iter'. Did you mean 'tracking.iters'\?.*Valid keys under tracking",
        ),
        (["dataset=replica/ofice0"], r"unknown dataset 'replica/ofice0'. Did you mean 'replica/office0'\?"),
        (["tracking.iters=abc"], r"tracking.iters: expected an integer"),
        (["mode=mnoo"], r"mode: 'mnoo' is not one of rgbd, mono. Did you mean 'mono'"),
        (["trackingiters"], r"not of the form key=value"),
        (["render.background=[1,1]"], r"expected 3 values"),
        (["mapping.min_iters=20"], r"mapping.min_iters \(20\) applies to asynchronous mapping only"),
        (["dataset.playback_fps=-30"], r"dataset.playback_fps: -30.0 is out of range"),
    ],
)
def test_errors(args, message):
    with pytest.raises(ConfigError, match=message):
        load_config(args)


def test_groups_and_help():
    assert {"replica/office0", "tum/fr1_desk", "synthetic/room0", "7scenes/redkitchen"} <= set(group_options("dataset"))
    text = help_text()
    assert "dataset: " in text and "tracking.iters = 10" in text and "mapping.lambda_dssim = 0.2" in text


def test_data_root(monkeypatch, tmp_path):
    monkeypatch.setenv("RGS_DATA", str(tmp_path))
    assert load_config(["dataset=replica/office0"]).dataset_path() == tmp_path / "Replica" / "office0"
    cfg = load_config(["dataset=replica/office0", "data_root=/x", "dataset.path=/abs/office0"])
    assert str(cfg.dataset_path()) == "/abs/office0"


def test_off_on_yes_no_stay_strings():
    # YAML 1.1 reads off / on / yes / no as booleans; the configs read YAML 1.2 booleans only
    assert load_config(["tracking.graph=off"]).tracking.graph == "off"
    assert load_config(["seeding.depth_fill=false"]).seeding.depth_fill is False
    with pytest.raises(ConfigError, match="expected true or false"):
        load_config(["seeding.depth_fill=no"])


def test_saved_config_round_trips(tmp_path):
    cfg = load_config(["dataset=tum/fr1_desk", "tracking.iters=45"])
    save_config(cfg, tmp_path / "config.yaml")
    data = yaml.safe_load((tmp_path / "config.yaml").read_text())
    assert data["tracking"]["iters"] == 45 and data["dataset"]["path"] == "TUM/rgbd_dataset_freiburg1_desk"
    args = [
        f"{k}.{kk}={vv}"
        for k, v in data.items()
        if isinstance(v, dict)
        for kk, vv in v.items()
        if vv is not None and not isinstance(vv, list)
    ]
    assert load_config(args + ["dataset.path=TUM/rgbd_dataset_freiburg1_desk"]).tracking.iters == 45


def test_cli(tmp_path, capsys):
    # a full run is tests/test_slam.py; here: configuration errors and help
    assert main(["tracking.iter=3"]) == 2
    assert main(["--help"]) == 0 and "Configuration groups" in capsys.readouterr().out


def test_group_file_settings_of_other_sections(tmp_path, monkeypatch):
    """A dataset file's ``settings`` set other sections' keys (7-Scenes: tracking and keyframes for a
    real Kinect); the command line still wins, and their keys are checked like any other."""
    cfg = load_config(["dataset=7scenes/redkitchen"])
    assert cfg.tracking.tau_grad == 0.0 and cfg.keyframes.max_loss_ratio == 1.3
    assert load_config([]).tracking.tau_grad == 0.05 and load_config([]).keyframes.max_loss_ratio == 0.0
    assert load_config(["dataset=7scenes/redkitchen", "tracking.tau_grad=0.02"]).tracking.tau_grad == 0.02
    import rgs_warp.config as config_module

    (tmp_path / "dataset" / "x").mkdir(parents=True)
    (tmp_path / "dataset" / "x" / "bad.yaml").write_text("type: synthetic\nsettings:\n  tracking:\n    tau_gard: 0\n")
    monkeypatch.setattr(config_module, "CONFIG_DIR", tmp_path)
    with pytest.raises(ConfigError, match="tau_gard"):
        config_module.load_config(["dataset=x/bad"])


def test_cpu_sized_run_only_on_the_cpu_without_sizes():
    from rgs_warp.app.cpu_size import CPU_SIZED, cpu_sized_overrides

    extra, message = cpu_sized_overrides(load_config([]), [], "cpu")
    assert extra == [f"{k}={v}" for k, v in CPU_SIZED.items()]
    assert "cpu_sized=false" in message and "120x68" in message and "25 of 100" in message
    cfg = load_config(extra)
    assert (cfg.dataset.width, cfg.dataset.height, cfg.dataset.max_frames, cfg.mapping.window) == (120, 68, 25, 3)
    office = ["dataset=synthetic/office0", "seed=3"]  # neither is a size
    assert cpu_sized_overrides(load_config(office), office, "cpu")[0] == extra
    final = ["mapping.final_share=0.5"]  # a share of the run's iterations: it scales with the CPU-sized run
    assert cpu_sized_overrides(load_config(final), final, "cpu")[0] == extra
    for overrides in (
        ["dataset.max_frames=10"],
        ["dataset.n_frames=50"],
        ["mapping.init_iters=100"],
        ["cpu_sized=false"],
    ):
        assert cpu_sized_overrides(load_config(overrides), overrides, "cpu") == ([], ""), overrides
    assert cpu_sized_overrides(load_config([]), [], "cuda:0") == ([], "")
    tum = ["dataset=tum/fr1_desk"]  # a recorded sequence keeps its size
    assert cpu_sized_overrides(load_config(tum), tum, "cpu") == ([], "")


@pytest.mark.parametrize(
    ("argv", "device", "sized"),
    [([], "cpu", True), ([], "cuda:0", False), (["dataset.width=200", "dataset.height=100"], "cpu", False)],
)
def test_cli_applies_the_cpu_sized_run_and_says_so(argv, device, sized, monkeypatch, capsys, tmp_path):
    """The command line resolves the device (mocked here), and on the CPU without sizes runs the
    CPU-sized config and prints how to get the full run."""
    import rgs_warp.app.cli as run_module

    seen = {}

    def fake_run(cfg, viewer=None):
        seen["cfg"] = cfg
        return tmp_path, {"frames": 1, "keyframes": 1, "gaussians": 1, "fps": 1.0}

    monkeypatch.setattr(run_module, "resolve_device", lambda name: device)
    monkeypatch.setattr(run_module, "run", fake_run)
    assert main(argv) == 0
    err = capsys.readouterr().err
    width = seen["cfg"].dataset.width
    if sized:
        assert width == 120 and seen["cfg"].dataset.max_frames == 25
        assert "CPU-sized" in err and "cpu_sized=false" in err
    else:
        assert width == (200 if argv else 240) and "CPU-sized" not in err


def test_timing_groups():
    """``timing=live``: asynchronous mapping that keeps pace with the camera (keys override it);
    ``timing=offline``, the default, leaves the synchronous mode."""
    live = load_config(["timing=live", "mapping.init_iters=700"])
    assert live.mapping.asynchronous and live.mapping.min_iters == 15 and live.mapping.init_iters == 700
    assert live.mapping.init_wait == "first" and live.mapping.async_queue == 2 and live.mapping.publish_after == 15
    assert live.mapping.rate_fps == load_config([]).mapping.rate_fps
    assert load_config([]) == load_config(["timing=offline"])
    assert not load_config([]).mapping.asynchronous
    assert "timing: live, offline" in help_text()
    with pytest.raises(ConfigError, match="applies to asynchronous mapping only"):
        load_config(["timing=live", "mapping.asynchronous=false", "mapping.init_wait=window"])
    with pytest.raises(ConfigError, match="mapping.publish_after \\(0\\) applies to asynchronous mapping only"):
        load_config(["mapping.publish_after=0"])
    with pytest.raises(ConfigError, match="mapping.init_wait=first applies to asynchronous mapping only"):
        load_config(["timing=live", "mapping.asynchronous=false", "mapping.min_iters=0", "mapping.publish_after=-1"])
    with pytest.raises(ConfigError, match="mapping.publish_after \\(15\\) applies to asynchronous mapping only"):
        load_config(["timing=live", "mapping.asynchronous=false", "mapping.min_iters=0", "mapping.init_wait=window"])


def test_a_saved_config_without_a_middle_section_is_another_versions_not_a_cut_copy(tmp_path):
    """A config.yaml cut short lacks its last sections (said: truncated); one lacking a section before
    others that are there was written by another version (a section added since): said so."""
    path = tmp_path / "config.yaml"
    save_config(Config(), path)
    data = yaml.safe_load(path.read_text())
    del data["keypoints"]
    path.write_text(yaml.safe_dump(data))
    with pytest.raises(ConfigError, match=r"sections keypoints missing \(written by another version"):
        load_saved_config(path)
    for name in ("keypoints", "eval", "export"):
        data.pop(name, None)
    path.write_text(yaml.safe_dump(data))
    with pytest.raises(ConfigError, match=r"sections keypoints, eval, export missing \(truncated\?\)"):
        load_saved_config(path)


def test_reference_page_lists_every_key_with_its_default_and_range():
    # docs/config.md: a table row a key, "| `key` | `default` | range | what it is |"
    text = (Path(__file__).parents[1] / "docs" / "config.md").read_text()
    rows = {m[1]: (m[2], m[3]) for m in re.finditer(r"^\| `([\w.]+)` \| `([^`]*)` \|([^|]*)\|", text, re.M)}
    keys = dict(leaves(Config()))
    assert sorted(set(keys) - set(rows)) == [] and sorted(set(rows) - set(keys)) == []
    for key, default in keys.items():
        cell, bound = rows[key]
        documented = parse_yaml(cell)
        if isinstance(default, tuple):
            documented = tuple(float(v) for v in documented)
        elif isinstance(default, float):
            documented = float(documented)
        elif isinstance(default, str):
            documented = "" if documented is None else str(documented)
        assert documented == default and type(documented) is type(default), (key, cell, default)
        expected = str(CONSTRAINTS[key]).removeprefix("in ") if key in CONSTRAINTS else ""
        assert bound.strip() == expected, (key, bound, expected)
