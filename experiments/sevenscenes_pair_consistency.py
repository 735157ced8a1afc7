"""Which relative motions explain the 7-Scenes images better: the ground truth's, or a SLAM run's?

For frame pairs (i, i + gap): frame i's registered depth is lifted to 3D, moved into frame i + gap
with the relative pose under test, and frame i + gap's colour is sampled there (bilinear).  The score
of a pose is the median absolute grey-level difference against frame i over the pixels that land
inside the image, after a gain (ratio of the medians) for the auto-exposure.  The same pixels are
used for both poses of a pair.  Lower is better.  Per 100-frame stretch: median score of each, and
the fraction of pairs where the run's motion explains the images better.

    python experiments/sevenscenes_pair_consistency.py RUN/trajectory.txt [OVERRIDES...] [--out F.json]

The trajectory is the run's TUM file (``python -m rgs_warp.slam ...``), in the loader's ground-truth
frame (the colour camera for 7-Scenes); the overrides name the run's dataset.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from rgs_warp.config import load_config
from rgs_warp.datasets import open_dataset

STRETCH = 100


def read_tum(path: Path) -> np.ndarray:
    a = np.loadtxt(path)
    T = np.tile(np.eye(4), (len(a), 1, 1))
    T[:, :3, 3] = a[:, 1:4]
    T[:, :3, :3] = Rotation.from_quat(a[:, 4:8]).as_matrix()
    return T


def grey(rgb: np.ndarray) -> np.ndarray:
    return cv2.GaussianBlur(rgb @ np.array([0.299, 0.587, 0.114], dtype=np.float32), (5, 5), 1.0)


def sample_coords(depth: np.ndarray, K: np.ndarray, T_ji: np.ndarray):
    """Pixels of frame i with depth, moved by T_ji (frame i's camera -> frame j's) and projected."""
    v, u = np.nonzero(depth > 0)
    z = depth[v, u].astype(np.float64)
    X = np.stack([(u - K[0, 2]) * z / K[0, 0], (v - K[1, 2]) * z / K[1, 1], z], axis=1)
    Y = X @ T_ji[:3, :3].T + T_ji[:3, 3]
    ok = Y[:, 2] > 0.1
    uj = K[0, 0] * Y[:, 0] / np.maximum(Y[:, 2], 1e-6) + K[0, 2]
    vj = K[1, 1] * Y[:, 1] / np.maximum(Y[:, 2], 1e-6) + K[1, 2]
    h, w = depth.shape
    ok &= (uj >= 1) & (uj < w - 2) & (vj >= 1) & (vj < h - 2)
    return v, u, uj, vj, ok


def bilinear(img: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """img sampled at (x, y) (pixel centres at integers), bilinear; coordinates clamped into the image."""
    h, w = img.shape
    x = np.clip(x, 0, w - 1.001)
    y = np.clip(y, 0, h - 1.001)
    x0, y0 = np.floor(x).astype(int), np.floor(y).astype(int)
    fx, fy = x - x0, y - y0
    return (
        img[y0, x0] * (1 - fx) * (1 - fy)
        + img[y0, x0 + 1] * fx * (1 - fy)
        + img[y0 + 1, x0] * (1 - fx) * fy
        + img[y0 + 1, x0 + 1] * fx * fy
    )


def by_stretch(rows: list[dict], n: int) -> list[tuple[str, list[dict]]]:
    """The rows (pairs keyed by their first frame "i") of each STRETCH-frame piece of n frames."""
    out = []
    for a in range(0, n, STRETCH):
        sel = [r for r in rows if a <= r["i"] < a + STRETCH]
        if sel:
            out.append((f"{a}-{min(a + STRETCH, n) - 1}", sel))
    return out


def score(gi, gj, v, u, uj, vj, keep) -> float:
    ref = gi[v[keep], u[keep]]
    warped = bilinear(gj, uj[keep], vj[keep])
    gain = np.median(ref) / max(np.median(warped), 1e-6)
    return float(np.median(np.abs(gain * warped - ref)))


def plot(rows: list[dict], gap: int, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    i = [r["i"] for r in rows]
    fig, ax = plt.subplots(figsize=(9, 3.2))
    ax.plot(i, [r["gt"] for r in rows], ".-", lw=0.8, ms=3, label="ground-truth relative motion")
    ax.plot(i, [r["run"] for r in rows], ".-", lw=0.8, ms=3, label="the run's relative motion")
    ax.set_xlabel(f"frame i (pair i, i + {gap})")
    ax.set_ylabel("median |I_i - g I_j(warped)|")
    ax.legend(loc="upper left", fontsize=8)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("trajectory", help="a run's trajectory.txt (TUM)")
    ap.add_argument(
        "overrides",
        nargs="*",
        help="config overrides naming the dataset (default: the shared 7-Scenes sample; any dataset with "
        "depth and ground truth works, e.g. dataset=synthetic/office0 as a control where the truth is exact)",
    )
    ap.add_argument("--gap", type=int, default=6)
    ap.add_argument("--every", type=int, default=2)
    ap.add_argument("--out", default="")
    args = ap.parse_args(argv)
    shared = Path(__file__).resolve().parents[2] / "shared/data"
    cfg = load_config(
        args.overrides or ["dataset=7scenes/redkitchen", f"data_root={shared}", "dataset.path=7scenes-redkitchen"]
    )
    ds = open_dataset(cfg)
    cam = ds.camera
    K = np.array([[cam.fx, 0, cam.cx], [0, cam.fy, cam.cy], [0, 0, 1]])
    est = read_tum(Path(args.trajectory))
    n = min(len(ds), len(est))
    rows = []
    cache: dict[int, tuple] = {}

    def frame(k):
        if k not in cache:
            f = ds[k]
            cache[k] = (grey(f.rgb), f.depth, np.asarray(f.pose_gt))
            cache.pop(k - 3 * args.gap, None)
        return cache[k]

    for i in range(0, n - args.gap, args.every):
        j = i + args.gap
        gi, di, Ti = frame(i)
        gj, _, Tj = frame(j)
        poses = {"gt": np.linalg.inv(Tj) @ Ti, "run": np.linalg.inv(est[j]) @ est[i]}
        coords = {k: sample_coords(di, K, T) for k, T in poses.items()}
        keep = coords["gt"][4] & coords["run"][4]
        if keep.sum() < 1000:
            continue
        s = {k: score(gi, gj, *c[:4], keep) for k, c in coords.items()}
        rows.append({"i": i, "gt": s["gt"], "run": s["run"]})
    table = [
        {
            "frames": frames,
            "pairs": len(sel),
            "gt": float(np.median([r["gt"] for r in sel])),
            "run": float(np.median([r["run"] for r in sel])),
            "run_better": float(np.mean([r["run"] < r["gt"] for r in sel])),
        }
        for frames, sel in by_stretch(rows, n)
    ]
    print(f"median |I_i - g I_(i+{args.gap})(warped)| (grey 0-1): relative motion of the ground truth vs the run")
    print("| frames | pairs | ground truth | run | run better in |")
    print("|---|---|---|---|---|")
    for r in table:
        print(f"| {r['frames']} | {r['pairs']} | {r['gt']:.4f} | {r['run']:.4f} | {100 * r['run_better']:.0f} % |")
    if args.out:
        record = {"trajectory": args.trajectory, "gap": args.gap, "table": table, "rows": rows}
        Path(args.out).write_text(json.dumps(record, indent=1))
        plot(rows, args.gap, Path(args.out).with_suffix(".png"))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
