"""The evaluation suite (rgs_warp.app.suite) with a fake SLAM runner: aggregation against NumPy, bold for
the best per column, errors and n/a reasons in eval.md, the device and plan it names, the convergence
comparison, plots, eval.json, the default plans' scene selection, the plan printed before the runs,
sweeps, and the Ray path's options without Ray."""

import json
import sys
from pathlib import Path

import numpy as np
import pytest

from rgs_warp.app import suite
from rgs_warp.app.cpu_size import CPU_SIZED
from rgs_warp.app.suite import cli
from rgs_warp.config import ConfigError, load_config

SCENES = ("synthetic/room0", "synthetic/office0", "7scenes/redkitchen")
METHODS = ("rgs", "baseline")
REPEATS = 3


def _numbers(scene: str, method: str, seed: int) -> dict:
    """rgs: lower ATE, higher PSNR on every scene; baseline: higher FPS; seeds spread the numbers."""
    k = SCENES.index(scene)
    rgs = method == "rgs"
    return {
        "ate": (1.0 if rgs else 2.0) + 0.5 * k + (0.1 if rgs else 0.3) * seed**2,
        "psnr": (30.0 if rgs else 27.0) - k + 0.25 * seed,
        "fps": (2.0 if rgs else 3.0) + 0.1 * seed,
    }


