"""Is the 7-Scenes ground truth right where our tracker disagrees with it?  (experiments/results/slam.md:
frames 100-199 of redkitchen seq-01 come out 12-13 % short in every run, whatever the tracking and
mapping settings.)

A check that shares nothing with our tracker or map: point-to-plane ICP (Open3D) between the raw
depth images of frames i and i + gap (the depth camera, 585 px, no registration), started at the
ground-truth relative pose and, separately, at the identity.  For each pair: the ratio of the ICP
translation along the ground truth's to the ground truth's length.  Median ratio per stretch of
frames; 1 = depth agrees with the ground truth's motion.

    python experiments/sevenscenes_icp_check.py [FOLDER] [--gap 5] [--out F.json]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import cv2
import numpy as np
import open3d as o3d

DEPTH = (585.0, 585.0, 320.0, 240.0)
STRETCHES = ((0, 100), (100, 200), (200, 300), (300, 400), (400, 499))


def cloud(folder: Path, i: int) -> o3d.geometry.PointCloud:
    raw = cv2.imread(str(folder / f"frame-{i:06d}.depth.png"), cv2.IMREAD_UNCHANGED).astype(np.float64)
    raw[(raw == 65535) | (raw < 300) | (raw > 4000)] = 0.0  # 7-Scenes: mm, 65535 = invalid
    fx, fy, cx, cy = DEPTH
    v, u = np.nonzero(raw)
    z = raw[v, u] / 1000.0
    pts = np.stack([(u - cx) * z / fx, (v - cy) * z / fy, z], axis=1)
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
    pc = pc.voxel_down_sample(0.01)
    pc.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=0.05, max_nn=30))
    return pc


def pose(folder: Path, i: int) -> np.ndarray:
    return np.loadtxt(folder / f"frame-{i:06d}.pose.txt").reshape(4, 4)


def icp(source, target, init: np.ndarray) -> np.ndarray:
    loss = o3d.pipelines.registration.TukeyLoss(k=0.02)
    est = o3d.pipelines.registration.TransformationEstimationPointToPlane(loss)
    crit = o3d.pipelines.registration.ICPConvergenceCriteria(max_iteration=60)
    return np.asarray(o3d.pipelines.registration.registration_icp(source, target, 0.05, init, est, crit).transformation)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    shared = Path(__file__).resolve().parents[2] / "shared/data"
    ap.add_argument("folder", nargs="?", default=str(shared / "7scenes-redkitchen"))
    ap.add_argument("--gap", type=int, default=5)
    ap.add_argument("--every", type=int, default=2)
    ap.add_argument("--out", default="")
    args = ap.parse_args(argv)
    folder = Path(args.folder)
    n = len(list(folder.glob("frame-*.depth.png")))
    pairs = []
    for i in range(0, n - args.gap, args.every):
        j = i + args.gap
        Ti, Tj = pose(folder, i), pose(folder, j)
        T_ij = np.linalg.inv(Ti) @ Tj  # frame j's camera in frame i's: maps j's points into i
        t_gt = T_ij[:3, 3]
        length = float(np.linalg.norm(t_gt))
        if length < 0.01:
            continue
        src, dst = cloud(folder, j), cloud(folder, i)
        row = {"i": i, "gt_m": length}
        for name, init in (("from_gt", T_ij), ("from_identity", np.eye(4))):
            T = icp(src, dst, init)
            row[name] = float(np.dot(T[:3, 3], t_gt) / length**2)
        pairs.append(row)
    table = []
    for a, b in STRETCHES:
        sel = [p for p in pairs if a <= p["i"] < b]
        if sel:
            table.append(
                {
                    "frames": f"{a}-{b - 1}",
                    "pairs": len(sel),
                    "gt_step_cm": float(100 * np.median([p["gt_m"] for p in sel])),
                    "ratio_from_gt": float(np.median([p["from_gt"] for p in sel])),
                    "ratio_from_identity": float(np.median([p["from_identity"] for p in sel])),
                }
            )
    print(f"ICP translation along the ground truth's / its length, frames i -> i + {args.gap} (median)")
    print("| frames | pairs | GT step (cm) | ICP from GT | ICP from identity |")
    print("|---|---|---|---|---|")
    for r in table:
        print(
            f"| {r['frames']} | {r['pairs']} | {r['gt_step_cm']:.1f} | {r['ratio_from_gt']:.3f} "
            f"| {r['ratio_from_identity']:.3f} |"
        )
    if args.out:
        Path(args.out).write_text(json.dumps({"gap": args.gap, "table": table, "pairs": pairs}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
