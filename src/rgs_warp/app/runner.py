"""A run of the SLAM system on a dataset, and the command line ``python -m rgs_warp.slam``: ``run``
tracks every frame with ``SLAM``, saves what it tracked (also when stopped), and evaluates it
(``evaluate_run``: ATE, photometric metrics on held-out frames, mesh metrics) into the run folder's
report and figures.
"""

from __future__ import annotations

import ctypes
import dataclasses
import importlib.util
import itertools
import json
import shutil
import sys
import threading
import time
from dataclasses import dataclass, field
from datetime import datetime
from pathlib import Path

import numpy as np
import warp as wp

from rgs_warp.compile import preload
from rgs_warp.config import (
    Config,
    ConfigError,
    config_from_dict,
    cpu_sized_overrides,
    help_text,
    load_config,
    load_saved_config,
    parse_yaml,
    resolve_device,
    save_config,
)
from rgs_warp.datasets import DatasetError, generates_scene, open_dataset
from rgs_warp.datasets.base import RGBDDataset
from rgs_warp.eval import (
    LPIPS,
    ate_keyframes_and_all,
    cached_alexnet_path,
    compensate_exposure,
    eval_frame_indices,
    metric_device,
    photometric_metrics,
    plot_trajectory_topview,
    psnr_raw_and_compensated,
    write_frame_scores,
    write_report,
)
from rgs_warp.io.atomic import SaveError, write_text_atomic
from rgs_warp.progress import KernelLoads, RunProgress, watch_kernel_loads
from rgs_warp.slam import SLAM

USAGE = """usage: python -m rgs_warp.slam [group=option ...] [key=value ...]
       python -m rgs_warp.slam resume=RUN_DIR [device=...] [data_root=...]

examples:
  python -m rgs_warp.slam                                  # generated synthetic room (CPU-sized without a GPU)
  python -m rgs_warp.slam cpu_sized=false                  # ... at its full size on the CPU too
  python -m rgs_warp.slam dataset=realsense/d435           # a RealSense camera (dataset.path=REC: a recording)
  python -m rgs_warp.slam method=baseline                  # the same with the dense initialization baseline
  python -m rgs_warp.slam dataset=replica/office0 data_root=/data tracking.iters=40
  python -m rgs_warp.slam dataset=7scenes/redkitchen dataset.path=../shared/data/7scenes-redkitchen
  python -m rgs_warp.slam run_name=office overwrite=true  # reuse runs/office (else runs/office-2, ...)
  python -m rgs_warp.slam resume=runs/office               # continue a stopped run from its checkpoint
  python -m rgs_warp.slam viewer=true                      # watch it in a browser (saved: python -m rgs_warp.view)
"""


class OutputError(OSError):
    """The run folder cannot be made, cleared or written; the message names it."""


def make_run_dir(cfg: Config) -> Path:
    """A new folder for a run, ``output_dir/run_name`` (default ``<dataset>-<date>-<time>``), never
    one another run uses: a name that exists gets ``-2``, ``-3``, ... (``mkdir`` fails on an existing
    folder, so two runs started in the same second cannot share one), unless ``overwrite`` is set with
    a ``run_name``: then the old run folder is cleared and reused.  Raises ``OutputError``."""
    base = Path(cfg.output_dir)
    name = cfg.run_name or f"{cfg.dataset.type}-{cfg.dataset.name}-{datetime.now():%Y%m%d-%H%M%S}"
    path = base / name
    try:
        base.mkdir(parents=True, exist_ok=True)
        if cfg.overwrite and cfg.run_name:
            if path.exists():
                _clear_run_dir(path)
            path.mkdir(exist_ok=True)
            return path
        for k in itertools.count(2):
            try:
                path.mkdir()
                return path
            except FileExistsError:
                path = base / f"{name}-{k}"
    except OSError as e:
        raise OutputError(f"cannot create the run folder {path}: {e.strerror or e}") from e
    raise AssertionError("unreachable")


def _clear_run_dir(path: Path) -> None:
    """Empty an old run folder for ``overwrite=true``, so no file of the old run (metrics, renders,
    checkpoints) sits beside the new one's; a folder that is not a run's is refused, not emptied."""
    if not path.is_dir():
        raise OutputError(f"cannot reuse {path} for the run: it is not a folder")
    children = list(path.iterdir())
    if children and not (path / "config.yaml").is_file():
        raise OutputError(f"overwrite=true refused: {path} is not a run folder (no config.yaml); remove it yourself")
    for child in children:
        if child.is_dir() and not child.is_symlink():
            shutil.rmtree(child)
        else:
            child.unlink()


# what the evaluation at the end of a run imports, and the pip name that provides it
EVALUATION_IMPORTS = {"torch": "torch", "pytorch_msssim": "pytorch-msssim"}


def check_evaluation_imports() -> None:
    """Refuse to start a run whose evaluation could not import what it needs (a run of minutes
    would otherwise end in a ModuleNotFoundError); an ``ImportError`` naming what to install."""
    missing = [pip for module, pip in EVALUATION_IMPORTS.items() if importlib.util.find_spec(module) is None]
    if missing:
        raise ImportError(
            f"the evaluation at the end of a run needs {', '.join(missing)}, which is not installed: "
            f"pip install {' '.join(missing)} (nothing was run)"
        )


def _own_run_dir(run_dir: Path) -> Path:
    """A run folder the caller chose (``run(cfg, run_dir=...)``, the eval suite): made if needed."""
    try:
        run_dir.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise OutputError(f"cannot create the run folder {run_dir}: {e.strerror or e}") from e
    return run_dir


def dataset_summary(ds) -> dict:
    c = ds.camera
    return {
        "dataset": repr(ds),
        "frames": None if _is_stream(ds) else len(ds),  # a stream's length is known at its end
        "resolution": [c.width, c.height],
        "intrinsics": {"fx": c.fx, "fy": c.fy, "cx": c.cx, "cy": c.cy},
    }


def ground_truth_mesh(cfg: Config, ds) -> Path | None:
    """The sequence's ground-truth mesh when there is one: the synthetic scenes' ``mesh.ply``, or
    Replica's ``<scene>_mesh.ply`` next to the scene folder (the NICE-SLAM layout)."""
    path = getattr(ds, "mesh_path", None)
    if path is not None and Path(path).is_file():
        return Path(path)
    if cfg.dataset.type == "replica":
        folder = cfg.dataset_path()
        candidate = folder.parent / f"{folder.name}_mesh.ply"
        if candidate.is_file():
            return candidate
    return None


def memory_mib(device) -> float | None:
    """GPU memory the run holds now (Warp's memory pool), in MiB; None on the CPU."""
    device = wp.get_device(device)
    if not device.is_cuda or not wp.is_mempool_enabled(device):
        return None
    return wp.get_mempool_used_mem_current(device) / 2**20


def peak_memory_mib(device) -> float | None:
    """The high-water mark of Warp's memory pool in MiB (since ``start_peak_memory``); None on the CPU."""
    device = wp.get_device(device)
    if not device.is_cuda or not wp.is_mempool_enabled(device):
        return None
    return wp.get_mempool_used_mem_high(device) / 2**20


# CUmemPool_attribute CU_MEMPOOL_ATTR_USED_MEM_HIGH (cuda.h): set to 0, the mark restarts at the memory in use
_CU_MEMPOOL_ATTR_USED_MEM_HIGH = 8