def _curve(method: str, final_db: float) -> list[dict]:
    """A convergence.json as rgs_warp.slam writes it: initialization samples every 10 iterations up to
    100, then one point per keyframe.  rgs rises faster (time constant 15 against 40 iterations) but
    dips by 5 dB at iteration 40 (a keyframe joining its window), after it first crossed the common
    PSNR; a point without a PSNR (empty map) is skipped by the reader."""
    tau = 15.0 if method == "rgs" else 40.0
    points = [
        (i, "init", final_db * (1 - np.exp(-i / tau)) - (5.0 if method == "rgs" and i == 40 else 0.0))
        for i in range(10, 101, 10)
    ]
    points += [(160, "keyframe", final_db), (220, "keyframe", final_db + 0.5), (280, "keyframe", None)]
    return [{"iteration": i, "frame": i // 25, "phase": ph, "psnr_db": v, "gaussians": 100 + i} for i, ph, v in points]


def fake_runner(cfg, run_dir: Path, progress: bool = True):
    scene = f"{cfg.dataset.type}/{cfg.dataset.name}"
    if cfg.method == "baseline" and scene == "7scenes/redkitchen":
        raise ValueError("baseline: dense init not implemented | yet")
    x = _numbers(scene, cfg.method, cfg.seed)
    metrics = {
        "dataset": scene,
        "method": cfg.method,
        "fps": x["fps"],
        "tracking_fps": 2 * x["fps"],
        "peak_memory_mib": None,
        "peak_memory_mib_na_reason": "measured on CUDA devices only",
        "gaussians": 1000 + cfg.seed,
        "tracking": {"tracked_frames": 20, "lost_frames": 0 if cfg.method == "rgs" else cfg.seed + 1},
        "ate": {
            "keyframes": {"rmse_cm": x["ate"]},
            "all_frames": {"rmse_cm": x["ate"] + 0.2},
        },
        "photometric": {
            "psnr_db": x["psnr"],
            "ssim": 0.9,
            "lpips": None,
            "lpips_na_reason": "no LPIPS weights given",
            "depth_l1_cm": 1.5,
        },
    }
    if scene.startswith("synthetic"):
        metrics["mesh"] = {"acc_cm": 1.0 + cfg.seed, "comp_cm": 2.0, "comp_ratio_pct": 90.0}
        run_dir.mkdir(parents=True, exist_ok=True)
        (run_dir / "convergence.json").write_text(json.dumps(_curve(cfg.method, x["psnr"])))
    else:
        metrics["mesh"] = None
        metrics["mesh_na_reason"] = "no ground-truth mesh for this sequence"
    run_dir.mkdir(parents=True, exist_ok=True)
    (run_dir / "metrics.json").write_text(json.dumps(metrics))
    return run_dir, metrics


PLAN = [{"scene": s, "overrides": [f"dataset={s}"], "skipped": None} for s in SCENES] + [
    {"scene": "replica/room1", "overrides": ["dataset=replica/room1"], "skipped": "no data at /nowhere/Replica/room1"}
]


@pytest.fixture(scope="module")
def result(tmp_path_factory):
    out = tmp_path_factory.mktemp("eval")
    res = suite.run_suite(
        PLAN, METHODS, REPEATS, out, runner=fake_runner, extra_overrides=["device=cpu"], plan_name="cpu"
    )
    return out, res


def _tables(md: str) -> dict:
    """{(group, benchmark, metric label, method): [cells]} from eval.md's tables."""
    cells, group, bench, label = {}, None, None, None
    for line in md.splitlines():
        if line.startswith("## "):
            group = line[3:]
        elif line.startswith("### "):
            bench = line[4:]
        elif line.startswith("| ") and bench and not line.startswith("| Metric"):
            parts = [p.strip() for p in line.strip("|").split(" | ")]
            label = parts[0] or label
            cells[group, bench, label, parts[1]] = parts[2:]
    return cells


def test_aggregate_matches_numpy(result):
    _, res = result
    for scene in SCENES[:2]:
        for method in METHODS:
            values = [_numbers(scene, method, s)["ate"] for s in range(REPEATS)]
            cell = res["aggregate"][scene][method]["ate_keyframes_rmse_cm"]
            assert cell["n"] == REPEATS
            assert cell["mean"] == pytest.approx(np.mean(values), rel=1e-12)
            assert cell["std"] == pytest.approx(np.std(values, ddof=1), rel=1e-12)
    avg = res["averages"]["synthetic"]["rgs"]["psnr_db"]["mean"]
    scene_means = [np.mean([_numbers(s, "rgs", k)["psnr"] for k in range(REPEATS)]) for s in SCENES[:2]]
    assert avg == pytest.approx(np.mean(scene_means))
    failed = res["aggregate"]["7scenes/redkitchen"]["baseline"]["ate_keyframes_rmse_cm"]
    assert failed["n"] == 0 and failed["n_failed"] == REPEATS and failed["mean"] is None


def test_bold_goes_to_best_per_column(result):
    out, _ = result
    t = _tables((out / "eval.md").read_text())
    ate = "ATE RMSE keyframes (cm) ↓"
    rgs, base = t["Tracking", "synthetic", ate, "rgs"], t["Tracking", "synthetic", ate, "baseline"]
    assert len(rgs) == 3  # room0, office0, Avg.
    assert all(c.startswith("**") for c in rgs) and not any("**" in c for c in base)
    fps = "FPS ↑"  # higher is better: the baseline wins
    rgs, base = t["Speed and memory", "synthetic", fps, "rgs"], t["Speed and memory", "synthetic", fps, "baseline"]
    assert all(c.startswith("**") for c in base) and not any("**" in c for c in rgs)
    # no competitor on 7-Scenes (the baseline failed): nothing is bold
    assert "**" not in t["Tracking", "7scenes", ate, "rgs"][0]
    # equal numbers (SSIM 0.9 for both): both bold
    ssim = t["Rendering", "synthetic", "SSIM raw ↑", "rgs"] + t["Rendering", "synthetic", "SSIM raw ↑", "baseline"]
    assert all(c.startswith("**0.900") for c in ssim)
    # lost frames: fewer is better (rgs 0, the baseline 1, 2, 3 over the seeds)
    lost = "Lost frames ↓"
    rgs, base = t["Tracking", "synthetic", lost, "rgs"], t["Tracking", "synthetic", lost, "baseline"]
    assert all(c.startswith("**0.0") for c in rgs) and base == ["2.0 ± 1.0", "2.0 ± 1.0", "2.0"]  # room0, office0, Avg.
    # the Gaussian count has no better direction
    assert not any("**" in c for c in t["Speed and memory", "synthetic", "Gaussians", "rgs"])


def test_errors_and_na_reasons_in_markdown(result):
    out, _ = result
    md = (out / "eval.md").read_text()
    t = _tables(md)
    cell = t["Tracking", "7scenes", "ATE RMSE keyframes (cm) ↓", "baseline"][0]
    assert cell.startswith("error [^")
    note = cell.split()[-1]
    assert f"{note}: run failed: ValueError: baseline: dense init not implemented | yet" in md
    lpips = t["Rendering", "synthetic", "LPIPS AlexNet ↓", "rgs"][0]
    assert lpips.startswith("n/a [^") and f"{lpips.split()[-1]}: no LPIPS weights given" in md
    assert "no ground-truth mesh for this sequence" in md
    assert "measured on CUDA devices only" in md
    assert "- replica/room1: skipped: no data at /nowhere/Replica/room1" in md
    assert "- synthetic/room0: `dataset=synthetic/room0`" in md
    # an average over scenes of which one has no number says which
    assert t["Tracking", "7scenes", "ATE RMSE keyframes (cm) ↓", "baseline"][1] == "n/a"
    assert "| 7scenes/redkitchen | baseline | 2 | error [^" in md
    mean, std = np.mean([1.0, 1.1, 1.4]), np.std([1.0, 1.1, 1.4], ddof=1)
    assert f"**{mean:.2f} ± {std:.2f}**" in t["Tracking", "synthetic", "ATE RMSE keyframes (cm) ↓", "rgs"][0]


def test_convergence_comparison(result):
    out, res = result
    md = (out / "eval.md").read_text()
    assert "## Convergence" in md and "minus 0.5 dB" in md
    for scene in SCENES[:2]:
        curves = {m: [_curve(m, _numbers(scene, m, k)["psnr"]) for k in range(REPEATS)] for m in METHODS}
        # the definition, written out: the common PSNR is the lower mean final initialization PSNR
        # minus 0.5 dB; a run needs the first sample from which on its PSNR stays at or above it
        finals = {
            m: np.mean([[p for p in c if p["phase"] == "init"][-1]["psnr_db"] for c in cs]) for m, cs in curves.items()
        }
        target = min(finals.values()) - 0.5
        entry = res["convergence"][scene]
        assert entry["target_db"] == pytest.approx(target)
        cells = []
        for m in METHODS:
            needed = []
            for c in curves[m]:
                init = [(p["iteration"], p["psnr_db"]) for p in c if p["phase"] == "init"]
                above = [i for k, (i, _) in enumerate(init) if all(v >= target for _, v in init[k:])]
                needed.append(above[0])
            got = entry["methods"][m]
            assert got["values"] == needed and got["iterations"] == pytest.approx(np.mean(needed)), m
            assert got["final_init_db"] == pytest.approx(finals[m])
            cells.append(f"{np.mean(needed):.0f} ({finals[m]:.2f} dB)")
        # rgs first reaches the target at 30 but dips below at 40: it counts from 50
        assert entry["methods"]["rgs"]["values"][0] == 50
        assert entry["methods"]["rgs"]["iterations"] < entry["methods"]["baseline"]["iterations"]
        assert f"| {scene} | {target:.2f} | {cells[0]} | {cells[1]} |" in md
    # no curves (7-Scenes: the fake writes none, the baseline failed): no row
    assert "7scenes/redkitchen" not in res["convergence"]
    run = next(r for r in res["runs"] if r["scene"] == "synthetic/room0")
    assert len(run["convergence"]) == 12 and {p["phase"] for p in run["convergence"]} == {"init", "keyframe"}


def test_plots_and_json(result):
    out, res = result
    assert res["plots"] == ["eval_ate.png", "eval_psnr.png", "eval_convergence.png"]
    for name in res["plots"]:
        assert (out / name).stat().st_size > 1000
        assert f"![{name}]({name})" in (out / "eval.md").read_text()
    assert json.loads((out / "eval.json").read_text()) == res
    assert len(res["runs"]) == len(SCENES) * len(METHODS) * REPEATS
    run = next(r for r in res["runs"] if r["scene"] == "synthetic/room0" and r["method"] == "rgs" and r["seed"] == 2)
    assert Path(run["run_dir"]) == out / "eval_runs" / "synthetic-room0-rgs-2"
    assert (Path(run["run_dir"]) / "metrics.json").is_file()
    assert res["header"]["repeats"] == REPEATS and res["header"]["device"] == "cpu"
    assert res["skipped"] == [{"scene": "replica/room1", "reason": "no data at /nowhere/Replica/room1"}]


def test_markdown_names_the_device_and_the_plan(result):
    out, res = result
    md = (out / "eval.md").read_text()
    name = res["header"]["device_name"]
    assert name.endswith(" cores") and res["header"]["plan"] == "cpu"
    assert md.startswith(f"# rgs_warp evaluation: plan cpu on {name}\n")
    assert f"- device: cpu ({name})" in md
    assert "- plan: cpu (CPU-sized" in md and "`nox -s eval -- --full`" in md


def test_unknown_method_is_a_failed_row(tmp_path):
    res = suite.run_suite(PLAN[:1], ("rgs", "nosuch"), 1, tmp_path, runner=fake_runner, progress=False)
    bad = next(r for r in res["runs"] if r["method"] == "nosuch")
    assert bad["status"] == "error" and "ConfigError" in bad["error"]
    assert "run failed: ConfigError" in (tmp_path / "eval.md").read_text()


@pytest.mark.slow
def test_resume_reuses_finished_runs_with_the_same_overrides(tmp_path):
    calls = []

    def counting_runner(cfg, run_dir, progress=True):
        calls.append((cfg.dataset.name, cfg.method, cfg.seed))
        return fake_runner(cfg, run_dir, progress)

    def run(extra=(), resume=True):
        return suite.run_suite(
            PLAN[:2],
            ("rgs",),
            2,
            tmp_path,
            runner=counting_runner,
            extra_overrides=list(extra),
            progress=False,
            resume=resume,
        )

    first = run(resume=False)
    assert len(calls) == 4
    again = run()  # all four finished with the same overrides: read back, none run
    assert len(calls) == 4 and all(r["resumed"] for r in again["runs"])
    assert [r["metrics"] for r in again["runs"]] == [r["metrics"] for r in first["runs"]]
    # a cut-short suite: one run's record is gone (it never finished), a different override reruns all
    (tmp_path / "eval_runs" / "synthetic-office0-rgs-1" / suite.RECORD_FILE).unlink()
    run()
    assert calls[4:] == [("office0", "rgs", 1)]
    run(extra=["tracking.iters=7"])
    assert len(calls) == 9


CPU_SIZE = [f"{k}={v}" for k, v in CPU_SIZED.items()]


def _data_root(tmp_path: Path, *folders: str) -> Path:
    root = tmp_path / "data"
    for folder in folders:
        (root / folder).mkdir(parents=True)
    return root


def test_cpu_plan_runs_cpu_sized_scenes_and_one_real_sequence_per_benchmark(tmp_path):
    root = _data_root(tmp_path, "Replica/office0", "Replica/room1", "TUM/rgbd_dataset_freiburg1_desk")
    plan = {e["scene"]: e for e in suite.default_plan("cpu", root)}
    present = [s for s, e in plan.items() if not e["skipped"]]
    assert present == ["synthetic/room0", "synthetic/office0", "replica/office0", "tum/fr1_desk"]
    assert plan["synthetic/room0"]["overrides"] == ["dataset=synthetic/room0", *CPU_SIZE]
    # a present sequence beyond the cpu plan's one per benchmark: the full plan's
    assert plan["replica/room1"]["skipped"] == "in the full plan only (`nox -s eval -- --full`)"
    # a missing one says where it looked and how to get it
    seven = plan["7scenes/redkitchen"]["skipped"]
    assert seven.startswith(f"no data at {root.resolve() / '7scenes/redkitchen/seq-01'}")
    assert seven.endswith("get it with `python -m rgs_warp.download 7scenes/redkitchen`")
    # the overrides are valid and point where the presence check looked, at about the CPU size
    office = load_config(plan["replica/office0"]["overrides"])
    assert office.dataset_path() == (root / "Replica" / "office0").resolve() and office.dataset.downscale == 10
    assert office.dataset.max_frames == CPU_SIZED["dataset.max_frames"] and office.mapping.init_iters == 100
    assert not any(o.startswith(("dataset.width", "dataset.height")) for o in plan["replica/office0"]["overrides"])
    quick = {e["scene"]: e for e in suite.default_plan("cpu", root, quick=True)}
    assert load_config(quick["tum/fr1_desk"]["overrides"]).dataset.max_frames == suite.QUICK_MAX_FRAMES


def test_full_plan_runs_every_present_sequence_whole(tmp_path, monkeypatch):
    root = _data_root(tmp_path, "Replica/office0", "Replica/room1", "7scenes/redkitchen/seq-01")
    plan = suite.default_plan("full", root)
    present = [e["scene"] for e in plan if not e["skipped"]]
    assert present == [
        "synthetic/room0_replica_size",
        "synthetic/office0_replica_size",
        "7scenes/redkitchen",
        "replica/office0",
        "replica/room1",
    ]
    assert all(e["overrides"] == [f"dataset={e['scene']}", f"data_root={root.resolve()}"] for e in plan[2:])
    # without data_root the data root is $RGS_DATA's
    monkeypatch.setenv("RGS_DATA", str(root))
    assert suite.default_plan("full") == plan
    with pytest.raises(ValueError, match="one of cpu, full"):
        suite.default_plan("gpu", root)


def test_select_scenes_takes_any_known_scene_at_the_plan_size(tmp_path):
    root = _data_root(tmp_path, "Replica/room1")
    (room1,) = suite.select_scenes("cpu", ["replica/room1"], root)
    assert not room1["skipped"] and load_config(room1["overrides"]).dataset.downscale == 10
    with pytest.raises(ConfigError, match="unknown scene.s. replica/nosuch"):
        suite.select_scenes("cpu", ["replica/nosuch"], root)


def test_plan_printed_before_the_runs(tmp_path, monkeypatch, capsys):
    """The command says up front what it runs (runs, sizes, an estimate), what it skips and how to get
    it, and how to get the full plan; the tables then name the plan."""
    seen = {}
    monkeypatch.setattr(cli, "check_evaluation_imports", lambda: None)
    monkeypatch.setattr(cli, "run_suite", lambda plan, *a, **k: seen.update(k, plan=plan) or {"runs": []})
    root = _data_root(tmp_path, "Replica/office0", "Replica/room1")
    assert cli.main(["--device", "cpu", "--out", str(tmp_path / "out"), f"data_root={root}"]) == 1  # no run ok
    printed = capsys.readouterr().out
    first = "Evaluation plan cpu on cpu: 6 runs (3 scenes x 2 methods x 1 repeat), about 10 minutes on 2 cores"
    assert printed.startswith(first), printed
    assert "  synthetic/room0: 120x68, 25 frames\n" in printed
    assert "  replica/office0: 1/10 size, 25 frames\n" in printed
    assert f"Skipped, no data under {root.resolve()} (data_root= or $RGS_DATA" in printed
    assert "python -m rgs_warp.download NAME" in printed and "  tum/fr1_desk tum/fr1_desk2 " in printed
    assert "Skipped, in the full plan only (`nox -s eval -- --full`): replica/room1\n" in printed
    assert printed.endswith(
        "meant for a GPU): nox -s eval -- --full\n0 of 0 runs ok; report " + str(tmp_path / "out/eval.md\n")
    )
    assert seen["plan_name"] == "cpu" and [e["scene"] for e in seen["plan"] if not e["skipped"]] == [
        "synthetic/room0",
        "synthetic/office0",
        "replica/office0",
    ]
    cli.main(["--device", "cpu", "--full", "--quick", "--out", str(tmp_path / "out"), f"data_root={root}"])
    printed = capsys.readouterr().out
    assert printed.startswith("Evaluation plan quick on cpu: 8 runs (4 scenes x 2 methods x 1 repeat), hours")
    assert "meant for a GPU" not in printed
    assert "  synthetic/room0_replica_size: 1200x680, 15 frames\n" in printed and seen["plan_name"] == "quick"
    cli.main(["--device", "cpu", "--full", "--out", str(tmp_path / "out"), f"data_root={root}"])
    assert seen["plan_name"] == "full" and capsys.readouterr().out.startswith("Evaluation plan full on cpu: 24 runs")


def test_second_best_underlined_among_three():
    lower = suite.METRIC_BY_ID["ate_keyframes_rmse_cm"]
    marks = suite.rank_marks({"a": 2.0, "b": 1.0, "c": 3.0, "d": None}, lower)
    assert marks == {"b": "best", "a": "second"}
    higher = suite.METRIC_BY_ID["psnr_db"]
    assert suite.rank_marks({"a": 30.001, "b": 30.004, "c": 20.0}, higher) == {"a": "best", "b": "best"}
    assert suite.rank_marks({"a": 2.0, "b": 1.0}, lower) == {"b": "best"}  # two methods: no underline


# ---- sweeps ------------------------------------------------------------------------------------------


def test_sweep_variants_name_and_combine():
    assert suite.sweep_variants(None, None) is None and suite.sweep_variants([], {}) is None
    sets = suite.sweep_variants(
        [{"name": "default", "overrides": []}, {"name": "", "overrides": ["tracking.iters=10"]}],
        {"mapping.iters_per_frame": [5, 9], "mapping.window": [2]},
    )
    assert [s["name"] for s in sets] == [
        "default mapping.iters_per_frame=5 mapping.window=2",
        "default mapping.iters_per_frame=9 mapping.window=2",
        "tracking.iters=10 mapping.iters_per_frame=5 mapping.window=2",
        "tracking.iters=10 mapping.iters_per_frame=9 mapping.window=2",
    ]
    assert sets[3]["overrides"] == ["tracking.iters=10", "mapping.iters_per_frame=9", "mapping.window=2"]
    assert suite.sweep_variants(None, {"eval.lpips": [True]})[0]["overrides"] == ["eval.lpips=true"]
    assert suite.sweep_variants([{"name": "", "overrides": []}], None) == [{"name": "default", "overrides": []}]
    assert suite.variant_slug("short tracking / x=1") == "short_tracking_x=1"
    assert suite.row_label("rgs", None) == "rgs" and suite.row_label("rgs", "a b") == "rgs [a b]"


def _spec(tmp_path, text: str) -> Path:
    path = tmp_path / "sweep.yaml"
    path.write_text(text)
    return path


def test_load_sweep_plan_order_of_overrides_and_errors(tmp_path):
    spec = _spec(
        tmp_path,
        """
scenes: [synthetic/room0, {scene: synthetic/office0_replica_size, overrides: [dataset.max_frames=7]}]
methods: [rgs, baseline]
repeats: 2
overrides: [dataset.max_frames=9]
variants: [{name: short, overrides: [tracking.iters=3]}]
""",
    )
    sweep = suite.load_sweep(spec, "cpu")
    assert sweep["name"] == "sweep" and sweep["methods"] == ["rgs", "baseline"] and sweep["repeats"] == 2
    assert sweep["variants"] == [{"name": "short", "overrides": ["tracking.iters=3"]}]
    room, office = sweep["plan"]
    # a scene of the plan keeps the plan's CPU sizing; the spec's overrides, then the scene's own, win
    assert room["overrides"] == ["dataset=synthetic/room0", *CPU_SIZE, "dataset.max_frames=9"]
    assert office["overrides"] == [
        "dataset=synthetic/office0_replica_size",
        "dataset.max_frames=9",
        "dataset.max_frames=7",
    ]
    assert load_config(office["overrides"]).dataset.max_frames == 7

    for text, message in (
        ("methods: [rgs]", "non-empty 'scenes'"),
        ("scenes: [synthetic/room0]\nrepeat: 2", "unknown key(s) repeat"),
        ("scenes: [synthetic/room0]\nmethods: [nosuch]", "unknown method(s) nosuch"),
        ("scenes: [synthetic/nowhere]", "unknown scene 'synthetic/nowhere'"),
        ("scenes: [synthetic/room0]\nrepeats: 0", "repeats must be an integer >= 1"),
        ("scenes: [synthetic/room0]\ngrid: {tracking.iters: 3}", "grid must map each key"),
        ("scenes: [synthetic/room0]\nvariants: [{name: a, overides: []}]", "variants must be a list"),
        ("scenes: [synthetic/room0]\nvariants: [{name: a b}, {name: a/b}]", "the same name"),
        ("scenes: [synthetic/room0]\nvariants: [{overrides: [tracking.nosuch=1]}]", "tracking.nosuch"),
    ):
        with pytest.raises(ConfigError, match=message.replace("(", r"\(").replace(")", r"\)")):
            suite.load_sweep(_spec(tmp_path, text), "cpu")


def test_example_sweep_loads():
    sweep = suite.load_sweep(Path(__file__).parents[1] / "sweeps" / "example.yaml", "cpu")
    assert sweep["name"] == "example" and len(sweep["variants"]) == 4 and len(sweep["plan"]) == 2


def test_sweep_rows_in_tables(tmp_path):
    """Each (method, override set) is a row of its own: its runs carry the set's overrides (last) and
    its name, their folders are apart, and the aggregates are per row."""
    variants = [{"name": "default", "overrides": []}, {"name": "short tracking", "overrides": ["tracking.iters=3"]}]
    seen = []

    def runner(cfg, run_dir, progress=True):
        seen.append((run_dir.name, cfg.tracking.iters))
        run_dir, metrics = fake_runner(cfg, run_dir, progress)
        metrics["ate"]["keyframes"]["rmse_cm"] += 10.0 * (cfg.tracking.iters == 3)
        return run_dir, metrics

    res = suite.run_suite(
        PLAN[:1],
        ("rgs",),
        2,
        tmp_path,
        runner=runner,
        extra_overrides=["tracking.iters=5"],
        variants=variants,
        progress=False,
    )
    assert [name for name, _ in seen] == [
        "synthetic-room0-rgs-default-0",
        "synthetic-room0-rgs-default-1",
        "synthetic-room0-rgs-short_tracking-0",
        "synthetic-room0-rgs-short_tracking-1",
    ]
    assert [iters for _, iters in seen] == [5, 5, 3, 3]  # the set's overrides come after the suite's
    assert res["header"]["rows"] == ["rgs [default]", "rgs [short tracking]"] and res["header"]["methods"] == ["rgs"]
    cells = res["aggregate"]["synthetic/room0"]
    ate = [_numbers("synthetic/room0", "rgs", k)["ate"] for k in range(2)]
    assert cells["rgs [default]"]["ate_keyframes_rmse_cm"]["values"] == ate
    assert cells["rgs [short tracking]"]["ate_keyframes_rmse_cm"]["values"] == [a + 10.0 for a in ate]
    md = (tmp_path / "eval.md").read_text()
    t = _tables(md)
    assert t["Tracking", "synthetic", "ATE RMSE keyframes (cm) ↓", "rgs [default]"][0].startswith("**")
    assert ("Tracking", "synthetic", "ATE RMSE keyframes (cm) ↓", "rgs [short tracking]") in t
    assert "  - short tracking: `tracking.iters=3`" in md and "  - default: (none)" in md
    assert "| synthetic/room0 | rgs [short tracking] | 1 | ok |" in md
    assert set(res["convergence"]["synthetic/room0"]["methods"]) == {"rgs [default]", "rgs [short tracking]"}
    # resume tells the sets apart: all four are read back
    again = suite.run_suite(
        PLAN[:1],
        ("rgs",),
        2,
        tmp_path,
        runner=runner,
        extra_overrides=["tracking.iters=5"],
        variants=variants,
        progress=False,
        resume=True,
    )
    assert len(seen) == 4 and all(r["resumed"] for r in again["runs"])


def test_without_a_sweep_the_records_and_header_are_as_before(result):
    _, res = result
    assert "rows" not in res["header"] and "variants" not in res["header"]
    assert not any("variant" in r for r in res["runs"])
    assert list(res["runs"][0])[:5] == ["scene", "method", "repeat", "seed", "run_dir"]


# ---- the Ray path without Ray (tests/test_app_suite_ray.py runs it) -----------------------------------


def test_ray_task_options_ask_for_a_gpu_on_cuda(monkeypatch):
    monkeypatch.delenv(suite.KILL_ENV, raising=False)
    gpu = suite.ray_task_options("cuda:0")
    assert gpu == {"num_gpus": 1.0, "num_cpus": 1, "max_retries": 1, "retry_exceptions": False}
    assert suite.ray_task_options("cuda:0", 0.5)["num_gpus"] == 0.5
    assert suite.ray_task_options("cpu") == {"num_cpus": 1, "max_retries": 1, "retry_exceptions": False}
    monkeypatch.setenv(suite.KILL_ENV, "x-rgs-0:1")
    assert suite.ray_task_options("cpu")["runtime_env"] == {"env_vars": {suite.KILL_ENV: "x-rgs-0:1"}}


def test_ray_path_without_ray_says_what_to_install(tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "ray", None)  # import ray raises ImportError
    with pytest.raises(ImportError, match=r"rgs_warp\[cluster\]"):
        suite.run_suite(PLAN[:1], ("rgs",), 1, tmp_path, runner=fake_runner, progress=False, cluster="")
    argv = ["--ray", "--device", "cpu", "--scenes", "synthetic/room0", "--out", str(tmp_path), "--repeats", "1"]
    monkeypatch.setattr(cli, "check_evaluation_imports", lambda: None)
    assert suite.main(argv) == 1


def test_ray_without_address_before_overrides(monkeypatch, tmp_path):
    """``--ray key=value``: the override is an override, not the cluster's address."""
    seen = {}
    monkeypatch.setattr(cli, "check_evaluation_imports", lambda: None)
    monkeypatch.setattr(cli, "run_suite", lambda *a, **k: seen.update(k) or {"runs": []})
    argv = [
        "--scenes",
        "synthetic/room0",
        "--device",
        "cpu",
        "--out",
        str(tmp_path),
        "--ray",
        "tracking.iters=3",
        "seed=1",
    ]
    suite.main(argv)
    assert seen["cluster"] == "" and seen["extra_overrides"] == ["device=cpu", "tracking.iters=3", "seed=1"]
    suite.main([*argv[:-3], "--ray", "ray://head:10001", "seed=1"])
    assert seen["cluster"] == "ray://head:10001" and seen["extra_overrides"] == ["device=cpu", "seed=1"]
    suite.main(argv[:-3])
    assert seen["cluster"] is None


def test_ray_with_another_gpu_than_cuda0_is_refused(capsys):
    assert suite.main(["--ray", "--device", "cuda:1"]) == 2
    assert "each task sees its own GPU as cuda:0" in capsys.readouterr().err


def test_peer_metrics_named_in_the_tables(result):
    """The peers' numbers each under a name that says whose they are (SplaTAM's "SSIM" is MS-SSIM)."""
    out, _ = result
    t = _tables((out / "eval.md").read_text())
    for label in ("SSIM raw ↑", "SSIM 3DGS zero-padded (MonoGS's) ↑", "MS-SSIM (SplaTAM's SSIM) ↑", "LPIPS AlexNet ↓"):
        assert ("Rendering", "synthetic", label, "rgs") in t, label


def test_git_commit_names_edited_code(tmp_path):
    # a number measured on edited code must not carry the bare commit (a machine that runs a copied
    # working tree over an older .git would name code it did not run)
    import subprocess

    from rgs_warp.app.report import git_commit

    assert git_commit(tmp_path) == "unknown"
    git = ["git", "-c", "user.name=t", "-c", "user.email=t@t", "-C", str(tmp_path)]
    subprocess.run([*git, "init", "-q"], check=True)
    (tmp_path / "a.txt").write_text("1")
    subprocess.run([*git, "add", "a.txt"], check=True)
    subprocess.run([*git, "commit", "-q", "-m", "c"], check=True)
    head = subprocess.run([*git, "rev-parse", "--short", "HEAD"], capture_output=True, text=True).stdout.strip()
    assert git_commit(tmp_path) == head
    (tmp_path / "a.txt").write_text("2")
    assert git_commit(tmp_path) == head + "+changes"


def test_unknown_methods_are_refused_before_any_run(tmp_path, capsys, monkeypatch):
    def no_runs(*args, **kwargs):
        raise AssertionError("runs were started")

    monkeypatch.setattr(cli, "run_suite", no_runs)
    assert suite.main(["--methods", "rgs,foo", "--device", "cpu", "--out", str(tmp_path)]) == 2
    assert "error: unknown method(s) foo; valid: rgs, baseline" in capsys.readouterr().err


def test_cpu_plan_reads_the_shared_7scenes_frames_under_a_data_root(tmp_path, shared_data):
    """The shared 500 frames as the data root's 7scenes/redkitchen/seq-01: the cpu plan runs them at
    128x96, every 5th frame, 25 frames (frames 0-120)."""
    from rgs_warp.datasets import open_dataset

    root = tmp_path / "data"
    (root / "7scenes" / "redkitchen").mkdir(parents=True)
    (root / "7scenes" / "redkitchen" / "seq-01").symlink_to(shared_data / "7scenes-redkitchen")
    (entry,) = [e for e in suite.default_plan("cpu", root) if e["scene"] == "7scenes/redkitchen"]
    assert not entry["skipped"]
    ds = open_dataset(load_config([*entry["overrides"], "device=cpu"]))
    frame = ds[len(ds) - 1]
    assert len(ds) == 25 and frame.rgb.shape == (96, 128, 3)
