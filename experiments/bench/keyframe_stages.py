"""Where a run's wall time goes, stage by stage (issue 19): each stage's method wrapped, synchronised
before and after (``sync``) or not (``none``: the run's own wall time, for comparison), in a
synchronous run.

    python experiments/bench/keyframe_stages.py [--out FILE] [--mode sync|none] [--warm 60]
        [--frames 300] [override ...]

Runs ``--warm`` frames untimed, then ``--frames`` frames with every wrapped call's seconds summed:
tracking, a keyframe and its parts (matching, triangulation, seeding from matches and from depth, the
window mapping, maintenance, the convergence log), the frame fills and ``Tracker.prepare``.  Prints per
call and per keyframe; FILE (JSON) gets the same.  Synchronising each stage makes the GPU's share of each
visible at the cost of overlap: the sum is slower than the plain run (``--mode none``).
"""

from __future__ import annotations

import argparse
import functools
import json
import time
from collections import defaultdict

import numpy as np
import warp as wp

import rgs_warp.features.classic as classic
import rgs_warp.maintenance as maintenance
import rgs_warp.mapping as mapping
import rgs_warp.matching as matching
import rgs_warp.seeding as seeding
import rgs_warp.slam as slam_module
import rgs_warp.tracking as tracking
import rgs_warp.triangulation as triangulation
from rgs_warp import SLAM, load_config, open_dataset

STAGES = [  # (owner, method, label)
    (tracking.Tracker, "track", "track"),
    (tracking.Tracker, "prepare", "track.prepare"),
    (slam_module.SLAM, "_add_keyframe", "keyframe"),
    (slam_module.SLAM, "_fill_frame", "fill"),
    (slam_module.SLAM, "_seed", "keyframe.seed"),
    (matching.DenseMatcher, "match", "keyframe.seed.match"),
    (classic.ClassicBackbone, "describe", "keyframe.seed.match.describe"),
    (matching, "thin_blue_noise", "keyframe.seed.match.thin_blue_noise"),
    (triangulation.Triangulator, "triangulate", "keyframe.seed.triangulate"),
    (seeding.Seeder, "seed_matches", "keyframe.seed.seed_matches"),
    (seeding.Seeder, "seed_depth", "keyframe.seed.seed_depth"),
    (mapping.Mapper, "optimize", "mapper.optimize (keyframes and refinements)"),
    (mapping.Mapper, "convergence", "mapper.convergence"),
    (maintenance.Maintainer, "maintain", "keyframe.maintain"),
    (seeding.PointSeeder, "enqueue", "seeding.enqueue (keyframes and fills)"),
    (seeding.PointSeeder, "collect", "seeding.collect (keyframes and fills)"),
]


def wrap(owner, name: str, label: str, sync: bool, seconds: dict, calls: dict) -> None:
    f = getattr(owner, name)

    @functools.wraps(f)
    def timed(*args, **kwargs):
        capturing = wp.get_device().is_capturing
        if sync and not capturing:
            wp.synchronize()
        t0 = time.perf_counter()
        out = f(*args, **kwargs)
        if sync and not capturing:
            wp.synchronize()
        seconds[label] += time.perf_counter() - t0
        calls[label] += 1
        return out

    setattr(owner, name, timed)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default="keyframe_stages.json")
    ap.add_argument("--mode", choices=["sync", "none"], default="sync")
    ap.add_argument("--warm", type=int, default=60, help="frames run before timing")
    ap.add_argument("--frames", type=int, default=300, help="frames timed")
    ap.add_argument("overrides", nargs="*", default=["dataset=7scenes/redkitchen"])
    args = ap.parse_args(argv)
    seconds, calls = defaultdict(float), defaultdict(int)
    if args.mode == "sync":
        for owner, name, label in STAGES:
            wrap(owner, name, label, True, seconds, calls)
    cfg = load_config(args.overrides)
    ds = open_dataset(cfg)
    slam = SLAM(cfg, ds.camera, T_first_WC=ds[0].pose_gt)
    for i in range(min(args.warm, len(ds))):
        f = ds[i]
        slam.process(f.rgb, f.depth, f.timestamp)
    frames = [ds[i] for i in range(args.warm, min(args.warm + args.frames, len(ds)))]
    seconds.clear()
    calls.clear()
    wp.synchronize()
    t0 = time.perf_counter()
    per_frame, per_keyframe = [], []
    for f in frames:
        t1 = time.perf_counter()
        result = slam.process(f.rgb, f.depth, f.timestamp)
        (per_keyframe if result.keyframe else per_frame).append(time.perf_counter() - t1)
    wp.synchronize()
    wall = time.perf_counter() - t0
    n_kf = max(len(per_keyframe), 1)
    report = {
        "mode": args.mode,
        "overrides": args.overrides,
        "gpu": wp.get_device().name,
        "frames": len(frames),
        "keyframes": len(per_keyframe),
        "wall_s": wall,
        "frame_ms_median": 1e3 * float(np.median(per_frame)) if per_frame else None,
        "keyframe_ms_median": 1e3 * float(np.median(per_keyframe)) if per_keyframe else None,
        "stages": {
            k: {"calls": calls[k], "total_s": v, "per_call_ms": 1e3 * v / calls[k], "per_keyframe_ms": 1e3 * v / n_kf}
            for k, v in sorted(seconds.items())
        },
    }
    frame_ms, keyframe_ms = report["frame_ms_median"], report["keyframe_ms_median"]
    print(
        f"{args.mode}: {len(frames)} frames, {len(per_keyframe)} keyframes, {1e3 * wall / max(len(frames), 1):.1f} ms"
    )
    print(f"  median frame {frame_ms} ms, median keyframe {keyframe_ms} ms")
    for k, row in report["stages"].items():
        print(
            f"  {k:48s} {row['calls']:5d} calls  {row['per_call_ms']:7.2f} ms a call  "
            f"{row['per_keyframe_ms']:7.2f} ms a keyframe"
        )
    with open(args.out, "w") as fh:
        json.dump(report, fh, indent=1)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
