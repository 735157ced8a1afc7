"""The SLAM's storage: ``SLAM.save`` and ``SLAM.load`` (``snapshot_slam``, ``load_slam``), the files of a
run folder and the full state of a checkpoint.  Part of the SLAM itself: it reads and restores the
state the stages keep between frames."""

from __future__ import annotations

import json
import zipfile
import zlib
from pathlib import Path

import numpy as np

from rgs_warp.config import load_saved_config, save_config
from rgs_warp.io.atomic import SaveError, atomic_write
from rgs_warp.io.ply import load_ply, write_ply
from rgs_warp.io.trajectory import read_tum_trajectory, write_tum_trajectory
from rgs_warp.types import Camera, GaussianMap


class SlamSnapshot:
    """What ``SLAM.save`` writes, already copied into host memory (``snapshot_slam``): ``write`` puts it
    in a folder without reading the SLAM, so it can run in another thread while the SLAM goes on (a
    run's checkpoints and final save).  A part that could not be gathered (``state.npz`` while the
    monocular bootstrap waits) fails its file in ``write``'s ``SaveError``."""

    def __init__(self, writers: dict, failed: dict[str, Exception], state: bool):
        self._writers, self._failed, self.state = writers, failed, state

    def write(self, directory: str | Path) -> Path:
        directory = Path(directory)
        directory.mkdir(parents=True, exist_ok=True)
        if not self.state:
            (directory / "state.npz").unlink(missing_ok=True)
        saved, failed = [], {}
        for name, write in self._writers.items():
            if name in self._failed:
                failed[name] = self._failed[name]
                continue
            try:
                write(directory / name)
            except Exception as e:  # noqa: BLE001 (reported with the others in SaveError)
                failed[name] = e
            else:
                saved.append(name)
        if failed:
            raise SaveError(directory, saved, failed)
        return directory


def snapshot_slam(slam, state: bool = False) -> SlamSnapshot:
    """``SLAM.save``'s files, gathered now: device arrays copied to the host, and every array copied (on
    the CPU device a Warp array's NumPy view is the live memory), so the snapshot stays as the SLAM was
    while the SLAM goes on.

    ``write(directory)`` writes ``trajectory.txt`` (TUM), ``keyframes.npz``, ``map.ply`` and
    ``config.yaml``, in that order, each atomically (``rgs_warp.io.atomic``): a crash or a full disk
    leaves each file whole or as it was.  A file that fails does not stop the others; then ``SaveError``
    (an OSError) names it and what was saved.  The frame-fill seeds still waiting for a keyframe are
    not in ``map.ply`` unless ``finish`` ran.

    ``state``: also ``state.npz``, everything else the stages carry from frame to frame (the
    optimiser's moments and clocks, the mapper's statistics, the keyframe selector's reference, the
    motion model, the waiting seeds, the timers and convergence points), so that ``load`` continues
    exactly where this SLAM is: a run's checkpoint.  A checkpoint favours speed: its
    ``keyframes.npz`` is not compressed (ten 1200x680 keyframes: 0.2 s against 6 s compressed).
    Without ``state``, a ``state.npz`` of an earlier save in the folder is removed."""
    gathered: dict = {}
    failed: dict[str, Exception] = {}
    # each part's arrays are copies of their own, copied once: the trajectory and the keyframes are
    # gathered as new arrays, the map's columns as their live rows (GaussianMap.live_rows), the stages'
    # state as their state_dict's copies
    parts = {
        "trajectory.txt": slam.trajectory,
        "keyframes.npz": lambda: _keyframe_arrays(slam),
        "map.ply": lambda: (slam.map.to_numpy(), slam.map.num_sh),
        "config.yaml": lambda: slam.cfg,
    }
    if state:
        parts["state.npz"] = lambda: _state_arrays(slam)
    for name, gather in parts.items():
        try:
            gathered[name] = gather()
        except Exception as e:  # noqa: BLE001 (reported by write, with the files that were written)
            failed[name] = e
    writers = {
        "trajectory.txt": lambda path: write_tum_trajectory(path, *gathered["trajectory.txt"]),
        # a checkpoint's keyframes uncompressed (ten 1200x680 keyframes: 0.2 s against 6 s)
        "keyframes.npz": lambda path: _write_npz(path, gathered["keyframes.npz"], compress=not state),
        "map.ply": lambda path: write_ply(path, *gathered["map.ply"]),
        "config.yaml": lambda path: save_config(gathered["config.yaml"], path),
    }
    if state:
        # uncompressed: optimiser moments do not compress, and checkpoints are frequent
        writers["state.npz"] = lambda path: _write_npz(path, gathered["state.npz"], compress=False)
    return SlamSnapshot(writers, failed, state)


