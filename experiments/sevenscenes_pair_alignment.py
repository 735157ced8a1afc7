"""How long is each 7-Scenes motion by the images alone?  A check without SLAM, for several colour
calibrations (experiments/results/slam.md, runs 26-31: frames 100-199 come out 12 % short in every
run, and the run's relative motions fit the images better than the ground truth's).

For frame pairs (i, i + gap): the relative pose that best explains the pair is found by direct
alignment, as in ``sevenscenes_pair_consistency.py`` (frame i's registered depth lifted to 3D, moved
into frame i + gap, frame i + gap's grey level sampled there), here minimised over the 6 pose
parameters and a gain (``scipy.optimize.least_squares``, soft-L1, from the ground truth's relative
pose).  Nothing of our tracker, map or renderer is used; the only inputs are the images, the depth,
and the calibration that registers the depth to the colour camera.

Per 100-frame stretch: the median of |t_aligned| / |t_truth| (1 = the images agree with the length of
the ground truth's motion; 0.88 = as short as our runs) and of the angle between the two directions.
With ``--out F.json`` also F.png (per pair: the angle and the length ratio); each row of F.json keeps
the aligned relative pose (``T_aligned``), which ``sevenscenes_image_odometry.py`` chains.  Run with the dataset
overrides of a calibration, e.g.

    python experiments/sevenscenes_pair_alignment.py --out F.json
    python experiments/sevenscenes_pair_alignment.py --out F.json dataset.colour_intrinsics=[525,525,320,240]
    python experiments/sevenscenes_pair_alignment.py --out F.json --dataset synthetic  # control: exact truth
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import cv2
import numpy as np
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from rgs_warp.config import load_config
from rgs_warp.datasets import open_dataset
from sevenscenes_pair_consistency import bilinear, by_stretch  # experiments/, next to this script


def base_overrides(dataset: str) -> list[str]:
    """The config of ``--dataset``: the shared 7-Scenes sequence, or the synthetic control."""
    if dataset == "7scenes":
        shared = Path(__file__).resolve().parents[2] / "shared/data"
        return ["dataset=7scenes/redkitchen", f"data_root={shared}", "dataset.path=7scenes-redkitchen"]
    return ["dataset=synthetic/office0", "dataset.width=320", "dataset.height=180"]


def grey(rgb: np.ndarray, sigma: float) -> np.ndarray:
    return cv2.GaussianBlur(rgb @ np.array([0.299, 0.587, 0.114], dtype=np.float32), (0, 0), sigma)


def pose(params: np.ndarray, T0: np.ndarray) -> np.ndarray:
    """exp-like left update of T0: rotation vector params[:3], translation params[3:6] (metres)."""
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(params[:3]).as_matrix()
    T[:3, 3] = params[3:6]
    return T @ T0


def align(gi, gj, X: np.ndarray, ref: np.ndarray, K: np.ndarray, T0: np.ndarray) -> tuple[np.ndarray, float, float]:
    """The relative pose (frame i's camera -> frame j's) minimising |g I_j(warp) - I_i|, from T0;
    returns it, the median residual at T0 and at the optimum (same pixels)."""
    h, w = gj.shape

    def project(T, X):
        Y = X @ T[:3, :3].T + T[:3, 3]
        z = np.maximum(Y[:, 2], 1e-3)
        return K[0, 0] * Y[:, 0] / z + K[0, 2], K[1, 1] * Y[:, 1] / z + K[1, 2]

    u0, v0 = project(T0, X)
    inside = (u0 >= 2) & (u0 < w - 3) & (v0 >= 2) & (v0 < h - 3)
    Xs, refs = X[inside], ref[inside]

    def residual(p):
        return p[6] * bilinear(gj, *project(pose(p, T0), Xs)) - refs

    g0 = float(np.median(refs) / max(np.median(bilinear(gj, u0[inside], v0[inside])), 1e-6))
    p0 = np.array([0, 0, 0, 0, 0, 0, g0], dtype=np.float64)
    sol = least_squares(residual, p0, loss="soft_l1", f_scale=0.02, x_scale=[1e-3] * 6 + [1e-2], diff_step=1e-4)
    return pose(sol.x, T0), float(np.median(np.abs(residual(p0)))), float(np.median(np.abs(residual(sol.x))))


def plot(rows: list[dict], gap: int, title: str, path: Path) -> None:
    """Per pair: angle between the aligned and the true direction of motion, and the length ratio."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    i = [r["i"] for r in rows]
    fig, (a0, a1) = plt.subplots(2, 1, figsize=(9, 4.6), sharex=True)
    a0.plot(i, [r["angle_deg"] for r in rows], ".", ms=3)
    a0.set_ylabel("direction: aligned vs truth (deg)")
    a0.set_ylim(0, 60)
    a1.plot(i, [r["along_ratio"] for r in rows], ".", ms=3)
    a1.axhline(1.0, color="k", lw=0.6)
    a1.set_ylim(0, 2)
    a1.set_ylabel("aligned along truth / truth")
    a1.set_xlabel(f"frame i (pair i, i + {gap})")
    for a in (a0, a1):
        a.grid(alpha=0.3)
    a0.set_title(title, fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("overrides", nargs="*", help="config overrides (after the dataset's), e.g. a calibration")
    ap.add_argument("--dataset", choices=("7scenes", "synthetic"), default="7scenes")
    ap.add_argument("--gap", type=int, default=6)
    ap.add_argument("--every", type=int, default=5)
    ap.add_argument("--pixel_step", type=int, default=3, help="every n-th pixel of frame i in each direction")
    ap.add_argument("--sigma", type=float, default=1.5, help="Gaussian blur of the grey images (px)")
    ap.add_argument("--out", default="")
    args = ap.parse_args(argv)
    cfg = load_config([*base_overrides(args.dataset), *args.overrides])
    ds = open_dataset(cfg)
    cam = ds.camera
    K = np.array([[cam.fx, 0, cam.cx], [0, cam.fy, cam.cy], [0, 0, 1]])
    rows = []
    t0 = time.perf_counter()
    for i in range(0, len(ds) - args.gap, args.every):
        fi, fj = ds[i], ds[i + args.gap]
        gi, gj = grey(fi.rgb, args.sigma), grey(fj.rgb, args.sigma)
        d = fi.depth[:: args.pixel_step, :: args.pixel_step]
        v, u = np.nonzero(d > 0)
        z = d[v, u].astype(np.float64)
        u, v = u * args.pixel_step, v * args.pixel_step
        X = np.stack([(u - K[0, 2]) * z / K[0, 0], (v - K[1, 2]) * z / K[1, 1], z], axis=1)
        T_gt = np.linalg.inv(fj.pose_gt) @ fi.pose_gt
        T_opt, r_gt, r_opt = align(gi, gj, X, gi[v, u].astype(np.float64), K, T_gt)
        t_gt, t_opt = T_gt[:3, 3], T_opt[:3, 3]
        n_gt = float(np.linalg.norm(t_gt))
        if n_gt < 5e-3:  # too little motion for a length ratio
            continue
        cos = float(t_opt @ t_gt / max(np.linalg.norm(t_opt) * n_gt, 1e-12))
        rows.append(
            {
                "i": i,
                "gt_cm": 100 * n_gt,
                "aligned_cm": 100 * float(np.linalg.norm(t_opt)),
                "along_ratio": float(t_opt @ t_gt) / n_gt**2,
                "angle_deg": float(np.degrees(np.arccos(np.clip(cos, -1, 1)))),
                "T_aligned": np.round(T_opt, 9).tolist(),  # frame i's camera -> frame i + gap's
                "residual_gt": r_gt,
                "residual_aligned": r_opt,
            }
        )
    table = [
        {
            "frames": frames,
            "pairs": len(sel),
            "along_ratio_median": float(np.median([r["along_ratio"] for r in sel])),
            "angle_deg_median": float(np.median([r["angle_deg"] for r in sel])),
            "gt_cm_median": float(np.median([r["gt_cm"] for r in sel])),
            "residual_gt": float(np.median([r["residual_gt"] for r in sel])),
            "residual_aligned": float(np.median([r["residual_aligned"] for r in sel])),
        }
        for frames, sel in by_stretch(rows, len(ds))
    ]
    took = time.perf_counter() - t0
    print(f"{args.dataset} {' '.join(args.overrides)}: {len(rows)} pairs (i, i + {args.gap}), {took:.0f} s")
    print("| frames | pairs | true step cm | aligned along truth / truth | angle deg | residual truth | aligned |")
    print("|---|---|---|---|---|---|---|")
    for r in table:
        print(
            f"| {r['frames']} | {r['pairs']} | {r['gt_cm_median']:.1f} | {r['along_ratio_median']:.3f} | "
            f"{r['angle_deg_median']:.1f} | {r['residual_gt']:.4f} | {r['residual_aligned']:.4f} |"
        )
    if args.out:
        head = {"dataset": args.dataset, "overrides": args.overrides, "gap": args.gap, "table": table}
        body = ",\n".join(json.dumps(r) for r in rows)  # one pair a line
        Path(args.out).write_text(json.dumps(head, indent=1)[:-2] + ',\n "rows": [\n' + body + "\n ]\n}\n")
        plot(rows, args.gap, f"{args.dataset} {' '.join(args.overrides)}", Path(args.out).with_suffix(".png"))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
