"""What the viewer costs a run (the requirement: nothing measurable with nobody connected, at most 10 % of
the tracking frames/s with someone connected).

    python experiments/bench/viewer_fps.py [--out DIR] [--commit SHA] [--case NAME:override,override ...]

Each case runs three times: ``off`` (no viewer), ``idle`` (the viewer serving, nobody connected) and
``client`` (a simulated browser, ``rgs_warp.app.view.SimulatedClient`` in a process of its own, that
moves its camera 30 times a second over a 1280x720 canvas, so that the viewer renders a 640x360
view whenever ``max_fps`` lets it, besides the panel and the scene).  The hook,
``Viewer.update(slam, result, rgb, gt_poses, lost_frames)``, runs after each frame in the run loop;
its time per frame is ``viewer_seconds`` in ``log.jsonl`` (``seconds`` is the SLAM's own).  DIR gets
``viewer_fps.json``: per case and mode frames/s and tracking frames/s of the run, the per-frame time
p50 / p99 with and without the hook, tracking p50, the hook's p50 / p99 / mean, the views sent and
received, and each mode's cost against ``off`` in %.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import os
import sys
import time
from pathlib import Path

import numpy as np
from slam import case_configs  # experiments/bench/slam.py (the script's folder is on sys.path)

from rgs_warp.app.runner import run
from rgs_warp.app.view import SimulatedClient, Viewer

DEFAULT_CASES = ["office:dataset=synthetic/office0,dataset.width=1200,dataset.height=680"]
MODES = ("off", "idle", "client")


def _client_process(url: str, stop, ready, views) -> None:
    client = SimulatedClient(url, fps=30.0, width=1280, height=720)
    ready.set()
    stop.wait()
    views.value = client.views
    client.close()


def measure(cfg, mode: str, progress: bool) -> dict:
    """One run of ``cfg`` in ``mode`` (``MODES``); its numbers."""
    ctx = multiprocessing.get_context("spawn")
    viewer = None if mode == "off" else Viewer(port=0, host="127.0.0.1")
    process, stop, views = None, ctx.Event(), ctx.Value("i", 0)
    try:
        if mode == "client":
            ready = ctx.Event()
            process = ctx.Process(target=_client_process, args=(viewer.url, stop, ready, views), daemon=True)
            process.start()
            if not ready.wait(60.0):
                raise RuntimeError("the simulated browser did not connect")
            deadline = time.monotonic() + 30.0
            while viewer.clients == 0 and time.monotonic() < deadline:
                time.sleep(0.05)
        run_dir, metrics = run(cfg, progress=progress, viewer=viewer)
    finally:
        stop.set()
        if process is not None:
            process.join(10.0)
        if viewer is not None:
            viewer.close()
    log = [json.loads(line) for line in (run_dir / "log.jsonl").read_text().splitlines()][1:]  # frame 0 compiles
    seconds = np.array([e["seconds"] for e in log])
    hook = np.array([e.get("viewer_seconds", 0.0) for e in log])
    tracking = np.array([e.get("tracking_seconds", np.nan) for e in log])
    out = {
        "frames": metrics["frames"],
        "fps": metrics["fps"],
        "tracking_fps": metrics.get("tracking_fps"),
        "frame_ms_p50": float(np.percentile(seconds + hook, 50) * 1e3),
        "frame_ms_p99": float(np.percentile(seconds + hook, 99) * 1e3),
        "slam_ms_p50": float(np.percentile(seconds, 50) * 1e3),
        "tracking_ms_p50": float(np.nanpercentile(tracking, 50) * 1e3),
    }
    if viewer is not None:
        out.update(
            hook_ms_p50=float(np.percentile(hook, 50) * 1e3),
            hook_ms_p99=float(np.percentile(hook, 99) * 1e3),
            hook_ms_mean=float(hook.mean() * 1e3),
            views_sent=viewer.stats.views,
            views_received=views.value,
            panels=viewer.stats.panels,
            scenes=viewer.stats.scenes,
        )
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default=os.environ.get("OUT", "bench_out"))
    ap.add_argument("--commit", default="unknown", help="the commit measured (git on a copied tree may not know)")
    ap.add_argument("--case", action="append", help="name:override,override (repeatable)")
    ap.add_argument("--common", default="", help="overrides applied to every case, comma separated")
    ap.add_argument("--modes", default=",".join(MODES), help=f"which of {', '.join(MODES)} to run, comma separated")
    args = ap.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    import warp as wp

    results: dict = {}
    for name, overrides, _ in case_configs(args.case or DEFAULT_CASES, args.common, out):
        results[name] = {"overrides": overrides}
        for mode in args.modes.split(","):
            cfg = next(case_configs([f"{name}_{mode}:{overrides}"], args.common, out))[2]
            cfg.overwrite = True
            results[name][mode] = measure(cfg, mode, sys.stderr.isatty())
            print(name, mode, json.dumps(results[name][mode]), file=sys.stderr)
        base = results[name].get("off")
        for mode in MODES[1:]:
            r = results[name].get(mode)
            if base and r:
                r["cost_pct"] = {
                    "fps": 100.0 * (1.0 - r["fps"] / base["fps"]),
                    "tracking_fps": 100.0 * (1.0 - r["tracking_fps"] / base["tracking_fps"]),
                    "frame_ms_p50": 100.0 * (r["frame_ms_p50"] / base["frame_ms_p50"] - 1.0),
                }
        report = {"commit": args.commit, "device": wp.get_device().name, "results": results}
        (out / "viewer_fps.json").write_text(json.dumps(report, indent=2))
    print(json.dumps(results, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