def _write_npz(path: Path, arrays: dict[str, np.ndarray], compress: bool) -> None:
    """``np.savez`` / ``np.savez_compressed``'s format (a zip of ``.npy`` files, read by ``np.load``),
    compressed at zlib's fastest level: float images barely compress, and level 1 writes an office's
    final keyframes 3.6x faster than ``savez_compressed``'s default for a third more bytes."""
    method, level = (zipfile.ZIP_DEFLATED, 1) if compress else (zipfile.ZIP_STORED, None)
    with atomic_write(path) as f, zipfile.ZipFile(f, "w", compression=method, compresslevel=level) as z:
        for name, array in arrays.items():
            with z.open(f"{name}.npy", "w", force_zip64=True) as member:
                np.lib.format.write_array(member, np.asanyarray(array), allow_pickle=False)


def _keyframe_arrays(slam) -> dict[str, np.ndarray]:
    """The keyframe buffer's arrays, each a new array (index arrays, stacks): no view of live memory.  A frame
    that an interrupt stopped in its keyframe's mapping has its keyframe but not yet its pose: it is left out, so
    that what was tracked loads."""
    kf, n = slam.keyframes, len(slam.poses)
    slots = [s for s in kf.slots() if kf.frame_ids[s] < n]
    return dict(
        frame_ids=kf.frame_ids[slots],
        poses=kf.poses[slots],
        exposure=kf.exposure[slots],
        rgb=np.stack([kf.rgb[s].numpy() for s in slots]) if slots else np.zeros((0,)),
        depth=np.stack([kf.depth[s].numpy() for s in slots]) if slots else np.zeros((0,)),
        slots=np.array(slots, dtype=np.int64),  # load puts each keyframe back in its slot
        keyframe_indices=np.array([i for i in slam.keyframe_indices if i < n], dtype=np.int64),
        frames=np.array(n),  # trajectory.txt's length: load tells a truncated one
        mapping_iters=np.array(slam.mapper.total_iters),  # the densification schedule's clock
        camera=np.array([slam.camera.fx, slam.camera.fy, slam.camera.cx, slam.camera.cy]),
        size=np.array([slam.camera.width, slam.camera.height]),
        first_pose=np.array(slam.T_first),
    )


def _state_arrays(slam) -> dict[str, np.ndarray]:
    if slam.mono_start is not None and slam.mono_start.frames:
        raise ValueError("the monocular bootstrap is waiting for parallax: its frames are not saved")
    n = len(slam.map)
    columns = [name for name in slam.map.column_names() if name not in GaussianMap.PARAMETERS]
    state = {f"map.{name}": slam.map.live_rows(name) for name in columns}
    for prefix, stage in (("selector.", slam.selector), ("tracker.", slam.tracker), ("mapper.", slam.mapper)):
        state.update({prefix + k: v for k, v in stage.state_dict().items()})
    state.update({f"seeder.{k}": v for k, v in slam.seeder.state_dict().items()})
    if slam.history is not None:
        state.update({f"history.{k}": v for k, v in slam.history.state_dict().items()})
    if slam.frame_views is not None:
        state.update({f"frame_views.{k}": v for k, v in slam.frame_views.state_dict().items()})
    meta = {
        "frames": len(slam.poses),
        "gaussians": n,
        "init_window_end": slam._init_window_end,
        "stats": dict(slam.stats),
        "convergence": slam.convergence,
        "budget": slam.budget.state_dict(),
        "mapping_iterations": slam.mapping_iterations,
    }
    state["slam.meta"] = np.array(json.dumps(meta))
    # the poses bit-exact (trajectory.txt's rotations pass through quaternions)
    state["slam.poses"], state["slam.timestamps"] = slam.trajectory()[1], np.array(slam.timestamps)
    return state


