"""Tracking's direct alignment (``tracking.direct_levels``, kernels/direct.py): the frame aligned to one
render of the map by Gauss-Newton on an image pyramid, coarse to fine, before the tracker's Adam steps.
With depth and ``tracking.geometric``, the frame's measured depth joins the colour point to plane, both
terms weighted by their noise as estimated from their residuals (kernels/direct.py, "Geometric mode").

Everything stays on the device (pose, unknowns and sums; the step is solved by one thread), so the
alignment can be captured in a CUDA graph with the tracker's steps.
"""

from __future__ import annotations

import numpy as np
import warp as wp

from rgs_warp.config import TrackingConfig
from rgs_warp.kernels import direct as dk
from rgs_warp.kernels import tracking as tk
from rgs_warp.kernels.math import N_TERMS
from rgs_warp.render import Renderer
from rgs_warp.types import Camera, GaussianMap

__all__ = ["DIRECT_MIN_PX", "DirectAlignment"]

# the direct alignment's coarsest level must keep this many pixels a side (its sampler reads one pixel
# either side of the warped point)
DIRECT_MIN_PX = 8


class DirectAlignment:
    """The frame's and the reference's image pyramids (``cfg.direct_levels`` levels: level 0 at ``camera``,
    the tracking resolution, each level half the one before), the unknowns and the sums.  ``frame``: the
    level-0 (rgb, depth) frame images, the tracker's, read in place.  No levels: ``align`` is not to be
    called and ``downsample_frame`` does nothing.

    ``scales``: the device array of the noise scales (math.TERM_*) that the last geometric alignment
    estimated (``tracking.geometric`` with depth), else the fixed ones (``SIGMA_COLOUR``, 1)."""

    def __init__(self, cfg: TrackingConfig, camera: Camera, frame: tuple[wp.array, wp.array], device):
        self.cfg = cfg
        self.geometric = cfg.geometric
        self.camera = camera
        self.device = dev = wp.get_device(device)
        self.levels = levels = cfg.direct_levels
        self._levels: list[tuple] = []
        # the noise scales (``scales``), each alignment starting from the fixed ones
        self._scales_prior = wp.array([dk.SIGMA_COLOUR, 1.0], dtype=wp.float32, device=dev)
        self.scales = wp.clone(self._scales_prior)
        for level in range(levels):
            cam = camera.scaled(2**level)
            if min(cam.width, cam.height) < DIRECT_MIN_PX:
                raise ValueError(
                    f"tracking.direct_levels = {levels}: level {level} of the {camera.width}x{camera.height} "
                    f"tracking images is {cam.width}x{cam.height}, below {DIRECT_MIN_PX} px a side; use fewer levels"
                )
            size = (cam.height, cam.width)
            images = frame if level == 0 else _rgbd_images(size, dev)
            reference = _rgbd_images(size, dev)
            self._levels.append((cam, images, reference))
        if levels:
            self._T_rel = wp.zeros(1, dtype=wp.mat44d, device=dev)
            self._T_CW_ref = wp.zeros(1, dtype=wp.mat44d, device=dev)
            self._affine = wp.zeros(2, dtype=wp.float64, device=dev)
            self._identity = wp.array([np.eye(4)], dtype=wp.mat44d, device=dev)
            self._affine_identity = wp.array([1.0, 0.0], dtype=wp.float64, device=dev)
            self._sums = wp.zeros(dk.N_COLUMNS, dtype=wp.float64, device=dev)
            self._histogram = wp.zeros((N_TERMS, dk.HIST_BINS), dtype=wp.int32, device=dev)
            self._blocks = [(cam.width * cam.height + dk.BLOCK - 1) // dk.BLOCK for cam, _, _ in self._levels]

    def downsample_frame(self, has_depth: bool) -> None:
        """Levels 1.. of the frame's pyramid from level 0 (after a new frame was staged there)."""
        self._downsample(1, has_depth)

    def _downsample(self, which: int, has_depth: bool) -> None:
        """Levels 1.. of the frame (``which`` 1) or reference (2) pyramid from level 0."""
        for level in range(1, len(self._levels)):
            src, dst = self._levels[level - 1][which], self._levels[level][which]
            wp.launch(
                tk.downsample_rgbd,
                dim=dst[0].shape,
                inputs=[src[0], src[1], 2, int(has_depth), self.cfg.depth_edge_spread],
                outputs=[dst[0], dst[1]],
                device=self.device,
            )

    def align(self, renderer: Renderer, gmap: GaussianMap, use_depth: bool, T_CW: wp.array, T_WC: wp.array) -> None:
        """Move the pose (``T_CW`` float64 and ``T_WC`` float32, one element each on the device): ``gmap``
        rendered once there is the reference; ``direct_iters`` Gauss-Newton steps a pyramid level, coarse
        to fine, move the pose on the device."""
        dev, cfg = self.device, self.cfg
        # sized by its own needs: sized by the previous render's, after a view that saw little of the map
        # (a lost try, a relocalisation's candidate) it dropped intersections, and the whole alignment
        # followed a wrong reference (3.6 cm off in the relocalisation test); a captured render has its
        # room reserved before the capture
        res = renderer.forward(gmap, self.camera, T_WC, fit=True)
        ref_rgb, ref_depth = self._levels[0][2]
        wp.launch(
            dk.reference_image,
            dim=ref_rgb.shape,
            inputs=[res.color, res.depth, res.alpha, cfg.tau_alpha],
            outputs=[ref_rgb, ref_depth],
            block_dim=dk.BLOCK,
            device=dev,
        )
        self._downsample(2, True)
        wp.copy(self._T_CW_ref, T_CW)
        wp.copy(self._T_rel, self._identity)
        wp.copy(self._affine, self._affine_identity)
        wp.copy(self.scales, self._scales_prior)
        geometric = use_depth and self.geometric
        depth_mode = dk.DEPTH_GEOMETRIC if geometric else (dk.DEPTH_PROJECTIVE if use_depth else dk.DEPTH_NONE)
        for level in range(len(self._levels) - 1, -1, -1):
            # geometric: a first pass at each level only estimates the terms' noise from its residuals,
            # and every step re-estimates it for the next (IRLS)
            for k in range(cfg.direct_iters + int(geometric)):
                self._normal_equations(level, depth_mode)
                if k > 0 or not geometric:
                    wp.launch(
                        dk.solve_step,
                        dim=1,
                        inputs=[self._sums, self._T_CW_ref],
                        outputs=[self._T_rel, self._affine, T_CW, T_WC],
                        block_dim=dk.BLOCK,
                        device=dev,
                    )
                if geometric:
                    wp.launch(
                        dk.solve_scales,
                        dim=N_TERMS,
                        inputs=[self._histogram],
                        outputs=[self.scales],
                        block_dim=dk.BLOCK,
                        device=dev,
                    )

    def _normal_equations(self, level: int, depth_mode: int) -> None:
        """The sums (and, in ``DEPTH_GEOMETRIC``, the residual histograms) of pyramid level ``level`` at the
        current pose."""
        dev = self.device
        cam, (rgb, depth), (ref_rgb, ref_depth) = self._levels[level]
        intrinsics = wp.vec4(cam.fx, cam.fy, cam.cx, cam.cy)
        self._sums.zero_()
        if depth_mode == dk.DEPTH_GEOMETRIC:
            self._histogram.zero_()
        wp.launch_tiled(
            dk.normal_equations,
            dim=[self._blocks[level]],
            inputs=[ref_rgb, ref_depth, rgb, depth, depth_mode, intrinsics, self._T_rel, self._affine, self.scales],
            outputs=[self._sums, self._histogram],
            block_dim=dk.BLOCK,
            device=dev,
        )
        if depth_mode == dk.DEPTH_GEOMETRIC:
            wp.launch_tiled(
                dk.geometric_equations,
                dim=[self._blocks[level]],
                inputs=[ref_depth, depth, intrinsics, self._T_rel, self.scales],
                outputs=[self._sums, self._histogram],
                block_dim=dk.BLOCK,
                device=dev,
            )


def _rgbd_images(shape: tuple[int, int], device) -> tuple[wp.array, wp.array]:
    return wp.zeros(shape, dtype=wp.vec3, device=device), wp.zeros(shape, dtype=wp.float32, device=device)
