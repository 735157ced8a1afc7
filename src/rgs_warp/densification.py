"""Residual-driven densification of the dense initialization baseline (supplement Table 2, method
``baseline``): the adaptive density control of 3DGS (Kerbl et al. 2023, §5.2).

The baseline grows its map where the photometric residual pulls Gaussians around in the image: the
norm of each Gaussian's screen-space mean gradient is averaged over the renders that saw it, and on
schedule the Gaussians above a threshold are cloned (small ones, under-reconstruction) or split in
two (large ones, over-reconstruction), transparent and oversized ones are pruned, and every few
thousand iterations the opacities are lowered so that the optimisation can drop unneeded Gaussians.

The Densifier appends rows (as a Seeder does) and returns the rows to remove; its statistics are
columns of the map, so they grow and compact with it, as the optimiser's moments do (the ``Mapper``,
which calls it inside its iterations, removes the flagged rows with ``GaussianMap.remove``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import warp as wp

from rgs_warp.kernels.densify import (
    accumulate_grad_stats,
    clamp_opacity_logits,
    classify_densify,
    flag_pruned,
    write_densified,
)
from rgs_warp.render import Renderer
from rgs_warp.types import GaussianMap

__all__ = ["DensifyStep", "Densifier"]


def _logit(p: float) -> float:
    if p <= 0.0:
        return -math.inf
    if p >= 1.0:
        return math.inf
    return math.log(p / (1.0 - p))


def _logit_at_most(p: float) -> float:
    """The largest float32 logit whose sigmoid does not exceed ``p`` (the rounding of logit(p) to
    float32 may land above it)."""
    x = np.float32(_logit(p))
    while 1.0 / (1.0 + math.exp(-float(x))) > p:
        x = np.nextafter(x, np.float32(-np.inf))
    return float(x)


@dataclass
class DensifyStep:
    """What one ``Densifier.step`` did.  ``remove``: int32 flags (nonzero = remove) over the map's
    rows after the appends, the split parents and the culled Gaussians, for the caller to remove
    through its removal path (``Mapper.remove``); None when nothing was densified.  It is the
    Densifier's scratch, valid until its next ``step``."""

    cloned: int = 0
    split: int = 0
    opacity_reset: bool = False
    remove: wp.array | None = None


