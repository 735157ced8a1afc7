"""Config values checked where they enter (``rgs_warp.config``: ``CONSTRAINTS``, ``ORDERED_KEYS``),
and the override parser fuzzed: a config loads with every value in range, or one ``ConfigError``."""

import functools

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from rgs_warp.config import ConfigError, load_config


@pytest.mark.parametrize(
    "override, message",
    [
        ("tracking.lr=-1", r"tracking.lr: -1.0 is out of range: it must be > 0"),
        ("mapping.init_iters=-5", r"mapping.init_iters: -5 is out of range: it must be >= 1"),
        ("dataset.downscale=1000", r"dataset.downscale = 1000 shrinks the 240x136 images to 0x0.*at least 16 px"),
        ("tracking.downscale=40", r"tracking.downscale = 40 shrinks the 240x136 images to 6x3 for tracking"),
        ("tracking.iters=0", r"tracking.iters: 0 is out of range"),
        ("tracking.lr=.nan", r"tracking.lr: nan is not a finite number"),
        ("mapping.lr_position=-1e-3", r"mapping.lr_position: -0.001 is out of range: it must be >= 0"),
        ("tracking.adam_beta2=1", r"tracking.adam_beta2: 1.0 is out of range: it must be in \[0, 1\)"),
        ("keyframes.buffer_size=1", r"keyframes.buffer_size: 1 is out of range: it must be >= 2"),
        ("render.background=[0,0,2]", r"render.background: \(0.0, 0.0, 2.0\) is out of range"),
        ("dataset.stride=0", r"dataset.stride: 0 is out of range"),
        ("matching.min_depth_m=20", r"matching.min_depth_m \(20.0\) must not exceed matching.max_depth_m \(10.0\)"),
        ("seed=-1", r"seed: -1 is out of range: it must be in \[0, 2147483647\]"),
        ("tracking.motion_min_ratio=1.5", r"tracking.motion_min_ratio: 1.5 is out of range: it must be in \[0, 1\]"),
        ("tracking.motion_min_step_m=-0.01", r"tracking.motion_min_step_m: -0.01 is out of range: it must be >= 0"),
        ("tracking.motion_min_rotation_deg=-1", r"tracking.motion_min_rotation_deg: -1.0 is out of range"),
        ("tracking.motion_check=yes", r"tracking.motion_check: 'yes' is not one of auto, on, off"),
        ("tracking.relocalize=always", r"tracking.relocalize: 'always' is not one of auto, on, off"),
    ],
)
def test_config_values_are_checked(override, message):
    with pytest.raises(ConfigError, match=message):
        load_config([override])


def test_constraints_name_real_keys_and_pass_every_shipped_config():
    from rgs_warp.config import CONSTRAINTS, ORDERED_KEYS, Config, group_options

    for key in [*CONSTRAINTS, *(k for pair in ORDERED_KEYS for k in pair[:2])]:
        functools.reduce(getattr, key.split("."), Config())  # AttributeError for a key that does not exist
    for option in group_options("dataset"):
        for method in group_options("method"):
            load_config([f"dataset={option}", f"method={method}", "mode=mono"])


def _keys() -> list[str]:
    import dataclasses

    from rgs_warp.config import Config

    def walk(obj, prefix):
        for f in dataclasses.fields(obj):
            v = getattr(obj, f.name)
            yield from walk(v, prefix + f.name + ".") if dataclasses.is_dataclass(v) else [prefix + f.name]

    return list(walk(Config(), ""))


VALUES = st.one_of(
    st.text(max_size=12),
    st.integers(-(2**40), 2**40).map(str),
    st.floats(allow_nan=True, allow_infinity=True).map(repr),
    st.sampled_from(["null", "[]", "[1, 2]", "[0, 0, 0]", "{a: 1}", "true", "1e-3", ".inf", "-.nan", "!!int 3", "'"]),
)


OVERRIDES = st.lists(
    st.one_of(
        st.tuples(st.sampled_from(_keys()), VALUES).map("=".join),
        st.tuples(st.sampled_from(["dataset", "method", "mode", "tracking", ""]), VALUES).map("=".join),
        st.text(max_size=30),
    ),
    max_size=4,
)


@settings(max_examples=300, deadline=None)
@given(OVERRIDES)
def test_fuzz_config_overrides(overrides):
    """Any list of override strings either loads into a config whose values all pass the constraints,
    or fails with a ConfigError; never another exception."""
    from rgs_warp.config import check_config

    try:
        cfg = load_config(overrides)
    except ConfigError as e:
        assert str(e)
        return
    assert check_config(cfg) is cfg


def test_an_unknown_device_names_the_devices_there_are():
    """``device=cuda:0`` on a machine without it: Warp said "Invalid device identifier"; now the error
    lists the devices and says what ``device=auto`` picks."""
    import warp as wp

    from rgs_warp.config import resolve_device

    assert resolve_device("cpu") == "cpu" and resolve_device("auto") in ("cpu", "cuda:0")
    missing = f"cuda:{len(wp.get_cuda_devices())}"
    with pytest.raises(ConfigError, match=rf"device={missing}: no such device.*the devices are cpu.*device=auto picks"):
        resolve_device(missing)
    with pytest.raises(ConfigError, match="device=gpu: no such device"):
        resolve_device("gpu")
