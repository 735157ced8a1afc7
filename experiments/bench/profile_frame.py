"""Where a frame's GPU time goes: per-kernel GPU time of tracked frames and of
keyframes in a synchronous run, from Warp's activity timing (``wp.timing_begin``), against the
frames' wall time.

    python experiments/bench/profile_frame.py [--out DIR] [--commit SHA] [--warm 60] [--frames 60]
        [override ...]

Runs the sequence (default the synthetic office at Replica size) for ``--warm`` frames untimed, then
times each of the next ``--frames`` frames: per kernel (or graph, copy, memset), the GPU milliseconds
per tracked frame and per keyframe; the GPU-busy share of the wall time (how much a second thread
could overlap: 1 means the GPU is the limit).  DIR gets ``profile_frame.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import time
from collections import defaultdict
from pathlib import Path

import warp as wp

from rgs_warp import SLAM, load_config, open_dataset


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default=os.environ.get("OUT", "bench_out"))
    ap.add_argument("--commit", default="unknown")
    ap.add_argument("--warm", type=int, default=60, help="frames run before timing")
    ap.add_argument("--frames", type=int, default=60, help="frames timed")
    ap.add_argument("overrides", nargs="*", default=["dataset=synthetic/office0_replica_size"])
    args = ap.parse_args(argv)
    cfg = load_config(args.overrides)
    ds = open_dataset(cfg)
    slam = SLAM(cfg, ds.camera, T_first_WC=ds[0].pose_gt)
    kinds = {"frame": defaultdict(float), "keyframe": defaultdict(float)}
    counts = {"frame": 0, "keyframe": 0}
    wall = {"frame": 0.0, "keyframe": 0.0}
    for i in range(min(args.warm + args.frames, len(ds))):
        f = ds[i]
        if i < args.warm:
            slam.process(f.rgb, f.depth, f.timestamp)
            continue
        wp.synchronize()
        wp.timing_begin(cuda_filter=wp.TIMING_ALL)
        t0 = time.perf_counter()
        result = slam.process(f.rgb, f.depth, f.timestamp)
        wp.synchronize()
        seconds = time.perf_counter() - t0
        timings = wp.timing_end()
        kind = "keyframe" if result.keyframe else "frame"
        counts[kind] += 1
        wall[kind] += seconds
        for t in timings:
            kinds[kind][t.name] += t.elapsed
    report = {"commit": args.commit, "gpu": wp.get_device().name, "overrides": args.overrides, "kinds": {}}
    for kind, per_kernel in kinds.items():
        n = max(counts[kind], 1)
        busy_ms = sum(per_kernel.values()) / n
        top = sorted(per_kernel.items(), key=lambda kv: -kv[1])
        report["kinds"][kind] = {
            "count": counts[kind],
            "wall_ms": 1e3 * wall[kind] / n,
            "gpu_busy_ms": busy_ms,
            "gpu_busy_share": busy_ms / max(1e3 * wall[kind] / n, 1e-9),
            "kernels_ms": {name: ms / n for name, ms in top[:40]},
        }
        print(f"{kind}: {counts[kind]} timed, wall {1e3 * wall[kind] / n:.1f} ms, GPU busy {busy_ms:.1f} ms")
        for name, ms in top[:15]:
            print(f"    {ms / n:8.2f} ms  {name}")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "profile_frame.json").write_text(json.dumps(report, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
