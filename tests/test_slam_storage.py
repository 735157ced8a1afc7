"""Saving and loading a SLAM (``rgs_warp.slam.storage``): files complete one at a time (trajectory
first), an empty map saves, a snapshot keeps the SLAM as it was, a failed rename keeps the previous
file whole, ``SLAM.load`` names a damaged file, and a checkpoint restores every state."""

import errno
import os
from pathlib import Path

import numpy as np
import pytest

from rgs_warp.config import load_config
from rgs_warp.io.ply import load_ply
from rgs_warp.io.trajectory import read_tum_trajectory
from rgs_warp.slam import SLAM
from rgs_warp.types import Camera

SMALL = ["dataset=synthetic/office0", "dataset.width=160", "dataset.height=90"]
CAMERA = Camera(80.0, 80.0, 79.5, 44.5, 160, 90)


def _slam(device, gaussians: int = 40, frames: int = 3, keyframes: int = 2) -> SLAM:
    """A SLAM holding a few random Gaussians, a trajectory and keyframes, without running a frame."""
    slam = SLAM(load_config([*SMALL, f"device={device}"]), CAMERA, device=device)
    rng = np.random.default_rng(0)
    if gaussians:
        n = gaussians
        slam.map.append(
            rng.normal(size=(n, 3)),
            rng.normal(size=(n, 4)),
            rng.normal(size=(n, 3)) - 3.0,
            rng.normal(size=n),
            rng.normal(size=(n, slam.map.num_sh, 3)),
        )
    for i in range(frames):
        T = np.eye(4)
        T[:3, 3] = [0.1 * i, 0.0, 0.0]
        slam.poses.append(T)
        slam.timestamps.append(0.1 * i)
    for i in range(keyframes):
        slam.keyframes.add(i, slam.poses[i], rng.random((90, 160, 3)), rng.random((90, 160)))
        slam.keyframe_indices.append(i)
    return slam


def test_empty_map_saves_and_loads_back(tmp_path, device):
    """8dc16f7: save_ply crashes on 0 Gaussians ("cannot reshape array of size 0"), after which no
    trajectory is written."""
    slam = _slam(device, gaussians=0)
    slam.save(tmp_path)
    loaded = SLAM.load(tmp_path, device=device)
    assert len(loaded.map) == 0 and len(load_ply(tmp_path / "map.ply")) == 0
    np.testing.assert_allclose(loaded.trajectory()[1], slam.trajectory()[1], atol=1e-12)
    assert loaded.keyframe_indices == [0, 1]


def test_a_failing_file_loses_no_other_and_the_error_says_what_was_saved(tmp_path, device, monkeypatch):
    """8dc16f7 writes map.ply first: a full disk there leaves no trajectory."""
    import rgs_warp.slam.storage as slam_module

    def disk_full(path, fields, num_sh):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(path))

    monkeypatch.setattr(slam_module, "write_ply", disk_full)
    slam = _slam(device)
    with pytest.raises(OSError) as e:
        slam.save(tmp_path)
    message = str(e.value)
    assert "map.ply" in message and "No space left on device" in message
    assert "saved: trajectory.txt, keyframes.npz, config.yaml" in message
    stamps, poses = read_tum_trajectory(tmp_path / "trajectory.txt")
    assert len(poses) == 3 and not (tmp_path / "map.ply").exists()
    assert set(np.load(tmp_path / "keyframes.npz").files) >= {"poses", "rgb"}


def test_a_snapshot_keeps_the_slam_as_it_was(tmp_path, device):
    """``SLAM.snapshot`` (what a run's checkpoints and final save write in a thread while the SLAM goes
    on) holds the SLAM as it was: changes after it reach no file.  On the CPU device a Warp array's
    NumPy view is the live memory: without the snapshot's copies the map, the optimiser's moments and
    the keyframes written would be the changed ones."""
    slam = _slam(device)
    n = len(slam.map)
    slam.map.column("adam_m.means").assign(np.ones((slam.map.capacity, 3), np.float32))
    fields = {k: v.copy() for k, v in slam.map.to_numpy().items()}
    rgb = slam.keyframes.rgb[slam.keyframes.slots()[0]].numpy().copy()
    snapshot = slam.snapshot(state=True)
    # the SLAM goes on: every Gaussian and moment moves, a keyframe's image changes, a frame is added
    slam.map.means.assign(np.zeros((slam.map.capacity, 3), np.float32))
    slam.map.column("adam_m.means").zero_()
    slam.keyframes.rgb[slam.keyframes.slots()[0]].zero_()
    slam.poses.append(np.eye(4))
    slam.timestamps.append(0.3)
    snapshot.write(tmp_path)
    for name, value in load_ply(tmp_path / "map.ply").to_numpy().items():
        np.testing.assert_array_equal(value, fields[name], err_msg=name)
    assert len(read_tum_trajectory(tmp_path / "trajectory.txt")[1]) == 3
    np.testing.assert_array_equal(np.load(tmp_path / "keyframes.npz")["rgb"][0], rgb)
    np.testing.assert_array_equal(np.load(tmp_path / "state.npz")["map.adam_m.means"], np.ones((n, 3)))


