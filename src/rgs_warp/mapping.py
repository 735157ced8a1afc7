"""Mapper (supplement §4.5-4.6): refinement of the Gaussians over a window of keyframes, with the
per-Gaussian statistics (m_i, v_i, EMA position of Eq. 15) that the regularizer and the maintenance
pass read.

One mapping iteration renders every keyframe of the window (gradients averaged over the views) and
takes one Adam step on the map: L1 with robust per-pixel weights + lambda_dssim (1 - SSIM) on the
exposure-corrected render x = g I_hat + b (g, b: the keyframe's exposure from tracking), + the depth
L1 for RGB-D, + the regularizer; Table 1 learning rates with cosine decay, clipped to a global
gradient norm of 1.0.  Keyframe poses are the tracker's: pose-only steps inside the window (§4.5)
moved keyframes away from the truth on the office (docs/decisions.md, "Keyframe poses in mapping").
Nothing is read back to the host inside the loop; the loss history comes back once per call.  Two
optional passengers of the loop read a little at their own iterations only: the residual-driven
densification of ``method=baseline`` (a ``Densifier``, stepped after every iteration with the
cumulative iteration count ``total_iters``: one count read per densification step, plus the one of
the map's compaction) and the convergence samples of ``psnr_every`` (renders of the window and one
read of its squared errors).
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np
import warp as wp

from rgs_warp.config import DensifyConfig, MappingConfig
from rgs_warp.densification import Densifier
from rgs_warp.kernels import mapping as km
from rgs_warp.kernels.math import REDUCE_BLOCK, reduce_blocks
from rgs_warp.kernels.tracking import advance_step
from rgs_warp.keyframes import KeyframeBuffer
from rgs_warp.losses import DSSIMLoss
from rgs_warp.optim import MapAdam, MapLearningRates, cosine_factor
from rgs_warp.render import GRAPH_HEADROOM, GaussianGrads, Renderer, RenderResult
from rgs_warp.types import Camera, GaussianMap, grown_capacity


@dataclass
class MappingResult:
    """Diagnostics of one ``Mapper.optimize`` call."""

    iters: int
    loss_history: np.ndarray  # (iters,) weighted L1 + depth + lambda_dssim (1 - SSIM) is not included
    l1_history: np.ndarray  # (iters,) mean |I - g I_hat - b| over pixels and channels
    depth_l1_history: np.ndarray  # (iters,) mean |D_hat - D| (m) over pixels with depth; nan without
    # densification (method=baseline): Gaussians cloned, split (each replaced by two children), pruned
    # by its culling (split parents not counted), opacity resets
    cloned: int = 0
    split: int = 0
    pruned: int = 0
    opacity_resets: int = 0
    # (cumulative iteration, mean window PSNR dB, Gaussians) every ``psnr_every`` iterations
    psnr_curve: list[tuple[int, float, int]] = field(default_factory=list)
    # steps as captured graphs (mapping.graph): run eagerly, captured, replayed; replayed renders that
    # needed more intersections than their graph had room for (they dropped the excess)
    graph_steps: dict[str, int] = field(default_factory=lambda: {"eager": 0, "captured": 0, "replayed": 0})
    graph_overflows: int = 0

    @property
    def final_l1(self) -> float:
        """Mean colour L1 over the last pass through the window."""
        tail = self.l1_history[-max(1, min(len(self.l1_history), 5)) :]
        return float(np.mean(tail))


STATISTICS = ("obs_count", "vis_count", "ema_means")  # map columns: m_i, v_i, EMA position (Eq. 15)


class Mapper:
    """Optimises a GaussianMap over keyframe windows; its optimiser state (``MapAdam``), statistics
    (``STATISTICS``: ``obs_count`` m_i, ``vis_count`` v_i, ``ema_means``) and gradients are columns
    of the map, so they follow every append and removal of rows, whoever makes them.

    ``camera``: the keyframes' camera (the buffer's image size).  ``densify``: the residual-driven
    densification of ``method=baseline`` (None: the map grows only from outside); its culling
    opacity is ``cfg.opacity_cull``.  ``total_iters`` counts the mapping iterations of every call,
    the densification schedule's clock.
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
                gmap,
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
                max_gaussians=cfg.max_gaussians,
            )
        self.device = wp.get_device(device)
        self.renderer = renderer or Renderer(self.device)
        lrs = MapLearningRates(
            means=cfg.lr_position,
            rotations=cfg.lr_rotation,
            log_scales=cfg.lr_scale,
            opacity_logits=cfg.lr_opacity,
            sh=cfg.lr_color,
            sh_rest=cfg.lr_color * cfg.lr_color_rest_factor,
        )
        self.adam = MapAdam(gmap, lrs, betas=(cfg.adam_beta1, cfg.adam_beta2), max_grad_norm=cfg.grad_clip)
        gmap.add_column("obs_count", wp.int32)
        gmap.add_column("vis_count", wp.float32)
        gmap.add_column("ema_means", wp.vec3, fill="means")
        for name, dtype, inner in gmap.parameter_layout():
            gmap.add_column(f"grad.{name}", dtype, inner, scratch=True)
        gmap.add_column("grad.opacity_before", wp.float32, scratch=True)
        self.rng = np.random.default_rng(seed)
        dev = self.device
        shape = (camera.height, camera.width)
        self.dssim = DSSIMLoss(camera.height, camera.width, dev)
        self._x = wp.zeros(shape, dtype=wp.vec3, device=dev)
        self._grad_x = wp.zeros(shape, dtype=wp.vec3, device=dev)
        self._d_color = wp.zeros(shape, dtype=wp.vec3, device=dev)
        self._d_depth = wp.zeros(shape, dtype=wp.float32, device=dev)
        self._loss = wp.zeros((1, km.L_COLUMNS), dtype=wp.float64, device=dev)
        self._squared_error = wp.zeros(1, dtype=wp.float64, device=dev)
        self._window_capacity = 0
        self.total_iters = 0
        # the step counter of an optimize call: the loss row and the learning rates of a step are read
        # from it on the device (tk.advance_step), so one captured graph replays every step of its view
        self._step = wp.zeros(1, dtype=wp.int32, device=dev)
        self._overflows = wp.zeros(1, dtype=wp.int32, device=dev)
        self.use_graph = cfg.graph == "on" or (cfg.graph == "auto" and self.device.is_cuda)
        # steps of every call so far: eager, captured, replayed (mapping.graph), and overflowed replays
        self.graph_counts = {"eager": 0, "captured": 0, "replayed": 0, "overflowed": 0}

    def state_dict(self) -> dict[str, np.ndarray]:
        """The optimiser's clocks besides the map's columns: Adam's step count (bias correction), the
        view-order generator and the cumulative iterations; ``load_state_dict`` restores them."""
        rng = json.dumps(self.rng.bit_generator.state)
        return {"adam_t": np.array(self.adam.t), "rng": np.array(rng), "total_iters": np.array(self.total_iters)}

    def load_state_dict(self, state: dict[str, np.ndarray]) -> None:
        self.adam.t = int(state["adam_t"])
        self.rng.bit_generator.state = json.loads(str(state["rng"]))
        self.total_iters = int(state["total_iters"])

    def grads(self) -> GaussianGrads:
        """The gradient columns of the map (valid until it grows)."""
        return GaussianGrads(*(self.gmap.column(f"grad.{name}") for name in GaussianMap.PARAMETERS))

    def _upload_window(
        self, keyframes: KeyframeBuffer, window: list[int], history: Sequence[tuple[KeyframeBuffer, int]] = ()
    ) -> None:
        """The window's camera-to-world poses as the renderer's float32 device matrices, ``_T_WC[j]``,
        and its keyframes' exposures (g, b) ``_exposure[j]``; the ``history`` views (buffer, slot) follow
        the window's at ``j >= len(window)``."""
        views = [(keyframes, s) for s in window] + list(history)
        k, dev = len(views), self.device
        if k > self._window_capacity:
            self._window_capacity = cap = grown_capacity(self._window_capacity, k, minimum=8)
            self._T_WC = wp.zeros(cap, dtype=wp.mat44, device=dev)
            self._exposure = wp.zeros(cap, dtype=wp.vec2, device=dev)
        self._T_WC[:k].assign(np.stack([b.poses[s] for b, s in views]).astype(np.float32))
        self._exposure[:k].assign(np.stack([b.exposure[s] for b, s in views]).astype(np.float32))

    def _view_loss(self, keyframes, slot, j, weight, use_depth, blocks, graph_capacity=None) -> RenderResult:
        """Render window view j (keyframe ``slot``) and leave dL/d(image) of its share ``weight`` of the
        loss in ``_d_color``, ``_d_depth``; its loss sums go to the step counter's row.
        ``graph_capacity``: the render is being captured with room for that many intersections (a
        replay that needs more is counted in ``_overflows``)."""
        cfg, dev = self.cfg, self.device
        # consecutive iterations render different views: each sized by its own last render (view key)
        view = int(keyframes.frame_ids[slot])
        res = self.renderer.forward(self.gmap, self.camera, self._T_WC[j : j + 1], view=view)
        if graph_capacity is not None:
            needed = self.renderer.intersection_count_array
            wp.launch(km.count_overflow, dim=1, inputs=[needed, graph_capacity], outputs=[self._overflows], device=dev)
        wp.launch_tiled(
            km.mapping_loss,
            dim=blocks,
            inputs=[keyframes.rgb[slot], keyframes.depth[slot], res.color, res.depth, self._exposure, j]
            + [cfg.robust_scale, use_depth, weight * cfg.depth_weight, weight, 0, self._step],
            outputs=[self._x, self._grad_x, self._d_depth, self._loss],
            block_dim=REDUCE_BLOCK,
            device=dev,
        )
        self.dssim.accumulate_grad(self._x, keyframes.rgb[slot], weight * cfg.lambda_dssim, self._grad_x)
        wp.launch(
            km.scale_image_grad,
            dim=self._x.shape,
            inputs=[self._grad_x, self._exposure, j],
            outputs=[self._d_color],
            device=dev,
        )
        return res

    # ---- optimisation --------------------------------------------------------------------------
    def optimize(
        self,
        keyframes: KeyframeBuffer,
        window: Sequence[int],
        iters: int,
        psnr_every: int = 0,
        pause: Callable[[], None] | None = None,
        history: Sequence[tuple[KeyframeBuffer, int]] = (),
        stop: Callable[[int], bool] | None = None,
        history_share: float | None = None,
    ) -> MappingResult:
        """``iters`` mapping iterations over the keyframe ``window`` (buffer slots), each keyframe's render
        at its exposure (g, b) from tracking.  ``psnr_every`` > 0: after every iteration whose cumulative
        count ``total_iters`` is a multiple of it, the mean PSNR of the window (``window_psnr``) goes to
        ``MappingResult.psnr_curve`` (measured before that iteration's densification, whose fresh clones
        and split children the following iterations have yet to fit).  ``pause``: called after every
        iteration but the last (asynchronous mapping: where tracking may take the device).  ``history``:
        older keyframes as (buffer, slot); each view an iteration renders is one of them, drawn at random,
        with probability ``mapping.history``, so that the window's steps do not undo what earlier windows
        fitted.
        ``stop``: called with the iterations done after every iteration but the last; True ends the call
        there (asynchronous mapping keeping pace with the camera: ``mapping.min_iters``), and the result
        then holds the iterations that ran.  ``history_share``: that probability instead of
        ``mapping.history``."""
        dev, gmap = self.device, self.gmap
        window = list(window)
        if not window:
            raise ValueError("empty mapping window")
        if keyframes.rgb.shape[1:] != (self.camera.height, self.camera.width):
            raise ValueError(f"keyframes are {keyframes.rgb.shape[1:]}, the Mapper's camera is {self.camera}")
        iters = int(iters)
        if iters <= 0 or len(gmap) == 0:
            return MappingResult(0, np.zeros(0), np.zeros(0), np.zeros(0))
        share = self.cfg.history if history_share is None else history_share
        k_win, history = len(window), list(history) if share > 0.0 else []
        self._upload_window(keyframes, window, history)
        buffers = [keyframes] * k_win + [b for b, _ in history]
        slots = window + [s for _, s in history]
        if self._loss.shape[0] < iters:
            self._loss = wp.zeros((iters, km.L_COLUMNS), dtype=wp.float64, device=dev)
        self._loss.zero_()

        use_depth = int(self.mode == "rgbd")
        n_pixels = self.camera.width * self.camera.height
        blocks = [reduce_blocks(n_pixels)]
        result = MappingResult(iters, np.zeros(0), np.zeros(0), np.zeros(0))
        self._step.zero_()
        self._overflows.zero_()
        self.adam.schedule([cosine_factor(it, iters, self.cfg.lr_final_factor) for it in range(iters)])
        graphs = _StepGraphs(self) if self._graphs_apply() else None
        for it in range(iters):
            views = list(self.rng.permutation(k_win))[::-1]  # every view, in a fresh order each iteration
            if 0 < self.cfg.views_per_iter < k_win:
                views = views[: self.cfg.views_per_iter]  # or a fresh random subset of them
            if history:
                older = self.rng.random(len(views)) < share
                picks = self.rng.integers(len(history), size=len(views))
                views = [k_win + int(p) if o else v for v, o, p in zip(views, older, picks, strict=True)]
            if graphs is not None:
                graphs.step(buffers, slots, views[0], use_depth, blocks, result)
            else:
                self._map_step(buffers, slots, views, use_depth, blocks)
            self.total_iters += 1
            if psnr_every > 0 and self.total_iters % psnr_every == 0:
                psnr_db = self._window_psnr(keyframes, window, self._T_WC)
                result.psnr_curve.append((self.total_iters, psnr_db, len(gmap)))
            if self.densifier is not None:
                self._densify(result)
            if it + 1 < iters and stop is not None and stop(it + 1):
                iters = result.iters = it + 1
                break
            if pause is not None and it + 1 < iters:
                pause()

        if graphs is not None and result.graph_steps["captured"]:
            result.graph_overflows = int(self._overflows.numpy()[0])
            self.renderer.overflowed_renders += result.graph_overflows
        if graphs is not None:
            for k, v in result.graph_steps.items():
                self.graph_counts[k] += v
            self.graph_counts["overflowed"] += result.graph_overflows
        loss = self._loss[:iters].numpy()
        pixels = np.maximum(loss[:, km.L_PIXELS], 1.0)
        depth_px = loss[:, km.L_DEPTH_PIXELS]
        result.loss_history = loss[:, km.L_LOSS].copy()
        result.l1_history = loss[:, km.L_ABS] / pixels
        result.depth_l1_history = np.where(depth_px > 0, loss[:, km.L_DEPTH] / np.maximum(depth_px, 1.0), np.nan)
        return result

    def _graphs_apply(self) -> bool:
        """Whether this call's steps run as captured graphs (``mapping.graph``): one view per step, and
        nothing a step does on the host that a replay would not repeat."""
        cfg = self.cfg
        return self.use_graph and cfg.views_per_iter == 1 and self.densifier is None

    def _map_step(self, buffers, slots, views, use_depth, blocks, graph_capacity=None) -> None:
        """One Adam step on the map from the gradients of ``views`` (positions j of the uploaded views:
        keyframe ``slots[j]`` of ``buffers[j]``), averaged; the step counter advances at its end (the loss
        row and the learning rates are read from it).  ``graph_capacity``: the step is being captured
        (``_view_loss``)."""
        cfg, dev, gmap = self.cfg, self.device, self.gmap
        n = len(gmap)
        share = 1.0 / len(views)
        grads = self.grads()
        before = gmap.column("grad.opacity_before")
        obs_count, vis_count = gmap.column("obs_count"), gmap.column("vis_count")
        for v, j in enumerate(views):
            res = self._view_loss(buffers[j], slots[j], j, share, use_depth, blocks, graph_capacity)
            if v == 0:
                before[:n].zero_()
            else:
                wp.copy(before, grads.opacity_logits, count=n)
            self.renderer.backward(
                self._d_color, self._d_depth, None, grads_out=grads, accumulate=v > 0, with_pose=False
            )
            wp.launch(
                km.update_statistics,
                dim=n,
                inputs=[res.radii, grads.opacity_logits, before],
                outputs=[obs_count, vis_count],
                device=dev,
            )
            if self.densifier is not None:
                self.densifier.accumulate(self.renderer, share)
        ema_means = gmap.column("ema_means")
        wp.launch(
            km.regularize,
            dim=n,
            inputs=[gmap.means, gmap.log_scales, gmap.opacity_logits, ema_means]
            + [cfg.reg_elongation, math.log(cfg.max_anisotropy), cfg.reg_opacity, cfg.max_abs_opacity_logit]
            + [cfg.reg_anchor],
            outputs=[grads.means, grads.log_scales, grads.opacity_logits],
            device=dev,
        )
        self.adam.step(grads, counter=self._step)
        wp.launch(km.update_ema, dim=n, inputs=[gmap.means, cfg.ema_eta], outputs=[ema_means], device=dev)
        wp.launch(advance_step, dim=1, inputs=[self._step], device=dev)

    def _densify(self, result: MappingResult) -> None:
        """The densifier's step at iteration ``total_iters``: the appended rows got their optimiser
        state and statistics from the map's column fills; flagged rows leave the map."""
        step = self.densifier.step(self.total_iters, self.densify_cfg.scene_extent_m)
        if step.opacity_reset:
            # 3DGS restarts the opacity moments with the reset, so that the momentum gathered at the old
            # opacities does not undo it
            self.adam.reset_field("opacity_logits")
            result.opacity_resets += 1
        if step.remove is None:
            return
        before = len(self.gmap)
        self.gmap.remove(step.remove)
        result.cloned += step.cloned
        result.split += step.split
        result.pruned += before - len(self.gmap) - step.split

    def refine_all(
        self,
        keyframes: KeyframeBuffer,
        window: Sequence[int],
        history: Sequence[tuple[KeyframeBuffer, int]],
        iters: int,
        scored: Sequence[tuple[KeyframeBuffer, int]],
        stop: Callable[[int], bool] | None = None,
    ) -> dict:
        """``iters`` iterations in one call over the keyframes ``window`` (slots of ``keyframes``) and the
        ``history`` views (buffer, slot), each view an iteration renders (``mapping.views_per_iter`` of the
        window's) drawn alike from all of them (so the call's steps replay as captured graphs, as a
        keyframe's mapping does); ``stop`` as ``optimize``'s.
        Returns the iterations run and planned, the views it drew from, the keyframes ``scored`` (buffer,
        slot) and their mean PSNR (``window_psnr``) before and after."""
        window, history = list(window), list(history)
        before = self.views_psnr(scored)
        share = len(history) / (len(history) + len(window))
        result = self.optimize(keyframes, window, iters, history=history, stop=stop, history_share=share)
        return {
            "iters": result.iters,
            "iters_planned": int(iters),
            "views": len(window) + len(history),
            "keyframes": len(scored),
            "keyframe_psnr_before_db": before,
            "keyframe_psnr_after_db": self.views_psnr(scored),
        }

    def views_psnr(self, views: Sequence[tuple[KeyframeBuffer, int]]) -> float:
        """``window_psnr`` over views (buffer, slot) that may lie in several buffers: their mean."""
        groups: dict[int, tuple[KeyframeBuffer, list[int]]] = {}
        for buffer, slot in views:
            groups.setdefault(id(buffer), (buffer, []))[1].append(slot)
        total = sum(self.window_psnr(buffer, slots) * len(slots) for buffer, slots in groups.values())
        return total / max(1, len(views))

    # ---- convergence ---------------------------------------------------------------------------
    def convergence(
        self, keyframes: KeyframeBuffer, window: Sequence[int], mapping: MappingResult, frame: int, phase: str
    ) -> list[dict]:
        """The convergence points of one mapping call (``SLAM.convergence``): its ``psnr_curve`` samples,
        then the window's PSNR now (after the maintenance too), which replaces a sample at the same
        iteration; each {"iteration", "frame", "phase", "psnr_db" (None for an empty map),
        "gaussians"}.  None without mapping."""
        if mapping.iters == 0:
            return []
        points = list(mapping.psnr_curve)
        if points and points[-1][0] == self.total_iters:
            points.pop()
        points.append((self.total_iters, self.window_psnr(keyframes, window), len(self.gmap)))
        return [
            {
                "iteration": it,
                "frame": frame,
                "phase": phase,
                "psnr_db": float(p) if np.isfinite(p) else None,
                "gaussians": n,
            }
            for it, p, n in points
        ]

    def window_psnr(self, keyframes: KeyframeBuffer, window: Sequence[int]) -> float:
        """Mean over the keyframes of ``window`` (slots) of the PSNR (dB) of the exposure-corrected
        render clip(g I_hat + b, 0, 1) at the keyframe's pose against the keyframe image."""
        window = list(window)
        self._upload_window(keyframes, window)
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
        blocks = [reduce_blocks(n_pixels)]
        for j, slot in enumerate(window):
            # sized by its own count (the view before may have seen far less of the map: dropped intersections)
            view = int(keyframes.frame_ids[slot])
            res = self.renderer.forward(self.gmap, self.camera, T_WC[j : j + 1], view=view, fit=True)
            wp.launch_tiled(
                km.exposed_squared_error,
                dim=blocks,
                inputs=[keyframes.rgb[slot], res.color, self._exposure, j],
                outputs=[self._squared_error],
                block_dim=REDUCE_BLOCK,
                device=self.device,
            )
        mse = np.maximum(self._squared_error.numpy()[:k] / (3.0 * n_pixels), 1e-20)
        return float(np.mean(-10.0 * np.log10(mse)))