def _reset_mempool_high(ordinal: int) -> bool:
    """Reset the high-water mark of CUDA device ``ordinal``'s default memory pool (the pool Warp
    allocates from) through the CUDA driver; False where the driver or a call is missing or fails."""
    try:
        cuda = ctypes.CDLL("nvcuda.dll" if sys.platform == "win32" else "libcuda.so.1")
        dev, pool, zero = ctypes.c_int(), ctypes.c_void_p(), ctypes.c_uint64(0)
        return (
            cuda.cuDeviceGet(ctypes.byref(dev), ctypes.c_int(ordinal)) == 0
            and cuda.cuDeviceGetDefaultMemPool(ctypes.byref(pool), dev) == 0
            and cuda.cuMemPoolSetAttribute(pool, _CU_MEMPOOL_ATTR_USED_MEM_HIGH, ctypes.byref(zero)) == 0
        )
    except (OSError, AttributeError):
        return False


def start_peak_memory(device) -> float | None:
    """Start measuring a run's peak memory; returns the floor (MiB) a peak must exceed to be this run's
    (0 after a reset), None on the CPU.  The pool's high-water mark spans the process, and the suite
    runs several runs in one process (Ray reuses its workers too): without the reset every run after a
    bigger one reported that one's peak (session 12: 4801 MiB for 7-Scenes runs of 2.3 GiB).  Where the
    driver cannot reset it, a run that stays under the mark it found has no peak of its own to report."""
    device = wp.get_device(device)
    if not device.is_cuda or not wp.is_mempool_enabled(device):
        return None
    _reset_mempool_high(device.ordinal)
    high, current = wp.get_mempool_used_mem_high(device), wp.get_mempool_used_mem_current(device)
    return 0.0 if high <= current else high / 2**20


def run_peak_memory(device, floor_mib: float | None) -> tuple[float | None, str | None]:
    """(the run's peak memory in MiB, None) or (None, why it is n/a); ``floor_mib`` from ``start_peak_memory``."""
    mem = peak_memory_mib(device)
    if mem is None:
        return None, "measured on CUDA devices only (Warp's memory pool)"
    if floor_mib and mem <= floor_mib:
        return None, (
            f"an earlier run in this process left the memory pool's high-water mark at {floor_mib:.0f} MiB, "
            "above this run's peak, and the CUDA driver could not reset it"
        )
    return mem, None


@dataclass
class RunState:
    """What a run gathers besides the SLAM, checkpointed with it (``run_state.json``): the next frame
    to process (of ``frames_total``), the ground-truth poses of the frames so far (None where the
    dataset has none), their tracking losses and lost frames, the seconds spent, and the keyframe
    count at the last checkpoint."""

    next_frame: int = 0
    frames_total: int = 0
    gt_poses: list = field(default_factory=list)
    frame_losses: list[float] = field(default_factory=list)
    # each frame's affine exposure (gain, bias) as its tracking estimated it, None where it was not
    # tracked (the first frame, the monocular bootstrap's waiting ones, unusable input)
    exposures: list = field(default_factory=list)
    # each tracked frame's Adam steps until its pose stayed put (``TrackingResult.settled_iters``)
    settled_iters: list[int] = field(default_factory=list)
    tracked: int = 0  # frames tracked or lost (the first frame and the monocular bootstrap's waiting ones are not)
    # monocular: the keypoint odometry's result of each frame it gave a pose or tracking's start for:
    # [landmarks agreeing, rotation only, lost]
    odometry: list = field(default_factory=list)
    lost: list[tuple[int, str]] = field(default_factory=list)
    elapsed_s: float = 0.0
    checkpoint_keyframes: int = 0
    # seconds the frame loop spent waiting for the next frame (reading and decoding it), and gathering
    # the checkpoints' state (their files are written beside the run: CheckpointWriter)
    input_wait_s: float = 0.0
    checkpoint_s: float = 0.0

    def to_json(self) -> dict:
        data = dataclasses.asdict(self)
        data["gt_poses"] = [None if T is None else np.asarray(T).tolist() for T in self.gt_poses]
        return data

    @classmethod
    def from_json(cls, data: dict) -> RunState:
        state = cls(**data)
        state.gt_poses = [None if T is None else np.array(T, dtype=np.float64) for T in state.gt_poses]
        state.lost = [(int(i), str(reason)) for i, reason in state.lost]
        return state


CHECKPOINT = "checkpoint.json"  # in the run folder: the latest complete checkpoint's folder


def run(cfg: Config, run_dir: Path | None = None, progress: bool = True, source=None, viewer=None) -> tuple[Path, dict]:
    """Run SLAM on the configured sequence and evaluate it; returns (run folder, metrics).

    ``source``: frames from elsewhere instead of ``open_dataset(cfg)``: a ``CallbackSource`` (a ROS
    subscriber, a camera SDK; README, "Sensors") or any loader.  A stream (a source without random
    access, e.g. ``dataset.type=realsense``) has no checkpoints, and the run keeps host copies of the
    frames its evaluation reads again (the keyframes and every ``eval.every``-th frame).

    The folder (``make_run_dir``; made once the dataset opened, its first frame was read and the SLAM
    was built, so a run failing at start-up leaves none) gets: ``config.yaml``, ``dataset.json``,
    ``trajectory.txt`` (TUM, readable by evo), ``map.ply`` (3DGS layout), ``keyframes.npz``,
    ``metrics.json`` + ``metrics.md``, ``trajectory_topview.png``, ``renders/*.png`` (render | ground
    truth side by side), ``log.jsonl`` (one line per frame) and ``convergence.json`` +
    ``convergence.png`` (``SLAM.convergence``: window PSNR against the cumulative mapping iterations).
    While it runs, a checkpoint every ``checkpoint_every`` keyframes (``write_checkpoint``), removed
    when the run finished.  If the run stops early (error, Ctrl-C, SIGTERM), what was tracked so far is
    still saved, and the error is re-raised; ``resume(run_dir)`` continues it from its last checkpoint.
    The progress bar names the phase (generating the scene, compiling kernels, tracking, evaluating).

    ``viewer``: an ``rgs_warp.view.Viewer`` whose ``update`` runs after each frame (its time per frame is
    ``viewer_seconds`` in ``log.jsonl``); by default, with ``cfg.viewer``, one opened for this run and
    closed at its end (the command line keeps its own open after the run).
    """
    if cfg.checkpoint_every < 0:
        raise ValueError(f"checkpoint_every must be >= 0 (0 = no checkpoints), got {cfg.checkpoint_every}")
    check_evaluation_imports()
    if viewer is None and cfg.viewer:
        from rgs_warp.view import open_viewer

        with open_viewer(cfg.viewer_port) as viewer:
            return run(cfg, run_dir, progress, source, viewer)
    device = resolve_device(cfg.device)
    bar = RunProgress(getattr(source, "name", f"{cfg.dataset.type}/{cfg.dataset.name}"), enabled=progress)
    with watch_kernel_loads(bar.kernel_load) as kernels:
        try:
            preload(device)  # on a GPU: every kernel module now, in parallel, not one by one as reached
            if source is None:
                bar.phase("generating the scene (first use)" if generates_scene(cfg) else "opening the dataset")
            ds = open_dataset(cfg, device=device) if source is None else source
            frames = None
            if _is_stream(ds):
                bar.phase("waiting for the first frame")
                frames = iter(ds)
                first = next(frames, None)
                if first is None:
                    raise DatasetError(f"{ds!r}: no frame came")
                frames = itertools.chain([first], frames)
            else:
                first = ds[0]
            bar.phase("starting")
            slam = SLAM(cfg, ds.camera, device=device, T_first_WC=first.pose_gt)
            run_dir = make_run_dir(cfg) if run_dir is None else _own_run_dir(Path(run_dir))
            if progress and cfg.run_name and run_dir.name != cfg.run_name:
                bar.write(f"note: {Path(cfg.output_dir) / cfg.run_name} exists; this run writes {run_dir}", sys.stderr)
            try:
                save_config(cfg, run_dir / "config.yaml")
                write_text_atomic(run_dir / "dataset.json", json.dumps(dataset_summary(ds), indent=2))
            except OSError as e:
                raise OutputError(f"cannot write into the run folder {run_dir}: {e.strerror or e}") from e
        except BaseException:
            bar.close()
            raise
        state = RunState(frames_total=0 if frames is not None else len(ds))
        return _run_frames(cfg, ds, slam, run_dir, state, bar, kernels, frames, viewer)


