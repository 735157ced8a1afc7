"""Shared set-up of the renderer tests: camera, poses, scenes as GaussianMaps."""

import numpy as np

from rgs_warp.geometry import pose_from_tq
from rgs_warp.types import Camera, GaussianMap

CAMERA = Camera(fx=60.0, fy=60.0, cx=31.5, cy=23.5, width=64, height=48)
# 40x30: not a multiple of the 16-pixel tile, so partial tiles are exercised
SMALL_CAMERA = Camera(fx=38.0, fy=38.0, cx=19.5, cy=14.5, width=40, height=30)
T_WC = pose_from_tq(np.array([0.1, -0.2, 0.3]), np.array([0.05, -0.1, 0.02, 1.0]))
BACKGROUND = (0.1, 0.2, 0.3)


def to_map(scene: dict, device, requires_grad: bool = False) -> GaussianMap:
    return GaussianMap.from_numpy(
        scene["means"],
        scene["quats"],
        scene["log_scales"],
        scene["opacity_logits"],
        scene["sh"],
        device=device,
        requires_grad=requires_grad,
    )