class _StepGraphs:
    """The captured mapping steps of one ``Mapper.optimize`` call, one graph per view (its pose,
    keyframe images and exposure are the graph's arrays; the step counter gives the rest).  A view's
    first step in the call runs eagerly, and its render sizes the renderer for that view; the second is
    captured with ``GRAPH_HEADROOM`` x those intersections reserved, and replayed from then on.  The
    renderer reallocating its buffers (an eager render of a denser view) drops every graph (they hold
    its addresses); the map does not change size within a call.  Views rendered once (most history
    views) stay eager: a capture costs more than it saves there."""

    def __init__(self, mapper: Mapper):
        self.mapper = mapper
        self._graphs: dict[int, tuple] = {}
        self._seen: set[int] = set()

    def step(self, buffers, slots, j: int, use_depth: int, blocks, result: MappingResult) -> None:
        m = self.mapper
        renderer = m.renderer
        entry = self._graphs.get(j)
        if entry is not None and entry[1] != renderer.buffers_version:
            self._graphs.clear()
            entry = None
        if entry is not None:
            wp.capture_launch(entry[0])
            m.adam.t += 1  # the replayed step's, as an eager step counts it
            result.graph_steps["replayed"] += 1
            return
        view = int(buffers[j].frame_ids[slots[j]])
        # (settles the latest eager render's count under its view: the capture's forward cannot)
        needed = renderer.view_intersections(view) if j in self._seen else 0
        if needed <= 0:
            m._map_step(buffers, slots, [j], use_depth, blocks)
            self._seen.add(j)
            result.graph_steps["eager"] += 1
            return
        renderer.reserve_intersections(math.ceil(GRAPH_HEADROOM * needed))
        capacity, version = renderer.intersection_capacity, renderer.buffers_version
        with wp.ScopedCapture(device=m.device) as capture:
            m._map_step(buffers, slots, [j], use_depth, blocks, graph_capacity=capacity)
        self._graphs[j] = (capture.graph, version)
        wp.capture_launch(capture.graph)  # the captured step itself (Adam counted it while capturing)
        result.graph_steps["captured"] += 1
