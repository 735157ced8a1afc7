"""A run of the SLAM system on a dataset: ``run`` tracks every frame with ``SLAM``, checkpoints it,
saves what it tracked (also when stopped) and evaluates it into the run folder; ``resume`` continues a
stopped run from its last checkpoint.
"""

from __future__ import annotations

import contextlib
import dataclasses
import itertools
import json
import signal
import sys
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from rgs_warp.app.checkpoint import CHECKPOINT, CheckpointWriter, remove_checkpoints, save_run
from rgs_warp.app.evaluate import check_evaluation_imports, evaluate_run, tracking_section
from rgs_warp.app.memory import memory_mib, start_peak_memory
from rgs_warp.app.progress import KernelLoads, RunProgress, watch_kernel_loads
from rgs_warp.app.rundir import OutputError, dataset_summary, is_stream, make_run_dir, own_run_dir, read_frames
from rgs_warp.compile import preload
from rgs_warp.config import (
    Config,
    ConfigError,
    config_from_dict,
    load_saved_config,
    parse_yaml,
    resolve_device,
    save_config,
)
from rgs_warp.datasets import DatasetError, generates_scene, open_dataset
from rgs_warp.io.atomic import SaveError, write_text_atomic
from rgs_warp.slam import SLAM


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
        from rgs_warp.app.view import open_viewer

        with open_viewer(cfg.viewer_port, cfg.viewer_host) as viewer:
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
            if is_stream(ds):
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
            run_dir = make_run_dir(cfg) if run_dir is None else own_run_dir(Path(run_dir))
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
            save_run(cfg, slam, run_dir, refine=False).write()  # a stopped run saves at once
        except Exception as e:  # noqa: BLE001 (the error that stopped the run is the one raised)
            print(f"error: the run stopped, and saving what it tracked failed: {e}", file=sys.stderr)
        else:  # said for an error too (a frame that cannot be read): the error follows
            again = (
                f"; python -m rgs_warp.slam resume={run_dir} continues it" if (run_dir / CHECKPOINT).is_file() else ""
            )
            why = "" if isinstance(stop, KeyboardInterrupt | SystemExit) else " by the error below"
            print(
                f"stopped at frame {state.next_frame}{why}: what was tracked is saved in {run_dir}{again}",
                file=sys.stderr,
            )
        raise
    log.close()
    writer.close()
    save = None
    try:
        final = slam.final_iters()
        bar.phase("saving" if final <= 0 else f"final refinement 0/{final} (Ctrl-C ends it)")
        # the map and keyframes are copied to the host now and written while the run is evaluated
        with _ctrl_c_ends() as ended:

            def stop(done: int) -> bool:  # after each iteration of the final refinement
                if done % 100 == 0:
                    bar.phase(f"final refinement {done}/{final} (Ctrl-C ends it)")
                return ended.is_set()

            save = save_run(cfg, slam, run_dir, stop=stop)
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


@contextlib.contextmanager
def _ctrl_c_ends() -> Iterator[threading.Event]:
    """An event that the first Ctrl-C sets instead of stopping the run (the final refinement ends at its
    next iteration, and the map is saved and scored as it is); a second Ctrl-C stops the run.  Only in
    the main thread, where signal handlers can be set (elsewhere the event stays clear)."""
    ended = threading.Event()
    if threading.current_thread() is not threading.main_thread():
        yield ended
        return
    previous = signal.getsignal(signal.SIGINT)

    def end(signum, frame):
        ended.set()
        signal.signal(signal.SIGINT, previous)
        print("Ctrl-C: the final refinement ends here; the map is saved as it is (again: stop)", file=sys.stderr)

    signal.signal(signal.SIGINT, end)
    try:
        yield ended
    finally:
        signal.signal(signal.SIGINT, previous)


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
    elif result.seeded:  # frame fill: seeds waiting for the next keyframe
        entry["seeded"] = result.seeded
    if result.mapping is not None and result.mapping.iters:  # a keyframe's window mapping, or a refinement
        entry.update(mapping_iters=result.mapping.iters, mapping_l1=result.mapping.final_l1)
        if cfg.method == "baseline":  # the densification inside it
            entry.update(cloned=result.mapping.cloned, split=result.mapping.split, pruned=result.pruned)
    if cfg.mapping.asynchronous:
        entry["fills_waiting"] = result.fills_waiting  # the worker's backlog of frame fills
    return entry


class ResumeError(ValueError):
    """A run folder that cannot be resumed; the message says why."""


# what `resume=RUN_DIR` lets the command line change: where the run computes, where its data is and
# whether a browser watches it, never what it computes (docs/decisions.md, "Resuming a run")
RESUME_OVERRIDES = ("device", "data_root", "viewer", "viewer_port", "viewer_host")


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
        from rgs_warp.app.view import open_viewer

        with open_viewer(cfg.viewer_port, cfg.viewer_host) as viewer:
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
            if is_stream(ds):
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