def test_a_frame_stopped_in_its_keyframe_mapping_leaves_a_loadable_save(tmp_path, device):
    """Ctrl-C (or an error) while a keyframe's window is mapped, most of a synchronous run's time: the frame is
    in the keyframe buffer and ``keyframe_indices``, its pose not yet in the trajectory.  The run's save of what
    was tracked had then failed to load ("3 poses, but frame 3 is a keyframe (truncated?)"); the frame is left
    out of the saved keyframes."""
    slam = _slam(device, frames=3, keyframes=2)
    rng = np.random.default_rng(1)
    slam.keyframes.add(3, np.eye(4), rng.random((90, 160, 3)), rng.random((90, 160)))
    slam.keyframe_indices.append(3)
    slam.save(tmp_path)
    loaded = SLAM.load(tmp_path, device=device)
    assert len(loaded.poses) == 3 and loaded.keyframe_indices == [0, 1]
    assert sorted(int(loaded.keyframes.frame_ids[s]) for s in loaded.keyframes.slots()) == [0, 1]


def test_a_failed_rename_keeps_the_previous_file_whole(tmp_path, device, monkeypatch):
    """A full disk while a newer map is written (here: at its rename) leaves the previous map.ply
    whole, and every other file is updated; 8dc16f7 writes in place, so it raises nothing here."""
    slam = _slam(device)
    slam.save(tmp_path)
    slam.map.remove(np.arange(len(slam.map)) % 2 == 0)  # the map changes: 20 of the 40 Gaussians left
    slam.poses.append(np.eye(4))
    slam.timestamps.append(0.3)
    real_replace = os.replace

    def replace(src, dst):
        if Path(dst).name == "map.ply":
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(dst))
        return real_replace(src, dst)

    monkeypatch.setattr(os, "replace", replace)
    with pytest.raises(OSError, match="map.ply.*No space left.*saved: trajectory.txt, keyframes.npz, config.yaml"):
        slam.save(tmp_path)
    assert len(load_ply(tmp_path / "map.ply")) == 40  # the previous map, whole
    assert len(read_tum_trajectory(tmp_path / "trajectory.txt")[1]) == 4
    assert sorted(p.name for p in tmp_path.iterdir()) == ["config.yaml", "keyframes.npz", "map.ply", "trajectory.txt"]


@pytest.mark.parametrize("name", ["map.ply", "keyframes.npz", "config.yaml", "trajectory.txt"])
def test_load_names_a_truncated_file(tmp_path, device, name):
    """A copy cut short: the error names the file and says what is wrong.  8dc16f7: plyfile's and
    zipfile's errors name no file, a half config.yaml loads with defaults for the lost keys, and a
    trajectory cut at a line end loads with frames missing."""
    slam = _slam(device)
    slam.save(tmp_path)
    path = tmp_path / name
    data = path.read_bytes()
    if name == "trajectory.txt":  # at a line end: every remaining line is valid
        path.write_bytes(b"".join(data.splitlines(keepends=True)[:-1]))
    else:
        path.write_bytes(data[: len(data) // 2])
    with pytest.raises(ValueError) as e:
        SLAM.load(tmp_path, device=device)
    assert str(path) in str(e.value) and "truncated" in str(e.value)


def test_load_says_what_is_missing(tmp_path, device):
    """A folder that is not there, and one without a saved run's files, each said so (the first had been
    reported as a missing map.ply)."""
    from rgs_warp.slam.storage import LoadError

    with pytest.raises(LoadError, match=rf"^{tmp_path / 'nothere'}: no such folder$"):
        SLAM.load(tmp_path / "nothere", device=device)
    with pytest.raises(LoadError, match=r"map.ply: missing \(not a folder written by SLAM.save\)"):
        SLAM.load(tmp_path, device=device)


def test_load_of_a_checkpoint_restores_every_state(tmp_path, device):
    """``save(..., state=True)``: the optimiser's columns and clocks, the selector's reference and the
    motion model come back exactly (what makes a resumed run equal to an uninterrupted one)."""
    slam = _slam(device)
    n = len(slam.map)
    rng = np.random.default_rng(5)
    slam.map.column("adam_m.means").assign(rng.normal(size=(slam.map.capacity, 3)).astype(np.float32))
    slam.map.column("vis_count").assign(rng.random(slam.map.capacity).astype(np.float32))
    slam.mapper.adam.t, slam.mapper.total_iters = 17, 42
    slam.mapper.rng.random(3)
    slam.tracker.reset(slam.poses[-1], slam.poses[0])
    slam.stats["tracking_s"] = 1.5
    slam.save(tmp_path, state=True)
    loaded = SLAM.load(tmp_path, device=device)
    for name in ("adam_m.means", "vis_count", "ema_means"):
        np.testing.assert_array_equal(loaded.map.column(name).numpy()[:n], slam.map.column(name).numpy()[:n])
    assert (loaded.mapper.adam.t, loaded.mapper.total_iters) == (17, 42)
    assert loaded.mapper.rng.random() == slam.mapper.rng.random()
    np.testing.assert_array_equal(loaded.tracker.predict(), slam.tracker.predict())
    assert loaded.stats["tracking_s"] == 1.5 and loaded.keyframes.slots() == slam.keyframes.slots()
    for key, value in slam.selector.state_dict().items():
        np.testing.assert_array_equal(loaded.selector.state_dict()[key], value)
    # a plain save into the same folder removes the state: it would belong to another SLAM
    slam.save(tmp_path)
    assert not (tmp_path / "state.npz").exists()
