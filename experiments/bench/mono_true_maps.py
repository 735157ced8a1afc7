"""Monocular tracking against maps built from the true poses and depth (issue 22): is it the tracker or
the map?

    python experiments/bench/mono_true_maps.py [--size 1200x680] [--frames 300] [--first 50] [--last 130]
        [--device cuda:0] [override ...]

The SLAM processes frames 0..last of the synthetic office with their true poses and depth (RGB-D
mapping).  Two measurements, each for a monocular and an RGB-D tracker (the overrides apply to both):

* causal: before frame i (first < i <= last) is mapped, it is tracked from the true poses of frames
  i-1 and i-2 against the map of the frames before it (each frame's error alone, on the map a
  perfect SLAM could have by then);
* complete map: after the last frame, frames first..last are tracked on from the trackers' own
  estimates (no resets) against the whole map (also monocular with 60 steps).

Prints one line per frame (``causal mono 97 err 0.41 cm 0.05 deg``, ``mono 30 97 err ...``) and
``SUMMARY`` lines (max and mean position error, cm).  Results: experiments/results/mono.md.
"""

from __future__ import annotations

import argparse
import time
from dataclasses import replace

import numpy as np

from rgs_warp.config import load_config
from rgs_warp.datasets import open_dataset
from rgs_warp.slam import SLAM
from rgs_warp.tracking import Tracker, pose_error


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--size", default="1200x680")
    ap.add_argument("--frames", type=int, default=300, help="frames of the whole path (its sampling)")
    ap.add_argument("--first", type=int, default=50)
    ap.add_argument("--last", type=int, default=130)
    ap.add_argument("--device", default="cuda:0")
    ap.add_argument("overrides", nargs="*")
    args = ap.parse_args(argv)
    w, h = (int(v) for v in args.size.split("x"))
    a, b, dev = args.first, args.last, args.device
    if not 2 <= a < b:
        raise SystemExit(f"need 2 <= --first < --last, got {a}, {b}")
    cfg = load_config(
        ["dataset=synthetic/office0", f"dataset.width={w}", f"dataset.height={h}", f"dataset.n_frames={args.frames}"]
        + [f"device={dev}", *args.overrides]
    )
    ds = open_dataset(cfg, device=dev)
    slam = SLAM(cfg, ds.camera, device=dev, T_first_WC=ds[0].pose_gt)
    causal = {m: Tracker(cfg.tracking, ds.camera, dev, mode=m) for m in ("mono", "rgbd")}
    errors = {m: [] for m in causal}
    t0 = time.time()
    for i in range(b + 1):
        f = ds[i]
        if i > a:
            for mode, tracker in causal.items():
                tracker.reset(ds[i - 1].pose_gt, ds[i - 2].pose_gt)
                r = tracker.track(f.rgb, f.depth if mode == "rgbd" else None, slam.map)
                e = pose_error(r.T_WC, f.pose_gt)
                errors[mode].append(100 * e[0])
                lost = " lost" if r.lost else ""
                print(f"causal {mode} {i} err {100 * e[0]:.2f} cm {e[1]:.2f} deg{lost}", flush=True)
        slam.process(f.rgb, f.depth, f.timestamp, T_WC=f.pose_gt)
    print("SUMMARY causal", {m: (round(max(v), 2), round(float(np.mean(v)), 2)) for m, v in errors.items()})
    kfs = len(slam.keyframe_indices)
    print(f"map: {len(slam.map)} Gaussians, {kfs} keyframes, {time.time() - t0:.0f} s", flush=True)
    for mode, tcfg in (("mono", cfg.tracking), ("rgbd", cfg.tracking), ("mono", replace(cfg.tracking, iters=60))):
        tracker = Tracker(tcfg, ds.camera, dev, mode=mode)
        tracker.reset(ds[a].pose_gt, ds[a - 1].pose_gt)
        errs = []
        for i in range(a + 1, b + 1):
            f = ds[i]
            r = tracker.track(f.rgb, f.depth if mode == "rgbd" else None, slam.map)
            e = pose_error(r.T_WC, f.pose_gt)
            errs.append(100 * e[0])
            print(
                f"{mode} {tcfg.iters} {i} err {100 * e[0]:.2f} cm {e[1]:.2f} deg{' lost' if r.lost else ''}", flush=True
            )
        print(f"SUMMARY {mode} {tcfg.iters} max err cm {max(errs):.2f} mean {np.mean(errs):.2f}", flush=True)


if __name__ == "__main__":
    main()
