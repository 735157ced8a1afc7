"""How much of a run's held-out PSNR is the pose: each held-out frame scored at the run's pose and again
after tracking it once more against the saved map (from that pose; the keyframes alike, as the control).

    python experiments/bench/heldout_pose.py RUN_DIR [--rounds 3] [--out FILE.json]

RUN_DIR is a run folder (``SLAM.save``'s files); its ``config.yaml`` names the dataset.  Held out: every 5th
frame that is no keyframe.  A frame is tracked ``--rounds`` times (the direct alignment and the tracker's
steps each time, from the last round's pose); PSNR compensated (one gain and bias fitted,
``rgs_warp.eval.photometric``).  If the held-out frames gain much more than the keyframes, their poses, not
the map, hold their PSNR down.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from rgs_warp import SLAM, open_dataset
from rgs_warp.eval.photometric import compensate_exposure, psnr


def score(slam: SLAM, T: np.ndarray, rgb: np.ndarray) -> float:
    res = slam.render(T)
    render, alpha = res.color.numpy(), res.alpha.numpy()
    return psnr(np.clip(compensate_exposure(render, rgb, alpha), 0.0, 1.0), rgb)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("run_dir", type=Path)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--out", type=Path)
    ap.add_argument("--device")
    args = ap.parse_args()
    slam = SLAM.load(args.run_dir, device=args.device)
    ds = open_dataset(slam.cfg)
    keyframes = set(slam.keyframe_indices)
    rows = []
    for i in range(0, len(slam.poses), 5):
        frame = ds[i]
        T0 = np.asarray(slam.poses[i])
        before = score(slam, T0, frame.rgb)
        T = T0
        for _ in range(args.rounds):
            slam.tracker.reset(T)
            T = slam.tracker.track(frame.rgb, frame.depth, slam.map, T_init_WC=T).T_WC
        after = score(slam, T, frame.rgb)
        moved_mm = float(np.linalg.norm(T[:3, 3] - T0[:3, 3]) * 1e3)
        rows.append({"frame": i, "keyframe": i in keyframes, "before": before, "after": after, "moved_mm": moved_mm})
        print(json.dumps(rows[-1]), flush=True)
    summary = {}
    for name, sel in (("held_out", False), ("keyframes", True)):
        r = [x for x in rows if x["keyframe"] == sel]
        if r:
            summary[name] = {
                "frames": len(r),
                "psnr_before_db": float(np.mean([x["before"] for x in r])),
                "psnr_after_db": float(np.mean([x["after"] for x in r])),
                "moved_mm_median": float(np.median([x["moved_mm"] for x in r])),
            }
    print(json.dumps(summary, indent=1))
    if args.out:
        args.out.write_text(json.dumps({"summary": summary, "rows": rows}, indent=1))


if __name__ == "__main__":
    main()