class Playback:
    """A recorded sequence handed to the SLAM as a live camera at ``fps`` would deliver it
    (``dataset.playback_fps``): ``wait`` before each frame sleeps until that frame is due (the k-th
    frame since the first at k / fps s after it); ``taken`` after the SLAM returned the frame records
    how late its result came (lag: 0 while the SLAM keeps pace, growing while it falls behind; no frame
    is dropped); ``slept_s``: the seconds ``wait`` slept (the run's ``input_wait_s`` is the loader's
    alone)."""

    def __init__(self, fps: float):
        self.period = 1.0 / fps
        self.fps = fps
        self._t0: float | None = None
        self._due = 0.0
        self.lags: list[float] = []
        self.slept_s = 0.0

    def wait(self) -> None:
        now = time.perf_counter()
        if self._t0 is None:
            self._t0 = now
        self._due = self._t0 + len(self.lags) * self.period
        if self._due > now:
            time.sleep(self._due - now)
            self.slept_s += self._due - now

    def taken(self) -> float:
        lag = max(0.0, time.perf_counter() - self._due)
        self.lags.append(lag)
        return lag

    def summary(self) -> dict:
        """``metrics.json``'s ``playback``: the rate, and the frames' lag (ms) at p50 / p99 / worst / last;
        ``kept_pace``: the last frame's result came within two frame periods of its frame; ``slept_s``."""
        lag = np.array(self.lags) * 1e3 if self.lags else np.zeros(1)
        return {
            "fps": self.fps,
            "lag_ms_p50": float(np.percentile(lag, 50)),
            "lag_ms_p99": float(np.percentile(lag, 99)),
            "lag_ms_max": float(lag.max()),
            "lag_ms_last": float(lag[-1]),
            "kept_pace": bool(lag[-1] <= 2e3 * self.period),
            "slept_s": self.slept_s,
        }


def _is_stream(ds) -> bool:
    """A frame source without random access (``CallbackSource``, ``RealSenseSource``)."""
    return not hasattr(ds, "__getitem__")


def read_frames(ds, indices):
    """``ds[i]`` for each of ``indices``, read ahead in background threads where ``ds`` is a dataset
    (``RGBDDataset.frames``; a stream's ``KeptFrames`` holds the frames already)."""
    return ds.frames(indices) if isinstance(ds, RGBDDataset) else (ds[int(i)] for i in indices)


class KeptFrames:
    """The frames of a stream that a run's evaluation reads again (``ds[i]``), kept as they pass."""

    def __init__(self, camera):
        self.camera = camera
        self._by_index: dict[int, object] = {}

    def keep(self, index: int, frame) -> None:
        self._by_index[index] = frame

    def __getitem__(self, i: int):
        return self._by_index[i]


