"""Are a tracker's captured-graph steps the eager steps on a GPU, or as far apart as two eager runs are?

    PYTHONPATH=src:tests python experiments/bench/graph_determinism.py [--device cuda:0] [--out DIR]

The scene and map sequence of ``tests/test_tracking.py::test_graph_replays_give_the_eager_steps_poses``
(the room map, frames 1-6 against the map, its first three quarters, and the map again; 30 Adam steps at
5e-3 from a pose 1 cm / 1 deg off): two eager trackers and one that replays captured graphs track each
frame from the same start.  Per frame: the pose difference (mm, deg) and the last step's loss of each
pair.  On the CPU all three agree bit for bit; on a GPU float atomics add in a varying order, and the
eager pair shows how far that alone carries the steps.  Writes DIR/graph_determinism.json.
"""

from __future__ import annotations

import argparse
import json
import os
from dataclasses import replace
from pathlib import Path

import warp as wp

from helpers_maps import perturbed, room_scene
from rgs_warp.config import TrackingConfig
from rgs_warp.tracking import Tracker, pose_error
from rgs_warp.types import GaussianMap


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", default="cuda:0" if wp.get_cuda_device_count() else "cpu")
    ap.add_argument("--out", default=os.environ.get("OUT", "bench_out"))
    args = ap.parse_args(argv)
    device = args.device
    scene = room_scene(device)
    poses, cam = scene["poses"], scene["camera"]
    arrays = scene["map"].to_numpy()
    names = ("means", "rotations", "log_scales", "opacity_logits", "sh")
    gmap = GaussianMap.from_numpy(*(arrays[k] for k in names), device=device)
    smaller = GaussianMap.from_numpy(*(arrays[k][: len(gmap) * 3 // 4] for k in names), device=device)
    report = {"device": wp.get_device(device).name, "cases": {}}
    for tile_stride in (1, 2):
        cfg = TrackingConfig(tile_stride=tile_stride, direct_levels=0, iters=30, lr=5e-3)
        trackers = {
            "eager_a": Tracker(replace(cfg, graph="off"), cam, device),
            "eager_b": Tracker(replace(cfg, graph="off"), cam, device),
            "graph": Tracker(replace(cfg, graph="on"), cam, device),
        }
        rows = []
        for i, m in enumerate([gmap, gmap, gmap, smaller, smaller, gmap], start=1):
            rgb, depth = scene["observe"](i)
            T0 = perturbed(poses[i], 0.01, 1.0, seed=i)
            res = {k: t.track(rgb, depth, m, T0) for k, t in trackers.items()}
            row = {"frame": i, "map": "smaller" if m is smaller else "full"}
            for k, r in res.items():
                row[f"loss_{k}"] = float(r.loss)
                row[f"error_mm_{k}"] = 1e3 * pose_error(r.T_WC, poses[i])[0]
            for a, b in (("eager_a", "eager_b"), ("eager_a", "graph")):
                dt, dr = pose_error(res[a].T_WC, res[b].T_WC)
                row[f"{a}_vs_{b}_mm"], row[f"{a}_vs_{b}_deg"] = 1e3 * dt, dr
            rows.append(row)
            print(
                f"stride {tile_stride} frame {i} ({row['map']}): eager-eager {row['eager_a_vs_eager_b_mm']:.4f} mm, "
                f"eager-graph {row['eager_a_vs_graph_mm']:.4f} mm; loss "
                + " ".join(f"{k} {row[f'loss_{k}']:.3e}" for k in trackers)
            )
        report["cases"][f"tile_stride_{tile_stride}"] = rows
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "graph_determinism.json").write_text(json.dumps(report, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
