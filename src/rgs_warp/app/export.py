"""Mesh export: the TSDF fusion of the map's depth and colour rendered at every keyframe, as a coloured
triangle mesh (PLY, opens in Open3D and MeshLab); the same surface the mesh metrics score.

    python -m rgs_warp.export RUN_DIR [--out PATH] [--voxel-m 0.01] [--max-depth-m 5]

reads a run folder written by ``python -m rgs_warp.slam`` (or ``SLAM.save``) and writes
``RUN_DIR/mesh.ply``.  Needs open3d, the optional extra ``mesh``.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path

import numpy as np

# rendered pixels whose accumulated opacity is below this carry no depth into the fusion
MIN_ALPHA = 0.5


def keyframe_renders(slam, poses: Sequence[np.ndarray]) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Depth (metres, alpha-normalised, 0 where the map covers less than ``MIN_ALPHA``) and colour of
    the map rendered from each camera-to-world pose, as NumPy arrays."""
    depths, colours = [], []
    for T_WC in poses:
        res = slam.render(T_WC)
        alpha = res.alpha.numpy()
        depth = np.where(alpha > MIN_ALPHA, res.depth.numpy() / np.maximum(alpha, 1e-6), 0.0)
        depths.append(depth.astype(np.float32))
        colours.append(np.clip(res.color.numpy(), 0.0, 1.0).astype(np.float32))
    return depths, colours


def fuse_keyframes(slam, voxel_m: float = 0.01, max_depth_m: float = 5.0, colour: bool = True):
    """The Open3D triangle mesh of the TSDF fusion of the map rendered at every keyframe (their poses
    in ``slam.trajectory()``)."""
    from rgs_warp.eval import tsdf_fuse

    _, poses = slam.trajectory()
    keyframe_poses = [poses[i] for i in slam.keyframe_indices if i < len(poses)]
    if not keyframe_poses:
        raise ValueError("the run has no keyframe to render: no mesh")
    depths, colours = keyframe_renders(slam, keyframe_poses)
    return tsdf_fuse(
        depths,
        keyframe_poses,
        slam.camera,
        voxel_m=voxel_m,
        max_depth_m=max_depth_m,
        colours=colours if colour else None,
    )


def export_mesh(slam, path: str | Path, voxel_m: float = 0.01, max_depth_m: float = 5.0) -> Path:
    """Write the coloured keyframe mesh (``fuse_keyframes``) as PLY to ``path``; returns the path."""
    from rgs_warp.eval.reconstruction import require_open3d

    mesh = fuse_keyframes(slam, voxel_m, max_depth_m)
    if len(mesh.triangles) == 0:
        raise ValueError("the fused mesh is empty: the map renders no surface at its keyframes")
    path = Path(path)
    if not require_open3d().io.write_triangle_mesh(str(path), mesh, write_vertex_colors=True):
        raise OSError(f"{path}: open3d could not write the mesh")
    return path


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m rgs_warp.export", description=__doc__.split("\n\n")[0])
    ap.add_argument("run_dir", type=Path, help="a run folder (map.ply, trajectory.txt, keyframes.npz, config.yaml)")
    ap.add_argument("--out", type=Path, default=None, help="mesh path (default RUN_DIR/mesh.ply)")
    ap.add_argument("--voxel-m", type=float, default=0.01, help="TSDF voxel size in metres")
    ap.add_argument("--max-depth-m", type=float, default=5.0, help="rendered depth beyond this is not fused")
    ap.add_argument("--device", default=None, help="Warp device (default: the run's)")
    args = ap.parse_args(argv)
    from rgs_warp.app.progress import quiet_warp
    from rgs_warp.slam import SLAM

    quiet_warp()

    try:
        slam = SLAM.load(args.run_dir, device=args.device)
        path = export_mesh(slam, args.out or args.run_dir / "mesh.ply", args.voxel_m, args.max_depth_m)
    except (FileNotFoundError, ValueError, ImportError, OSError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 1
    print(f"mesh      {path}")
    return 0
