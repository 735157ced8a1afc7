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
per call.  Two optional passengers of the loop read a little at their own iterations only: the
residual-driven densification of ``method=baseline`` (a ``Densifier``, stepped after every iteration
with the cumulative iteration count ``total_iters``: one count read per densification step, plus the
one of the map's compaction) and the convergence samples of ``psnr_every`` (renders of the window
and one read of its squared errors).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
import warp as wp

from rgs_warp.config import DensifyConfig, MappingConfig
from rgs_warp.densification import Densifier
from rgs_warp.geometry import invert_pose
from rgs_warp.kernels import mapping as km
from rgs_warp.kernels.map_ops import scatter_kept
from rgs_warp.kernels.tracking import REDUCE_BLOCK
from rgs_warp.keyframes import KeyframeBuffer
from rgs_warp.losses import DSSIMLoss
from rgs_warp.optim import MapAdam, MapLearningRates, cosine_factor
from rgs_warp.render import GaussianGrads, Renderer, RenderResult
from rgs_warp.types import Camera, GaussianMap, grown_capacity

wp.set_module_options({"enable_backward": False})


@wp.kernel
def _exposed_squared_error(
    # in: keyframe image, render of the map at its pose, its exposure (Eq. 3)
    observed: wp.array2d(dtype=wp.vec3),
    rendered: wp.array2d(dtype=wp.vec3),
    gain: float,
    bias: float,
    row: int,
    # out: sum over pixels and channels of (clip(g I_hat + b, 0, 1) - I)^2, added to entry `row`
    sums_out: wp.array(dtype=wp.float64),
):
    block, lane = wp.tid()
    i = block * REDUCE_BLOCK + lane
    width = observed.shape[1]
    e = float(0.0)
    if i < observed.shape[0] * width:
        y = i // width
        x = i - y * width
        c = gain * rendered[y, x] + wp.vec3(bias)
        r = wp.vec3(wp.clamp(c[0], 0.0, 1.0), wp.clamp(c[1], 0.0, 1.0), wp.clamp(c[2], 0.0, 1.0)) - observed[y, x]
        e = wp.dot(r, r)
    total = wp.tile_extract(wp.tile_sum(wp.tile(e)), 0)
    if lane == 0:
        wp.atomic_add(sums_out, row, wp.float64(total))


@dataclass
class MappingResult:
    """Diagnostics of one ``Mapper.optimize`` call."""

    iters: int
    loss_history: np.ndarray  # (iters,) weighted L1 + depth + lambda_dssim (1 - SSIM) is not included
    l1_history: np.ndarray  # (iters,) mean |I - g I_hat - b| over pixels and channels
    depth_l1_history: np.ndarray  # (iters,) mean |D_hat - D| (m) over pixels with depth; nan without
    pose_updates: int
    map_updates: int
    # densification (method=baseline): Gaussians cloned, split (each replaced by two children), pruned
    # by its culling (split parents not counted), opacity resets
    cloned: int = 0
    split: int = 0
    pruned: int = 0
    opacity_resets: int = 0
    # (cumulative iteration, mean window PSNR dB, Gaussians) every ``psnr_every`` iterations
    psnr_curve: list[tuple[int, float, int]] = field(default_factory=list)

    @property
    def final_l1(self) -> float:
        """Mean colour L1 over the last pass through the window."""
        tail = self.l1_history[-max(1, min(len(self.l1_history), 5)) :]
        return float(np.mean(tail))


