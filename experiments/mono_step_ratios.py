"""Where does a monocular run go wrong?  Per 10-frame piece: the estimated motion's length and rotation
over the truth's (slam.md, runs 32-35: on the synthetic office every run is exact until frame 60, then
the translation collapses in frames 60-90 while the rotation stays near the truth's, before tracking is
flagged lost at ~100).

The run's scale is fixed once, by a Sim(3) alignment of its first ``--scale_frames`` frames to the
truth (before anything goes wrong), so a length ratio below 1 is motion the tracker did not find, not
a change of gauge.

    python experiments/mono_step_ratios.py RUN/trajectory.txt [...] [--out F.json] [OVERRIDES...]

The overrides name the dataset whose ground truth the runs are scored against (default: the synthetic
office's trajectory, which ``synthetic/office0_replica_size`` shares at any image size).
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
from sevenscenes_pair_consistency import read_tum  # experiments/, next to this script

PIECE = 10


def ratios(est: np.ndarray, gt: np.ndarray, scale: float) -> list[dict]:
    rows = []
    for k in range(0, len(est) - PIECE + 1, PIECE):
        j = k + PIECE - 1
        true_m = float(np.linalg.norm(gt[j, :3, 3] - gt[k, :3, 3]))
        true_deg = rotation_angle_deg(gt[k, :3, :3].T @ gt[j, :3, :3])
        rows.append(
            {
                "frames": f"{k}-{j}",
                "true_cm": 100 * true_m,
                "true_deg": true_deg,
                "length_ratio": scale * float(np.linalg.norm(est[j, :3, 3] - est[k, :3, 3])) / max(true_m, 1e-9),
                "rotation_ratio": rotation_angle_deg(est[k, :3, :3].T @ est[j, :3, :3]) / max(true_deg, 1e-9),
            }
        )
    return rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("runs", nargs="+", help="TUM trajectories (named by their folder)")
    ap.add_argument("--scale_frames", type=int, default=50)
    ap.add_argument("--out", default="")
    args, overrides = ap.parse_known_args(argv)
    base = ["dataset=synthetic/office0", "dataset.width=160", "dataset.height=90", "dataset.n_frames=300"]
    trajectories = {Path(p).parent.name: read_tum(Path(p)) for p in args.runs}
    n = max(len(T) for T in trajectories.values())
    ds = open_dataset(load_config([*base, *overrides]), device="cpu")
    if len(ds) < n:
        raise SystemExit(f"the dataset has {len(ds)} frames, a run has {n}: give its dataset.n_frames")
    gt = np.array([ds[k].pose_gt for k in range(n)])
    record = {"piece_frames": PIECE, "scale_frames": args.scale_frames, "runs": {}}
    for name, est in trajectories.items():
        start = ate(est[: args.scale_frames], gt[: args.scale_frames], align="sim3")
        rows = ratios(est, gt[: len(est)], start["align_scale"])
        record["runs"][name] = {"ate_scale_frames_cm": start["rmse_cm"], "pieces": rows}
        print(f"{name}: Sim(3) ATE over frames 0-{args.scale_frames - 1}: {start['rmse_cm']:.2f} cm")
        print("  length ratio:   " + " ".join(f"{r['length_ratio']:.2f}" for r in rows))
        print("  rotation ratio: " + " ".join(f"{r['rotation_ratio']:.2f}" for r in rows))
    if args.out:
        Path(args.out).write_text(json.dumps(record, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