def _load_state(slam, path: Path) -> None:
    """Restore what ``_save_state`` wrote, onto a SLAM just loaded from the same folder."""
    state = _read_npz(path, ("slam.meta", "slam.poses", "slam.timestamps"))
    meta = json.loads(str(state["slam.meta"]))
    n = len(slam.map)
    if (meta["frames"], meta["gaussians"]) != (len(slam.poses), n):
        raise LoadError(
            f"{path}: saved with {meta['frames']} frames and {meta['gaussians']} Gaussians, the folder's "
            f"trajectory.txt and map.ply have {len(slam.poses)} and {n} (files of different saves?)"
        )
    for key, value in state.items():
        if not key.startswith("map."):
            continue
        name = key[len("map.") :]
        column = slam.map.column(name) if slam.map.has_column(name) else None
        if column is None or value.shape[0] != n:
            raise LoadError(f"{path}: column {name!r} does not fit this SLAM's map (another method?)")
        if n:
            column[:n].assign(value)
    for prefix, stage in (("selector.", slam.selector), ("tracker.", slam.tracker), ("mapper.", slam.mapper)):
        stage.load_state_dict({k[len(prefix) :]: v for k, v in state.items() if k.startswith(prefix)})
    slam.seeder.load_state_dict({k[len("seeder.") :]: v for k, v in state.items() if k.startswith("seeder.")})
    if slam.history is not None and "history.slots" in state:
        slam.history.load_state_dict({k[len("history.") :]: v for k, v in state.items() if k.startswith("history.")})
    if slam.frame_views is not None and "frame_views.kept" in state:
        views = {k[len("frame_views.") :]: v for k, v in state.items() if k.startswith("frame_views.")}
        slam.frame_views.load_state_dict(views)
    slam.poses, slam.timestamps = list(state["slam.poses"]), [float(t) for t in state["slam.timestamps"]]
    slam._init_window_end = int(meta["init_window_end"])
    slam.stats, slam.convergence = {**slam.stats, **meta["stats"]}, list(meta["convergence"])
    slam.budget.load_state_dict(meta["budget"])
    slam.mapping_iterations = dict(meta["mapping_iterations"])


