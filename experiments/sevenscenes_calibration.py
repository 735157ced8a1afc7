"""Measure 7-Scenes' colour camera against its depth camera (the dataset gives only the depth camera's
calibration, 585 / 585 / 320 / 240).

    python experiments/sevenscenes_calibration.py [FOLDER] [--out experiments/results/sevenscenes_calibration.json]

Score of a hypothesis (colour fx = fy, cx, cy, depth-to-colour offset tx): the mean colour gradient
magnitude at the colour pixels where the near sides of depth discontinuities (> 10 % jumps) land when
reprojected with it.  Discontinuities are object outlines, which are colour edges too, so the right
calibration puts them on high gradients.  A grid search over 20 frames (every 25th), repeated on three
disjoint frame sets; a coarse search without offset first, then a fine one with it.
"""

from __future__ import annotations

import argparse
import itertools
import json
from pathlib import Path

import cv2
import numpy as np

DEPTH = (585.0, 585.0, 320.0, 240.0)


def load(folder: Path, frames) -> list:
    data = []
    for i in frames:
        grey = cv2.imread(str(folder / f"frame-{i:06d}.color.jpg"), cv2.IMREAD_GRAYSCALE).astype(np.float32) / 255.0
        grey = cv2.GaussianBlur(grey, (5, 5), 1.0)
        grad = np.hypot(cv2.Sobel(grey, cv2.CV_32F, 1, 0), cv2.Sobel(grey, cv2.CV_32F, 0, 1))
        d = cv2.imread(str(folder / f"frame-{i:06d}.depth.png"), cv2.IMREAD_UNCHANGED).astype(np.float32) / 1000.0
        d[d >= 65.0] = 0.0
        far = cv2.erode(np.where(d > 0, d, 100.0).astype(np.float32), np.ones((3, 3)))
        edge = (d > 0) & (cv2.dilate(d, np.ones((3, 3))) > 1.1 * d) & (d <= far + 1e-6)
        v, u = np.nonzero(edge)
        z = d[v, u].astype(np.float64)
        fx, fy, cx, cy = DEPTH
        data.append((grad, np.stack([(u - cx) / fx * z, (v - cy) / fy * z, z], axis=1)))
    return data


def score(data, f: float, cx: float, cy: float, tx: float) -> float:
    values = []
    for grad, X in data:
        x, y, z = X[:, 0] + tx, X[:, 1], X[:, 2]
        u, v = f * x / z + cx, f * y / z + cy
        ok = (u >= 0) & (u < grad.shape[1] - 1) & (v >= 0) & (v < grad.shape[0] - 1)
        mu, mv = u[ok].astype(np.float32)[None], v[ok].astype(np.float32)[None]
        values.append(cv2.remap(grad, mu, mv, cv2.INTER_LINEAR)[0])
    return float(np.concatenate(values).mean())


def search(data) -> dict:
    grid = itertools.product(range(480, 621, 10), range(300, 341, 5), range(220, 261, 5))
    _, f0, cx0, cy0 = max((score(data, f, cx, cy, 0.0), f, cx, cy) for f, cx, cy in grid)
    fine = itertools.product(
        range(f0 - 8, f0 + 9, 2),
        np.round(np.arange(-0.05, 0.051, 0.005), 3),
        range(cx0 - 14, cx0 + 15, 2),
        range(cy0 - 6, cy0 + 7, 2),
    )
    s, f, tx, cx, cy = max((score(data, f, cx, cy, tx), f, tx, cx, cy) for f, tx, cx, cy in fine)
    return {
        "fx": f,
        "cx": cx,
        "cy": cy,
        "tx_m": float(tx),
        "score": s,
        "score_depth_calibration": score(data, 585.0, 320.0, 240.0, 0.0),
        "score_f525_no_offset": max(
            score(data, 525.0, cx, cy, 0.0) for cx in range(300, 341, 2) for cy in range(220, 261, 2)
        ),
    }


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("folder", nargs="?", default="../shared/data/7scenes-redkitchen")
    ap.add_argument("--out", default="experiments/results/sevenscenes_calibration.json")
    args = ap.parse_args(argv)
    folder = Path(args.folder)
    results = {}
    head = f"{'frames':<14} {'fx':>5} {'cx':>5} {'cy':>5} {'tx m':>6} {'score':>6}"
    print(f"{head} {'585 as given':>12} {'525 no offset':>13}")
    for first in (0, 8, 16):
        r = search(load(folder, range(first, 500, 25)))
        results[f"{first}::25"] = r
        print(
            f"{first:>3}, {first + 25}, ..  {r['fx']:>5} {r['cx']:>5} {r['cy']:>5} {r['tx_m']:>6.3f} "
            f"{r['score']:>6.3f} {r['score_depth_calibration']:>12.3f} {r['score_f525_no_offset']:>13.3f}"
        )
    Path(args.out).write_text(json.dumps(results, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
