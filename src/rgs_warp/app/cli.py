"""The command line ``python -m rgs_warp.slam``: a run (or a resumed one) from ``group=option`` and
``key=value`` arguments, its summary, and the viewer kept up after it."""

from __future__ import annotations

import signal
import sys
import warnings
from pathlib import Path

import warp as wp

from rgs_warp.app.cpu_size import cpu_sized_overrides
from rgs_warp.app.progress import quiet_warp
from rgs_warp.app.runner import ResumeError, resume, resume_config, run
from rgs_warp.config import DEFAULTS, GROUPS, Config, ConfigError, group_options, leaves, load_config, resolve_device
from rgs_warp.datasets import DatasetError, DatasetWarning

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


# what a monocular run is told at its start (README, "Where it stands")
MONO_NOTICE = (
    "note: mode=mono is not reliable yet: on the synthetic office it tracks the first 150 frames to 1.3-1.5 cm "
    "(Sim(3) ATE; RGB-D 0.4 cm) and loses the scale later (about 20 cm over 300 frames), and on 7-Scenes its "
    "scale drifts (8.6-8.8 cm; RGB-D 4.4); frames it flags lost are counted at the end and named in log.jsonl "
    "(experiments/results/mono.md)"
)


def help_text() -> str:
    lines = ["Configuration groups (group=option):"]
    for group in GROUPS:
        lines.append(f"  {group}: {', '.join(group_options(group))}   (default: {DEFAULTS[group]})")
    lines.append("")
    lines.append("Keys (key=value; default shown; docs/config.md says what each does):")
    lines += [f"  {key} = {value!r}" for key, value in leaves(Config())]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if any(a in ("-h", "--help") for a in argv):
        print(USAGE)
        print(help_text())
        return 0
    resume_dirs = [a.partition("=")[2] for a in argv if a.startswith("resume=")]
    quiet_warp()
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
                from rgs_warp.app.view import open_viewer

                viewer = open_viewer(cfg.viewer_port, cfg.viewer_host)
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


def command() -> int:
    """``python -m rgs_warp.slam``: ``main`` with SIGTERM leaving through the run's ``finally`` and a
    dataset's warnings on one line."""
    # a job scheduler stops a run with SIGTERM: leave through the run's `finally`, which saves what was
    # tracked (as Ctrl-C does), with the shell's exit status for it
    signal.signal(signal.SIGTERM, lambda signum, frame: sys.exit(128 + signum))
    format_warning = warnings.formatwarning

    def one_line(message, category, filename, lineno, line=None):
        """A dataset's warning (e.g. frames dropped) as one line, as the command's own warnings."""
        if issubclass(category, DatasetWarning):
            return f"warning: {message}\n"
        return format_warning(message, category, filename, lineno, line)

    warnings.formatwarning = one_line
    return main()


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
        # the primary numbers: at the exposure tracking estimated, on held-out frames and by SplaTAM's protocol
        held_out = photo["psnr_tracked_exposure_db"]
        splatam = (photo.get("every_5th_with_keyframes") or {}).get("psnr_tracked_exposure_db")
        if held_out is None:
            print(f"PSNR      {photo['psnr_db']:.2f} dB held out, raw (no tracked exposure)")
        else:
            protocol = "" if splatam is None else f", {splatam:.2f} every 5th frame with keyframes (SplaTAM's)"
            print(f"PSNR      {held_out:.2f} dB held out{protocol}, at the tracked exposure")
    final = metrics.get("final_refinement")
    if final:
        seconds = metrics["time_s"]["final_s"]
        ended = f" (of {final['iters_planned']}: ended by Ctrl-C)" if final["iters"] < final["iters_planned"] else ""
        print(
            f"final     {final['iters']} iterations{ended} over {final['keyframes']} keyframes in {seconds:.1f} s: "
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
        # the fill bound first when fills queued up to it: the likeliest cause on a slower machine (perf.md:
        # 7-Scenes at 60 Hz kept pace in 3 of 3 runs with 8, in 2 of 6 with 32)
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
