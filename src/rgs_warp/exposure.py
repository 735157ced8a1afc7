"""The exposure (g, b) of a frame in the first keyframe's gauge (issue 18), from the keyframes' images.

The map's colour is the first keyframe's exposure only if every later keyframe's (g, b) of Eq. 3 is
its exposure relative to the first: the seeds are coloured (I - b) / g and the mapper fits the map to
the same.  The tracker's gain-only model against the map's render (kernels/tracking.py
``solve_brightness``) reads a bias as part of the gain (about b / the mean intensity), which keeps the
map's mean colour but not its contrast: with a synthetic exposure drift of std 0.3 the map's dark
regions render 5 % too bright (tests/test_exposure_gauge.py).  An affine fit against the render cannot
fix it: the map is blurrier than the frames, so such a fit reads a gain too high (least squares 5 %,
the reduced major axis 12 %, on the synthetic room), and the mapper would feed that back.

Against the older keyframes' images the two sides are images of the same kind: a surface point with
measured depth in the frame is looked up (nearest pixel) in each reference keyframe whose measured
depth there agrees, that keyframe's colour brought to the first keyframe's exposure with its own
(g, b); then the reduced major axis g = std(y) / std(x), b = mean(y) - g mean(x) over all such pairs
and channels, which treats the errors of both sides alike (least squares of y on x reads them as a
gain below 1).  The first keyframe is the identity, so every estimate is chained to it.  On the
drifting room (std 0.3) the keyframe gains come out 0.4 % from the truth, against 15 % for the gain
against the map, and the map's colour is that of the true exposures (experiments/results/fidelity.md).
"""

from __future__ import annotations

import numpy as np
import warp as wp

from rgs_warp.geometry import invert_pose
from rgs_warp.kernels import exposure as ke
from rgs_warp.kernels.math import REDUCE_BLOCK, camera_params, reduce_blocks
from rgs_warp.keyframes import KeyframeBuffer
from rgs_warp.types import Camera

__all__ = ["KeyframeExposure"]

# A reference sees the frame's surface point where its measured depth agrees to this fraction.
MAX_REL_DEPTH = 0.05
# Fewer co-visible channel samples than this (about 300 pixels) leave the fallback exposure.
MIN_SAMPLES = 1000


class KeyframeExposure:
    """``estimate(keyframes, rgb, depth, T_WC, fallback, exclude)`` -> (g, b) of the frame against
    every keyframe of ``keyframes`` but ``exclude`` (module docstring).  ``rgb``, ``depth``: (H, W)
    device arrays of the camera's size.  Returns ``fallback`` where the references see too little of
    the frame (or there is no depth)."""

    def __init__(self, camera: Camera, capacity: int, device=None):
        self.device = wp.get_device(device)
        self.cam = camera_params(camera)
        self.capacity = capacity
        pinned = self.device.is_cuda
        self._T_CW = wp.zeros(capacity, dtype=wp.mat44, device=self.device)
        self._slot = wp.zeros(capacity, dtype=wp.int32, device=self.device)
        self._exposure = wp.zeros(capacity, dtype=wp.vec2, device=self.device)
        self._T_CW_host = wp.zeros(capacity, dtype=wp.mat44, device="cpu", pinned=pinned)
        self._slot_host = wp.zeros(capacity, dtype=wp.int32, device="cpu", pinned=pinned)
        self._exposure_host = wp.zeros(capacity, dtype=wp.vec2, device="cpu", pinned=pinned)
        self._moments = wp.zeros(ke.M_COLUMNS, dtype=wp.float64, device=self.device)
        self._moments_host = wp.zeros(ke.M_COLUMNS, dtype=wp.float64, device="cpu", pinned=pinned)
        self._blocks = [reduce_blocks(camera.width * camera.height)]

    def estimate(
        self,
        keyframes: KeyframeBuffer,
        rgb: wp.array,
        depth: wp.array | None,
        T_WC: np.ndarray,
        fallback: tuple[float, float],
        exclude: int = -1,
    ) -> tuple[float, float]:
        refs = [s for s in keyframes.slots() if s != exclude][-self.capacity :]
        if depth is None or not refs:
            return fallback
        n = len(refs)
        self._T_CW_host.numpy()[:n] = [invert_pose(keyframes.poses[s]).astype(np.float32) for s in refs]
        self._slot_host.numpy()[:n] = refs
        self._exposure_host.numpy()[:n] = keyframes.exposure[refs]
        for dst, src in ((self._T_CW, self._T_CW_host), (self._slot, self._slot_host)):
            wp.copy(dst, src, count=n)
        wp.copy(self._exposure, self._exposure_host, count=n)
        self._moments.zero_()
        wp.launch_tiled(
            ke.exposure_moments,
            dim=self._blocks,
            inputs=[rgb, depth, wp.mat44(*np.asarray(T_WC, dtype=np.float32).ravel()), self.cam]
            + [keyframes.rgb, keyframes.depth, self._T_CW, self._slot, self._exposure, n, MAX_REL_DEPTH],
            outputs=[self._moments],
            block_dim=REDUCE_BLOCK,
            device=self.device,
        )
        wp.copy(self._moments_host, self._moments)
        wp.synchronize_device(self.device)
        return rma_exposure(self._moments_host.numpy(), fallback)


def rma_exposure(m: np.ndarray, fallback: tuple[float, float]) -> tuple[float, float]:
    """(g, b) of the reduced major axis y = g x + b from the sums ``m`` (columns ``M_*`` of
    kernels/exposure.py); ``fallback`` for fewer than MIN_SAMPLES samples or no positive correlation."""
    n = m[ke.M_N]
    if n < MIN_SAMPLES:
        return fallback
    mx, my = m[ke.M_X] / n, m[ke.M_Y] / n
    vx, vy = m[ke.M_XX] / n - mx * mx, m[ke.M_YY] / n - my * my
    cov = m[ke.M_XY] / n - mx * my
    if vx <= 0.0 or vy <= 0.0 or cov <= 0.0:
        return fallback
    g = float(np.sqrt(vy / vx))
    return g, float(my - g * mx)