def _run_frames(
    cfg: Config,
    ds,
    slam: SLAM,
    run_dir: Path,
    state: RunState,
    bar: RunProgress,
    kernels: KernelLoads,
    stream=None,
    viewer=None,
) -> tuple[Path, dict]:
    """Frames ``state.next_frame`` .. the end through ``slam`` (checkpoints on the way), then the final
    save and the evaluation; what ``run`` and ``resume`` share.  ``stream``: the frames of a stream
    (``ds`` is then its source; no checkpoints).  Closes ``bar``."""
    t_start = time.perf_counter() - state.elapsed_s
    peak_floor = start_peak_memory(slam.device)
    bar.start_frames(None if stream is not None else len(ds), state.next_frame)
    # a line per frame, readable while it runs; a resumed run appends to the lines up to its checkpoint
    log = (run_dir / "log.jsonl").open("a" if state.next_frame else "w", encoding="utf-8", buffering=1)
    if stream is not None:
        frames, kept = stream, KeptFrames(ds.camera)
    else:
        frames = read_frames(ds, range(state.next_frame, len(ds)))
        kept = None
    playback = Playback(cfg.dataset.playback_fps) if cfg.dataset.playback_fps > 0 else None
    # a stream cannot be read again to resume; a played sequence is run as a live stream, whose
    # camera would not wait for a checkpoint's copy of the map (0.3-0.5 s on a 1M-Gaussian map)
    checkpoints = cfg.checkpoint_every if kept is None and playback is None else 0
    writer = CheckpointWriter(run_dir, warn=bar.write)
    frames = iter(frames)
    try:
        while True:
            t_wait = time.perf_counter()
            frame = next(frames, None)
            state.input_wait_s += time.perf_counter() - t_wait
            if frame is None:
                break
            if playback is not None:
                playback.wait()  # the camera has not delivered the frame yet
            waiting = slam.bootstrap is not None  # monocular: the bootstrap has not built the map yet
            result = slam.process(frame.rgb, frame.depth if cfg.mode == "rgbd" else None, frame.timestamp)
            lag = None if playback is None else playback.taken()
            state.gt_poses.append(frame.pose_gt)
            state.next_frame = result.index + 1
            scored_later = result.keyframe or result.index % cfg.eval.every == 0 or slam.bootstrap is not None
            if kept is not None and scored_later:
                kept.keep(result.index, frame)
            entry = _log_entry(cfg, slam, result, state)
            if lag is not None:
                entry["lag_s"] = round(lag, 4)
            if waiting and slam.bootstrap is None and slam.bootstrap_fallback:  # said at once, not after the run
                bar.write(f"warning: {slam.bootstrap_fallback}", file=sys.stderr)
            if viewer is not None:
                t_view = time.perf_counter()
                viewer.update(slam, result, frame.rgb, state.gt_poses, len(state.lost))
                entry["viewer_seconds"] = round(time.perf_counter() - t_view, 5)
            log.write(json.dumps(entry) + "\n")
            if result.keyframe and 0 < checkpoints <= len(slam.keyframe_indices) - state.checkpoint_keyframes:
                state.checkpoint_keyframes = len(slam.keyframe_indices)
                state.elapsed_s = time.perf_counter() - t_start
                t_checkpoint = time.perf_counter()
                writer.write(slam, state)
                state.checkpoint_s += time.perf_counter() - t_checkpoint
            elapsed = time.perf_counter() - t_start
            postfix = dict(
                fps=f"{(result.index + 1) / elapsed:.2f}",
                kf=len(slam.keyframe_indices),
                gaussians=len(slam.map),
                loss=f"{state.frame_losses[-1]:.4f}" if state.frame_losses else "-",
                lost=len(state.lost),
            )
            if lag is not None:  # dataset.playback_fps: how far behind the camera this frame's result came
                postfix["lag"] = f"{lag:.2f}s"
            bar.set_postfix(**postfix)
            bar.update(1)
    except BaseException as stop:  # an error, Ctrl-C or SIGTERM: save what was tracked, then stop as asked
        bar.close()
        log.close()
        writer.close()
        try:
            _save_run(cfg, slam, run_dir, refine=False).write()  # a stopped run saves at once
        except Exception as e:  # noqa: BLE001 (the error that stopped the run is the one raised)
            print(f"error: the run stopped, and saving what it tracked failed: {e}", file=sys.stderr)
        else:
            if isinstance(stop, KeyboardInterrupt | SystemExit):
                again = (
                    f"; python -m rgs_warp.slam resume={run_dir} continues it"
                    if (run_dir / CHECKPOINT).is_file()
                    else ""
                )
                print(
                    f"stopped at frame {state.next_frame}: what was tracked is saved in {run_dir}{again}",
                    file=sys.stderr,
                )
        raise
    log.close()
    writer.close()
    save = None
    try:
        bar.phase("saving" if cfg.mapping.final_iters <= 0 else "final refinement, saving")
        # the map and keyframes are copied to the host now and written while the run is evaluated
        save = _save_run(cfg, slam, run_dir)
        wall = time.perf_counter() - t_start
        save.start()
        bar.phase("evaluating")
        tracking = tracking_section(state.tracked, state.lost, state.settled_iters, cfg.tracking.iters)
        if state.odometry:  # how the monocular front end held up: where it had too few landmarks for PnP
            inliers, rotation_only, lost = np.array(state.odometry, dtype=float).T
            tracking["odometry"] = {
                "frames": len(inliers),
                "inliers_p10": float(np.percentile(inliers, 10)),
                "inliers_p50": float(np.percentile(inliers, 50)),
                "rotation_only_frames": int(rotation_only.sum()),
                "lost_frames": int(lost.sum()),
            }
        # frames whose steps this process ran eagerly, captured (after one sizing step) and replayed
        # (tracking.graph; a captured frame is also replayed), and replays
        # that overflowed their graph's intersection buffers (tracked again eagerly)
        tracking.update({f"graph_{k}": v for k, v in slam.tracker.graph_counts.items()})
        scored = ds if kept is None else kept
        loop = {
            "input_wait_s": state.input_wait_s,
            "checkpoints_s": state.checkpoint_s,
            "checkpoint_writes_s": writer.seconds,
        }
        metrics = evaluate_run(
            cfg,
            scored,
            slam,
            state.gt_poses,
            run_dir,
            wall,
            tracking,
            kernels.summary(),
            peak_floor,
            state.exposures,
            loop_s=loop,
            save=save,
            playback=None if playback is None else playback.summary(),
        )
    except OSError as e:
        if isinstance(e, SaveError):
            raise
        saved = "trajectory.txt, keyframes.npz, map.ply, config.yaml, convergence.json"
        raise OutputError(f"{run_dir}: writing the report failed ({e}); saved before it: {saved}") from e
    finally:
        if save is not None:
            save.join()  # an evaluation that failed still leaves the saved files whole
        bar.close()
    remove_checkpoints(run_dir)
    return run_dir, metrics


def _log_entry(cfg: Config, slam: SLAM, result, state: RunState) -> dict:
    """A frame's line of ``log.jsonl``; records its tracking loss and loss of tracking in ``state``."""
    entry = {
        "frame": result.index,
        "keyframe": result.keyframe,
        "reason": result.keyframe_reason,
        "seconds": round(result.seconds, 4),
        "tracking_seconds": round(result.tracking_seconds, 4),
        "gaussians": len(slam.map),
    }
    memory = memory_mib(slam.device)
    if memory is not None:
        entry["memory_mib"] = round(memory, 1)
    tracking = result.tracking
    if tracking is not None:
        entry.update(loss=tracking.loss, lost=tracking.lost, gain=tracking.gain, bias=tracking.bias)
        entry["settled_iters"] = tracking.settled_iters
        if tracking.steps in ("captured", "overflowed"):  # a new map version's graphs, a replay run again
            entry["steps"] = tracking.steps
        entry["valid_ratio"] = round(tracking.valid_ratio, 4)  # the map's coverage of the frame
        state.frame_losses.append(tracking.loss)
        state.settled_iters.append(tracking.settled_iters)
    state.exposures.append(None if tracking is None else [tracking.gain, tracking.bias])
    state.tracked += result.tracking is not None or result.lost
    if result.lost:  # tracking lost, or the frame's input unusable (then not tracked)
        entry.update(lost=True, lost_reason=result.lost_reason)
        state.lost.append((result.index, result.lost_reason))
    odometry = result.odometry
    if odometry is not None:  # monocular: where tracking started, or the pose (keypoint_odometry.py)
        entry["odometry_inliers"] = odometry.inliers
        state.odometry.append([odometry.inliers, odometry.rotation_only, odometry.T_WC is None])
        if odometry.T_WC is None or odometry.rotation_only:
            entry["odometry"] = odometry.reason or ("lost" if odometry.T_WC is None else "rotation only")
    for key in ("nonfinite_rgb", "nonfinite_depth"):
        if getattr(result, key):
            entry[key] = getattr(result, key)
    if result.keyframe:
        entry.update(seeded=result.seeded, pruned=result.pruned, merged=result.merged)
        if result.mapping is not None and result.mapping.iters:
            entry["mapping_l1"] = result.mapping.final_l1
        if cfg.method == "baseline" and result.mapping is not None:
            entry.update(cloned=result.mapping.cloned, split=result.mapping.split)
    elif result.seeded:  # frame fill: seeds waiting for the next keyframe
        entry["seeded"] = result.seeded
    if cfg.mapping.asynchronous:
        entry["fills_waiting"] = result.fills_waiting  # the worker's backlog of frame fills
    return entry


def _save_run(cfg: Config, slam: SLAM, run_dir: Path, refine: bool = True) -> FinalSave:
    """The end of a run: the waiting frame-fill seeds join the map (and ``refine``: the final
    refinement of ``mapping.final_iters``), the convergence files, and what ``SLAM.save`` writes
    gathered into host memory: the returned ``FinalSave`` writes it (``start`` in a thread, ``write``
    here); one ``SaveError`` names what failed and what was saved."""
    slam.finish(refine)
    failed = {}
    try:
        write_convergence(run_dir, slam.convergence, title=f"{cfg.dataset.type}/{cfg.dataset.name} ({cfg.method})")
    except OSError as e:
        failed["convergence.json"] = e
    return FinalSave(run_dir, slam.snapshot(), failed)


