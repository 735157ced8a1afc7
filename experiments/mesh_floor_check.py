"""Floor of the mesh metrics on a synthetic scene: the same TSDF fusion and metrics as a run
(``rgs_warp.eval.tsdf_fuse`` / ``mesh_metrics``) fed with the *ground-truth* depth at the keyframe
poses of a run, next to the map's rendered depth, both from a case folder of the ``mesh_inputs.tar.gz``
that ``experiments/bench/slam.py --diagnose`` writes.  Result: experiments/results/slam.md (runs 4-8).

    python experiments/mesh_floor_check.py MESH_INPUTS/office --scene office0 --width 1200 --height 680
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np


def main(argv=None) -> int:
    import open3d as o3d

    from rgs_warp.datasets.synthetic import SequenceRenderer, SyntheticConfig
    from rgs_warp.eval import mesh_metrics, tsdf_fuse
    from rgs_warp.types import Camera

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("case", type=Path, help="a case folder of mesh_inputs (keyframe_depth.npz, mesh_gt.ply)")
    ap.add_argument("--scene", default="office0")
    ap.add_argument("--width", type=int, default=1200)
    ap.add_argument("--height", type=int, default=680)
    ap.add_argument("--frames", type=int, default=300)
    args = ap.parse_args(argv)
    data = np.load(args.case / "keyframe_depth.npz")
    fx, fy, cx, cy, w, h = (float(v) for v in data["camera"])
    camera = Camera(fx, fy, cx, cy, int(w), int(h))
    cfg = SyntheticConfig(scene=args.scene, width=args.width, height=args.height, n_frames=args.frames)
    seq = SequenceRenderer(cfg, device="cpu")
    poses = list(data["poses"])
    truth = [seq.renderer.render(camera, T[None], T, n_ss=1, seed=0)[1].astype(np.float32) for T in poses]
    rendered = [d.astype(np.float32) / 1000.0 for d in data["depth_mm"]]
    diffs = np.concatenate([(r - t)[(r > 0) & (t > 0)] for r, t in zip(rendered, truth, strict=True)])
    print(
        f"map depth - true depth: median |.| {100 * np.median(np.abs(diffs)):.2f} cm, signed median "
        f"{100 * np.median(diffs):.2f} cm, mean |.| {100 * np.mean(np.abs(diffs)):.2f} cm"
    )
    gt_mesh = o3d.io.read_triangle_mesh(str(args.case / "mesh_gt.ply"))
    for name, depths in (("ground-truth depth", truth), ("map depth", rendered)):
        print(name, mesh_metrics(tsdf_fuse(depths, poses, camera), gt_mesh))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
