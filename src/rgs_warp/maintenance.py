"""The mapper's maintenance pass (supplement §4.5): pruning and merging keep the map compact and
free of the extremely large or transparent splats that destabilise optimisation.

Both passes only compute removal masks (int32, 1 = remove, length ``len(gmap)``); the caller ORs
them (``merge_duplicates(..., exclude=prune)`` does it in one go) and applies the result with
``gmap.remove(mask)``, which compacts every column of the map (optimiser moments and statistics
included); the ``Maintainer`` stage does all three.  Merging rewrites the survivors' parameters in
place.

Host synchronisation: no read-back.  Counts come back as small device arrays (``PruneStats.read`` and
``int(n_merged.numpy()[0])`` read them, one synchronisation each, when the caller logs); the caller
syncs anyway when ``gmap.remove`` reads the number of removed rows.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import warp as wp

from rgs_warp.config import MappingConfig
from rgs_warp.geometry import invert_pose
from rgs_warp.kernels.maintenance import (
    PRUNE_STATS,
    merge_best_partner,
    merge_footprints,
    merge_pairs,
    prune_flags,
)
from rgs_warp.kernels.math import camera_params
from rgs_warp.types import Camera, GaussianMap, grown_capacity


@dataclass(frozen=True)
class PruneStats:
    """How many Gaussians a ``prune_mask`` call flagged, each counted under the first reason that
    applies, in this order: non-finite parameters, opacity, scale, hidden."""

    total: int
    invalid: int
    opacity: int
    scale: int
    hidden: int

    @classmethod
    def read(cls, stats: wp.array) -> PruneStats:
        """Read ``prune_mask``'s stats array back (one synchronisation)."""
        return cls(*(int(x) for x in stats.numpy()[:PRUNE_STATS]))

    def __str__(self) -> str:
        return (
            f"pruned {self.total} (opacity {self.opacity}, scale {self.scale}, hidden {self.hidden}, "
            f"invalid {self.invalid})"
        )


def _map_fields(gmap: GaussianMap, n: int) -> list[wp.array]:
    return [gmap.means[:n], gmap.rotations[:n], gmap.log_scales[:n], gmap.opacity_logits[:n], gmap.sh[:n]]


def prune_mask(
    gmap: GaussianMap,
    obs_count: wp.array | None,
    vis_count: wp.array | None,
    *,
    opacity_min: float = 0.05,
    max_scale_m: float = 0.5,
    max_scale_rel: float = 0.1,
    scene_extent_m: float | None = None,
    min_obs: int = 3,
    min_visibility_ratio: float = 0.1,
    out: wp.array | None = None,
    stats_out: wp.array | None = None,
) -> tuple[wp.array, wp.array]:
    """Flag the Gaussians that violate the bounds of supplement §4.5.

    A Gaussian is removed when any parameter is non-finite (or its quaternion is zero); when its
    opacity sigmoid(logit) is below ``opacity_min`` (Table 1: 0.05); when its extent sqrt(tr Sigma)
    = |exp(log_scales)| (metres; between the largest axis and sqrt(3) times it) exceeds
    ``max_scale_m``, or ``max_scale_rel * scene_extent_m`` when a scene extent is given (3DGS prunes
    splats above 0.1 of the scene's radius); or when it was inside ``obs_count[i] >= min_obs``
    rendered views but contributed to pixels in fewer than ``min_visibility_ratio`` of them
    (``vis_count[i] < ratio * obs_count[i]``: hidden behind surfaces).

    obs_count: (>= N,) int32, views the Gaussian was inside; vis_count: (>= N,) float32, its
    cumulative visibility score (views in which it contributed); both None skips the hidden test.
    Returns ``(mask, stats)``: mask (N,) int32, 1 = remove (``out`` if given); stats (5,) int32 on
    the device, [total, invalid, opacity, scale, hidden] (``stats_out`` if given; ``PruneStats.read``).
    """
    if (obs_count is None) != (vis_count is None):
        raise ValueError("give both obs_count and vis_count, or neither")
    n = len(gmap)
    if obs_count is not None and min(obs_count.shape[0], vis_count.shape[0]) < n:
        raise ValueError(f"obs_count / vis_count have {obs_count.shape[0]} / {vis_count.shape[0]} rows, map has {n}")
    device = gmap.device
    if out is None:
        out = wp.empty(n, dtype=wp.int32, device=device)
    if stats_out is None:
        stats_out = wp.zeros(PRUNE_STATS, dtype=wp.int32, device=device)
    stats_out.zero_()
    if n == 0:
        return out[:0], stats_out
    max_extent = max_scale_m if scene_extent_m is None else min(max_scale_m, max_scale_rel * scene_extent_m)
    has_visibility = obs_count is not None
    wp.launch(
        prune_flags,
        dim=n,
        inputs=_map_fields(gmap, n)
        + [obs_count[:n] if has_visibility else None, vis_count[:n] if has_visibility else None, int(has_visibility)]
        + [float(opacity_min), float(max_extent), int(min_obs), float(min_visibility_ratio)],
        outputs=[out[:n], stats_out],
        device=device,
    )
    return out[:n], stats_out