class FinalSave:
    """A run's last ``SLAM.save`` (``trajectory.txt``, ``keyframes.npz``, ``map.ply``, ``config.yaml``), from
    a snapshot: ``start`` writes it in a thread (the compressed keyframes of a 1200x680 run take seconds)
    while the run is evaluated, ``write`` waits for it, or writes it here if not started, and raises
    the ``SaveError`` naming what failed.  ``seconds``: the writing's."""

    def __init__(self, run_dir: Path, snapshot, failed: dict):
        self.run_dir, self.snapshot, self.failed = run_dir, snapshot, failed
        self.seconds = 0.0
        self._thread: threading.Thread | None = None
        self._error: BaseException | None = None

    def _write(self) -> None:
        t0 = time.perf_counter()
        try:
            self.snapshot.write(self.run_dir)
        except BaseException as e:  # noqa: BLE001 (raised again by write, in the run's thread)
            self._error = e
        self.seconds = time.perf_counter() - t0

    def start(self) -> None:
        self._thread = threading.Thread(target=self._write, name="rgs-save", daemon=False)
        self._thread.start()

    def join(self) -> None:
        if self._thread is not None:
            self._thread.join()

    def write(self) -> None:
        if self._thread is None:
            self._write()
        self.join()
        failed = dict(self.failed)
        if self._error is not None and not isinstance(self._error, SaveError):
            raise self._error
        if self._error is not None:
            failed.update(self._error.failed)
        if failed:
            names = ["trajectory.txt", "keyframes.npz", "map.ply", "config.yaml", "convergence.json"]
            raise SaveError(self.run_dir, [n for n in names if n not in failed], failed)


class CheckpointWriter:
    """A run's checkpoints, written beside it: ``write`` gathers the SLAM's state into host memory (the
    only part in the frame's time; ``SLAM.snapshot``) and returns; a thread then writes the folder
    ``checkpoints/frameNNNNNN/`` (``SLAM.save(..., state=True)``'s files and ``run_state.json``),
    replaces ``checkpoint.json`` to name it, and removes the older ones, in that order, so a kill at any
    moment leaves ``checkpoint.json`` naming a complete checkpoint.  One checkpoint at a time: ``write``
    first waits for the one before, ``close`` for the last.  A checkpoint that cannot be written (full
    disk) is reported through ``warn`` and the run goes on.  ``seconds``: the writing's, in the thread."""

    def __init__(self, run_dir: Path, warn=None):
        self.run_dir, self.warn = run_dir, warn or print
        self.seconds = 0.0
        self._thread: threading.Thread | None = None

    def write(self, slam: SLAM, state: RunState) -> None:
        self.close()
        snapshot = slam.snapshot(state=True, hurry=True)  # live: the camera does not wait for full windows
        run_state = json.dumps(state.to_json(), default=_plain)
        self._thread = threading.Thread(
            target=self._write, args=(snapshot, run_state, state.next_frame), name="rgs-checkpoint", daemon=False
        )
        self._thread.start()

    def close(self) -> None:
        if self._thread is not None:
            self._thread.join()
            self._thread = None

    def _write(self, snapshot, run_state: str, next_frame: int) -> None:
        t0 = time.perf_counter()
        write_checkpoint(self.run_dir, snapshot, run_state, next_frame, warn=self.warn)
        self.seconds += time.perf_counter() - t0


def write_checkpoint(run_dir: Path, snapshot, run_state: str, next_frame: int, warn=None) -> Path | None:
    """A checkpoint of the run in ``run_dir``: ``checkpoints/frameNNNNNN/`` gets the files of the
    snapshot (``SLAM.snapshot(state=True)``) and ``run_state.json`` (``RunState.to_json``, as JSON),
    then ``checkpoint.json`` is replaced to name it (each file written atomically), then the older
    checkpoints go.  A kill at any moment leaves ``checkpoint.json`` naming a complete checkpoint.  A
    checkpoint that cannot be written (full disk) is reported through ``warn`` and the run goes on;
    returns its folder or None."""
    folder = run_dir / "checkpoints" / f"frame{next_frame:06d}"
    try:
        if folder.exists():  # the leftover of a checkpoint that failed before its pointer was written
            shutil.rmtree(folder)
        snapshot.write(folder)
        write_text_atomic(folder / "run_state.json", run_state)
        pointer = {"folder": str(folder.relative_to(run_dir)), "next_frame": next_frame}
        write_text_atomic(run_dir / CHECKPOINT, json.dumps(pointer) + "\n")
    except OSError as e:
        shutil.rmtree(folder, ignore_errors=True)
        (warn or print)(f"warning: checkpoint at frame {next_frame} not written ({e}); the run goes on")
        return None
    for old in (run_dir / "checkpoints").iterdir():
        if old != folder:
            shutil.rmtree(old, ignore_errors=True)
    return folder


def _plain(value):
    """NumPy scalars as Python numbers for ``json.dumps`` (which keeps NaN and inf, unlike strict JSON:
    a lost frame's loss may be either)."""
    if isinstance(value, np.generic):
        return value.item()
    raise TypeError(f"{type(value).__name__} is not JSON serialisable")


def remove_checkpoints(run_dir: Path) -> None:
    """A finished run's checkpoints go (its folder holds the final state): the pointer first, so it
    never names a folder that is gone."""
    (run_dir / CHECKPOINT).unlink(missing_ok=True)
    shutil.rmtree(run_dir / "checkpoints", ignore_errors=True)


class ResumeError(ValueError):
    """A run folder that cannot be resumed; the message says why."""


# what `resume=RUN_DIR` lets the command line change: where the run computes, where its data is and
# whether a browser watches it, never what it computes (docs/decisions.md, "Resuming a run")
RESUME_OVERRIDES = ("device", "data_root", "viewer", "viewer_port")


def resume_config(run_dir: str | Path, overrides: list[str] | tuple[str, ...] = ()) -> Config:
    """The config a resumed run goes on with: ``run_dir/config.yaml`` with ``overrides`` (``key=value``
    of ``RESUME_OVERRIDES`` only); ``ResumeError`` for a folder that is not a run's or has nothing to
    resume."""
    run_dir = Path(run_dir)
    if not (run_dir / "config.yaml").is_file():
        raise ResumeError(f"{run_dir}: not a run folder (no config.yaml)")
    if not (run_dir / CHECKPOINT).is_file():
        why = "the run finished" if (run_dir / "metrics.json").is_file() else "no checkpoint"
        raise ResumeError(
            f"{run_dir}: nothing to resume ({why}; a run writes a checkpoint every checkpoint_every keyframes)"
        )
    cfg = load_saved_config(run_dir / "config.yaml")
    for item in overrides:
        key, _, value = item.partition("=")
        key = key.strip()
        if key not in RESUME_OVERRIDES or not value:
            raise ConfigError(
                f"resume: {item!r} refused; a resumed run keeps its config.yaml and may only set "
                f"{', '.join(k + '=...' for k in RESUME_OVERRIDES)}"
            )
        # the names as given (device=cuda:0, a folder), the viewer's values read as YAML and checked
        text = isinstance(getattr(cfg, key), str)
        cfg = config_from_dict({**cfg.to_dict(), key: value.strip() if text else parse_yaml(value)})
    return cfg