class Densifier:
    """3DGS adaptive density control over a GaussianMap and its MapAdam, on the device.

    Parameters (defaults: 3DGS's 30k-iteration schedule, culling opacity of supplement Table 1):

    * ``grad_threshold=2e-4``: densify Gaussians whose mean screen-space gradient norm (NDC units,
      see ``accumulate``) over the renders where they were visible is at least this.
    * ``interval=100``, ``start=500``, ``stop=15000``: densify and prune at iterations ``it`` with
      ``start < it < stop`` and ``it % interval == 0`` (3DGS's test: 600, 700, ..., 14900).
    * ``opacity_reset_interval=3000``: at ``it % opacity_reset_interval == 0`` (same window; 0 = never)
      the opacity of every Gaussian seen since the statistics were last restarted becomes
      ``min(opacity, opacity_reset_value)``, ``opacity_reset_value=0.1``.  3DGS resets every Gaussian
      (its training views see all of them within one interval); in SLAM the window sees a part of the
      map, and a Gaussian reset outside it would stay faded until the camera came back.
    * ``percent_dense=0.01``: Gaussians whose largest scale is at most ``percent_dense * scene_extent``
      are cloned, larger ones split.
    * ``split_factor=1.6``: the two children of a split have the parent's scales / ``split_factor``.
    * ``cull_opacity=0.05``: prune Gaussians with opacity below this at every densification step
      (supplement Table 1; 3DGS: 0.005 with a reset to 0.01).  The reset value must stay above it,
      or a reset followed by the next culling wipes the map: 0.1 keeps 3DGS's factor of 2.
    * ``prune_scale_fraction=0.1``: after the first opacity reset, also prune Gaussians whose largest
      scale exceeds this fraction of ``scene_extent`` (3DGS's world-space test; its screen-space test
      never fires in the reference code, which resets the statistic it reads just before, so it is
      left out here as in gsplat's default strategy).  0 disables it.
    * ``seed=0``: seeds the split children's sampling (``wp.rand_init(seed', gaussian)``, with seed'
      derived from ``seed`` and the iteration), so runs are deterministic.
    * ``max_gaussians=0``: a densification that would take the map over this many rows (clones and
      split children counted before their parents and the culled go) is skipped, its culling kept
      (``mapping.max_gaussians``: bounded memory; 0 = no cap).

    Statistics are map columns ``densify.grad_norm_sum`` (float32, running sum of gradient norms)
    and ``densify.visible_count`` (int32), zero for new rows; ``densify.new_rows``, ``.offsets`` and
    ``.remove`` are its scratch.
    """

    def __init__(
        self,
        gmap: GaussianMap,
        *,
        grad_threshold: float = 2e-4,
        interval: int = 100,
        start: int = 500,
        stop: int = 15000,
        opacity_reset_interval: int = 3000,
        opacity_reset_value: float = 0.1,
        percent_dense: float = 0.01,
        split_factor: float = 1.6,
        cull_opacity: float = 0.05,
        prune_scale_fraction: float = 0.1,
        seed: int = 0,
        max_gaussians: int = 0,
    ):
        if interval <= 0:
            raise ValueError(f"interval must be positive, got {interval}")
        if split_factor <= 0.0:
            raise ValueError(f"split_factor must be positive, got {split_factor}")
        if opacity_reset_interval > 0 and opacity_reset_value <= cull_opacity:
            raise ValueError(
                f"opacity_reset_value {opacity_reset_value} is not above cull_opacity {cull_opacity}: "
                "a reset followed by the next culling would remove every Gaussian"
            )
        self.grad_threshold = grad_threshold
        self.interval, self.start, self.stop = interval, start, stop
        self.opacity_reset_interval = opacity_reset_interval
        self.opacity_reset_value = opacity_reset_value
        self.percent_dense = percent_dense
        self.split_factor = split_factor
        self.cull_opacity = cull_opacity
        self.prune_scale_fraction = prune_scale_fraction
        self.seed = seed
        self.max_gaussians = max_gaussians
        self.gmap = gmap
        gmap.add_column("densify.grad_norm_sum", wp.float32)
        gmap.add_column("densify.visible_count", wp.int32)
        for name in ("new_rows", "offsets", "remove"):  # per-row actions, their offsets, removal flags
            gmap.add_column(f"densify.{name}", wp.int32, scratch=True)
        self._counts = wp.zeros(2, dtype=wp.int32, device=gmap.device)

    @property
    def grad_norm_sum(self) -> wp.array:
        return self.gmap.column("densify.grad_norm_sum")

    @property
    def visible_count(self) -> wp.array:
        return self.gmap.column("densify.visible_count")

    # ---- statistics --------------------------------------------------------------------------
    def accumulate(self, renderer: Renderer, loss_share: float = 1.0) -> None:
        """Add the latest full ``renderer.backward`` of the map to the statistics (launches only).

        3DGS thresholds the gradient w.r.t. the projected mean in NDC, where u = ((ndc_x + 1) W - 1) / 2
        (v alike with H), so dL/d ndc_x = dL/du * W / 2 and dL/d ndc_y = dL/dv * H / 2; the renderer's
        ``grad2d`` holds dL/du, dL/dv in pixels, scaled here before taking the norm.  The threshold
        also assumes 3DGS's loss scale: a mean over pixels (and channels), not a sum.
        ``loss_share``: the weight of this view's loss in the gradients (1 / views when an iteration
        averages several views); they are divided by it, so that each render counts with the gradient
        of its own whole loss, as in 3DGS's one-view iterations.
        Gaussians count as seen where their radius is positive (3DGS's visibility filter).
        """
        gmap = self.gmap
        n = len(gmap)
        if n == 0:
            return
        if renderer.grad2d.shape[0] < n or renderer.image_shape is None:
            raise ValueError("the renderer's latest backward is not of this map")
        height, width = renderer.image_shape
        wp.launch(
            accumulate_grad_stats,
            dim=n,
            inputs=[renderer.grad2d, renderer.radii, wp.vec2(0.5 * width / loss_share, 0.5 * height / loss_share)],
            outputs=[self.grad_norm_sum, self.visible_count],
            device=gmap.device,
        )

    def reset_stats(self) -> None:
        """Restart the statistics of every Gaussian (done after each densification step)."""
        self.grad_norm_sum.zero_()
        self.visible_count.zero_()

    # ---- schedule ----------------------------------------------------------------------------
    def step(self, iteration: int, scene_extent: float) -> DensifyStep:
        """Reset opacities, densify and flag Gaussians for pruning when ``iteration`` calls for it
        (see the class).

        ``scene_extent``: the scene's size in metres (the unit of ``percent_dense`` and
        ``prune_scale_fraction``).  Clones and split children are appended to the map (their optimiser
        state and statistics come from the column fills, as after a Seeder); the split parents and the
        culled Gaussians come back in ``DensifyStep.remove`` for the caller to remove.  The reset
        comes first, so that the statistics it reads are those of the rows before densification.
        A densification step reads one count back to the host; other iterations cost nothing.
        """
        gmap = self.gmap
        result = DensifyStep()
        if not self.start < iteration < self.stop or len(gmap) == 0:
            return result
        if self.opacity_reset_interval > 0 and iteration % self.opacity_reset_interval == 0:
            wp.launch(
                clamp_opacity_logits,
                dim=len(gmap),
                inputs=[self.visible_count, _logit_at_most(self.opacity_reset_value)],
                outputs=[gmap.opacity_logits],
                device=gmap.device,
            )
            result.opacity_reset = True
        if iteration % self.interval == 0:
            self._densify(iteration, gmap, scene_extent, result)
        return result

    def _densify(self, iteration: int, gmap: GaussianMap, scene_extent: float, result: DensifyStep) -> None:
        dev = gmap.device
        n = len(gmap)
        self._counts.zero_()
        wp.launch(
            classify_densify,
            dim=n,
            inputs=[self.grad_norm_sum, self.visible_count, gmap.log_scales]
            + [float(self.grad_threshold), float(self.percent_dense * scene_extent)],
            outputs=[gmap.column("densify.new_rows"), self._counts],
            device=dev,
        )
        new_rows, offsets = gmap.column("densify.new_rows"), gmap.column("densify.offsets")
        wp.utils.array_scan(new_rows[:n], offsets[:n], inclusive=False)
        result.cloned, result.split = (int(c) for c in self._counts.numpy())
        added = result.cloned + 2 * result.split
        if 0 < self.max_gaussians < n + added:  # at the cap: no growth, culling only
            new_rows[:n].zero_()
            result.cloned = result.split = added = 0
        if added:
            gmap.reserve(n + added)
            seed = (self.seed * 1_000_003 + iteration) % (2**31)
            wp.launch(
                write_densified,
                dim=n,
                inputs=[new_rows, offsets, n, gmap.num_sh, math.log(self.split_factor), seed],
                outputs=[gmap.means, gmap.rotations, gmap.log_scales, gmap.opacity_logits, gmap.sh],
                device=dev,
            )
            gmap.count = n + added  # the rows n .. n + added were just written on the device
        total = n + added
        # 3DGS prunes oversized Gaussians only once the first opacity reset is behind.
        prune_big = self.prune_scale_fraction > 0.0 and iteration > self.opacity_reset_interval > 0
        wp.launch(
            flag_pruned,
            dim=total,
            inputs=[new_rows, n, gmap.opacity_logits, gmap.log_scales, _logit(self.cull_opacity)]
            + [float(self.prune_scale_fraction * scene_extent) if prune_big else 0.0],
            outputs=[gmap.column("densify.remove")],
            device=dev,
        )
        result.remove = gmap.column("densify.remove")[:total]
        # 3DGS restarts the statistics of every Gaussian after densifying.
        self.reset_stats()
