"""The 7-Scenes colour camera's radial distortion, measured without the SLAM's map or the ground truth:
frame pairs (i, i + gap) aligned photometrically under each hypothesis k1, scored by what they leave.

    python experiments/bench/sevenscenes_distortion.py --data DATA/7scenes-redkitchen \
        --trajectory RUN_DIR/trajectory.txt --gap 24 --k1 0 -0.02 -0.035 -0.05 \
        [--k2 0] [--fx 526] [--cx 322] [--cy 238] [--out FILE.json]

For each hypothesis the loader undoes k1 (``dataset.colour_distortion``, depth registered as the SLAM sees
it); every 25th frame i is paired with frame i + gap.  Frame i's textured pixels with measured depth are
moved into frame j by a relative pose and a gain and bias, fitted by robust least squares (Huber at 0.03
of the grey range) from the run's trajectory (only its starting point), and sampled there.  The score is
the median |residual| in grey levels after the fit, over the centre (radius below 0.35 of the focal
length) and the periphery (above 0.55), averaged over the pairs: the right lens model lowers the
periphery's.  Results: ``experiments/results/slam.md``, "7-Scenes calibration".
"""

from __future__ import annotations

import argparse
import json

import cv2
import numpy as np
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from rgs_warp.datasets import SevenScenesDataset
from rgs_warp.io.trajectory import read_tum_trajectory


def pair_residuals(ds, poses, i, j, rng) -> tuple[float, float]:
    """Median |residual| (grey levels) over the centre and the periphery of pair (i, j) after the fit."""
    cam = ds.camera
    a, b = ds[i], ds[j]
    grey_i = cv2.GaussianBlur(cv2.cvtColor(a.rgb, cv2.COLOR_RGB2GRAY), (0, 0), 1.0)
    grey_j = cv2.GaussianBlur(cv2.cvtColor(b.rgb, cv2.COLOR_RGB2GRAY), (0, 0), 1.0)
    gx = cv2.Sobel(grey_i, cv2.CV_32F, 1, 0) / 8.0
    gy = cv2.Sobel(grey_i, cv2.CV_32F, 0, 1) / 8.0
    use = (a.depth > 0.3) & (np.hypot(gx, gy) > 0.01)
    use[:8], use[-8:], use[:, :8], use[:, -8:] = False, False, False, False
    idx = np.flatnonzero(use)
    idx = rng.choice(idx, min(40000, idx.size), replace=False)
    v, u = np.divmod(idx, cam.width)
    z = a.depth.ravel()[idx].astype(np.float64)
    pts = np.stack([(u - cam.cx) / cam.fx * z, (v - cam.cy) / cam.fy * z, z], axis=1)
    ref = grey_i.ravel()[idx]
    radius = np.hypot((u - cam.cx) / cam.fx, (v - cam.cy) / cam.fy)
    T = np.linalg.inv(poses[j]) @ poses[i]
    x0 = np.r_[Rotation.from_matrix(T[:3, :3]).as_rotvec(), T[:3, 3], 1.0, 0.0]
    n = idx.size
    rows = -(-n // 256)  # cv2.remap takes at most 32767 columns: sample on a rows x 256 grid

    def residual(x, valid_only=False):
        q = pts @ Rotation.from_rotvec(x[:3]).as_matrix().T + x[3:6]
        pu = np.zeros(rows * 256, np.float32)
        pv = np.zeros(rows * 256, np.float32)
        pu[:n] = cam.fx * q[:, 0] / q[:, 2] + cam.cx
        pv[:n] = cam.fy * q[:, 1] / q[:, 2] + cam.cy
        seen = cv2.remap(grey_j, pu.reshape(rows, 256), pv.reshape(rows, 256), cv2.INTER_LINEAR).ravel()[:n]
        inside = (pu[:n] > 2) & (pu[:n] < cam.width - 3) & (pv[:n] > 2) & (pv[:n] < cam.height - 3)
        r = np.where(inside, x[6] * seen + x[7] - ref, 0.0)
        return (r, inside) if valid_only else r

    fit = least_squares(residual, x0, loss="huber", f_scale=0.03, diff_step=1e-4, max_nfev=60)
    r, inside = residual(fit.x, valid_only=True)
    r, radius = np.abs(r[inside]) * 255.0, radius[inside]
    centre, periphery = radius < 0.35, radius > 0.55
    return (
        float(np.median(r[centre])) if centre.sum() > 500 else np.nan,
        float(np.median(r[periphery])) if periphery.sum() > 500 else np.nan,
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", required=True, help="the 7-Scenes sequence folder")
    ap.add_argument("--trajectory", required=True, help="a run's trajectory.txt (the fits' starting poses)")
    ap.add_argument("--gap", type=int, default=24, help="frames between the two of a pair")
    ap.add_argument("--k1", type=float, nargs="+", default=[0.0, -0.02, -0.035, -0.05])
    ap.add_argument("--k2", type=float, default=0.0, help="the second radial coefficient, for every k1")
    ap.add_argument("--fx", type=float, default=526.0, help="the colour camera's focal length (px)")
    ap.add_argument("--cx", type=float, default=322.0, help="its principal point (px)")
    ap.add_argument("--cy", type=float, default=238.0)
    ap.add_argument("--out", default="", help="JSON file of the results")
    args = ap.parse_args()

    stamps, traj = read_tum_trajectory(args.trajectory)
    results = []
    for k1 in args.k1:
        ds = SevenScenesDataset(
            args.data,
            colour_intrinsics=(args.fx, args.fx, args.cx, args.cy),
            colour_distortion=(k1, args.k2, 0.0, 0.0, 0.0),
        )
        poses = {}
        for k in range(len(ds)):
            poses[k] = traj[int(np.argmin(np.abs(stamps - k / 30.0)))]
        pairs = [(i, i + args.gap) for i in range(0, len(ds) - args.gap, 25)]
        rng = np.random.default_rng(0)
        scores = np.array([pair_residuals(ds, poses, i, j, rng) for i, j in pairs])
        row = {
            "k1": k1,
            "k2": args.k2,
            "fx": args.fx,
            "cx": args.cx,
            "cy": args.cy,
            "gap": args.gap,
            "pairs": len(pairs),
            "centre": round(float(np.nanmean(scores[:, 0])), 3),
            "periphery": round(float(np.nanmean(scores[:, 1])), 3),
        }
        results.append(row)
        print(json.dumps(row), flush=True)
    if args.out:
        with open(args.out, "w") as f:
            json.dump(results, f, indent=1)


if __name__ == "__main__":
    main()