def resume(
    run_dir: str | Path, overrides: list[str] | tuple[str, ...] = (), progress: bool = True, viewer=None
) -> tuple[Path, dict]:
    """Continue a stopped run (killed, out of time) from its last checkpoint in ``run_dir``, with the
    config of ``run_dir/config.yaml``; ``overrides`` may set only ``RESUME_OVERRIDES``.  The frames
    after the checkpoint are processed again (their lines in ``log.jsonl`` are replaced); the run then
    ends as ``run`` does, in the same folder.  The checkpoint holds the whole SLAM state (optimiser
    included), so on the same device the run goes on as if it had not stopped.  ``viewer``: as ``run``'s."""
    run_dir, pointer = Path(run_dir), Path(run_dir) / CHECKPOINT
    cfg = resume_config(run_dir, overrides)
    if viewer is None and cfg.viewer:
        from rgs_warp.view import open_viewer

        with open_viewer(cfg.viewer_port) as viewer:
            return resume(run_dir, overrides, progress, viewer)
    try:
        folder = run_dir / json.loads(pointer.read_text(encoding="utf-8"))["folder"]
        state = RunState.from_json(json.loads((folder / "run_state.json").read_text(encoding="utf-8")))
    except (OSError, ValueError, KeyError, TypeError) as e:
        raise ResumeError(f"{pointer}: the checkpoint it names cannot be read: {type(e).__name__}: {e}") from e
    device = resolve_device(cfg.device)
    bar = RunProgress(f"{cfg.dataset.type}/{cfg.dataset.name}", enabled=progress)
    with watch_kernel_loads(bar.kernel_load) as kernels:
        try:
            preload(device)
            bar.phase("opening the dataset")
            ds = open_dataset(cfg, device=device)
            if _is_stream(ds):
                raise ResumeError(f"{run_dir}: its frames came from a stream ({ds!r}), which cannot be read again")
            if len(ds) != state.frames_total:
                raise ResumeError(f"{run_dir}: the dataset has {len(ds)} frames now, the run had {state.frames_total}")
            bar.phase("loading the checkpoint")
            slam = SLAM.load(folder, device=device)
            if len(slam.poses) != state.next_frame:
                raise ResumeError(f"{folder}: {len(slam.poses)} poses, run_state.json says {state.next_frame} frames")
            lines = (run_dir / "log.jsonl").read_text(encoding="utf-8").splitlines(keepends=True)
            write_text_atomic(run_dir / "log.jsonl", "".join(lines[: state.next_frame]))
        except BaseException:
            bar.close()
            raise
        return _run_frames(cfg, ds, slam, run_dir, state, bar, kernels, viewer=viewer)


def tracking_section(
    tracked: int, lost: list[tuple[int, str]], settled: list[int] | None = None, iters: int | None = None
) -> dict:
    """The report's ``tracking`` section: how many of the ``tracked`` frames were lost (``lost``: frame
    index and the tracker's reason of each) and the first of them; with ``settled`` (each tracked
    frame's ``settled_iters``) their median and 90th percentile against the ``iters`` steps taken."""
    section: dict = {"tracked_frames": tracked, "lost_frames": len(lost)}
    if settled:
        section["settled_iters_p50"] = float(np.percentile(settled, 50))
        section["settled_iters_p90"] = float(np.percentile(settled, 90))
        section["iters"] = iters
    if lost:
        section["first_lost_frame"], section["first_lost_reason"] = lost[0]
    else:
        section["first_lost_frame"] = section["first_lost_reason"] = None
        section["first_lost_frame_na_reason"] = section["first_lost_reason_na_reason"] = "never lost"
    return section