class MergeScratch:
    """Buffers of ``merge_duplicates`` (hash grid, footprints, partners, merge count), reusable across
    calls so that a mapper allocates them once; they grow (doubling) with the map."""

    def __init__(self, device=None, capacity: int = 1024):
        self.device = wp.get_device(device)
        self.grid = wp.HashGrid(128, 128, 128, device=self.device)
        self.n_merged = wp.zeros(1, dtype=wp.int32, device=self.device)
        self._capacity = 0
        self.ensure(capacity)

    def ensure(self, n: int) -> None:
        if n <= self._capacity:
            return
        cap = grown_capacity(self._capacity, n, minimum=1024)
        kw = {"device": self.device}
        self.points = wp.zeros(cap, dtype=wp.vec3, **kw)
        self.cov2d = wp.zeros(cap, dtype=wp.vec3, **kw)
        self.valid = wp.zeros(cap, dtype=wp.int32, **kw)
        self.best = wp.zeros(cap, dtype=wp.int32, **kw)
        self._capacity = cap


def merge_duplicates(
    gmap: GaussianMap,
    camera: Camera,
    T_WC: np.ndarray,
    *,
    max_footprint_px: float = 0.5,
    max_depth_rel: float = 0.01,
    max_size_rel: float = 0.2,
    max_color_diff: float = 0.05,
    max_merged_opacity: float = 0.99,
    near_m: float = 0.01,
    exclude: wp.array | None = None,
    out: wp.array | None = None,
    scratch: MergeScratch | None = None,
) -> tuple[wp.array, wp.array]:
    """Merge pairs of Gaussians with almost identical footprints and colours in the view ``T_WC``.

    Two Gaussians are duplicates when both project with centres inside the image (``camera``,
    ``T_WC`` 4x4 camera-to-world), in front of ``near_m``, and
      * their projected centres lie within ``max_footprint_px`` pixels,
      * their depths differ by a ratio below exp(``max_depth_rel``) (|ln z_i - ln z_j| <= it),
      * their rendered 2D covariances (EWA, with the renderer's 0.3 px^2 dilation) differ by at most
        ``max_size_rel`` of their mean (Frobenius norm): same size, shape and orientation,
      * their SH DC colours (SH_C0 * dc) differ by at most ``max_color_diff`` in every channel.
    Each Gaussian picks its best duplicate (lowest normalised sum of the four differences, ties by
    index) and only mutual picks merge, so no Gaussian merges twice per call (a cluster of three
    merges one pair; call again to merge further).  The lower index survives with the averages of
    the two means, SH coefficients (all bands) and covariances (Sigma = R S^2 R^T, averaged and
    eigen-decomposed back into rotation and log-scales); its opacity becomes the two splats'
    composited coverage 1 - (1 - a)(1 - b), capped at ``max_merged_opacity`` yet never below
    max(a, b).  The survivor keeps its optimiser moments and statistics rows.

    exclude: optional (N,) int32 mask (e.g. ``prune_mask``'s), nonzero rows take no part and stay
    flagged.  Returns ``(mask, n_merged)``: mask (N,) int32 = exclude OR merged-away rows, 1 = remove
    (``out`` if given); n_merged (1,) int32 on the device, the number of pairs merged.
    """
    n = len(gmap)
    device = gmap.device
    scratch = scratch or MergeScratch(device, max(n, 1))
    if out is None:
        out = wp.empty(n, dtype=wp.int32, device=device)
    out = out[:n]
    scratch.n_merged.zero_()
    if n == 0:
        return out, scratch.n_merged
    if exclude is None:
        out.zero_()
    else:
        wp.copy(out, exclude, count=n)
    scratch.ensure(n)
    points, cov2d, valid, best = scratch.points[:n], scratch.cov2d[:n], scratch.valid[:n], scratch.best[:n]
    T_CW = invert_pose(np.asarray(T_WC, dtype=np.float64))
    W = wp.mat33(*T_CW[:3, :3].astype(np.float32).ravel())
    t = wp.vec3(*T_CW[:3, 3].astype(np.float32))
    fields = _map_fields(gmap, n)
    # no frustum margin: only footprints centred inside the image are compared, so the Jacobian
    # clamp is the image itself
    wp.launch(
        merge_footprints,
        dim=n,
        inputs=fields + [out, W, t, camera_params(camera, near_m), float(max_footprint_px / max_depth_rel)],
        outputs=[points, cov2d, valid],
        device=device,
    )
    radius = float(max_footprint_px) * 1.4142136
    scratch.grid.build(points, radius)
    wp.launch(
        merge_best_partner,
        dim=n,
        inputs=[scratch.grid.id, points, cov2d, valid, gmap.sh[:n]]
        + [float(max_footprint_px), float(max_size_rel), float(max_color_diff)],
        outputs=[best],
        device=device,
    )
    wp.launch(
        merge_pairs,
        dim=n,
        inputs=[best, float(max_merged_opacity)],
        outputs=fields + [out, scratch.n_merged],
        device=device,
    )
    return out, scratch.n_merged