class Mapper:
    """Owns the optimiser state of a GaussianMap (``MapAdam``) and its per-Gaussian statistics.

    ``camera``: the keyframes' camera (the buffer's image size).  Rows appended to the map (by a
    Seeder, or by the densifier) are picked up by ``sync`` (called by ``optimize``); rows are removed
    through ``remove(mask)``, so that the Adam moments and the statistics follow.  ``densify``: the
    residual-driven densification of ``method=baseline`` (None: the map grows only from outside);
    its culling opacity is ``cfg.opacity_cull``.  ``total_iters`` counts the mapping iterations of
    every call, the densification schedule's clock.
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
        densify: DensifyConfig | None = None,
    ):
        if mode not in ("rgbd", "mono"):
            raise ValueError(f"mode must be 'rgbd' or 'mono', got {mode!r}")
        self.cfg, self.camera, self.gmap, self.mode = cfg, camera, gmap, mode
        self.densify_cfg = densify
        self.densifier = None
        if densify is not None:
            self.densifier = Densifier(
                grad_threshold=densify.grad_threshold,
                interval=densify.interval,
                start=densify.start,
                stop=densify.stop,
                opacity_reset_interval=densify.opacity_reset_interval,
                opacity_reset_value=densify.opacity_reset_value,
                percent_dense=densify.percent_dense,
                cull_opacity=cfg.opacity_cull,
                prune_scale_fraction=densify.prune_scale_fraction,
                seed=seed,
            )
        self.device = wp.get_device(device)
        self.renderer = renderer or Renderer(self.device)
        self.grads: GaussianGrads | None = None
        lrs = MapLearningRates(
            means=cfg.lr_position,
            rotations=cfg.lr_rotation,
            log_scales=cfg.lr_scale,
            opacity_logits=cfg.lr_opacity,
            sh=cfg.lr_color,
            sh_rest=cfg.lr_color * cfg.lr_color_rest_factor,
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
        self._squared_error = wp.zeros(1, dtype=wp.float64, device=dev)
        self._pose_capacity = 0
        self.total_iters = 0

    # ---- per-Gaussian statistics ---------------------------------------------------------------
    def sync(self) -> None:
        """Follow the map: statistics, gradients and Adam moments to its capacity; rows appended
        since the last call (by a Seeder or the densifier) get zero moments and statistics and start
        their EMA at their position."""
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
        if self.densifier is not None:
            self.densifier.sync(gmap)
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
        moments and the statistics (the densifier's included), keeping the order of the others."""
        self.sync()
        n = len(self.gmap)
        if mask.shape[0] != n:
            raise ValueError(f"mask has {mask.shape[0]} entries for {n} Gaussians")
        self.adam.remove(mask)
        if self.densifier is not None:
            self.densifier.remove(mask)
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
        psnr_every: int = 0,
    ) -> MappingResult:
        """``iters`` mapping iterations over the keyframe ``window`` (buffer slots).  Keyframe poses
        are refined in place in ``keyframes.poses`` except those of the slots in ``fixed``.
        ``psnr_every`` > 0: after every iteration whose cumulative count ``total_iters`` is a multiple
        of it, the mean PSNR of the window (``window_psnr``) goes to ``MappingResult.psnr_curve``
        (measured before that iteration's densification, whose fresh clones and split children the
        following iterations have yet to fit)."""
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
        result = MappingResult(iters, np.zeros(0), np.zeros(0), np.zeros(0), 0, 0)
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
            if every > 0 and it % every == every - 1:
                views = [j for j in views if window[j] not in fixed_set]
                for j in views:
                    self._pose_step(keyframes, window[j], j, it, 1.0 / len(views), use_depth, blocks, lr_factor)
                result.pose_updates += len(views)
            else:
                self._map_step(keyframes, window, views, it, use_depth, blocks, lr_factor)
                result.map_updates += 1
            self.total_iters += 1
            if psnr_every > 0 and self.total_iters % psnr_every == 0:
                psnr_db = self._window_psnr(keyframes, window, self._T_WC)
                result.psnr_curve.append((self.total_iters, psnr_db, len(gmap)))
            if self.densifier is not None:
                self._densify(result)

        loss = self._loss[:iters].numpy()
        if optimize_poses and result.pose_updates:
            T_CW_new = self._T_CW[:k_win].numpy()
            for j, slot in enumerate(window):
                if slot not in fixed_set:
                    keyframes.poses[slot] = invert_pose(T_CW_new[j])
        pixels = np.maximum(loss[:, km.L_PIXELS], 1.0)
        depth_px = loss[:, km.L_DEPTH_PIXELS]
        result.loss_history = loss[:, km.L_LOSS].copy()
        result.l1_history = loss[:, km.L_ABS] / pixels
        result.depth_l1_history = np.where(depth_px > 0, loss[:, km.L_DEPTH] / np.maximum(depth_px, 1.0), np.nan)
        return result

    def _pose_step(self, keyframes, slot, j, it, weight, use_depth, blocks, lr_factor) -> None:
        """One Adam step on the twist of window view j (keyframe ``slot``), the map held fixed."""
        cfg = self.cfg
        self._view_loss(keyframes, slot, j, it, weight, use_depth, blocks, True)
        _, pose_grad = self.renderer.backward(self._d_color, self._d_depth, None, pose_only=True)
        wp.launch(
            km.adam_keyframe_pose_step,
            dim=1,
            inputs=[pose_grad, j, cfg.pose_lr * lr_factor, cfg.adam_beta1, cfg.adam_beta2, 1e-8],
            outputs=[self._pose_m, self._pose_v, self._pose_steps, self._T_CW, self._T_WC],
            device=self.device,
        )

    def _map_step(self, keyframes, window, views, it, use_depth, blocks, lr_factor) -> None:
        """One Adam step on the map from the gradients of ``views`` (window positions), averaged."""
        cfg, dev, gmap = self.cfg, self.device, self.gmap
        n = len(gmap)
        share = 1.0 / len(views)
        for v, j in enumerate(views):
            res = self._view_loss(keyframes, window[j], j, it, share, use_depth, blocks, False)
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
            if self.densifier is not None:
                self.densifier.accumulate(self.renderer, gmap, share)
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

    def _densify(self, result: MappingResult) -> None:
        """The densifier's step at iteration ``total_iters``: appended rows enter the optimiser state
        and statistics through ``sync``, flagged rows leave the map and both through ``remove``."""
        step = self.densifier.step(self.total_iters, self.gmap, self.densify_cfg.scene_extent_m)
        if step.opacity_reset:
            # 3DGS restarts the opacity moments with the reset, so that the momentum gathered at the old
            # opacities does not undo it
            self.adam.reset_field("opacity_logits")
            result.opacity_resets += 1
        if step.remove is None:
            return
        before = len(self.gmap)
        self.remove(step.remove)  # its sync() first gives the appended rows their fresh state
        result.cloned += step.cloned
        result.split += step.split
        result.pruned += before - len(self.gmap) - step.split

    # ---- convergence ---------------------------------------------------------------------------
    def window_psnr(self, keyframes: KeyframeBuffer, window: Sequence[int]) -> float:
        """Mean over the keyframes of ``window`` (slots) of the PSNR (dB) of the exposure-corrected
        render clip(g I_hat + b, 0, 1) at the keyframe's pose against the keyframe image."""
        window = list(window)
        self._ensure_poses(len(window))
        self._T_WC[: len(window)].assign(np.stack([keyframes.poses[s] for s in window]).astype(np.float32))
        return self._window_psnr(keyframes, window, self._T_WC)

    def _window_psnr(self, keyframes: KeyframeBuffer, window: list[int], T_WC: wp.array) -> float:
        """``window_psnr`` at the poses ``T_WC[j]`` (device): k renders, one read of k sums."""
        k = len(window)
        if len(self.gmap) == 0:
            return float("nan")
        if self._squared_error.shape[0] < k:
            self._squared_error = wp.zeros(k, dtype=wp.float64, device=self.device)
        self._squared_error.zero_()
        n_pixels = self.camera.width * self.camera.height
        blocks = [(n_pixels + REDUCE_BLOCK - 1) // REDUCE_BLOCK]
        for j, slot in enumerate(window):
            g, b = (float(v) for v in keyframes.exposure[slot])
            res = self.renderer.forward(self.gmap, self.camera, T_WC[j : j + 1])
            wp.launch_tiled(
                _exposed_squared_error,
                dim=blocks,
                inputs=[keyframes.rgb[slot], res.color, g, b, j],
                outputs=[self._squared_error],
                block_dim=REDUCE_BLOCK,
                device=self.device,
            )
        mse = np.maximum(self._squared_error.numpy()[:k] / (3.0 * n_pixels), 1e-20)
        return float(np.mean(-10.0 * np.log10(mse)))
