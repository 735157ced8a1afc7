"""Issue 20, the input half: bad input never reaches the map.  Frames are checked at SLAM.process (the
first one included), a pose that diverged never enters the map or the trajectory, intrinsics and
config values are checked where they enter, TUM says which frames it drops, the eval suite refuses
unknown methods; fuzzing of the config parser and of the frame check.  experiments/results/
reliability.md has the table of cases, before (8dc16f7) and now.

The tests that are not fuzz tests use only what 8dc16f7 had as well (SLAM, load_config, the loaders,
the command lines), importing anything newer inside the test, so that each can be run against it."""

import os
import subprocess
import sys
import warnings

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from rgs_warp.config import ConfigError, load_config
from rgs_warp.slam import SLAM
from rgs_warp.types import Camera

W, H = 64, 48
CAMERA = Camera(fx=60.0, fy=60.0, cx=31.5, cy=23.5, width=W, height=H)
SMALL = ["device=cpu", "mapping.init_iters=10", "mapping.iters=2", "tracking.iters=3"]
# whole-SLAM tests: the CPU-sized office of test_slam.py, shortened
OFFICE = [
    "dataset=synthetic/office0",
    "dataset.width=160",
    "dataset.height=90",
    "dataset.max_frames=6",
    "mapping.init_iters=20",
    "mapping.iters=3",
    "mapping.window=3",
    "mapping.init_window=2",
    "tracking.iters=6",
]