def least_visible_mask(gmap: GaussianMap, keep: int) -> np.ndarray:
    """Removal mask (bool, ``len(gmap)``) of all but the ``keep`` Gaussians that matter most to the
    renders: score = opacity x (v_i + 1) / (m_i + 1), the opacity weighted by the fraction of the
    views it was inside in which it contributed to a pixel (the mapper's ``vis_count`` v_i and
    ``obs_count`` m_i; 1 without them, and for Gaussians not seen yet: fresh seeds are kept for their
    first mapping to judge).  Ties keep the older rows.  Reads the columns back to the host."""
    n = len(gmap)
    score = 1.0 / (1.0 + np.exp(-gmap.opacity_logits.numpy()[:n].astype(np.float64)))
    if gmap.has_column("obs_count") and gmap.has_column("vis_count"):
        obs, vis = gmap.column("obs_count").numpy()[:n], gmap.column("vis_count").numpy()[:n]
        score *= (vis.astype(np.float64) + 1.0) / (obs.astype(np.float64) + 1.0)
    mask = np.ones(n, dtype=bool)
    mask[np.argsort(-score, kind="stable")[: max(keep, 0)]] = False
    return mask


class Maintainer:
    """The maintenance stage after each keyframe's mapping (§4.5): prune the Gaussians that violate
    the bounds of ``prune_mask`` (reading the mapper's statistics columns ``obs_count`` and
    ``vis_count`` of the map when it has them), then merge near-duplicates seen from the keyframe among
    the survivors, and remove both from the map (its every column compacts with it).  The masks
    combine on the device; one read of the two counts.

    Bounded memory (``mapping.max_gaussians`` > 0): when the map is still above ``cap_headroom`` x the
    cap after that, the least visible Gaussians go too (``least_visible_mask``), down to that level, so
    the next keyframe's seeds have room (the Seeder keeps a seeding under the cap itself)."""

    def __init__(self, cfg: MappingConfig, camera: Camera, device=None):
        self.cfg, self.camera = cfg, camera
        self.device = wp.get_device(device)
        self._scratch = MergeScratch(self.device)

    def maintain(self, gmap: GaussianMap, T_WC: np.ndarray) -> tuple[int, int]:
        """Prune and merge (seen from camera-to-world ``T_WC``), then ``cap``; returns (pruned with the
        capped, merged)."""
        cfg = self.cfg
        if len(gmap) == 0:
            return 0, 0
        statistics = gmap.has_column("obs_count") and gmap.has_column("vis_count")
        prune, prune_stats = prune_mask(
            gmap,
            gmap.column("obs_count") if statistics else None,
            gmap.column("vis_count") if statistics else None,
            opacity_min=cfg.opacity_cull,
            max_scale_m=cfg.max_scale_m,
            min_obs=cfg.min_obs,
            min_visibility_ratio=cfg.min_visibility_ratio,
        )
        remove, merged = prune, 0
        if cfg.merge_footprint_px > 0:  # 0: no merging
            remove, n_merged = merge_duplicates(
                gmap,
                self.camera,
                T_WC,
                max_footprint_px=cfg.merge_footprint_px,
                max_color_diff=cfg.merge_color_diff,
                exclude=prune,
                scratch=self._scratch,
            )
            merged = int(n_merged.numpy()[0])
        pruned = PruneStats.read(prune_stats).total
        if pruned + merged:
            gmap.remove(remove)
        return pruned + self.cap(gmap), merged

    def cap(self, gmap: GaussianMap) -> int:
        """Above ``cap_headroom`` x ``max_gaussians``: remove the least visible Gaussians down to it;
        returns how many (0 without a cap)."""
        target = int(self.cfg.cap_headroom * self.cfg.max_gaussians)
        if self.cfg.max_gaussians <= 0 or len(gmap) <= target:
            return 0
        removed = len(gmap) - target
        gmap.remove(least_visible_mask(gmap, target))
        return removed
