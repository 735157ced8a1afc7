"""What raw PSNR a perfect map could score on a sequence whose camera changes its exposure (issue 18's
raw target), from a finished run: its ``log.jsonl`` holds each frame's exposure as tracking estimated
it (frame = gain x render + bias, ``tracking.brightness``), and the frames are read from the dataset.

A perfect map in the run's colour gauge renders each scored frame as ``(frame - bias) / gain``; its raw
PSNR is that image's against the frame.  Any map with one colour (no per-frame exposure) is at best
this up to a constant gauge, so the script also reports the best constant gain ``g0`` applied to all
of them (``g0 (frame - bias) / gain``: the gauge chosen in hindsight).  Scored frames as the
evaluation picks them: every ``--every``-th frame, keyframes excluded.

    python experiments/analysis/raw_psnr_bound.py RUN_DIR DATA_DIR [--every 5] [--out result.json]

DATA_DIR: the 7-Scenes frames (``frame-NNNNNN.color.jpg``), e.g. ../shared/data/7scenes-redkitchen.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import cv2
import numpy as np


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    return float(-10.0 * np.log10(np.mean((a - b) ** 2)))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("run_dir", type=Path)
    ap.add_argument("data_dir", type=Path)
    ap.add_argument("--every", type=int, default=5)
    ap.add_argument("--out", type=Path)
    args = ap.parse_args(argv)
    log = [json.loads(line) for line in (args.run_dir / "log.jsonl").read_text().splitlines()]
    scored = [e for e in log if e["frame"] % args.every == 0 and not e["keyframe"] and "gain" in e]
    frames, gauged = [], []
    for e in scored:
        bgr = cv2.imread(str(args.data_dir / f"frame-{e['frame']:06d}.color.jpg"), cv2.IMREAD_COLOR)
        if bgr is None:
            raise SystemExit(f"{args.data_dir}: frame {e['frame']} missing")
        y = bgr[..., ::-1].astype(np.float64) / 255.0
        frames.append(y)
        gauged.append((y - e["bias"]) / e["gain"])  # the perfect map's render in the run's gauge
    per_frame = [psnr(np.clip(x, 0, 1), y) for x, y in zip(gauged, frames, strict=True)]
    g0s = np.linspace(0.6, 1.6, 101)
    means = [np.mean([psnr(np.clip(g0 * x, 0, 1), y) for x, y in zip(gauged, frames, strict=True)]) for g0 in g0s]
    best = int(np.argmax(means))
    gains = np.array([e["gain"] for e in scored])
    metrics = json.loads((args.run_dir / "metrics.json").read_text()).get("photometric") or {}
    result = {
        "run": str(args.run_dir),
        "scored_frames": [e["frame"] for e in scored],
        "tracked_gain_min_max": [float(gains.min()), float(gains.max())],
        "perfect_map_raw_psnr_run_gauge": float(np.mean(per_frame)),
        "perfect_map_raw_psnr_best_constant_gauge": float(means[best]),
        "best_constant_gauge": float(g0s[best]),
        "per_frame_run_gauge": dict(zip([e["frame"] for e in scored], map(float, per_frame), strict=True)),
        "run_raw_psnr": metrics.get("psnr_db"),
        "run_psnr_compensated": metrics.get("psnr_compensated_db"),
        "run_psnr_tracked_exposure": metrics.get("psnr_tracked_exposure_db"),
    }
    print(
        f"{len(scored)} scored frames, tracked gains {gains.min():.2f}-{gains.max():.2f}: a perfect map scores "
        f"{result['perfect_map_raw_psnr_run_gauge']:.2f} dB raw in the run's gauge, "
        f"{result['perfect_map_raw_psnr_best_constant_gauge']:.2f} dB in the best constant gauge "
        f"(x{result['best_constant_gauge']:.2f}); the run: raw {result['run_raw_psnr']}, compensated "
        f"{result['run_psnr_compensated']}, at the tracked exposure {result['run_psnr_tracked_exposure']}"
    )
    if args.out:
        args.out.write_text(json.dumps(result, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
