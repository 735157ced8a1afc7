"""The examples in examples/ run (CPU-sized), and do what their docstrings say."""

import importlib.util
import sys
from pathlib import Path

import numpy as np
import pytest
import warp as wp

from rgs_warp import SLAM, load_config, open_dataset
from rgs_warp.eval import ate
from rgs_warp.geometry import pose_to_transform, se3_exp, transform_to_pose

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"
TINY = [
    "dataset.width=96",
    "dataset.height=54",
    "dataset.max_frames=10",
    "mapping.init_iters=60",
    "mapping.iters_per_frame=2",
    "mapping.window=3",
]


def _example(name: str):
    spec = importlib.util.spec_from_file_location(f"example_{name}", EXAMPLES / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module


def test_pose_to_transform_round_trip():
    T = se3_exp(np.array([0.3, -1.2, 2.0, 0.4, -0.7, 1.9]))
    t = pose_to_transform(T)
    assert isinstance(t, wp.transform)
    np.testing.assert_allclose(transform_to_pose(t), T, atol=1e-6)
    # the transform moves points as the pose does
    x = np.array([0.1, 0.2, 0.3])
    np.testing.assert_allclose(wp.transform_point(t, wp.vec3(*x)), T[:3, :3] @ x + T[:3, 3], atol=1e-6)
    with pytest.raises(ValueError, match="not a rigid pose"):
        pose_to_transform(np.diag([2.0, 1.0, 1.0, 1.0]))


@pytest.mark.slow
def test_robot_loop_tracks_device_frames_without_host_round_trip(device, monkeypatch):
    """The frames stay on the device: during the loop no image-sized array is read to the host (on a
    GPU each ``numpy()`` of a device array is a device-to-host copy; on the CPU device every ``numpy()``
    is counted, host staging buffers included), what is read is a few kilobytes a frame, and the
    frames are copied only device to device."""
    robot = _example("robot_loop")
    cfg = load_config(["dataset=synthetic/office0", *TINY, f"device={device}"])
    dataset = open_dataset(cfg)
    camera = dataset.camera
    slam = SLAM(cfg, camera, device=device, T_first_WC=dataset[0].pose_gt)
    planner = robot.Planner(slam)

    reads, copies = [], []
    numpy, copy = wp.array.numpy, wp.copy

    def counted_numpy(self):
        reads.append((tuple(self.shape), self.size * wp.types.type_size_in_bytes(self.dtype)))
        return numpy(self)

    def counted_copy(dest, src, *args, **kwargs):
        copies.append((str(src.device), str(dest.device), tuple(src.shape)))
        return copy(dest, src, *args, **kwargs)

    frames = robot.camera_driver(dataset, device)
    monkeypatch.setattr(wp.array, "numpy", counted_numpy)
    monkeypatch.setattr(wp, "copy", counted_copy)
    steps, gt = [], []
    for rgb, depth, timestamp, pose_gt in frames:
        monkeypatch.setattr(wp.array, "numpy", counted_numpy)  # the driver's assign is the camera, not SLAM
        steps += robot.robot_loop(slam, [(rgb, depth, timestamp, None)], planner)
        monkeypatch.setattr(wp.array, "numpy", numpy)
        gt.append(pose_gt)
    monkeypatch.undo()

    image_px = camera.width * camera.height
    image_reads = [shape for shape, _ in reads if int(np.prod(shape)) >= image_px]
    assert image_reads == [], image_reads
    # what is read: the tracker's per-iteration history (loss terms and pose, 30 x 30 float64), the pose,
    # counters and the planner's number, also host staging buffers the CPU device cannot tell apart:
    # 10-13.5 kB a frame, whatever the image size (a 640x480 frame is 4.9 MB)
    read_per_frame = sum(size for _, size in reads) / len(steps)
    assert read_per_frame < 16_000, read_per_frame
    assert all(src == dst for src, dst, _ in copies)  # device to device only
    assert len(steps) == 10 and all(isinstance(T, wp.transform) for T, _ in steps)
    # the transforms are the SLAM's poses, and those track the scene
    np.testing.assert_allclose(transform_to_pose(steps[-1][0]), slam.poses[-1], atol=1e-5)
    assert ate(np.array(slam.poses), np.array(gt))["rmse_cm"] < 8.0
    clearance = np.array([c for _, c in steps])
    assert np.all((clearance > 0.1) & (clearance < 10.0)), clearance  # a room: a wall ahead, metres away


@pytest.mark.slow
def test_frames_from_a_callback_example(tmp_path, device):
    example = _example("frames_from_a_callback")
    run_dir, metrics = example.main([*TINY, f"device={device}", f"output_dir={tmp_path}", "run_name=cb"])
    assert metrics["frames"] == 10 and (run_dir / "trajectory.txt").is_file()
    assert metrics["photometric"]["psnr_db"] > 15.0


@pytest.mark.slow
def test_readme_library_example_runs_as_written(tmp_path, monkeypatch):
    """The README's "As a library" block, as written (device=auto: the CPU here), tracks and saves."""
    readme = (EXAMPLES.parent / "README.md").read_text()
    block = readme.split("## As a library", 1)[1].split("```python\n", 1)[1].split("```", 1)[0]
    monkeypatch.chdir(tmp_path)
    scope: dict = {}
    exec(compile(block, "README.md", "exec"), scope)
    slam, dataset = scope["slam"], scope["dataset"]
    assert len(slam.poses) == len(dataset) == 20 and (tmp_path / "out" / "map.ply").is_file()
    assert scope["image"].shape == (68, 120, 3) and len(slam.map) > 0
    gt = np.array([dataset[i].pose_gt for i in range(len(dataset))])
    assert ate(np.array(slam.poses), gt)["rmse_cm"] < 8.0