def load_slam(cls, directory: str | Path, device=None):
    """A SLAM restored from ``save``: map, trajectory, keyframe buffer and the count of mapping
    iterations; tracking continues from the last pose.  The optimiser state starts afresh, unless
    the folder has the ``state.npz`` of ``save(..., state=True)``: then the SLAM goes on exactly as
    the saved one would have.  A missing, truncated or inconsistent file raises ``LoadError`` (or
    the reader's own ``PlyFormatError``, ``TrajectoryFormatError``, ``ConfigError``), naming the
    file and what is wrong."""
    directory = Path(directory)
    if not directory.is_dir():
        raise LoadError(f"{directory}: no such folder")
    for name in ("map.ply", "trajectory.txt", "keyframes.npz", "config.yaml"):
        if not (directory / name).is_file():
            raise LoadError(f"{directory / name}: missing (not a folder written by SLAM.save)")
    cfg = load_saved_config(directory / "config.yaml")
    data = _read_npz(directory / "keyframes.npz", (*_KEYFRAME_ARRAYS, "first_pose"))
    stamps, poses = read_tum_trajectory(directory / "trajectory.txt")
    _check_consistent(directory, data, len(poses))
    fx, fy, cx, cy = (float(v) for v in data["camera"])
    w, h = (int(v) for v in data["size"])
    slam = cls(cfg, Camera(fx, fy, cx, cy, w, h), device=device, T_first_WC=data["first_pose"])
    loaded = load_ply(directory / "map.ply", device=slam.device)
    if loaded.sh_degree != slam.map.sh_degree:
        raise LoadError(f"{directory / 'map.ply'}: SH degree {loaded.sh_degree}, config.yaml says {slam.map.sh_degree}")
    n = len(loaded)
    if n:
        slam.map.append(
            loaded.means[:n], loaded.rotations[:n], loaded.log_scales[:n], loaded.opacity_logits[:n], loaded.sh[:n]
        )
    slam.poses = list(poses)
    slam.timestamps = [float(t) for t in stamps]
    slam.keyframe_indices = [int(v) for v in data["keyframe_indices"]]
    for k, frame_id in enumerate(int(v) for v in data["frame_ids"]):
        depth = data["depth"][k] if cfg.mode == "rgbd" else None
        slot = int(data["slots"][k]) if "slots" in data else None
        slam.keyframes.add(frame_id, data["poses"][k], data["rgb"][k], depth, data["exposure"][k], slot=slot)
    if "mapping_iters" in data:  # folders saved before it was recorded start the count afresh
        slam.mapper.total_iters = int(data["mapping_iters"])
    if slam.keyframe_indices and slam.mono_start is not None:  # a monocular map: its start is done
        slam.mono_start, slam._init_window_end = None, 0
        # the keypoint odometry's tracks and landmarks are not saved (they follow the frames, which a
        # saved run no longer has): the resumed frames start tracking from the constant-velocity prediction
        slam.odometry = None
    if (directory / "state.npz").is_file():
        _load_state(slam, directory / "state.npz")
        return slam
    if slam.poses:
        slam.tracker.reset(slam.poses[-1], slam.poses[-2] if len(slam.poses) > 1 else None)
    if len(slam.keyframes):
        T_kf = slam.keyframes.poses[slam.keyframes.slots()[-1]]
        slam._select_at(slam.map, T_kf)
        slam.selector.accept(T_kf)
    return slam


class LoadError(ValueError):
    """A folder that ``SLAM.load`` cannot restore; the message names the file and what is wrong."""


_KEYFRAME_ARRAYS = ("frame_ids", "poses", "exposure", "rgb", "depth", "keyframe_indices", "camera", "size")


def _read_npz(path: Path, required: tuple[str, ...]) -> dict[str, np.ndarray]:
    """Every array of an ``.npz`` of ``save``, read now (a damaged member fails here, naming the file)."""
    try:
        with np.load(path) as z:
            data = {name: z[name] for name in z.files}
    except (zipfile.BadZipFile, zlib.error, EOFError, ValueError, OSError) as e:
        raise LoadError(f"{path}: not a readable archive (truncated or damaged?): {type(e).__name__}: {e}") from e
    missing = [name for name in required if name not in data]
    if missing:
        raise LoadError(f"{path}: arrays {', '.join(missing)} missing (not written by SLAM.save?)")
    return data


def _check_consistent(directory: Path, data: dict[str, np.ndarray], n_poses: int) -> None:
    """The keyframe archive against the trajectory: a file cut short by a copy shows up here."""
    k = len(data["frame_ids"])
    shapes = {name: data[name].shape[:1] for name in ("poses", "exposure")}
    if k and (data["rgb"].shape[:1] != (k,) or any(shape != (k,) for shape in shapes.values())):
        raise LoadError(f"{directory / 'keyframes.npz'}: {k} keyframe ids but arrays of other lengths")
    if "frames" in data and int(data["frames"]) != n_poses:
        raise LoadError(
            f"{directory / 'trajectory.txt'}: {n_poses} poses, keyframes.npz was saved with {int(data['frames'])} "
            "(truncated?)"
        )
    indices = data["keyframe_indices"]
    if len(indices) and int(indices.max()) >= n_poses:
        raise LoadError(
            f"{directory / 'trajectory.txt'}: {n_poses} poses, but frame {int(indices.max())} is a keyframe "
            "(truncated?)"
        )
