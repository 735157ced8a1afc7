"""Adam over a GaussianMap (supplement Table 1: betas 0.9 / 0.999, per-group learning rates,
gradient-norm clipping at 1.0, cosine decay inside each optimisation window)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import warp as wp

from rgs_warp.kernels.adam import NORM_BLOCKS, adam_entries, clip_scale_from_sq_norms, grad_sq_norms, vec5i, vec6
from rgs_warp.kernels.math import REDUCE_BLOCK, reduce_blocks
from rgs_warp.types import GaussianMap


@dataclass
class MapLearningRates:
    means: float = 1e-3
    rotations: float = 1e-3
    log_scales: float = 1e-3
    opacity_logits: float = 2e-3
    sh: float = 2e-3  # the DC (degree-0) colour coefficients
    sh_rest: float | None = None  # the higher SH bands (3DGS: sh / 20); None: as sh

    def of(self, name: str) -> float:
        return getattr(self, name)

    def rest(self, name: str) -> float:
        """The rate of a field's non-leading entries (the higher SH bands; otherwise ``of``)."""
        return self.sh_rest if name == "sh" and self.sh_rest is not None else self.of(name)


def cosine_factor(step: int, total: int, final: float = 0.0) -> float:
    """Cosine decay from 1 at ``step`` 0 to ``final`` at ``step`` = ``total``."""
    if total <= 1:
        return 1.0
    t = min(max(step / (total - 1), 0.0), 1.0)
    return final + (1.0 - final) * 0.5 * (1.0 + math.cos(math.pi * t))


def _flat(field: wp.array) -> wp.array:
    """Zero-copy float32 view of a field (vec3 / quat / float rows, or the 2D SH rows)."""
    if field.ndim == 2:
        field = field.flatten()
    return field if field.dtype == wp.float32 else field.view(wp.float32).flatten()


class MapAdam:
    """Adam over the parameters of a GaussianMap.  Its first and second moments are columns of the
    map (``adam_m.<parameter>``, ``adam_v.<parameter>``, zero for new rows), so they grow and compact
    with the map.  ``step`` clips the global gradient norm to ``max_grad_norm`` and applies Adam; all
    on the device."""

    def __init__(
        self,
        gmap: GaussianMap,
        lrs: MapLearningRates,
        betas=(0.9, 0.999),
        eps: float = 1e-15,
        max_grad_norm: float = 1.0,
    ):
        self.gmap, self.lrs = gmap, lrs
        self.beta1, self.beta2 = betas
        self.eps, self.max_grad_norm = eps, max_grad_norm
        self.t = 0
        dev = gmap.device
        self._sq = wp.zeros(len(GaussianMap.PARAMETERS), dtype=wp.float32, device=dev)
        self.clip = wp.zeros(2, dtype=wp.float32, device=dev)  # [scale applied, gradient norm]
        self._schedule = wp.zeros(1, dtype=vec6, device=dev)
        self._views_key: tuple = ()
        self._flat_views: list[list[wp.array]] = []
        for name, dtype, inner in gmap.parameter_layout():
            for moment in ("adam_m", "adam_v"):
                gmap.add_column(f"{moment}.{name}", dtype, inner)

    def moments(self, name: str) -> tuple[wp.array, wp.array]:
        """(first, second) moment columns of parameter ``name``, as float32 views of the live layout."""
        if name not in GaussianMap.PARAMETERS:
            raise ValueError(f"unknown map parameter {name!r}; parameters: {', '.join(GaussianMap.PARAMETERS)}")
        return _flat(self.gmap.column(f"adam_m.{name}")), _flat(self.gmap.column(f"adam_v.{name}"))

    def reset_field(self, name: str) -> None:
        """Zero the moments of one parameter for every row (e.g. the opacities after a reset)."""
        for moment in self.moments(name):
            moment.zero_()

    def schedule(self, lr_factors) -> None:
        """The learning rates of the next ``len(lr_factors)`` steps on the device: each step's rates
        scaled by its factor (the cosine schedule), the bias correction of its step folded in.  ``step``
        reads row ``counter[0]``, so a captured step reads its own at each replay."""
        rows = [self._rates(f, self.t + 1 + k) for k, f in enumerate(lr_factors)]
        if self._schedule.shape[0] < len(rows):
            self._schedule = wp.zeros(len(rows), dtype=vec6, device=self.gmap.device)
        self._schedule[: len(rows)].assign(np.array(rows, dtype=np.float32).reshape(len(rows), 6))

    def _rates(self, lr_factor: float, t: int) -> vec6:
        scale = lr_factor * math.sqrt(1.0 - self.beta2**t) / (1.0 - self.beta1**t)
        return vec6(*[self.lrs.of(name) * scale for name in GaussianMap.PARAMETERS], self.lrs.rest("sh") * scale)

    def step(self, grads, counter: wp.array) -> None:
        """One Adam step on the live rows from ``grads`` (a ``GaussianGrads`` of the same capacity
        layout) at the learning rates of row ``counter[0]`` (a one-int device array, the caller's step
        counter) of ``schedule``'s: three launches over the flat entries of all five parameters (the
        squared gradient norms, the clip scale, the update)."""
        gmap = self.gmap
        n = len(gmap)
        if n == 0:
            return
        self.t += 1
        g, p, m, v = self._views(grads)
        rows = n * 3 * gmap.num_sh
        ends = vec5i(*np.cumsum([3 * n, 4 * n, 3 * n, n, rows]).tolist())
        self._sq.zero_()
        wp.launch_tiled(
            grad_sq_norms,
            dim=[min(reduce_blocks(ends[4]), NORM_BLOCKS)],
            inputs=[*g, ends],
            outputs=[self._sq],
            block_dim=REDUCE_BLOCK,
            device=gmap.device,
        )
        wp.launch(
            clip_scale_from_sq_norms,
            dim=1,
            inputs=[self._sq, float(self.max_grad_norm)],
            outputs=[self.clip],
            device=gmap.device,
        )
        wp.launch(
            adam_entries,
            dim=int(ends[4]),
            inputs=[*g, ends, self.clip, self._schedule, counter, 3 * gmap.num_sh, self.beta1, self.beta2, self.eps],
            outputs=[*p, *m, *v],
            device=gmap.device,
        )

    def _views(self, grads) -> tuple[list[wp.array], ...]:
        """Flat float32 views of the gradients, parameters and moments, made again only when an array
        changed (the map grew, or other gradient arrays)."""
        gmap, names = self.gmap, GaussianMap.PARAMETERS
        arrays = [getattr(grads, name) for name in names] + [getattr(gmap, name) for name in names]
        arrays += [gmap.column(f"{moment}.{name}") for moment in ("adam_m", "adam_v") for name in names]
        key = tuple(a.ptr for a in arrays) + tuple(a.shape[0] for a in arrays)
        if key != self._views_key:
            flat = [_flat(a) for a in arrays]
            self._flat_views = [flat[k : k + 5] for k in range(0, 20, 5)]
            self._views_key = key
        return tuple(self._flat_views)
