"""Tracking benchmark: one tracking iteration at 1200x680 with 300k Gaussians on the GPU.

Workload: the rasterizer benchmark's (experiments/bench/raster.py: Gaussians on the walls of a box room,
fx = fy = 600, SH degree 2).  The observed frame is the map rendered at the identity pose; tracking
starts 2 cm / 2 deg away.  One iteration = render (forward) + brightness sums and solve (Eq. 3-4) +
loss and image gradients (Eq. 5-8 + depth L1) + pose-only backward + Adam/SE(3) step.

Reported (median of ``--reps`` after warm-up, CUDA events): one iteration; a whole ``track`` call
(frame upload, ``iters`` iterations, one read-back) divided by ``iters``; the same iterations replayed
from a CUDA graph when the renderer allows capture; and a per-kernel profile of one iteration.

    PYTHONPATH=src python experiments/bench/tracking.py [--gaussians 300000] [--out $OUT]
    PYTHONPATH=src python experiments/bench/tracking.py --small      # CPU dry run, tiny sizes
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np
import warp as wp

sys.path.insert(0, str(Path(__file__).resolve().parent))
from raster import CAMERA, room_scene  # noqa: E402  (the rasterizer benchmark's workload)

from rgs_warp.app.report import git_commit  # noqa: E402
from rgs_warp.config import TrackingConfig  # noqa: E402
from rgs_warp.geometry import invert_pose, se3_exp  # noqa: E402
from rgs_warp.render import Renderer  # noqa: E402
from rgs_warp.tracking import Tracker, pose_error  # noqa: E402
from rgs_warp.types import Camera, GaussianMap  # noqa: E402


def median_ms(step, device, reps: int, warmup: int) -> float:
    for _ in range(warmup):
        step()
    times = []
    for _ in range(reps):
        if device.is_cuda:
            e0, e1 = wp.Event(device, enable_timing=True), wp.Event(device, enable_timing=True)
            wp.record_event(e0)
            step()
            wp.record_event(e1)
            wp.synchronize_event(e1)
            times.append(wp.get_event_elapsed_time(e0, e1))
        else:
            t0 = time.perf_counter()
            step()
            times.append(1e3 * (time.perf_counter() - t0))
    return float(np.median(times))


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--gaussians", type=int, default=300_000)
    parser.add_argument("--reps", type=int, default=100)
    parser.add_argument("--small", action="store_true", help="CPU dry run: 160x90, 3000 Gaussians, 5 reps")
    parser.add_argument("--out", default=os.environ.get("OUT", "bench_out"))
    args = parser.parse_args()
    wp.init()
    device = wp.get_device("cuda:0" if wp.get_cuda_device_count() else "cpu")
    camera, n, reps, warmup = CAMERA, args.gaussians, args.reps, 10
    if args.small:
        camera = Camera(fx=80.0, fy=80.0, cx=79.5, cy=44.5, width=160, height=90)
        n, reps, warmup = 3000, 5, 1
    commit = os.environ.get("RGS_COMMIT") or git_commit()

    scene = room_scene(n)
    gmap = GaussianMap.from_numpy(
        scene["means"], scene["quats_xyzw"], scene["log_scales"], scene["opacity_logits"], scene["sh"], device=device
    )
    res = Renderer(device).forward(gmap, camera, np.eye(4))
    alpha = res.alpha.numpy()
    rgb = res.color.numpy().copy()
    depth = np.where(alpha > 0.5, res.depth.numpy() / np.maximum(alpha, 1e-6), 0.0).astype(np.float32)
    T0 = invert_pose(se3_exp(np.array([0.012, -0.01, 0.012, 0.02, -0.015, 0.02])))  # ~2 cm, ~1.9 deg
    cfg = TrackingConfig()
    tracker = Tracker(cfg, camera, device, mode="rgbd")
    result = tracker.track(rgb, depth, gmap, T0)  # compiles every kernel, sizes every buffer
    out = {
        "device": device.name,
        "commit": commit,
        "warp": wp.config.version,
        "image": [camera.width, camera.height],
        "gaussians": n,
        "iters": cfg.iters,
        "reps": reps,
        "mean_alpha": float(alpha.mean()),
        "recovery_error_mm_deg": [1e3 * pose_error(result.T_WC, np.eye(4))[0], pose_error(result.T_WC, np.eye(4))[1]],
        "converged": result.converged,
    }

    tracker._begin(T0)  # the loop below runs single iterations from this state (private API: benchmark only)
    k = [0]

    def one_iteration():
        tracker._iteration(gmap, k[0] % cfg.iters, True)
        k[0] += 1

    out["iteration_ms"] = median_ms(one_iteration, device, reps, warmup)
    out["track_call_per_iteration_ms"] = (
        median_ms(lambda: tracker.track(rgb, depth, gmap, T0), device, max(3, reps // 10), 2) / cfg.iters
    )

    out["graph_iteration_ms"] = None
    if device.is_cuda:
        try:
            tracker.renderer.reserve_intersections(int(1.5 * res.num_intersections))
            tracker._begin(T0)
            with wp.ScopedCapture(device) as capture:
                for i in range(cfg.iters):
                    tracker._iteration(gmap, i, True)
            out["graph_iteration_ms"] = (
                median_ms(lambda: wp.capture_launch(capture.graph), device, max(3, reps // 10), 2) / cfg.iters
            )
            out["graph_overflowed"] = tracker.renderer.intersections_overflowed()
        except Exception as e:  # report why capture is not possible yet instead of failing the benchmark
            out["graph_error"] = f"{type(e).__name__}: {e}"

    tracker._begin(T0)
    with wp.ScopedTimer("profile", print=False, synchronize=True, cuda_filter=wp.TIMING_ALL) as timer:
        tracker._iteration(gmap, 0, True)
    profile: dict[str, float] = {}
    for r in timer.timing_results:
        profile[r.name] = profile.get(r.name, 0.0) + r.elapsed
    out["profile_ms"] = profile

    path = Path(args.out)
    path.mkdir(parents=True, exist_ok=True)
    name = "tracking_bench_small.json" if args.small else "tracking_bench.json"
    (path / name).write_text(json.dumps(out, indent=2))
    graph = out["graph_iteration_ms"]
    lines = [
        f"Device: {out['device']}; commit {commit}; warp-lang {out['warp']}; {camera.width}x{camera.height}, "
        f"{n:,} Gaussians, RGB-D; median of {reps} (ms)",
        "",
        "| one iteration | track() / iteration | graph replay / iteration | recovery (mm / deg) |",
        "|---|---|---|---|",
        f"| {out['iteration_ms']:.3f} | {out['track_call_per_iteration_ms']:.3f} | "
        f"{'n/a' if graph is None else f'{graph:.3f}'} | "
        f"{out['recovery_error_mm_deg'][0]:.3f} / {out['recovery_error_mm_deg'][1]:.4f} |",
    ]
    if "graph_error" in out:
        lines.append(f"\nGraph capture not possible: {out['graph_error']}")
    (path / name.replace(".json", ".md")).write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    print("profile (ms):", json.dumps({k: round(v, 4) for k, v in sorted(profile.items(), key=lambda kv: -kv[1])}))


if __name__ == "__main__":
    main()
