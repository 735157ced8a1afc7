"""What ``rgs_warp.slam`` does with bad input inside a run: a NaN patch is masked and the run goes on,
an unusable frame is lost at the last good pose, a pose that diverged never enters the map or the
trajectory, the tracker discards a non-finite estimate; the device check of uploaded frames tracks as
the host check."""

import numpy as np
import pytest

from rgs_warp.config import load_config
from rgs_warp.slam import SLAM
from rgs_warp.types import Camera

W, H = 64, 48
CAMERA = Camera(fx=60.0, fy=60.0, cx=31.5, cy=23.5, width=W, height=H)
SMALL = ["device=cpu", "mapping.init_iters=10", "mapping.iters_per_frame=1", "tracking.iters=3"]
# whole-SLAM tests: the CPU-sized office of test_slam.py, shortened
OFFICE = [
    "dataset=synthetic/office0",
    "dataset.width=160",
    "dataset.height=90",
    "dataset.max_frames=6",
    "mapping.init_iters=20",
    "mapping.iters_per_frame=2",
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


@pytest.mark.slow
def test_nan_patch_is_masked_and_counted(device):
    """A 2x2 NaN patch in an initial-window frame: on 8dc16f7 a NaN pose made a keyframe
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


@pytest.mark.slow
def test_uploaded_frame_check_tracks_as_the_host_check(monkeypatch):
    """The SLAM with frames uploaded and checked on the device (forced on the CPU) tracks bit for bit as
    with the host check: the tracker reads the checker's buffers in place."""
    import rgs_warp.slam.system as slam_module
    from rgs_warp.frame_check import FrameChecker

    cfg, camera, frames = _office("cpu", 6, ["dataset.width=80", "dataset.height=45"])  # bit for bit at any size
    poses = []
    for upload in (False, True):
        monkeypatch.setattr(slam_module, "FrameChecker", lambda *a, up=upload, **k: FrameChecker(*a, **k, upload=up))
        slam = SLAM(cfg, camera, device="cpu", T_first_WC=frames[0].pose_gt)
        assert slam.frame_check.upload == upload
        poses.append([slam.process(f.rgb, f.depth).T_WC for f in frames])
    assert len(slam.map) > 0
    np.testing.assert_array_equal(np.array(poses[0]), np.array(poses[1]))


def _missing_gpu() -> str:
    import warp as wp

    return f"cuda:{len(wp.get_cuda_devices())}"


def test_a_config_naming_a_missing_device_is_one_error():
    from rgs_warp.config import ConfigError

    with pytest.raises(ConfigError, match=rf"device={_missing_gpu()}: no such device.*device=auto picks"):
        SLAM(load_config([f"device={_missing_gpu()}"]), CAMERA)


def test_a_missing_device_given_to_the_slam_is_one_error():
    from rgs_warp.config import ConfigError

    with pytest.raises(ConfigError, match=rf"device={_missing_gpu()}: no such device.*device=auto picks"):
        SLAM(load_config(SMALL), CAMERA, device=_missing_gpu())
