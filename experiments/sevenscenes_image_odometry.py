"""Is the 7-Scenes ATE our error or the reference's?  Two image-based trajectories against the
ground truth (KinectFusion's, depth only), slam.md "7-Scenes: an image-only odometry".

Input: the pair alignments of ``sevenscenes_pair_alignment.py --every 1 --out F.json`` (for every frame
i the relative pose i -> i + gap that the images alone explain best: direct alignment of frame i's
registered depth and grey levels into frame i + gap, started from the truth; nothing of the SLAM
system) and the TUM trajectories of SLAM runs on the same dataset (``python -m rgs_warp.slam
dataset=7scenes/redkitchen``).

1. Per pair and 100-frame stretch: how far each run's relative motion and the truth's are from the
   images' (angle between translation directions; angle of the rotation difference).
2. The image odometry: the pair alignments chained (gap interleaved chains, each started at the
   truth's pose of its first frame; a pair the alignment skipped takes the truth's motion).  Its ATE
   against the truth and against each run, and each run's against the truth (SE(3), all frames).
   If the odometry sits as far from the truth as the runs do, and close to the runs, the runs' ATE
   is mostly the reference's disagreement with the images, not tracking error.

    python experiments/sevenscenes_image_odometry.py PAIRS.json RUN/trajectory.txt [...] [--out F.json]

The control: pair alignments of the synthetic office (``sevenscenes_pair_alignment.py --dataset
synthetic --every 1 dataset.n_frames=500 dataset.width=640 dataset.height=360``), where the truth is
exact, give the odometry's own drift (no runs needed).

With ``--out F.json`` also F.png: orientation and position against the truth, per frame.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from rgs_warp.config import load_config
from rgs_warp.datasets import open_dataset
from rgs_warp.eval.ate import ate
from rgs_warp.geometry import rotation_angle_deg
from sevenscenes_pair_alignment import base_overrides  # experiments/, next to this script
from sevenscenes_pair_consistency import by_stretch, read_tum


def angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip(a @ b / max(np.linalg.norm(a) * np.linalg.norm(b), 1e-12), -1, 1))))


def chain(pairs: dict[int, np.ndarray], gt: np.ndarray, gap: int) -> np.ndarray:
    """Camera-to-world poses from the pair alignments (frame i's camera -> frame i + gap's)."""
    T = gt.copy()
    for start in range(gap):
        for i in range(start, len(gt) - gap, gap):
            rel = pairs.get(i, np.linalg.inv(gt[i + gap]) @ gt[i])
            T[i + gap] = T[i] @ np.linalg.inv(rel)
    return T


def plot(curves: dict[str, np.ndarray], gt: np.ndarray, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (a0, a1) = plt.subplots(2, 1, figsize=(9, 5), sharex=True)
    for name, T in curves.items():
        a0.plot([rotation_angle_deg(T[k, :3, :3].T @ gt[k, :3, :3]) for k in range(len(gt))], lw=0.9, label=name)
        a1.plot(100 * np.linalg.norm(T[:, :3, 3] - gt[:, :3, 3], axis=1), lw=0.9, label=name)
    a0.set_ylabel("orientation vs truth (deg)")
    a1.set_ylabel("position vs truth (cm)")
    a1.set_xlabel("frame (no alignment: all start at the truth's first pose)")
    a0.legend(fontsize=8)
    for a in (a0, a1):
        a.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("pairs", help="output of sevenscenes_pair_alignment.py --every 1")
    ap.add_argument("runs", nargs="*", help="TUM trajectories of SLAM runs (named by their folder, or file stem)")
    ap.add_argument("--out", default="")
    args = ap.parse_args(argv)
    record = json.loads(Path(args.pairs).read_text())
    if "T_aligned" not in record["rows"][0]:
        raise SystemExit(f"{args.pairs}: no T_aligned in its rows (rerun sevenscenes_pair_alignment.py)")
    gap = record["gap"]
    cfg = load_config([*base_overrides(record["dataset"]), *record["overrides"]])
    ds = open_dataset(cfg)
    gt = np.array([ds[k].pose_gt for k in range(len(ds))])
    pairs = {r["i"]: np.array(r["T_aligned"]) for r in record["rows"]}
    odometry = chain(pairs, gt, gap)
    paths = [Path(p) for p in args.runs]
    runs = {(p.parent.name if p.stem == "trajectory" else p.stem): read_tum(p) for p in paths}
    for name, T in runs.items():
        if len(T) != len(gt):
            raise SystemExit(f"{name}: {len(T)} poses, the dataset has {len(gt)}")

    rows = []
    for r in record["rows"]:
        i = r["i"]
        images, truth = pairs[i], np.linalg.inv(gt[i + gap]) @ gt[i]
        row = {"i": i, "truth": {}, "runs": {}}
        for key, rel in [("truth", truth)] + [(n, np.linalg.inv(T[i + gap]) @ T[i]) for n, T in runs.items()]:
            entry = {
                "direction_deg": angle_deg(rel[:3, 3], images[:3, 3]),
                "rotation_deg": rotation_angle_deg(rel[:3, :3].T @ images[:3, :3]),
            }
            if key == "truth":
                row["truth"] = entry
            else:
                row["runs"][key] = entry
        rows.append(row)
    table = []
    for frames, sel in by_stretch(rows, len(gt)):
        line = {"frames": frames, "pairs": len(sel)}
        for key in ["truth", *runs]:
            got = [r["truth"] if key == "truth" else r["runs"][key] for r in sel]
            line[key] = {m: float(np.median([g[m] for g in got])) for m in ("direction_deg", "rotation_deg")}
        table.append(line)
    ates = {"odometry_vs_truth": ate(odometry, gt)["rmse_cm"]}
    for name, T in runs.items():
        ates[f"{name}_vs_truth"] = ate(T, gt)["rmse_cm"]
        ates[f"odometry_vs_{name}"] = ate(odometry, T)["rmse_cm"]

    calib = " ".join(record["overrides"]) or ("our calibration" if record["dataset"] == "7scenes" else "")
    print(f"{record['dataset']} {calib}: relative motions (i, i + {gap}) against the images' (median per stretch)")
    heads = ["truth: direction / rotation deg"] + [f"{n}: direction / rotation" for n in runs]
    print("| frames | " + " | ".join(heads) + " |")
    print("|---" * (2 + len(runs)) + "|")
    for line in table:
        cells = [f"{line[k]['direction_deg']:.1f} / {line[k]['rotation_deg']:.2f}" for k in ["truth", *runs]]
        print(f"| {line['frames']} | " + " | ".join(cells) + " |")
    print("ATE (cm, SE(3), all frames): " + ", ".join(f"{k} {v:.2f}" for k, v in ates.items()))
    if args.out:
        out = {"pairs": args.pairs, "overrides": record["overrides"], "gap": gap, "table": table, "ate_cm": ates}
        out["runs"] = list(runs)
        Path(args.out).write_text(json.dumps(out, indent=1))
        plot({"image odometry": odometry, **runs}, gt, Path(args.out).with_suffix(".png"))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
