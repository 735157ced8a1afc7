"""Whole-system speed and memory over a run: per-frame time and GPU memory
against the frame index, with the accuracy of the same run.

    python experiments/bench/slam_fps.py [--out DIR] [--commit SHA] [--case NAME:override,override ...] [--jobs N]

Each case is ``rgs_warp.app.runner.run`` on a sequence; its ``log.jsonl`` gives, per frame, the seconds
(whole frame and tracking), the Gaussians and the GPU memory held (Warp's memory pool).  DIR gets
``slam_fps.json`` (per case: frames/s, tracking frames/s, per-frame latency p50/p99 for the whole
frame and for tracking, peak and final memory, the memory and time trends over the run's second
half, ATE and PSNR) and ``slam_fps_<case>.png`` (memory, Gaussians and per-frame time against the
frame index).  The default case is the long one: 2,000 frames of the synthetic office at 640x360
(the same path as 300 frames, walked more slowly: the map should stop growing once the room is
seen, and so should memory and time).

Several cases run each in its own process (in DIR/cases/NAME, its log and plot beside it; their results
gathered into DIR/slam_fps.json), so that a case's peak memory is its own: in one process the memory pool
keeps what an earlier case held (a paced run after an unpaced one showed 2.1 GiB for 1.1).
``--jobs N`` runs N of them at a time on the one GPU, with ``"jobs": N`` in the results: for screening
settings by PSNR and ATE, which sharing the GPU leaves alone; their frames/s and latencies then mean nothing.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
from slam import case_configs  # experiments/bench/slam.py (the script's folder is on sys.path)

from rgs_warp.app.runner import run

DEFAULT_CASES = [
    "office_2000:dataset=synthetic/office0,dataset.width=640,dataset.height=360,dataset.n_frames=2000",
]


def trend(x: np.ndarray, y: np.ndarray) -> float:
    """Least-squares slope of y against x over the second half of the run, per 1,000 frames."""
    half = len(x) // 2
    if len(x) - half < 2:
        return float("nan")
    return float(np.polyfit(x[half:], y[half:], 1)[0] * 1000.0)


def summarise(log: list[dict]) -> dict:
    frame = np.array([e["frame"] for e in log], dtype=float)
    seconds = np.array([e["seconds"] for e in log])
    tracking = np.array([e.get("tracking_seconds", np.nan) for e in log])
    gaussians = np.array([e["gaussians"] for e in log], dtype=float)
    memory = np.array([e.get("memory_mib", np.nan) for e in log])
    rest = seconds[1:]  # the first frame builds the map and compiles kernels
    out = {
        "latency_ms_p50": float(np.percentile(rest, 50) * 1e3),
        "latency_ms_p99": float(np.percentile(rest, 99) * 1e3),
        "tracking_ms_p50": float(np.nanpercentile(tracking[1:], 50) * 1e3),
        "tracking_ms_p99": float(np.nanpercentile(tracking[1:], 99) * 1e3),
        "gaussians_final": int(gaussians[-1]),
        "gaussians_trend_per_1000": trend(frame, gaussians),
        "seconds_trend_ms_per_1000": trend(frame[1:], rest * 1e3),
        "keyframes": int(sum(bool(e["keyframe"]) for e in log)),
        "lost": int(sum(bool(e.get("lost")) for e in log)),
    }
    if np.isfinite(memory).any():
        out.update(
            memory_mib_max=float(np.nanmax(memory)),
            memory_mib_final=float(memory[-1]),
            memory_trend_mib_per_1000=trend(frame, memory),
        )
    return out


def plot(name: str, log: list[dict], path: Path, title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    frame = np.array([e["frame"] for e in log])
    seconds = np.array([e["seconds"] for e in log]) * 1e3
    tracking = np.array([e.get("tracking_seconds", np.nan) for e in log]) * 1e3
    memory = np.array([e.get("memory_mib", np.nan) for e in log])
    gaussians = np.array([e["gaussians"] for e in log]) / 1e3
    keyframes = frame[[bool(e["keyframe"]) for e in log]]
    fig, (top, bottom) = plt.subplots(2, 1, figsize=(10, 6.5), sharex=True)
    top.plot(frame, memory, color="tab:blue", label="GPU memory held (MiB)")
    top.set_ylabel("MiB", color="tab:blue")
    right = top.twinx()
    right.plot(frame, gaussians, color="tab:orange", label="Gaussians (k)")
    right.set_ylabel("Gaussians (thousands)", color="tab:orange")
    top.set_title(title)
    top.set_ylim(bottom=0)
    right.set_ylim(bottom=0)
    window = 51
    kernel = np.ones(window) / window
    bottom.plot(frame, seconds, ".", ms=1.5, color="0.7", label="whole frame")
    if len(seconds) > window:
        smooth = np.convolve(seconds, kernel, mode="same")
        bottom.plot(frame[window:-window], smooth[window:-window], color="k", label=f"whole frame, mean of {window}")
        smooth_t = np.convolve(np.nan_to_num(tracking), kernel, mode="same")
        bottom.plot(frame[window:-window], smooth_t[window:-window], color="tab:green", label="tracking, mean")
    lag = np.array([e.get("lag_s", np.nan) for e in log]) * 1e3
    if np.isfinite(lag).any():  # dataset.playback_fps: how far each frame's result came behind the camera
        bottom.plot(frame, np.maximum(lag, 0.1), color="tab:purple", lw=0.8, label="lag behind the camera")
    bottom.vlines(keyframes, 0, 3, color="tab:red", lw=0.5, label="keyframes")
    bottom.set_yscale("log")
    bottom.set_ylabel("ms per frame")
    bottom.set_xlabel("frame")
    bottom.legend(loc="upper right", fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def gpu_name() -> str:
    import warp as wp

    device = wp.get_device()
    return device.name if device.is_cuda else "cpu"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default=os.environ.get("OUT", "bench_out"))
    ap.add_argument("--commit", default="unknown", help="the commit measured (git on a copied tree may not know)")
    ap.add_argument("--case", action="append", help="name:override,override (repeatable)")
    ap.add_argument("--common", default="", help="overrides applied to every case, comma separated")
    ap.add_argument("--jobs", type=int, default=1, help="cases run as this many processes at a time (screening)")
    args = ap.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    cases = args.case or DEFAULT_CASES
    if len(cases) > 1:
        return run_jobs(cases, args, out)
    results = {}
    for name, overrides, cfg in case_configs(cases, args.common, out):
        try:
            run_dir, metrics = run(cfg, progress=sys.stderr.isatty())
        except Exception as e:  # record and go on with the next case
            results[name] = {"error": f"{type(e).__name__}: {e}"}
            print(f"{name}: FAILED {e}", file=sys.stderr)
            continue
        log = [json.loads(line) for line in (run_dir / "log.jsonl").read_text().splitlines()]
        ate_all = (metrics.get("ate") or {}).get("all_frames") or {}
        ate = ate_all.get("rmse_cm")
        photometric = metrics.get("photometric") or {}
        results[name] = {
            "overrides": overrides,
            "frames": metrics["frames"],
            "fps": metrics["fps"],
            "tracking_fps": metrics.get("tracking_fps"),
            "peak_memory_mib": metrics.get("peak_memory_mib"),
            "ate_cm": ate,
            "ate_align_scale": ate_all.get("align_scale"),
            "psnr_db": photometric.get("psnr_db"),
            "psnr_compensated_db": photometric.get("psnr_compensated_db"),
            "keyframe_psnr_db": photometric.get("keyframe_psnr_db"),
            "keyframe_psnr_compensated_db": photometric.get("keyframe_psnr_compensated_db"),
            "ssim_compensated": photometric.get("ssim_compensated"),
            "depth_l1_cm": photometric.get("depth_l1_cm"),
            "time_s": metrics.get("time_s"),
            "mapping": metrics.get("mapping"),
            "mapping_iterations": metrics.get("mapping_iterations"),
            "mapping_graph_steps": metrics.get("mapping_graph_steps"),
            "mapping_iterations_per_s": metrics.get("mapping_iterations", 0) / metrics["wall_s"],
            "keyframe_to_map_s": metrics.get("keyframe_to_map_s"),
            "frame_fills": metrics.get("frame_fills"),  # asynchronous: the worker's backlog of frame fills
            "playback": metrics.get("playback"),  # dataset.playback_fps: the frames' lag behind the camera
            **summarise(log),
        }
        title = f"{name}: {cfg.dataset.width}x{cfg.dataset.height}, {metrics['frames']} frames ({args.commit})"
        plot(name, log, out / f"slam_fps_{name}.png", title)
        report = {"commit": args.commit, "gpu": gpu_name(), "results": results}
        (out / "slam_fps.json").write_text(json.dumps(report, indent=2, default=str))
    for name, r in results.items():
        print(name, json.dumps(r, default=str))
    return 0


def run_jobs(cases: list[str], args, out: Path) -> int:
    """Each case in its own process (this script, one case, DIR/cases/NAME), ``args.jobs`` at a time;
    their results gathered into DIR/slam_fps.json."""
    pending = list(cases)
    running: list[tuple[str, subprocess.Popen, object]] = []
    names = [case.partition(":")[0] for case in cases]
    if len(set(names)) != len(names):
        raise SystemExit(f"case names must differ: {names}")
    while pending or running:
        while pending and len(running) < args.jobs:
            case = pending.pop(0)
            name = case.partition(":")[0]
            folder = out / "cases" / name
            folder.mkdir(parents=True, exist_ok=True)
            cmd = [sys.executable, __file__, "--out", str(folder), "--commit", args.commit, "--case", case]
            if args.common:
                cmd += ["--common", args.common]
            log = (folder / "log.txt").open("w")
            running.append((name, subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT), log))
        time.sleep(1.0)
        for entry in [r for r in running if r[1].poll() is not None]:
            running.remove(entry)
            entry[2].close()
            print(f"{entry[0]}: exit {entry[1].returncode}", file=sys.stderr)
    results, gpu = {}, "unknown"
    for name in names:
        report = out / "cases" / name / "slam_fps.json"
        if report.exists():
            data = json.loads(report.read_text())
            gpu = data.get("gpu", gpu)
            results.update(data["results"])
        else:
            results[name] = {"error": f"no results: see {out / 'cases' / name / 'log.txt'}"}
    summary = {"commit": args.commit, "gpu": gpu, "jobs": args.jobs, "results": results}
    (out / "slam_fps.json").write_text(json.dumps(summary, indent=2, default=str))
    for name, r in results.items():
        print(name, json.dumps(r, default=str))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
