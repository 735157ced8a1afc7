"""Mesh metrics (Acc / Comp / Comp.Ratio, §3) of runs made on a machine without open3d:
``experiments/bench/slam.py --diagnose`` writes ``mesh_inputs.tar.gz`` (per case: half-resolution
rendered depth of every keyframe, their poses, the camera and, when small, the dataset's
ground-truth mesh); this fuses the depth with the same TSDF and metrics as ``python -m
rgs_warp.slam`` (``rgs_warp.eval.tsdf_fuse`` / ``mesh_metrics``) and prints / writes JSON.

    python experiments/bench/mesh_from_inputs.py OUT/mesh_inputs.tar.gz [--gt-mesh mesh.ply] [--json out.json]
"""

from __future__ import annotations

import argparse
import json
import tarfile
import tempfile
from pathlib import Path

import numpy as np


def case_metrics(folder: Path, gt_mesh: Path | None) -> dict:
    import open3d as o3d

    from rgs_warp.eval import mesh_metrics, tsdf_fuse
    from rgs_warp.types import Camera

    data = np.load(folder / "keyframe_depth.npz")
    fx, fy, cx, cy, w, h = (float(v) for v in data["camera"])
    camera = Camera(fx, fy, cx, cy, int(w), int(h))
    depths = [d.astype(np.float32) / 1000.0 for d in data["depth_mm"]]
    gt_path = gt_mesh or folder / "mesh_gt.ply"
    if not Path(gt_path).is_file():
        return {"error": f"{gt_path}: no ground-truth mesh (pass --gt-mesh)"}
    rec = tsdf_fuse(depths, list(data["poses"]), camera)
    gt = o3d.io.read_triangle_mesh(str(gt_path))
    return mesh_metrics(rec, gt) | {"keyframes": len(depths), "resolution": [int(w), int(h)]}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("inputs", type=Path, help="mesh_inputs.tar.gz or its extracted folder")
    ap.add_argument("--gt-mesh", type=Path, default=None, help="ground-truth mesh for every case")
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        root = args.inputs
        if root.is_file():
            with tarfile.open(root) as tar:
                tar.extractall(tmp, filter="data")
            root = Path(tmp) / "mesh_inputs"
        results = {case.name: case_metrics(case, args.gt_mesh) for case in sorted(root.iterdir()) if case.is_dir()}
    for name, m in results.items():
        if "error" in m:
            print(f"{name:<16} {m['error']}")
        else:
            print(
                f"{name:<16} Acc {m['acc_cm']:.2f} cm  Comp {m['comp_cm']:.2f} cm  "
                f"Comp.Ratio {m['comp_ratio_pct']:.1f} %  ({m['keyframes']} keyframes)"
            )
    if args.json:
        args.json.write_text(json.dumps(results, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
