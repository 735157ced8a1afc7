"""``python -m rgs_warp.slam [group=option ...] [key=value ...]``: run SLAM on a sequence.

The pipeline stages land issue by issue; until the tracker and mapper exist this command loads
and checks the whole sequence, writes the run folder (resolved config, dataset summary) and
prints the stages it will run.
"""

from __future__ import annotations

import json
import sys
import time
from datetime import datetime
from pathlib import Path

import numpy as np
from tqdm import tqdm

from rgs_warp.config import Config, ConfigError, help_text, load_config, save_config
from rgs_warp.datasets import DatasetError, open_dataset

USAGE = """usage: python -m rgs_warp.slam [group=option ...] [key=value ...]

examples:
  python -m rgs_warp.slam                                  # generated synthetic room (CPU-sized)
  python -m rgs_warp.slam dataset=replica/office0 data_root=/data tracking.iters=40
  python -m rgs_warp.slam dataset=7scenes/redkitchen dataset.path=../shared/data/7scenes-redkitchen
"""


def resolve_device(name: str) -> str:
    import warp as wp

    if name != "auto":
        return name
    return "cuda:0" if wp.is_cuda_available() else "cpu"


def make_run_dir(cfg: Config) -> Path:
    name = cfg.run_name or f"{cfg.dataset.type}-{cfg.dataset.name}-{datetime.now():%Y%m%d-%H%M%S}"
    run_dir = Path(cfg.output_dir) / name
    run_dir.mkdir(parents=True, exist_ok=True)
    return run_dir


def summarize_sequence(ds) -> dict:
    """Read every frame once (proving the sequence is complete and readable) and summarise it."""
    n_valid, n_px, d_min, d_max = 0, 0, np.inf, 0.0
    has_depth = has_gt = True
    positions = []
    for frame in tqdm(ds, total=len(ds), desc="checking frames", unit="frame", leave=False):
        if frame.depth is None:
            has_depth = False
        else:
            valid = frame.depth > 0
            n_valid += int(valid.sum())
            n_px += valid.size
            if valid.any():
                d_min, d_max = (
                    min(d_min, float(frame.depth[valid].min())),
                    max(d_max, float(frame.depth.max())),
                )
        if frame.pose_gt is None:
            has_gt = False
        else:
            positions.append(frame.pose_gt[:3, 3])
    c = ds.camera
    summary = {
        "dataset": repr(ds),
        "frames": len(ds),
        "resolution": [c.width, c.height],
        "intrinsics": {"fx": c.fx, "fy": c.fy, "cx": c.cx, "cy": c.cy},
        "depth": has_depth,
        "ground_truth_poses": has_gt,
    }
    if has_depth and n_px:
        summary["depth_valid_pct"] = round(100.0 * n_valid / n_px, 2)
        summary["depth_range_m"] = [round(d_min, 3), round(d_max, 3)]
    if has_gt and len(positions) > 1:
        steps = np.linalg.norm(np.diff(np.array(positions), axis=0), axis=1)
        summary["trajectory_length_m"] = round(float(steps.sum()), 3)
    return summary


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if any(a in ("-h", "--help") for a in argv):
        print(USAGE)
        print(help_text())
        return 0
    try:
        cfg = load_config(argv)
    except ConfigError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    device = resolve_device(cfg.device)
    try:
        ds = open_dataset(cfg, device=device)
    except (DatasetError, ValueError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 1
    run_dir = make_run_dir(cfg)
    save_config(cfg, run_dir / "config.yaml")
    t0 = time.perf_counter()
    try:
        summary = summarize_sequence(ds)
    except DatasetError as e:
        print(f"error: {e}", file=sys.stderr)
        return 1
    summary["load_seconds"] = round(time.perf_counter() - t0, 2)
    (run_dir / "dataset.json").write_text(json.dumps(summary, indent=2))
    print(f"dataset   {summary['dataset']}")
    print(
        f"          depth: {summary['depth']}, ground truth: {summary['ground_truth_poses']}, "
        f"loaded in {summary['load_seconds']} s"
    )
    for k in ("depth_valid_pct", "depth_range_m", "trajectory_length_m"):
        if k in summary:
            print(f"          {k}: {summary[k]}")
    print(f"device    {device}")
    print(f"mode      {cfg.mode}, method {cfg.method}")
    print(f"run dir   {run_dir}")
    t, k, m, p = cfg.tracking, cfg.keyframes, cfg.matching, cfg.mapping
    print(
        f"would run: Tracker (iters={t.iters}) -> KeyframeSelector (IoU < {k.iou_threshold}) -> "
        f"DenseMatcher ({m.backbone}) -> Triangulator -> Seeder -> Mapper (iters={p.iters}, window={p.window})"
    )
    print("note: the SLAM stages are not implemented yet; this run only loaded and checked the sequence.")
    return 0


if __name__ == "__main__":
    sys.exit(main())
