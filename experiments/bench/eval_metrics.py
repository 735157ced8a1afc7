"""Seconds a run's image metrics take per scored frame: the host code (NumPy, SciPy, torch's CPU for
MS-SSIM) against the same metrics with torch on the GPU (``rgs_warp.eval.metric_device``).  On an
H100 machine the host code made the evaluation two thirds of an office run (experiments/results/
sweeps.md).  Writes OUT/eval_metrics.json.

    python experiments/bench/eval_metrics.py --out DIR [--width 1200 --height 680 --frames 20] [--commit SHA]
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

import numpy as np
import warp as wp
from scipy.ndimage import gaussian_filter

from rgs_warp.eval import metric_device, photometric_metrics


def frames(n: int, height: int, width: int, seed: int = 0):
    """Pairs (render, frame, alpha): a textured image and a blurred, exposure-shifted, noisy copy."""
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(n):
        ref = np.clip(gaussian_filter(rng.random((height, width, 3)), (2, 2, 0)) * 3 - 1, 0, 1)
        render = np.clip(0.9 * gaussian_filter(ref, (1, 1, 0)) + 0.03 + rng.normal(0, 0.01, ref.shape), 0, 1)
        out.append((render.astype(np.float32), ref.astype(np.float32), np.ones((height, width), np.float32)))
    return out


def time_metrics(pairs, device) -> tuple[float, dict]:
    renders, refs, alphas = (list(x) for x in zip(*pairs, strict=True))
    photometric_metrics(renders[:1], refs[:1], alphas=alphas[:1], device=device)  # warm-up
    t = time.perf_counter()
    out = photometric_metrics(renders, refs, alphas=alphas, device=device)
    return (time.perf_counter() - t) / len(pairs), out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default=os.environ.get("OUT", "bench_out"))
    ap.add_argument("--width", type=int, default=1200)
    ap.add_argument("--height", type=int, default=680)
    ap.add_argument("--frames", type=int, default=20)
    ap.add_argument("--commit", default="")
    args = ap.parse_args(argv)
    wp.init()
    pairs = frames(args.frames, args.height, args.width)
    host_s, host = time_metrics(pairs, None)
    result = {
        "commit": args.commit,
        "size": [args.width, args.height],
        "frames": args.frames,
        "cpu_count": os.cpu_count(),
        "host_s_per_frame": host_s,
    }
    device = metric_device("cuda:0") if wp.is_cuda_available() else None
    if device is not None:
        import torch

        result["gpu"] = torch.cuda.get_device_name(0)
        gpu_s, gpu = time_metrics(pairs, device)
        result["gpu_s_per_frame"] = gpu_s
        result["speed_up"] = host_s / gpu_s
        result["largest_difference"] = max(
            abs(gpu[k] - host[k]) for k, v in host.items() if isinstance(v, float) and np.isfinite(v)
        )
    else:
        result["gpu_s_per_frame"] = None
        result["gpu_na_reason"] = "no CUDA device for Warp, or torch without CUDA"
    print(json.dumps(result, indent=2))
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "eval_metrics.json").write_text(json.dumps(result, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