def write_convergence(run_dir: Path, points: list[dict], title: str) -> None:
    """``convergence.json`` (the points of ``SLAM.convergence``) and ``convergence.png``: the window's
    PSNR against the cumulative mapping iterations (initialization samples joined by a line, one
    marker per keyframe's mapping after it) with the number of Gaussians on a second axis."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    (run_dir / "convergence.json").write_text(json.dumps(points, indent=1) + "\n", encoding="utf-8")
    fig, ax = plt.subplots(figsize=(7.0, 4.0), dpi=150)
    count_ax = ax.twinx()
    for phase, style in (("init", "-o"), ("keyframe", "s")):
        shown = [p for p in points if p["phase"] == phase and p["psnr_db"] is not None]
        label = "initialization window" if phase == "init" else "window after a keyframe's mapping"
        ax.plot([p["iteration"] for p in shown], [p["psnr_db"] for p in shown], style, markersize=3, label=label)
    count_ax.plot([p["iteration"] for p in points], [p["gaussians"] for p in points], color="gray", linewidth=0.8)
    count_ax.set_ylabel("Gaussians", color="gray")
    ax.set_xlabel("mapping iterations (cumulative)")
    ax.set_ylabel("mean window PSNR (dB)")
    ax.set_title(title)
    ax.grid(True, linewidth=0.3)
    ax.legend(loc="lower right", fontsize=8)
    fig.tight_layout()
    fig.savefig(run_dir / "convergence.png")
    plt.close(fig)


def evaluate_run(
    cfg: Config,
    ds,
    slam: SLAM,
    gt_poses: list,
    run_dir: Path,
    wall_s: float,
    tracking: dict | None = None,
    kernels: dict | None = None,
    peak_floor_mib: float | None = 0.0,
    exposures: list | None = None,
    loop_s: dict | None = None,
    save: FinalSave | None = None,
    playback: dict | None = None,
) -> dict:
    """Metrics of a finished run (supplement §3) written with ``write_report``; ``tracking``: the
    section of ``tracking_section``; ``kernels``: ``KernelLoads.summary()`` (the seconds the run spent
    compiling Warp kernels, part of ``wall_s``); ``peak_floor_mib``: ``start_peak_memory``'s floor;
    ``exposures``: each frame's tracked (gain, bias) (``RunState.exposures``), for the scores at the
    tracked exposure; ``loop_s``: more seconds for ``time_s`` (the frame loop's waits); ``save``: the
    run's final save, written meanwhile: waited for (its ``SaveError`` raised) before the report, its
    seconds ``time_s.save_s``; ``playback``: ``Playback.summary()`` of a run played at
    ``dataset.playback_fps``.  ``time_s.evaluation_s``: this evaluation's seconds, up to the report (the
    final save's wait not included)."""
    t_start = time.perf_counter()
    _, est = slam.trajectory()
    n = len(est)
    metrics: dict = {
        "dataset": f"{cfg.dataset.type}/{cfg.dataset.name}",
        "method": cfg.method,
        "mode": cfg.mode,
        "device": str(slam.device),
        "frames": n,
        "keyframes": len(slam.keyframe_indices),
        "gaussians": len(slam.map),
        "fps": n / wall_s if wall_s > 0 else None,
        "tracking_fps": (n - 1) / slam.stats["tracking_s"] if slam.stats["tracking_s"] > 0 else None,
        "wall_s": wall_s,
    }
    metrics["peak_memory_mib"], reason = run_peak_memory(slam.device, peak_floor_mib)
    if reason:
        metrics["peak_memory_mib_na_reason"] = reason
    if metrics["tracking_fps"] is None:
        metrics["tracking_fps_na_reason"] = "a single frame"
    metrics["time_s"] = {k: v for k, v in slam.stats.items() if k.endswith("_s")}
    metrics["mapping_iterations"] = slam.mapper.total_iters
    # renders of the mapping renderer (mapping, seeding) found to have dropped intersections
    metrics["mapping_renders_overflowed"] = slam.renderer.overflowed_renders
    # mapping steps run eagerly, captured and replayed (mapping.graph), replays that overflowed
    metrics["mapping_graph_steps"] = dict(slam.mapper.graph_counts)
    metrics["mapping"] = "asynchronous" if cfg.mapping.asynchronous else "synchronous"
    # tracked frames that wanted a frame fill, and those that got none (mapping.fill_queue, asynchronous)
    metrics["frame_fills"] = dict(slam.frame_fills)
    if playback is not None:
        metrics["playback"] = playback
    if slam.keyframe_latency_s:  # asynchronous: from a keyframe's tracking to its map published
        lat = np.array(slam.keyframe_latency_s)
        metrics["keyframe_to_map_s"] = {
            "count": len(lat),
            "p50": float(np.median(lat)),
            "p99": float(np.percentile(lat, 99)),
            "max": float(lat.max()),
        }
    if kernels is not None:
        metrics["kernels"] = kernels
    if slam.final_refinement is not None:  # mapping.final_iters: reported apart from the run's mapping
        metrics["final_refinement"] = slam.final_refinement
    if tracking is not None:
        metrics["tracking"] = tracking
    has_gt = all(p is not None for p in gt_poses) and n >= 3
    if has_gt:
        gt = np.array(gt_poses)
        align = "sim3" if cfg.mode == "mono" else "se3"
        metrics["ate"] = ate_keyframes_and_all(est, gt, np.array(slam.keyframe_indices), align=align)
        for section in metrics["ate"].values():
            if isinstance(section, dict):
                section.pop("align_T", None)
        plot_trajectory_topview(est, gt, run_dir / "trajectory_topview.png", title=metrics["dataset"], align=align)
    else:
        metrics["ate"] = None
        metrics["ate_na_reason"] = "no ground-truth poses" if n >= 3 else "fewer than 3 frames"
        if n >= 2:
            plot_trajectory_topview(est, None, run_dir / "trajectory_topview.png", title=metrics["dataset"])
    # photometric metrics: every eval.every-th frame, keyframes excluded (§3), rendered at the estimate
    idx = eval_frame_indices(n, slam.keyframe_indices, cfg.eval.every)
    renders, refs, alphas, depths, ref_depths = [], [], [], [], []
    for i, frame in zip(idx, read_frames(ds, idx), strict=True):
        res = slam.render(est[i])
        renders.append(np.clip(res.color.numpy(), 0.0, 1.0))
        refs.append(frame.rgb)
        alphas.append(res.alpha.numpy().copy())
        if frame.depth is not None and cfg.mode == "rgbd":  # monocular depth has the map's own scale
            alpha = alphas[-1]
            depths.append(np.where(alpha > 0.5, res.depth.numpy() / np.maximum(alpha, 1e-6), 0.0))
            ref_depths.append(frame.depth)
    if renders:
        alexnet = cfg.eval.lpips_alexnet_path or cached_alexnet_path()
        on = metric_device(slam.device)
        lpips = LPIPS(alexnet, cfg.eval.lpips_linear_path or None, device=on or "cpu")
        tracked = None
        if exposures is not None and len(exposures) >= n:
            tracked = [tuple(exposures[int(i)] or (1.0, 0.0)) for i in idx]
        frame_psnr: list = []
        metrics["photometric"] = photometric_metrics(
            renders,
            refs,
            lpips,
            depths if depths else None,
            ref_depths if ref_depths else None,
            alphas,
            on,
            tracked,
            frame_psnr_out=frame_psnr,
        )
        fit, keyframe_scores = keyframe_fit(ds, slam, est, on)
        metrics["photometric"].update(fit)
        save_side_by_side(run_dir / "renders", [int(i) for i in idx], renders, refs, alphas)
        scored = [(int(i), raw, comp) for i, (raw, comp) in zip(idx, frame_psnr, strict=True)]
        title = f"{metrics['dataset']}: PSNR of every scored frame and keyframe"
        write_frame_scores(run_dir / "frame_scores.csv", run_dir / "frame_scores.png", scored, keyframe_scores, title)
    else:
        metrics["photometric"] = None
        metrics["photometric_na_reason"] = "no non-keyframe frame to score"
    metrics.update(mesh_section(cfg, ds, slam, run_dir))
    metrics["time_s"].update(loop_s or {})
    metrics["time_s"]["evaluation_s"] = time.perf_counter() - t_start
    if save is not None:
        save.write()
        metrics["time_s"]["save_s"] = save.seconds
    write_report(run_dir, metrics, title=f"rgs_warp {metrics['dataset']} ({cfg.method}, {cfg.mode})")
    return metrics


def mesh_section(cfg: Config, ds, slam: SLAM, run_dir: Path) -> dict:
    """Acc / Comp / Comp.Ratio of the TSDF fusion of rendered depth and colour at the keyframes
    (``rgs_warp.export.fuse_keyframes``); with ``export.mesh`` that mesh is also ``mesh.ply``."""
    mesh_path = ground_truth_mesh(cfg, ds)
    if cfg.mode != "rgbd":
        return {"mesh": None, "mesh_na_reason": "monocular run (scale-free map)"}
    if mesh_path is None and not cfg.export.mesh:
        return {"mesh": None, "mesh_na_reason": "no ground-truth mesh for this sequence"}
    try:
        from rgs_warp.eval.reconstruction import require_open3d

        o3d = require_open3d()
    except ImportError as e:
        return {"mesh": None, "mesh_na_reason": f"open3d not importable ({e})"}
    from rgs_warp.eval import mesh_metrics
    from rgs_warp.export import fuse_keyframes

    rec = fuse_keyframes(slam, voxel_m=cfg.export.voxel_m)
    if cfg.export.mesh:
        o3d.io.write_triangle_mesh(str(run_dir / "mesh.ply"), rec, write_vertex_colors=True)
    if mesh_path is None:
        return {"mesh": None, "mesh_na_reason": "no ground-truth mesh for this sequence"}
    return {"mesh": mesh_metrics(rec, o3d.io.read_triangle_mesh(str(mesh_path)))}


def keyframe_fit(ds, slam: SLAM, est: np.ndarray, device: str | None = None) -> tuple[dict, list]:
    """How well the map fits what it was trained on: the mean PSNR of the renders at every keyframe's
    pose against its frame, raw and exposure-compensated (``keyframe_psnr_db``,
    ``keyframe_psnr_compensated_db``), and each keyframe's (frame, raw, compensated); ``device``: the
    torch device of the scores (``psnr_raw_and_compensated``)."""
    scores = []
    for i, frame in zip(slam.keyframe_indices, read_frames(ds, slam.keyframe_indices), strict=True):
        res = slam.render(est[i])
        render = np.clip(res.color.numpy(), 0.0, 1.0)
        scores.append((int(i), *psnr_raw_and_compensated(render, frame.rgb, res.alpha.numpy(), device)))
    raw, comp = (float(np.mean([s[k] for s in scores])) for k in (1, 2))
    return {"keyframe_psnr_db": raw, "keyframe_psnr_compensated_db": comp}, scores


def error_image(render: np.ndarray, ref: np.ndarray, alpha: np.ndarray) -> np.ndarray:
    """|render at the frame's exposure - frame| (``compensate_exposure``), x4 in grey levels (H x W x 3)."""
    error = np.abs(compensate_exposure(render, ref, alpha) - ref).mean(axis=2, keepdims=True)
    return np.repeat(np.clip(4.0 * error, 0.0, 1.0), 3, axis=2)


def save_side_by_side(
    folder: Path, indices: list[int], renders: list, refs: list, alphas: list, count: int = 4
) -> None:
    """A few scored frames as PNG, evenly over the run: render | ground truth | error, the error being
    |render at the frame's exposure - frame| (``compensate_exposure``), x4 in grey levels."""
    import cv2

    folder.mkdir(parents=True, exist_ok=True)
    picks = np.unique(np.linspace(0, len(indices) - 1, min(count, len(indices))).round().astype(int))
    for k in picks:
        row = np.concatenate([renders[k], refs[k], error_image(renders[k], refs[k], alphas[k])], axis=1)
        image = (np.clip(row, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
        cv2.imwrite(str(folder / f"frame{indices[k]:05d}_render_gt_error.png"), image[..., ::-1])


# what a monocular run is told at its start (README, "Where it stands"; issue 22)
MONO_NOTICE = (
    "note: mode=mono is not reliable yet: on the synthetic office it tracks the first 150 frames to 1.3-1.5 cm "
    "(Sim(3) ATE; RGB-D 0.4 cm) and loses the scale later (about 20 cm over 300 frames), and on 7-Scenes its "
    "scale drifts (8.6-8.8 cm; RGB-D 4.4); frames it flags lost are counted at the end and named in log.jsonl "
    "(experiments/results/mono.md)"
)


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if any(a in ("-h", "--help") for a in argv):
        print(USAGE)
        print(help_text())
        return 0
    resume_dirs = [a.partition("=")[2] for a in argv if a.startswith("resume=")]
    # the progress bar names the kernel modules as Warp compiles them, instead of Warp's line for each
    wp.config.log_level = max(wp.config.log_level, wp.LOG_WARNING)
    try:
        cfg = None if resume_dirs else load_config(argv)
        if cfg is not None:
            extra, message = cpu_sized_overrides(cfg, argv, resolve_device(cfg.device))
            if extra:
                print(message, file=sys.stderr)
                cfg = load_config([*argv, *extra])
    except ConfigError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    if cfg is not None and cfg.mode == "mono":
        print(MONO_NOTICE, file=sys.stderr)
    viewer = None
    try:
        try:
            overrides = [a for a in argv if not a.startswith("resume=")]
            if resume_dirs:
                if len(resume_dirs) > 1 or not resume_dirs[0]:
                    raise ResumeError("give one run folder: resume=RUN_DIR")
                cfg = resume_config(resume_dirs[0], overrides)
            if cfg.viewer:  # opened before the run (a missing viser fails now), kept up after it
                from rgs_warp.view import open_viewer

                viewer = open_viewer(cfg.viewer_port)
            if resume_dirs:
                run_dir, metrics = resume(resume_dirs[0], overrides, viewer=viewer)
            else:
                run_dir, metrics = run(cfg, viewer=viewer)
        except ConfigError as e:
            print(f"error: {e}", file=sys.stderr)
            return 2
        except (DatasetError, ValueError, OSError, ImportError) as e:  # OSError: OutputError, SaveError, a full disk
            print(f"error: {e}", file=sys.stderr)
            return 1
        except KeyboardInterrupt:  # Ctrl-C: the run saved what it tracked and said where
            return 130
        print_summary(run_dir, metrics)
        if viewer is not None:
            print(f"viewer: still serving the run at {viewer.url}; Ctrl-C to stop", file=sys.stderr)
            try:
                viewer.serve()
            except KeyboardInterrupt:
                pass
        return 0
    finally:
        if viewer is not None:
            viewer.close()


def print_summary(run_dir: Path, metrics: dict) -> None:
    """The end of ``main``: where the run is and its headline numbers, how far behind the camera a played
    run ended, and warnings when it fell behind or tracking was lost."""
    ate = (metrics.get("ate") or {}).get("all_frames", {})
    photo = metrics.get("photometric") or {}
    print(f"run dir   {run_dir}")
    print(
        f"frames {metrics['frames']}, keyframes {metrics['keyframes']}, Gaussians {metrics['gaussians']}, "
        f"{metrics['fps']:.2f} frames/s"
    )
    if ate:
        print(f"ATE RMSE  {ate['rmse_cm']:.2f} cm (all frames)")
    if photo:
        raw, compensated = photo["psnr_db"], photo["psnr_compensated_db"]
        print(f"PSNR      {raw:.2f} dB raw, {compensated:.2f} exposure-compensated; SSIM {photo['ssim']:.3f}")
    final = metrics.get("final_refinement")
    if final:
        print(
            f"final     {final['iters']} iterations over {final['keyframes']} keyframes in {final['seconds']:.1f} s: "
            f"keyframe PSNR {final['keyframe_psnr_before_db']:.2f} -> {final['keyframe_psnr_after_db']:.2f} dB"
        )
    kernels = metrics.get("kernels") or {}
    if kernels.get("compiled_modules"):
        print(
            f"kernels   {kernels['compiled_modules']} Warp modules compiled in {kernels['compile_s']:.0f} s of the run "
            f"(the first run only: cached in {wp.config.kernel_cache_dir})"
        )
    playback, fills = metrics.get("playback"), metrics.get("frame_fills") or {}
    if playback:
        skipped = f"; {fills['skipped']} of {fills['wanted']} frame fills skipped" if fills.get("skipped") else ""
        print(
            f"camera    {playback['fps']:g} Hz: behind it by {playback['lag_ms_last']:.0f} ms at the last frame, "
            f"{playback['lag_ms_p50']:.0f} ms at the median{skipped}"
        )
    evaluation_s = (metrics.get("time_s") or {}).get("evaluation_s")
    if evaluation_s is not None:
        print(f"report    {run_dir / 'metrics.md'} (evaluated in {evaluation_s:.1f} s)")
    else:
        print(f"report    {run_dir / 'metrics.md'}")
    if playback and not playback["kept_pace"]:
        # the fill bound first when fills queued up to it: the likeliest cause on a slower machine (perf.md,
        # session 36: 7-Scenes at 60 Hz kept pace in 3 of 3 runs with 8, in 2 of 6 with 32)
        most = fills.get("most_waiting", 0)
        queue = (
            f"fewer frame fills waiting for the mapping (mapping.fill_queue: {most} waited; 8 kept a 60 Hz camera's "
            "pace on slower machines) or "
            if most > 8
            else ""
        )
        print(
            f"warning: the run fell {playback['lag_ms_last'] / 1e3:.2f} s behind a {playback['fps']:g} Hz camera; "
            f"timing=live keeps pace by mapping less, try {queue}fewer iterations a keyframe (mapping.min_iters); "
            "a lower dataset.playback_fps or fewer tracking steps (tracking.iters) leave it more time "
            "(experiments/results/perf.md)",
            file=sys.stderr,
        )
    tracking = metrics.get("tracking") or {}
    if tracking.get("lost_frames"):
        print(
            f"warning: tracking was lost in {tracking['lost_frames']} of {tracking['tracked_frames']} tracked frames, "
            f"first at frame {tracking['first_lost_frame']} ({tracking['first_lost_reason']}); poses from there on "
            f"are unreliable (each frame's entry in {run_dir / 'log.jsonl'} says why)",
            file=sys.stderr,
        )