def _frame(seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    return rng.random((H, W, 3), dtype=np.float32), np.full((H, W), 2.0, np.float32)


def _office(device, n: int, extra=()):
    from rgs_warp.datasets import open_dataset

    cfg = load_config([*OFFICE, f"device={device}", *extra])
    ds = open_dataset(cfg, device="cpu")
    return cfg, ds.camera, [ds[i] for i in range(n)]


# ---- 1. frames at the library's boundary ---------------------------------------------------------
def _transposed(rgb, depth):
    return np.ascontiguousarray(rgb.transpose(1, 0, 2)), depth


@pytest.mark.parametrize(
    "name, bad, message",
    [
        ("rgb transposed", _transposed, r"rgb: expected shape \(48, 64, 3\).*got \(64, 48, 3\): transposed"),
        ("rgb half-size", lambda r, d: (r[::2, ::2], d), r"32x24 images need a Camera of that size"),
        ("rgb uint8", lambda r, d: ((r * 255).astype(np.uint8), d), r"uint8 is not converted.*/ 255"),
        ("rgb 0-255 floats", lambda r, d: (r * 255, d), r"expected \[0, 1\] \(8-bit values\? divide by 255\)"),
        ("rgb RGBA", lambda r, d: (np.dstack([r, r[..., :1]]), d), r"drop the alpha channel"),
        ("depth transposed", lambda r, d: (r, np.ascontiguousarray(d.T)), r"depth: expected shape.*transposed"),
        ("depth uint16 mm", lambda r, d: (r, (d * 1000).astype(np.uint16)), r"uint16 is not converted.*metres"),
        ("depth HxWx3", lambda r, d: (r, np.dstack([d] * 3)), r"depth: expected shape \(48, 64\) .*got \(48, 64, 3\)"),
        ("depth negative", lambda r, d: (r, -d), r"3072 pixels are negative"),
        ("depth all zero", lambda r, d: (r, 0 * d), r"frame 0 cannot start the map: depth at 0 of 3072 pixels"),
        ("depth all NaN", lambda r, d: (r, np.full_like(d, np.nan)), r"frame 0 cannot start the map: depth at 0"),
        ("rgb 10 % NaN", lambda r, d: (np.where(np.arange(H)[:, None, None] < 5, np.nan, r), d), r"not finite"),
    ],
)
def test_first_frame_is_checked(name, bad, message):
    """8dc16f7 checked frames in the tracker only, which the first frame skips: a transposed, half-size
    or uint8 first frame built a map.  Now each is refused with what to do, and nothing changes."""
    slam = SLAM(load_config(SMALL), CAMERA, device="cpu")
    rgb, depth = bad(*_frame())
    with pytest.raises(ValueError, match=message):
        slam.process(rgb, depth)
    assert len(slam.poses) == 0 and len(slam.map) == 0 and len(slam.keyframes) == 0


def test_frame_check_masks_and_counts_nonfinite_pixels():
    from rgs_warp.frame_check import MAX_NONFINITE_RGB, MIN_VALID_DEPTH, FrameChecker

    check = FrameChecker(CAMERA, "cpu").check
    rgb, depth = _frame()
    clean = check(rgb, depth)
    assert clean.rgb is rgb and clean.depth is depth and not clean.unusable  # valid input: untouched
    assert (clean.nonfinite_rgb, clean.nonfinite_depth) == (0, 0)

    patch = rgb.copy()
    patch[10:12, 20:22] = np.nan  # the 2x2 patch
    patch[30, 5, 1] = np.inf
    depth_holes = depth.copy()
    depth_holes[0, :7] = np.nan
    depth_holes[1, 0] = -np.inf
    out = check(patch, depth_holes)
    assert (out.nonfinite_rgb, out.nonfinite_depth, out.unusable) == (5, 8, "")
    assert np.isfinite(out.rgb).all() and np.isfinite(out.depth).all()
    # the nearest finite pixel's colour, and no depth there; the rest as given
    assert np.array_equal(out.rgb[30, 5], rgb[29, 5]) or np.array_equal(out.rgb[30, 5], rgb[30, 4])
    assert {tuple(out.rgb[10, 20])} <= {tuple(rgb[9, 20]), tuple(rgb[10, 19])}
    assert (out.depth[10:12, 20:22] == 0).all() and out.depth[30, 5] == 0 and (out.depth[:2, :7][0] == 0).all()
    untouched = np.ones((H, W), bool)
    untouched[10:12, 20:22] = untouched[30, 5] = untouched[0, :7] = untouched[1, 0] = False
    assert np.array_equal(out.rgb[untouched], rgb[untouched]) and np.array_equal(out.depth[untouched], depth[untouched])

    too_many = rgb.copy()
    too_many[: int(np.ceil(MAX_NONFINITE_RGB * H)) + 1] = np.nan
    assert "colour pixels" in check(too_many, depth).unusable
    sparse = np.zeros_like(depth)
    sparse.flat[: int(MIN_VALID_DEPTH * H * W) - 1] = 1.0
    assert "depth at 29 of 3072 pixels" in check(rgb, sparse).unusable
    assert not FrameChecker(CAMERA, "cpu", mode="mono").check(rgb, sparse).unusable  # mono ignores depth


def test_frame_check_device_arrays_agree_with_host():
    """wp.array frames are counted by a kernel and only copied to the host when something is off:
    the same outcome as the host check."""
    import warp as wp

    from rgs_warp.frame_check import FrameChecker

    check = FrameChecker(CAMERA, "cpu").check
    rgb, depth = _frame()
    as_wp = (wp.array(rgb, dtype=wp.vec3, device="cpu"), wp.array(depth, dtype=wp.float32, device="cpu"))
    out = check(*as_wp)
    assert out.rgb is as_wp[0] and out.depth is as_wp[1] and not out.unusable
    rgb[3, 3] = np.nan
    depth[4, 4] = np.inf
    host, device = check(rgb, depth), check(wp.array(rgb, dtype=wp.vec3), wp.array(depth, dtype=wp.float32))
    assert (host.nonfinite_rgb, host.nonfinite_depth) == (device.nonfinite_rgb, device.nonfinite_depth) == (1, 1)
    assert np.array_equal(host.rgb, device.rgb) and np.array_equal(host.depth, device.depth)
    with pytest.raises(ValueError, match="8-bit values"):
        check(wp.array(rgb * 255, dtype=wp.vec3), wp.array(depth, dtype=wp.float32))
    with pytest.raises(ValueError, match=r"expected a \(48, 64\) wp.array of vec3f?.*got \(64, 48\)"):
        check(wp.zeros((W, H), dtype=wp.vec3), as_wp[1])
    with pytest.raises(ValueError, match="depth at 0 of 3072"):
        SLAM(load_config(SMALL), CAMERA, device="cpu").process(as_wp[0], wp.zeros((H, W), dtype=wp.float32))


@pytest.mark.slow
def test_nan_patch_is_masked_and_counted(device):
    """The issue's 2x2 NaN patch in an initial-window frame: on 8dc16f7 a NaN pose made a keyframe
    and the next frame raised LinAlgError.  Now the patch is filled and counted, and the run goes on
    with finite poses and a finite map."""
    cfg, camera, frames = _office(device, 4)
    slam = SLAM(cfg, camera, device=device, T_first_WC=frames[0].pose_gt)
    results = []
    for k, f in enumerate(frames):
        rgb = f.rgb.copy()
        if k == 1:
            rgb[40:42, 70:72] = np.nan
        results.append(slam.process(rgb, f.depth, f.timestamp))
    assert results[1].nonfinite_rgb == 4 and results[1].keyframe and not results[1].lost
    assert all(np.isfinite(r.T_WC).all() and not r.lost for r in results)
    assert all(np.isfinite(v).all() for v in slam.map.to_numpy().values())
    assert np.abs(results[1].T_WC[:3, 3] - frames[1].pose_gt[:3, 3]).max() < 0.06  # 4.1 cm without the patch


@pytest.mark.slow
def test_unusable_later_frame_is_lost_at_the_last_good_pose(device):
    """Depth all zeros, then 20 % of the colour NaN, after the start: each frame is lost with its
    reason, keeps the last good pose, is neither tracked nor mapped; the frames after it track (from
    the motion model's prediction, as after a lost frame)."""
    cfg, camera, frames = _office(device, 6, ["tracking.iters=20"])
    slam = SLAM(cfg, camera, device=device, T_first_WC=frames[0].pose_gt)
    results = []
    for k, f in enumerate(frames):
        rgb, depth = f.rgb, f.depth
        if k == 2:
            depth = np.zeros_like(depth)
        if k == 3:
            rgb = rgb.copy()
            rgb[:18] = np.nan
        before = (len(slam.map), len(slam.keyframes))
        results.append(slam.process(rgb, depth, f.timestamp))
        if k in (2, 3):
            assert (len(slam.map), len(slam.keyframes)) == before
    lost = [r for r in results if getattr(r, "lost", False)]
    assert [r.index for r in lost] == [2, 3]
    assert "depth at 0 of 14400 pixels" in lost[0].lost_reason and "colour pixels (20.0%)" in lost[1].lost_reason
    assert all(r.tracking is None and not r.keyframe for r in lost)
    assert np.array_equal(results[2].T_WC, results[1].T_WC) and np.array_equal(results[3].T_WC, results[1].T_WC)
    assert results[4].tracking is not None and not results[4].tracking.lost
    assert np.abs(results[5].T_WC[:3, 3] - frames[5].pose_gt[:3, 3]).max() < 0.06  # 4.3 cm without the gap


@pytest.mark.slow
def test_diverged_pose_never_enters_map_or_trajectory(device):
    """tracking.lr = 50 throws the pose 100 m away within one frame; on 8dc16f7 it became an
    initial-window keyframe.  Now the frame is lost with the reason, keeps the last good pose, and the
    map stays the first keyframe's."""
    cfg, camera, frames = _office(device, 3, ["tracking.lr=50"])
    slam = SLAM(cfg, camera, device=device, T_first_WC=frames[0].pose_gt)
    first = slam.process(frames[0].rgb, frames[0].depth, frames[0].timestamp)
    n_first = len(slam.map)
    for f in frames[1:]:
        r = slam.process(f.rgb, f.depth, f.timestamp)
        assert not r.keyframe and np.array_equal(r.T_WC, first.T_WC)
        assert r.lost and "diverged: the pose moved" in r.lost_reason
    assert len(slam.map) == n_first and slam.keyframe_indices == [0]
    _, poses = slam.trajectory()
    assert np.allclose(poses, frames[0].pose_gt)


def test_tracker_discards_a_nonfinite_estimate():
    """A NaN in what the tracker is given (the SLAM masks them; the Tracker is public too) gives a
    non-finite loss: the estimate is discarded, the start pose returned, the frame lost."""
    from rgs_warp.tracking import Tracker
    from rgs_warp.types import GaussianMap

    cfg = load_config(SMALL)
    tracker = Tracker(cfg.tracking, CAMERA, "cpu")
    rgb, depth = _frame()
    rgb[5, 5] = np.nan
    T0 = np.eye(4)
    T0[:3, 3] = (1.0, 2.0, 3.0)
    result = tracker.track(rgb, depth, GaussianMap(16, device="cpu"), T0)
    assert result.lost and result.diverged and "non-finite" in result.reason
    assert np.array_equal(result.T_WC, T0) and np.array_equal(tracker.predict(), T0)


def test_given_poses_must_be_rigid():
    slam = SLAM(load_config(SMALL), CAMERA, device="cpu")
    with pytest.raises(ValueError, match="T_WC: the rotation is not orthonormal"):
        slam.process(*_frame(), T_WC=np.diag([2.0, 1.0, 1.0, 1.0]))
    with pytest.raises(ValueError, match="T_first_WC: expected a finite 4x4"):
        SLAM(load_config(SMALL), CAMERA, device="cpu", T_first_WC=np.full((4, 4), np.nan))


# ---- 2. intrinsics where they enter --------------------------------------------------------------
@pytest.mark.parametrize(
    "values, message",
    [
        (dict(fx=-60.0), "fx = -60.0: a focal length must be a positive"),
        (dict(fy=0.0), "fy = 0.0: a focal length"),
        (dict(fx=float("nan")), "fx = nan"),
        (dict(cx=64.0), r"cx = 64.0: the principal point must lie inside the 64x48 image \(-0.5 .. 63.5"),
        (dict(cy=-3.0), "cy = -3.0: the principal point"),
        (dict(width=0), "width = 0: the image size"),
    ],
)
def test_camera_refuses_bad_intrinsics(values, message):
    args = dict(fx=60.0, fy=60.0, cx=31.5, cy=23.5, width=W, height=H) | values
    with pytest.raises(ValueError, match=message):
        Camera(**args)


def _tiny_tum(root, n_rgb=4, n_depth=4, camera=None):
    """A TUM-layout folder of n_rgb colour frames (64x48) and the first n_depth depth images."""
    import cv2

    (root / "rgb").mkdir(parents=True)
    (root / "depth").mkdir()
    rgb, depth = _frame()
    rgb_lines, depth_lines = [], []
    for k in range(n_rgb):
        t = 100.0 + k / 30
        cv2.imwrite(str(root / "rgb" / f"{t:.6f}.png"), (np.roll(rgb, k, axis=1) * 255).astype(np.uint8))
        rgb_lines.append(f"{t:.6f} rgb/{t:.6f}.png")
        if k < n_depth:
            cv2.imwrite(str(root / "depth" / f"{t:.6f}.png"), (depth * 1000).astype(np.uint16))
            depth_lines.append(f"{t:.6f} depth/{t:.6f}.png")
    (root / "rgb.txt").write_text("\n".join(rgb_lines) + "\n")
    (root / "depth.txt").write_text("\n".join(depth_lines) + "\n")
    cam = {"w": W, "h": H, "fx": 60.0, "fy": 60.0, "cx": 31.5, "cy": 23.5, "scale": 1000} | (camera or {})
    import json

    (root / "cam_params.json").write_text(json.dumps({"camera": cam}))
    return root


@pytest.mark.parametrize(
    "camera, message",
    [
        ({"fx": -60.0}, "fx = -60.0: a focal length"),
        ({"fx": 0.0}, "fx = 0.0: a focal length"),
        ({"fy": float("nan")}, "fy = nan"),
        ({"cx": 640.0}, "cx = 640.0: the principal point"),
        ({"scale": 0}, "scale = 0.0: the depth scale"),
    ],
)
def test_cam_params_errors_name_the_file(tmp_path, camera, message):
    """TUM (your own data) and Replica read cam_params.json; on 8dc16f7 these ran, or ended in a
    ZeroDivisionError or an empty trajectory."""
    from rgs_warp.datasets import DatasetError, ReplicaDataset, TUMDataset

    tum = _tiny_tum(tmp_path / "tum", camera=camera)
    with pytest.raises(DatasetError, match=rf"{tum / 'cam_params.json'}: {message}"):
        TUMDataset(tum, require_pose=False)
    replica = tmp_path / "replica"
    (replica / "results").mkdir(parents=True)
    (replica / "results" / "frame000000.jpg").write_bytes(b"")
    (replica / "cam_params.json").write_text((tum / "cam_params.json").read_text())
    with pytest.raises(DatasetError, match=rf"{replica / 'cam_params.json'}: {message}"):
        ReplicaDataset(replica)


def test_sevenscenes_intrinsics_are_checked(tmp_path):
    """A negative focal length in 7-Scenes' camera-intrinsics.txt ran silently on 8dc16f7."""
    from rgs_warp.datasets import DatasetError, SevenScenesDataset

    (tmp_path / "frame-000000.color.png").write_bytes(b"")
    (tmp_path / "frame-000000.pose.txt").write_text(" ".join(map(str, np.eye(4).ravel())))
    (tmp_path / "camera-intrinsics.txt").write_text("-585 0 320\n0 585 240\n0 0 1\n")
    with pytest.raises(DatasetError, match=r"camera-intrinsics.txt: fx = -585.0: a focal length"):
        SevenScenesDataset(tmp_path, register_depth=False)
    (tmp_path / "camera-intrinsics.txt").write_text("585 0 320\n0 585 240\n0 0 1\n")
    with pytest.raises(DatasetError, match=r"dataset.colour_intrinsics \(526.0, 526.0, 900.0, 238.0\): cx = 900.0"):
        SevenScenesDataset(tmp_path, colour_intrinsics=(526.0, 526.0, 900.0, 238.0))


def test_cli_bad_intrinsics_one_error_no_run_folder(tmp_path, capsys):
    from rgs_warp.run import main

    root = _tiny_tum(tmp_path / "mine", camera={"fx": 0.0})
    out = tmp_path / "runs"
    argv = ["dataset.type=tum", f"dataset.path={root}", "dataset.require_pose=false", f"output_dir={out}"]
    assert main([*argv, "device=cpu", "mapping.init_iters=10", "dataset.max_frames=3"]) == 1
    err = capsys.readouterr().err
    assert f"error: {root / 'cam_params.json'}: fx = 0.0: a focal length" in err and "Traceback" not in err
    assert not out.exists()


# ---- 3. config values where they enter -----------------------------------------------------------
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
    from rgs_warp.config import CONSTRAINTS, ORDERED_KEYS, Config, _config_value, group_options

    for key in [*CONSTRAINTS, *(k for pair in ORDERED_KEYS for k in pair[:2])]:
        _config_value(Config(), key)  # AttributeError for a key that does not exist
    for option in group_options("dataset"):
        for method in group_options("method"):
            load_config([f"dataset={option}", f"method={method}", "mode=mono"])


def test_downscale_of_a_loaded_dataset_is_checked(tmp_path):
    """The native size of a real dataset is known once it is open: still before any run folder."""
    from rgs_warp.datasets import open_dataset

    root = _tiny_tum(tmp_path / "mine")
    base = ["dataset.type=tum", f"dataset.path={root}", "dataset.require_pose=false"]
    with pytest.raises(ConfigError, match=r"dataset.downscale = 4 shrinks the 64x48 images to 16x12"):
        open_dataset(load_config([*base, "dataset.downscale=4"]))
    with pytest.raises(ValueError, match=r"the camera is 64x12"):
        SLAM(load_config(SMALL), Camera(60.0, 60.0, 31.5, 5.5, 64, 12), device="cpu")


def test_cli_config_error_is_one_line_and_exit_2(tmp_path):
    proc = subprocess.run(
        [sys.executable, "-m", "rgs_warp.slam", "tracking.lr=-1", f"output_dir={tmp_path / 'runs'}"],
        capture_output=True,
        text=True,
        env=os.environ.copy(),
        timeout=120,
    )
    lines = [line for line in proc.stderr.splitlines() if not line.startswith("Warp")]
    assert proc.returncode == 2 and lines == ["error: tracking.lr: -1.0 is out of range: it must be > 0"], proc.stderr
    assert not (tmp_path / "runs").exists()


def test_a_missing_evaluation_package_stops_before_any_run(tmp_path, monkeypatch, capsys):
    """The evaluation imports pytorch-msssim at the end of a run; without it the command says so at
    once (one line, no run folder) instead of after minutes of tracking."""
    import importlib.util

    from rgs_warp import run as run_module
    from rgs_warp.eval import suite

    find_spec = importlib.util.find_spec
    monkeypatch.setattr(
        importlib.util, "find_spec", lambda name, *a: None if name == "pytorch_msssim" else find_spec(name, *a)
    )
    small = ["dataset.max_frames=2", "mapping.init_iters=5", "device=cpu"]  # were it to run: seconds
    assert run_module.main([f"output_dir={tmp_path / 'runs'}", *small]) == 1
    assert suite.main(["--quick", "--out", str(tmp_path / "suite"), "--device", "cpu"]) == 1
    err = capsys.readouterr().err.splitlines()
    assert (
        err
        == [
            "error: the evaluation at the end of a run needs pytorch-msssim, which is not installed: "
            "pip install pytorch-msssim (nothing was run)"
        ]
        * 2
    ), err
    assert not (tmp_path / "runs").exists() and not (tmp_path / "suite").exists()


# ---- 4. TUM: frames without depth ----------------------------------------------------------------
def test_tum_says_how_many_frames_it_drops_and_why(tmp_path):
    from rgs_warp.datasets import TUMDataset

    root = _tiny_tum(tmp_path / "mine", n_rgb=5, n_depth=3)
    with pytest.warns(UserWarning, match=r"2 of 5 colour frames in rgb.txt dropped: 2 without a depth image"):
        ds = TUMDataset(root, require_pose=False)
    assert len(ds) == 3 and "2 of 5 colour frames in rgb.txt dropped" in repr(ds)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # nothing dropped: no warning
        ds = TUMDataset(_tiny_tum(tmp_path / "whole", n_rgb=3, n_depth=3), require_pose=False)
    assert "dropped" not in repr(ds)


# ---- 5. eval suite: unknown methods --------------------------------------------------------------
def test_suite_refuses_unknown_methods_before_any_run(tmp_path, capsys, monkeypatch):
    from rgs_warp.eval import suite

    def no_runs(*args, **kwargs):
        raise AssertionError("runs were started")

    monkeypatch.setattr(suite, "run_suite", no_runs)
    assert suite.main(["--methods", "rgs,foo", "--device", "cpu", "--out", str(tmp_path)]) == 2
    assert "error: unknown method(s) foo; valid: rgs, baseline" in capsys.readouterr().err


# ---- 6. fuzzing -----------------------------------------------------------------------------------
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


DTYPES = st.sampled_from([np.float32, np.float64, np.float16, np.uint8, np.uint16, np.int32, np.bool_, np.complex64])
SHAPES = st.one_of(
    st.just((H, W, 3)),
    st.just((W, H, 3)),
    hnp.array_shapes(min_dims=0, max_dims=4, min_side=0, max_side=70),
)


def _image(shape, dtype):
    floats = st.one_of(st.floats(0, 1, width=32), st.sampled_from([np.nan, np.inf, -np.inf, -0.5, 255.0, 1.0005]))
    elements = floats if np.dtype(dtype).kind == "f" else None
    return hnp.arrays(dtype, shape, elements=elements)


@st.composite
def frames(draw):
    """Mostly (3 in 4) frames of the right shape and dtype with patches of NaN, inf, out-of-range and
    valid values, the others of any shape and dtype."""
    right = draw(st.sampled_from([True, True, True, False]))
    rgb_shape = (H, W, 3) if right else draw(SHAPES)
    depth_shape = (H, W) if right or draw(st.booleans()) else draw(SHAPES)
    rgb_dtype = np.float32 if right else draw(DTYPES)
    depth_dtype = np.float32 if right else draw(DTYPES)
    if right:
        rgb = np.full(rgb_shape, 0.5, np.float32)
        depth = np.full(depth_shape, draw(st.sampled_from([2.0, 2.0, 2.0, 0.0])), np.float32)
        for _ in range(draw(st.integers(0, 6))):  # patches of a special value, mostly small
            y, x = draw(st.integers(0, H - 1)), draw(st.integers(0, W - 1))
            h, w = (draw(st.sampled_from([1, 2, 3, 8, n])) for n in (H, W))
            target = draw(st.sampled_from(["rgb", "depth"]))
            value = draw(st.sampled_from([np.nan, np.nan, np.inf, -np.inf, 0.0, 0.0, 0.7, 2.0, -1.0, 1.5, 1e30]))
            (rgb if target == "rgb" else depth)[y : y + h, x : x + w] = value
        return rgb, depth
    return draw(_image(rgb_shape, rgb_dtype)), draw(_image(depth_shape, depth_dtype))


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(frames())
def test_fuzz_frame_check(frame):
    """Whatever the frame, the check raises ValueError (a message, no other exception) or returns a
    frame of the camera's shape, float32, finite, colour in [0, 1], depth >= 0, with its counts; a
    usable one has more than 1 % of its pixels with depth and at most 1 % of its colour filled.  Given
    as wp.arrays (where they can be), the frame gets the same answer from the device check."""
    import warp as wp

    from rgs_warp.frame_check import RANGE_TOL, FrameChecker

    def check(rgb, depth):
        try:
            return FrameChecker(CAMERA, "cpu").check(rgb, depth)
        except ValueError as e:
            return str(e)

    rgb, depth = frame
    out = check(rgb, depth)
    if rgb.shape == (H, W, 3) and depth.shape == (H, W) and rgb.dtype == depth.dtype == np.float32:
        on_device = check(wp.array(rgb, dtype=wp.vec3, device="cpu"), wp.array(depth, dtype=wp.float32, device="cpu"))
        if isinstance(out, str):
            assert on_device == out
        else:
            assert (on_device.nonfinite_rgb, on_device.nonfinite_depth) == (out.nonfinite_rgb, out.nonfinite_depth)
            assert on_device.unusable == out.unusable
            as_host = [a.numpy() if isinstance(a, wp.array) else a for a in (on_device.rgb, on_device.depth)]
            assert np.array_equal(as_host[0], out.rgb, equal_nan=True) and np.array_equal(as_host[1], out.depth)
    if isinstance(out, str):
        assert out.startswith(("rgb:", "depth:")), out
        return
    assert out.rgb.shape == (H, W, 3) and out.depth.shape == (H, W)
    assert out.rgb.dtype == np.float32 and out.depth.dtype == np.float32
    assert out.depth.min() >= 0 and np.isfinite(out.depth).all()
    if not out.unusable:
        assert np.isfinite(out.rgb).all() and -RANGE_TOL <= out.rgb.min() and out.rgb.max() <= 1 + RANGE_TOL
        assert np.count_nonzero(out.depth) >= 0.01 * H * W and out.nonfinite_rgb <= 0.01 * H * W
    assert out.nonfinite_rgb == np.count_nonzero(~np.isfinite(np.asarray(rgb, np.float32)).all(axis=2))


def test_frame_check_uploaded_numpy_frames_agree_with_host():
    """NumPy frames uploaded first and counted by the kernel (the default on CUDA devices, forced here
    on the CPU) get the host check's answers; a clean frame comes back as the checker's device arrays."""
    import warp as wp

    from rgs_warp.frame_check import FrameChecker

    host, uploaded = FrameChecker(CAMERA, "cpu", upload=False), FrameChecker(CAMERA, "cpu", upload=True)
    rgb, depth = _frame()
    out = uploaded.check(rgb, depth)
    assert isinstance(out.rgb, wp.array) and isinstance(out.depth, wp.array) and not out.unusable
    assert np.array_equal(out.rgb.numpy(), rgb) and np.array_equal(out.depth.numpy(), depth)
    rgb[3, 3] = np.nan
    depth[4, 4] = np.inf
    a, b = host.check(rgb, depth), uploaded.check(rgb, depth)
    assert (a.nonfinite_rgb, a.nonfinite_depth) == (b.nonfinite_rgb, b.nonfinite_depth) == (1, 1)
    assert np.array_equal(a.rgb, b.rgb) and np.array_equal(a.depth, b.depth)
    for bad, message in (((rgb * 255, depth), "8-bit values"), ((rgb, -np.abs(depth)), "negative")):
        with pytest.raises(ValueError, match=message):
            uploaded.check(*bad)
    sparse = np.zeros_like(depth)
    assert uploaded.check(np.nan_to_num(rgb), sparse).unusable == host.check(np.nan_to_num(rgb), sparse).unusable != ""
    # float64 frames take the host path (which converts them)
    assert isinstance(uploaded.check(np.nan_to_num(rgb).astype(np.float64), depth.astype(np.float64)).rgb, np.ndarray)


@pytest.mark.slow
def test_uploaded_frame_check_tracks_as_the_host_check(monkeypatch):
    """The SLAM with frames uploaded and checked on the device (forced on the CPU) tracks bit for bit as
    with the host check: the tracker reads the checker's buffers in place."""
    import rgs_warp.slam as slam_module
    from rgs_warp.frame_check import FrameChecker

    cfg, camera, frames = _office("cpu", 6)
    poses = []
    for upload in (False, True):
        monkeypatch.setattr(slam_module, "FrameChecker", lambda *a, up=upload, **k: FrameChecker(*a, **k, upload=up))
        slam = SLAM(cfg, camera, device="cpu", T_first_WC=frames[0].pose_gt)
        assert slam.frame_check.upload == upload
        poses.append([slam.process(f.rgb, f.depth).T_WC for f in frames])
    assert len(slam.map) > 0
    np.testing.assert_array_equal(np.array(poses[0]), np.array(poses[1]))


@pytest.mark.slow
@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.lists(frames(), min_size=2, max_size=3))
def test_fuzz_slam_process(frame_list):
    """Frames from the same generator through a whole SLAM: ValueError or a result with a finite pose;
    the map stays finite."""
    slam = SLAM(load_config([*SMALL, "mapping.init_window=2"]), CAMERA, device="cpu")
    for rgb, depth in frame_list:
        try:
            result = slam.process(rgb, depth)
        except ValueError:
            continue
        assert np.isfinite(result.T_WC).all()
    assert all(np.isfinite(v).all() for v in slam.map.to_numpy().values())
