"""Generate a synthetic indoor RGB-D sequence in the Replica (NICE-SLAM) or TUM layout.

    python data_tools/make_synthetic.py room0 --out data/synthetic/room0 --width 1200 --height 680 \
        --frames 300 --layout replica --exposure-drift --depth-noise 0.001 --motion-blur
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from rgs_warp.datasets.synthetic import SCENES, SyntheticConfig, write_sequence
from rgs_warp.datasets.synthetic.generate import DEFAULT_EXPOSURE_DRIFT, DEFAULT_MOTION_BLUR, default_device


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("scene", choices=sorted(SCENES))
    p.add_argument("--out", type=Path, required=True, help="output folder (created)")
    p.add_argument("--width", type=int, default=240)
    p.add_argument("--height", type=int, default=136)
    p.add_argument("--fx", type=float, help="default width / 2 (Replica's proportions); fy the same")
    p.add_argument("--frames", type=int, default=100, help="frames over the whole trajectory")
    p.add_argument("--layout", choices=("replica", "tum"), default="replica")
    p.add_argument("--depth-noise", type=float, default=0.0, metavar="STD_M", help="Gaussian depth noise (m)")
    p.add_argument(
        "--exposure-drift",
        type=float,
        nargs="?",
        const=DEFAULT_EXPOSURE_DRIFT,
        default=0.0,
        metavar="STD",
        help=f"smooth random gain/bias walk (log-gain std; flag alone: {DEFAULT_EXPOSURE_DRIFT})",
    )
    p.add_argument(
        "--motion-blur",
        type=float,
        nargs="?",
        const=DEFAULT_MOTION_BLUR,
        default=0.0,
        metavar="SHUTTER",
        help=f"exposure as a fraction of the frame interval (flag alone: {DEFAULT_MOTION_BLUR})",
    )
    p.add_argument("--supersample", type=int, default=3, help="n x n jittered sub-pixels per pixel")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--device", default=None, help="Warp device (default: cuda:0 if available, else cpu)")
    a = p.parse_args(argv)

    cfg = SyntheticConfig(
        scene=a.scene,
        width=a.width,
        height=a.height,
        fx=a.fx,
        fy=a.fx,
        n_frames=a.frames,
        supersample=a.supersample,
        depth_noise_m=a.depth_noise,
        exposure_drift=a.exposure_drift,
        motion_blur=a.motion_blur,
        seed=a.seed,
    )
    device = a.device or default_device()
    start = time.perf_counter()
    write_sequence(cfg, a.out, a.layout, device=device)
    print(
        f"{a.scene}: {cfg.n_frames} frames {cfg.width}x{cfg.height} ({a.layout} layout) on {device} "
        f"in {time.perf_counter() - start:.1f} s -> {a.out}"
    )


if __name__ == "__main__":
    main()
