"""Mapper (supplement §4.5-4.6): joint refinement of the Gaussians and the keyframe poses over a
window of keyframes, with the per-Gaussian statistics (m_i, v_i, EMA position of Eq. 15) that the
regularizer and the maintenance pass read.

One mapping iteration renders the keyframes of the window (``views_per_iter`` of them, default all,
the gradients averaged over the views) and takes one Adam step:
- on the map ("full" iterations): L1 with robust per-pixel weights + lambda_dssim (1 - SSIM) on the
  exposure-corrected render x = g I_hat + b (g, b: the keyframe's exposure from tracking), + the
  depth L1 for RGB-D, + the regularizer; Table 1 learning rates with cosine decay, clipped to a
  global gradient norm of 1.0;
- on the poses of those keyframes ("pose-only" iterations, every ``pose_only_every``-th): the same
  loss's twist gradient, Adam on each twist.  Keyframes in ``fixed`` (the first keyframe of the run,
  which fixes the gauge) keep their pose.
Nothing is read back to the host inside the loop; the poses and the loss history come back once
per call.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import warp as wp

from rgs_warp.config import MappingConfig
from rgs_warp.geometry import invert_pose
from rgs_warp.kernels import mapping as km
from rgs_warp.kernels.map_ops import scatter_kept
from rgs_warp.kernels.tracking import REDUCE_BLOCK
from rgs_warp.keyframes import KeyframeBuffer
from rgs_warp.losses import DSSIMLoss
from rgs_warp.optim import MapAdam, MapLearningRates, cosine_factor
from rgs_warp.render import GaussianGrads, Renderer, RenderResult
from rgs_warp.types import Camera, GaussianMap, grown_capacity


@dataclass
class MappingResult:
    """Diagnostics of one ``Mapper.optimize`` call."""

    iters: int
    loss_history: np.ndarray  # (iters,) weighted L1 + depth + lambda_dssim (1 - SSIM) is not included
    l1_history: np.ndarray  # (iters,) mean |I - g I_hat - b| over pixels and channels
    depth_l1_history: np.ndarray  # (iters,) mean |D_hat - D| (m) over pixels with depth; nan without
    pose_updates: int
    map_updates: int

    @property
    def final_l1(self) -> float:
        """Mean colour L1 over the last pass through the window."""
        tail = self.l1_history[-max(1, min(len(self.l1_history), 5)) :]
        return float(np.mean(tail))


class Mapper:
    """Owns the optimiser state of a GaussianMap (``MapAdam``) and its per-Gaussian statistics.

    ``camera``: the keyframes' camera (the buffer's image size).  Rows appended to the map (by a
    Seeder) are picked up by ``sync`` (called by ``optimize``); rows are removed through
    ``remove(mask)``, so that the Adam moments and the statistics follow.
    """

    def __init__(
        self,
        cfg: MappingConfig,
        camera: Camera,
        gmap: GaussianMap,
        device=None,
        mode: str = "rgbd",
        renderer: Renderer | None = None,
        seed: int = 0,
    ):
        if mode not in ("rgbd", "mono"):
            raise ValueError(f"mode must be 'rgbd' or 'mono', got {mode!r}")
        self.cfg, self.camera, self.gmap, self.mode = cfg, camera, gmap, mode
        self.device = wp.get_device(device)
        self.renderer = renderer or Renderer(self.device)
        self.grads: GaussianGrads | None = None
        lrs = MapLearningRates(
            means=cfg.lr_position,
            rotations=cfg.lr_rotation,
            log_scales=cfg.lr_scale,
            opacity_logits=cfg.lr_opacity,
            sh=cfg.lr_color,
        )
        self.adam = MapAdam(gmap, lrs, betas=(cfg.adam_beta1, cfg.adam_beta2), max_grad_norm=cfg.grad_clip)
        self.rng = np.random.default_rng(seed)
        dev = self.device
        shape = (camera.height, camera.width)
        self.dssim = DSSIMLoss(camera.height, camera.width, dev)
        self._x = wp.zeros(shape, dtype=wp.vec3, device=dev)
        self._grad_x = wp.zeros(shape, dtype=wp.vec3, device=dev)
        self._d_color = wp.zeros(shape, dtype=wp.vec3, device=dev)
        self._d_depth = wp.zeros(shape, dtype=wp.float32, device=dev)
        self._stats_capacity = 0
        self._stats_rows = 0
        self.sync()
        self._loss = wp.zeros((1, km.L_COLUMNS), dtype=wp.float64, device=dev)
        self._pose_capacity = 0
        self.total_iters = 0

    # ---- per-Gaussian statistics ---------------------------------------------------------------
    def sync(self) -> None:
        """Follow the map: statistics, gradients and Adam moments to its capacity; rows appended
        since the last call (e.g. by a Seeder) get zero moments and statistics and start their EMA
        at their position."""
        gmap, dev = self.gmap, self.device
        n = len(gmap)
        kept = min(self._stats_rows, n)
        if gmap.capacity != self._stats_capacity:
            old = (self.obs_count, self.vis_count, self.ema_means) if self._stats_capacity else None
            self.obs_count = wp.zeros(gmap.capacity, dtype=wp.int32, device=dev)
            self.vis_count = wp.zeros(gmap.capacity, dtype=wp.float32, device=dev)
            self.ema_means = wp.zeros(gmap.capacity, dtype=wp.vec3, device=dev)
            if old is not None and kept:
                for dst, src in zip((self.obs_count, self.vis_count, self.ema_means), old, strict=True):
                    wp.copy(dst, src, count=kept)
            self._stats_capacity = gmap.capacity
        if self.grads is None or self.grads.means.shape[0] != gmap.capacity:
            self._opacity_grad_before = wp.zeros(gmap.capacity, dtype=wp.float32, device=dev)
            self.grads = GaussianGrads(
                wp.zeros(gmap.capacity, dtype=wp.vec3, device=dev),
                wp.zeros(gmap.capacity, dtype=wp.quat, device=dev),
                wp.zeros(gmap.capacity, dtype=wp.vec3, device=dev),
                wp.zeros(gmap.capacity, dtype=wp.float32, device=dev),
                wp.zeros((gmap.capacity, gmap.num_sh), dtype=wp.vec3, device=dev),
            )
        self.adam.sync()
        if n > kept:
            self.adam.reset_rows(kept, n - kept)
            wp.launch(
                km.init_statistics,
                dim=n - kept,
                inputs=[gmap.means, kept],
                outputs=[self.obs_count, self.vis_count, self.ema_means],
                device=dev,
            )
        self._stats_rows = n

    def remove(self, mask: wp.array) -> None:
        """Remove rows where ``mask`` (int32, length len(map)) is nonzero from the map, the Adam
        moments and the statistics, keeping the order of the others."""
        self.sync()
        n = len(self.gmap)
        if mask.shape[0] != n:
            raise ValueError(f"mask has {mask.shape[0]} entries for {n} Gaussians")
        self.adam.remove(mask)
        dev = self.device
        removed_before = wp.empty(n, dtype=wp.int32, device=dev)
        wp.utils.array_scan(mask, removed_before, inclusive=False)
        for name in ("obs_count", "vis_count", "ema_means"):
            src = getattr(self, name)
            tmp = wp.zeros_like(src)
            wp.launch(scatter_kept, dim=n, inputs=[src[:n], mask, removed_before], outputs=[tmp], device=dev)
            setattr(self, name, tmp)
        self.gmap.remove(mask)
        self._stats_rows = len(self.gmap)

    # ---- poses ---------------------------------------------------------------------------------
    def _view_loss(self, keyframes, slot, j, it, weight, use_depth, blocks, pose_jacobians) -> RenderResult:
        """Render window view j (keyframe ``slot``) and leave dL/d(image) of its share ``weight`` of the
        loss in ``_d_color``, ``_d_depth``; its loss sums go to row ``it``."""
        cfg, dev = self.cfg, self.device
        g, b = (float(v) for v in keyframes.exposure[slot])
        res = self.renderer.forward(self.gmap, self.camera, self._T_WC[j : j + 1], pose_jacobians=pose_jacobians)
        wp.launch_tiled(
            km.mapping_loss,
            dim=blocks,
            inputs=[keyframes.rgb[slot], keyframes.depth[slot], res.color, res.depth, g, b, cfg.robust_scale]
            + [use_depth, weight * cfg.depth_weight, weight, it],
            outputs=[self._x, self._grad_x, self._d_depth, self._loss],
            block_dim=REDUCE_BLOCK,
            device=dev,
        )
        self.dssim.accumulate_grad(self._x, keyframes.rgb[slot], weight * cfg.lambda_dssim, self._grad_x)
        wp.launch(km.scale_image_grad, dim=self._x.shape, inputs=[self._grad_x, g], outputs=[self._d_color], device=dev)
        return res

    def _ensure_poses(self, k: int) -> None:
        if k <= self._pose_capacity:
            return
        cap = grown_capacity(self._pose_capacity, k, minimum=8)
        dev = self.device
        self._T_CW = wp.zeros(cap, dtype=wp.mat44d, device=dev)
        self._T_WC = wp.zeros(cap, dtype=wp.mat44, device=dev)
        self._pose_m = wp.zeros((cap, 6), dtype=wp.float32, device=dev)
        self._pose_v = wp.zeros((cap, 6), dtype=wp.float32, device=dev)
        self._pose_steps = wp.zeros(cap, dtype=wp.int32, device=dev)
        self._pose_capacity = cap

    # ---- optimisation --------------------------------------------------------------------------
    def optimize(
        self,
        keyframes: KeyframeBuffer,
        window: Sequence[int],
        iters: int,
        fixed: Sequence[int] = (),
        optimize_poses: bool = True,
    ) -> MappingResult:
        """``iters`` mapping iterations over the keyframe ``window`` (buffer slots).  Keyframe poses
        are refined in place in ``keyframes.poses`` except those of the slots in ``fixed``."""
        cfg, dev, gmap = self.cfg, self.device, self.gmap
        window = list(window)
        if not window:
            raise ValueError("empty mapping window")
        if keyframes.rgb.shape[1:] != (self.camera.height, self.camera.width):
            raise ValueError(f"keyframes are {keyframes.rgb.shape[1:]}, the Mapper's camera is {self.camera}")
        self.sync()
        iters = int(iters)
        if iters <= 0 or len(gmap) == 0:
            return MappingResult(0, np.zeros(0), np.zeros(0), np.zeros(0), 0, 0)
        k_win = len(window)
        self._ensure_poses(k_win)
        T_CW = np.stack([invert_pose(keyframes.poses[s]) for s in window])
        self._T_CW[:k_win].assign(T_CW)
        self._T_WC[:k_win].assign(np.stack([keyframes.poses[s] for s in window]).astype(np.float32))
        self._pose_m.zero_()
        self._pose_v.zero_()
        self._pose_steps.zero_()
        if self._loss.shape[0] < iters:
            self._loss = wp.zeros((iters, km.L_COLUMNS), dtype=wp.float64, device=dev)
        self._loss.zero_()

        use_depth = int(self.mode == "rgbd")
        n_pixels = self.camera.width * self.camera.height
        blocks = [(n_pixels + REDUCE_BLOCK - 1) // REDUCE_BLOCK]
        pose_updates = map_updates = 0
        fixed_set = set(fixed)
        every = cfg.pose_only_every if optimize_poses else 0
        per_iter = k_win if cfg.views_per_iter <= 0 else min(cfg.views_per_iter, k_win)
        order: list[int] = []
        for it in range(iters):
            views = []
            for _ in range(per_iter):
                if not order:
                    order = list(self.rng.permutation(k_win))
                views.append(order.pop())
            lr_factor = cosine_factor(it, iters, cfg.lr_final_factor)
            pose_iter = every > 0 and it % every == every - 1
            if pose_iter:
                views = [j for j in views if window[j] not in fixed_set]
                if not views:
                    continue
            n = len(gmap)
            for v, j in enumerate(views):
                slot = window[j]
                res = self._view_loss(keyframes, slot, j, it, 1.0 / len(views), use_depth, blocks, pose_iter)
                if pose_iter:
                    _, pose_grad = self.renderer.backward(self._d_color, self._d_depth, None, pose_only=True)
                    wp.launch(
                        km.adam_keyframe_pose_step,
                        dim=1,
                        inputs=[pose_grad, j, cfg.pose_lr * lr_factor, cfg.adam_beta1, cfg.adam_beta2, 1e-8],
                        outputs=[self._pose_m, self._pose_v, self._pose_steps, self._T_CW, self._T_WC],
                        device=dev,
                    )
                    pose_updates += 1
                    continue
                if v == 0:
                    self._opacity_grad_before[:n].zero_()
                else:
                    wp.copy(self._opacity_grad_before, self.grads.opacity_logits, count=n)
                grads, _ = self.renderer.backward(
                    self._d_color, self._d_depth, None, grads_out=self.grads, accumulate=v > 0
                )
                wp.launch(
                    km.update_statistics,
                    dim=n,
                    inputs=[res.radii, grads.opacity_logits, self._opacity_grad_before],
                    outputs=[self.obs_count, self.vis_count],
                    device=dev,
                )
            if pose_iter:
                continue
            grads = self.grads
            wp.launch(
                km.regularize,
                dim=n,
                inputs=[gmap.means, gmap.log_scales, gmap.opacity_logits, self.ema_means]
                + [cfg.reg_elongation, math.log(cfg.max_anisotropy), cfg.reg_opacity, cfg.max_abs_opacity_logit]
                + [cfg.reg_anchor],
                outputs=[grads.means, grads.log_scales, grads.opacity_logits],
                device=dev,
            )
            self.adam.step(grads, lr_factor)
            wp.launch(km.update_ema, dim=n, inputs=[gmap.means, cfg.ema_eta], outputs=[self.ema_means], device=dev)
            map_updates += 1
        self.total_iters += iters

        loss = self._loss[:iters].numpy()
        if optimize_poses and pose_updates:
            T_CW_new = self._T_CW[:k_win].numpy()
            for j, slot in enumerate(window):
                if slot not in fixed_set:
                    keyframes.poses[slot] = invert_pose(T_CW_new[j])
        pixels = np.maximum(loss[:, km.L_PIXELS], 1.0)
        depth_px = loss[:, km.L_DEPTH_PIXELS]
        depth_l1 = np.where(depth_px > 0, loss[:, km.L_DEPTH] / np.maximum(depth_px, 1.0), np.nan)
        return MappingResult(
            iters=iters,
            loss_history=loss[:, km.L_LOSS].copy(),
            l1_history=loss[:, km.L_ABS] / pixels,
            depth_l1_history=depth_l1,
            pose_updates=pose_updates,
            map_updates=map_updates,
        )
