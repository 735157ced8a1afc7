"""Adam over a GaussianMap (supplement Table 1: betas 0.9 / 0.999, per-group learning rates,
gradient-norm clipping at 1.0, cosine decay inside each optimisation window)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import warp as wp

from rgs_warp.kernels.adam import adam_step, clip_scale_from_sq_norms
from rgs_warp.kernels.map_ops import scatter_kept_rows
from rgs_warp.types import GaussianMap

FIELDS = ("means", "rotations", "log_scales", "opacity_logits", "sh")


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
    """First and second moments for every GaussianMap field, kept in step with the map's capacity
    (``sync``) and compaction (``remove``). ``step`` clips the global gradient norm to
    ``max_grad_norm`` and applies Adam; all on the device."""

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
        self._sq = wp.zeros(len(FIELDS), dtype=wp.float32, device=dev)
        self.clip = wp.zeros(2, dtype=wp.float32, device=dev)  # [scale applied, gradient norm]
        self._capacity = 0
        self.sync()

    def sync(self) -> None:
        """Follow the map's growth: new moment arrays of its capacity, live rows copied."""
        gmap = self.gmap
        if gmap.capacity == self._capacity:
            return
        old = getattr(self, "_m", None), getattr(self, "_v", None)
        self._m, self._v = {}, {}
        for name in FIELDS:
            field = getattr(gmap, name)
            for store, prev in ((self._m, old[0]), (self._v, old[1])):
                store[name] = wp.zeros_like(_flat(field))
                if prev is not None:
                    wp.copy(store[name], prev[name], count=min(prev[name].shape[0], store[name].shape[0]))
        self._capacity = gmap.capacity

    def _width(self, name: str) -> int:
        """Floats per Gaussian of a field (3 for means, 4 for rotations, 3 K for SH, ...)."""
        return self._m[name].shape[0] // self._capacity

    def reset_rows(self, start: int, count: int) -> None:
        """Zero the moments of rows ``start .. start + count`` (e.g. Gaussians just appended)."""
        self.sync()
        for name in FIELDS:
            w = self._width(name)
            for store in (self._m, self._v):
                store[name][start * w : (start + count) * w].zero_()

    def reset_field(self, name: str) -> None:
        """Zero the moments of one field for every row (e.g. the opacities after a reset)."""
        if name not in FIELDS:
            raise ValueError(f"unknown map field {name!r}; fields: {', '.join(FIELDS)}")
        self.sync()
        for store in (self._m, self._v):
            store[name].zero_()

    def remove(self, mask) -> None:
        """Compact the moments as ``GaussianMap.remove(mask)`` compacts the fields; call it first,
        with the same mask (length: the map's count before removal, nonzero = remove)."""
        dev = self.gmap.device
        if not isinstance(mask, wp.array):
            mask = wp.array(np.asarray(mask).astype(np.int32), dtype=wp.int32, device=dev)
        n = mask.shape[0]
        removed_before = wp.empty(n, dtype=wp.int32, device=dev)
        wp.utils.array_scan(mask, removed_before, inclusive=False)
        for name in FIELDS:
            w = self._width(name)
            for store in (self._m, self._v):
                rows = store[name].reshape((self._capacity, w))
                tmp = wp.zeros_like(rows)
                wp.launch(scatter_kept_rows, dim=(n, w), inputs=[rows, mask, removed_before, tmp], device=dev)
                wp.copy(store[name], tmp.flatten())

    def step(self, grads, lr_factor: float = 1.0) -> None:
        """One Adam step on the live rows from ``grads`` (a ``GaussianGrads`` of the same capacity
        layout), learning rates scaled by ``lr_factor`` (the cosine schedule)."""
        self.sync()
        n = len(self.gmap)
        if n == 0:
            return
        self.t += 1
        correction = math.sqrt(1.0 - self.beta2**self.t) / (1.0 - self.beta1**self.t)
        flats = []
        for i, name in enumerate(FIELDS):
            g = _flat(getattr(grads, name))
            count = n * self._width(name)
            wp.utils.array_inner(g, g, out=self._sq[i : i + 1], count=count)
            flats.append((name, g, count))
        wp.launch(
            clip_scale_from_sq_norms,
            dim=1,
            inputs=[self._sq, float(self.max_grad_norm)],
            outputs=[self.clip],
            device=self.gmap.device,
        )
        width_sh = 3 * self.gmap.num_sh
        for name, g, count in flats:
            scale = lr_factor * correction
            lr_t, lr_rest_t = self.lrs.of(name) * scale, self.lrs.rest(name) * scale
            width, lead = (width_sh, 3) if name == "sh" else (1, 1)
            wp.launch(
                adam_step,
                dim=count,
                inputs=[g, self.clip, lr_t, width, lead, lr_rest_t, self.beta1, self.beta2, self.eps],
                outputs=[_flat(getattr(self.gmap, name)), self._m[name], self._v[name]],
                device=self.gmap.device,
            )
