"""Seeding (supplement §4.4-4.5): blue-noise thinning of matches in image space, Poisson-disk
subsampling of triangulated seeds in world space, and the ``Seeder`` stage that turns the
Triangulator's points into Gaussians (Eq. 13-14).

Thinning and Poisson-disk subsampling are rounds of prioritised dart throwing
(``kernels/poisson.py`` explains the scheme and its guarantees) looping on a device counter of
undecided points: on CUDA the loop is a CUDA graph conditional while-node (``loop_until_zero``), so
the rounds run without a host round trip.
"""

from __future__ import annotations

from collections.abc import Sequence

import warp as wp

from rgs_warp.config import SeedingConfig
from rgs_warp.geometry import invert_pose
from rgs_warp.kernels.poisson import poisson_accept, poisson_init, poisson_reject, scatter_kept
from rgs_warp.kernels.seeding import MAX_VIEWS, SeedParams, seed_footprint, seed_gaussians
from rgs_warp.kernels.thinning import thinning_accept, thinning_init, thinning_reject
from rgs_warp.keyframes import KeyframeBuffer
from rgs_warp.triangulation import TriangulatedPoints
from rgs_warp.types import Camera, GaussianMap, grown_capacity

# Confidence levels of the dart priority: finer levels follow the confidence more closely but allow
# longer chains of rounds (a chain climbs at most one level per round); 32 levels resolve Eq. 12's
# confidence to 0.03, below the spread of its inputs.
CONFIDENCE_LEVELS = 32


def loop_until_zero(condition: wp.array, body) -> None:
    """Run ``body()`` while ``condition[0] != 0`` (the body updates it) without a host round trip
    on CUDA: the loop is captured as a CUDA graph with a conditional while-node and launched once.
    ``wp.capture_while`` alone reads the condition back to the host before every round when no
    capture is active.  Inside an enclosing capture, or where the driver lacks conditional nodes
    (CUDA < 12.4), the loop is recorded / run as ``wp.capture_while`` does; on the CPU the condition
    is read from host memory at no cost."""
    device = condition.device
    if device.is_cuda and not device.is_capturing and wp.is_conditional_graph_supported():
        with wp.ScopedCapture(device=device) as capture:
            wp.capture_while(condition, body)
        wp.capture_launch(capture.graph)
    else:
        wp.capture_while(condition, body)


def poisson_disk_subsample(
    points: wp.array,
    radius: wp.array,
    confidence: wp.array,
    candidate: wp.array | None = None,
    cell_size: float | None = None,
    grid: wp.HashGrid | None = None,
    keep_out: wp.array | None = None,
    counters: wp.array | None = None,
    radius_max: wp.array | None = None,
    levels: int = CONFIDENCE_LEVELS,
) -> wp.array:
    """Poisson-disk subset of world points, higher confidence winning conflicts.

    points: (N,) ``wp.vec3``; radius: (N,) float32 per-point disk radius (e.g. the pixel footprint
    ``k * depth / focal``); confidence: (N,) float32 in [0, 1]; candidate: optional (N,) int32,
    0 excludes a point.  Two points conflict when closer than the larger of their radii.
    Returns keep (N,) int32, 1 for kept points: no kept pair conflicts, every candidate lies within
    max(its radius, the kept point's radius) of a kept point.

    ``cell_size`` sets the hash grid's cells (performance only; default: the largest radius, read
    back once).  ``grid`` (a ``wp.HashGrid``), ``keep_out``, ``counters`` ((2,) int32) and
    ``radius_max`` ((1,) float32) let a stage reuse its buffers; ``counters[1]`` holds the number
    of rounds afterwards.
    """
    device = points.device
    n = points.shape[0]
    if keep_out is None:
        keep_out = wp.empty(n, dtype=wp.int32, device=device)
    if n == 0:
        return keep_out
    if counters is None:
        counters = wp.zeros(2, dtype=wp.int32, device=device)
    if radius_max is None:
        radius_max = wp.zeros(1, dtype=wp.float32, device=device)
    if candidate is None:
        candidate = wp.ones(n, dtype=wp.int32, device=device)
    if grid is None:
        grid = wp.HashGrid(128, 128, 128, device=device)
    radius_max.zero_()
    wp.launch(poisson_init, dim=n, inputs=[radius, candidate], outputs=[keep_out, radius_max], device=device)
    if cell_size is None:
        cell_size = float(radius_max.numpy()[0]) or 1.0
    grid.build(points, cell_size)
    counters.fill_(1)

    def one_round():
        counters[:1].zero_()
        wp.launch(
            poisson_accept,
            dim=n,
            inputs=[grid.id, points, radius, confidence, levels, radius_max],
            outputs=[keep_out],
            device=device,
        )
        wp.launch(
            poisson_reject,
            dim=n,
            inputs=[grid.id, points, radius, radius_max],
            outputs=[keep_out, counters],
            device=device,
        )

    counters[1:2].zero_()
    # the loop condition is counters[0]: capture_while needs a one-element array (CUDA checks its size)
    loop_until_zero(counters[:1], one_round)
    return keep_out


def thin_blue_noise(
    confidence: wp.array,
    spacing_px: float,
    keep_out: wp.array | None = None,
    counters: wp.array | None = None,
    levels: int = CONFIDENCE_LEVELS,
) -> wp.array:
    """Blue-noise subset of the pixels of a confidence image, the most confident preferred.

    confidence: (H, W) float32 (Eq. 12; 0 = no match); spacing_px: minimum distance in pixels
    between kept pixels.  Returns keep (H, W) int32, 1 for kept pixels: no kept pair closer than
    ``spacing_px``, every pixel of positive confidence within ``spacing_px`` of a kept one.
    ``counters``: optional (2,) int32 scratch; ``counters[1]`` holds the number of rounds afterwards.
    """
    device = confidence.device
    if keep_out is None:
        keep_out = wp.empty(confidence.shape, dtype=wp.int32, device=device)
    if counters is None:
        counters = wp.zeros(2, dtype=wp.int32, device=device)
    wp.launch(thinning_init, dim=confidence.shape, inputs=[confidence], outputs=[keep_out], device=device)
    counters.fill_(1)

    def one_round():
        counters[:1].zero_()
        wp.launch(
            thinning_accept,
            dim=confidence.shape,
            inputs=[confidence, float(spacing_px), levels],
            outputs=[keep_out],
            device=device,
        )
        wp.launch(
            thinning_reject,
            dim=confidence.shape,
            inputs=[float(spacing_px)],
            outputs=[keep_out, counters],
            device=device,
        )

    counters[1:2].zero_()
    # the loop condition is counters[0]: capture_while needs a one-element array (CUDA checks its size)
    loop_until_zero(counters[:1], one_round)
    return keep_out


def compact_mask(
    keep: wp.array, indices_out: wp.array | None = None, count_out: wp.array | None = None, offsets=None
) -> tuple[wp.array, wp.array]:
    """Indices (int32, ascending, flat for 2-d masks) of the 1s of a 0/1 int32 mask and their count
    (a 1-element device array), without a host round trip; ``indices_out`` holds at least as many
    entries as the mask, ``offsets`` is optional scratch of the mask's size."""
    flat = keep.flatten()
    n = flat.shape[0]
    device = keep.device
    if indices_out is None:
        indices_out = wp.empty(n, dtype=wp.int32, device=device)
    if count_out is None:
        count_out = wp.zeros(1, dtype=wp.int32, device=device)
    if offsets is None:
        offsets = wp.empty(n, dtype=wp.int32, device=device)
    wp.utils.array_scan(flat, offsets, inclusive=False)
    wp.launch(scatter_kept, dim=n, inputs=[flat, offsets], outputs=[indices_out, count_out], device=device)
    return indices_out, count_out


CELL_PRIOR_POINTS = 1000  # weight of the nominal hash-grid cell size against measured radii


class Seeder:
    """Initialises one Gaussian per Poisson-disk-subsampled triangulated point (supplement §4.5).

    Per point: mean = the triangulated point; rotation = the frame U = [t1, t2, v] of a plane
    fitted to the valid triangulated neighbours within ``plane_radius_px`` pixel footprints (v the
    normal, facing the reference camera; the viewing direction when fewer than
    ``plane_min_neighbours``); scales (Eq. 13) s_perp = ``tangential_scale`` x the Poisson radius
    (``poisson_radius_px`` one-pixel footprints z / f at the reference view) and s_parallel = the
    depth uncertainty along the normal from the baseline angle and residual
    (``kernels/seeding.py: axial_scale``); colour = per-channel median over the supporting views of
    exposure-corrected bilinear samples, as SH DC with higher bands zero; opacity = Eq. 14 of the
    aggregated confidence, as a logit.

    Host synchronisation: one read of the number of Gaussians added, at the end, because
    ``GaussianMap.count`` is a host integer that every later launch is sized by.  Everything before
    it (footprints, subsampling, compaction, initialisation, the writes into the map) runs on the
    device without a read-back: the map is reserved for the worst case (every point kept) and the
    initialisation kernel reads the kept count from the device.  The hash grid's cell size (a
    performance parameter only) is the mean plane-fit radius of the previous calls, read with the
    count, as a running mean weighted by point counts (see ``__init__``).
    """

    def __init__(self, cfg: SeedingConfig, camera: Camera, device=None):
        if not 0.0 < cfg.alpha_min <= cfg.alpha_max < 1.0:
            raise ValueError(f"need 0 < alpha_min <= alpha_max < 1, got {cfg.alpha_min}, {cfg.alpha_max}")
        self.cfg = cfg
        self.camera = camera
        self.device = wp.get_device(device)
        p = SeedParams()
        p.fx, p.fy, p.cx, p.cy = camera.fx, camera.fy, camera.cx, camera.cy
        p.width, p.height = camera.width, camera.height
        p.poisson_radius_px, p.plane_radius_px = cfg.poisson_radius_px, cfg.plane_radius_px
        p.plane_min_neighbours, p.tangential_scale = cfg.plane_min_neighbours, cfg.tangential_scale
        p.min_residual_px, p.axial_min_ratio, p.axial_max_ratio = (
            cfg.min_residual_px,
            cfg.axial_min_ratio,
            cfg.axial_max_ratio,
        )
        p.alpha_min, p.alpha_max = cfg.alpha_min, cfg.alpha_max
        self._params = p
        kw = {"device": self.device}
        host = {"device": "cpu", "pinned": self.device.is_cuda}
        self._grid = wp.HashGrid(128, 128, 128, device=self.device)
        self._counters = wp.zeros(2, dtype=wp.int32, **kw)
        self._radius_max = wp.zeros(1, dtype=wp.float32, **kw)
        self._count = wp.zeros(1, dtype=wp.int32, **kw)
        self._plane_radius_stats = wp.zeros(2, dtype=wp.float32, **kw)
        self._count_host = wp.zeros(1, dtype=wp.int32, **host)
        self._plane_radius_stats_host = wp.zeros(2, dtype=wp.float32, **host)
        self._view_T_CW = wp.zeros(MAX_VIEWS, dtype=wp.mat44, **kw)
        self._view_slot = wp.zeros(MAX_VIEWS, dtype=wp.int32, **kw)
        self._view_exposure = wp.zeros(MAX_VIEWS, dtype=wp.vec2, **kw)
        self._view_T_CW_host = wp.zeros(MAX_VIEWS, dtype=wp.mat44, **host)
        self._view_slot_host = wp.zeros(MAX_VIEWS, dtype=wp.int32, **host)
        self._view_exposure_host = wp.zeros(MAX_VIEWS, dtype=wp.vec2, **host)
        # hash grid cell size: running, point-count-weighted mean of the plane-fit radius over the
        # calls so far (halved weight per call), starting from the radius at a nominal 2 m with the
        # weight of CELL_PRIOR_POINTS points: a call with a handful of (possibly outlying) points
        # must not set it, or the next call's queries visit thousands of cells or whole-map cells
        f = 0.5 * (camera.fx + camera.fy)
        self._radius_sum = CELL_PRIOR_POINTS * cfg.plane_radius_px * 2.0 / f
        self._radius_count = float(CELL_PRIOR_POINTS)
        self._capacity = 0
        self._ensure(1024)

    def _ensure(self, n: int) -> None:
        if n <= self._capacity:
            return
        cap = grown_capacity(self._capacity, n, minimum=1024)
        kw = {"device": self.device}
        self._points = wp.zeros(cap, dtype=wp.vec3, **kw)
        self._footprint = wp.zeros(cap, dtype=wp.float32, **kw)
        self._radius = wp.zeros(cap, dtype=wp.float32, **kw)
        self._keep = wp.zeros(cap, dtype=wp.int32, **kw)
        self._indices = wp.zeros(cap, dtype=wp.int32, **kw)
        self._offsets = wp.zeros(cap, dtype=wp.int32, **kw)
        self.seed_index = wp.zeros(cap, dtype=wp.int32, **kw)
        self._capacity = cap

    def _upload_views(self, keyframes: KeyframeBuffer, view_slots: Sequence[int]) -> int:
        views = len(view_slots)
        if not 1 <= views < MAX_VIEWS:
            raise ValueError(f"need the reference and at most {MAX_VIEWS - 2} neighbours, got {views} views")
        self._view_T_CW_host.numpy()[:views] = [invert_pose(keyframes.poses[s]) for s in view_slots]
        self._view_slot_host.numpy()[:views] = view_slots
        self._view_exposure_host.numpy()[:views] = keyframes.exposure[list(view_slots)]
        for dst, src in (
            (self._view_T_CW, self._view_T_CW_host),
            (self._view_slot, self._view_slot_host),
            (self._view_exposure, self._view_exposure_host),
        ):
            wp.copy(dst, src, count=views)
        return views

    def seed(
        self,
        points: TriangulatedPoints,
        confidence: wp.array,
        keyframes: KeyframeBuffer,
        view_slots: Sequence[int],
        gmap: GaussianMap,
    ) -> int:
        """Append Gaussians seeded from the Triangulator's N points to ``gmap``; returns how many:
        ``enqueue`` then ``collect`` (arguments as ``enqueue``)."""
        return self.collect(gmap, self.enqueue(points, confidence, keyframes, view_slots, gmap))

    def enqueue(
        self,
        points: TriangulatedPoints,
        confidence: wp.array,
        keyframes: KeyframeBuffer,
        view_slots: Sequence[int],
        gmap: GaussianMap,
    ) -> int:
        """Launch the seeding of the Triangulator's N points into ``gmap`` rows ``len(gmap)..``
        without any host synchronisation (it can be captured in a CUDA graph once the map has
        capacity); returns that first row.  ``collect(gmap, row)`` then reads how many were added.

        points: the Triangulator's output for a reference keyframe; confidence: (N,) float32
        aggregated confidence (Eq. 12, the matcher's per-pixel aggregate); view_slots: the keyframe
        slots of the Triangulator's views in its order (the reference first, then neighbour n at
        position n + 1, as the support bits count them): their colours, poses (camera-to-world) and
        exposures (g, b) are read from ``keyframes``, whose images have this stage's camera size.
        ``self.seed_index[:added]`` holds the point index of each Gaussian added (map rows
        ``len(gmap) - added ..``).
        """
        n = points.X.shape[0]
        if keyframes.rgb.shape[1:] != (self.camera.height, self.camera.width):
            raise ValueError(f"keyframes are {keyframes.rgb.shape[1:]}, the Seeder's camera is {self.camera}")
        if confidence.shape[0] != n:
            raise ValueError(f"confidence has {confidence.shape[0]} entries for {n} points")
        if n == 0:
            return -1
        dev = self.device
        views = self._upload_views(keyframes, view_slots)
        view_T_CW = self._view_T_CW[:views]
        self._ensure(n)
        pts, footprint, radius, keep = self._points[:n], self._footprint[:n], self._radius[:n], self._keep[:n]
        self._plane_radius_stats.zero_()
        wp.launch(
            seed_footprint,
            dim=n,
            inputs=[points.X, points.valid, view_T_CW, self._params],
            outputs=[pts, footprint, radius, self._plane_radius_stats],
            device=dev,
        )
        poisson_disk_subsample(
            pts,
            radius,
            confidence,
            candidate=points.valid,
            cell_size=self._radius_sum / self._radius_count,
            grid=self._grid,
            keep_out=keep,
            counters=self._counters,
            radius_max=self._radius_max,
        )
        compact_mask(keep, self._indices, self._count, self._offsets[:n])
        row0 = len(gmap)
        gmap.reserve(row0 + n)
        wp.launch(
            seed_gaussians,
            dim=n,
            inputs=[self._grid.id, self._indices, self._count, pts, footprint, points.residual_px]
            + [points.parallax_deg, points.support, confidence, keyframes.rgb, view_T_CW]
            + [self._view_slot[:views], self._view_exposure[:views], self._params, row0],
            outputs=[gmap.means, gmap.rotations, gmap.log_scales, gmap.opacity_logits, gmap.sh, self.seed_index],
            device=dev,
        )
        return row0

    def collect(self, gmap: GaussianMap, row0: int) -> int:
        """The one host synchronisation of a seeding: reads the number of Gaussians the last
        ``enqueue`` added at ``row0`` (-1: it had no points), sets ``gmap.count`` and returns it."""
        if row0 < 0:
            return 0
        wp.copy(self._count_host, self._count)
        self._update_cell_size()
        added = int(self._count_host.numpy()[0])
        gmap.count = row0 + added
        return added

    def _update_cell_size(self) -> None:
        """Fold this call's plane-fit radii (sum, count) into the running cell size; the one
        synchronisation also completes any copy to the host queued before it."""
        wp.copy(self._plane_radius_stats_host, self._plane_radius_stats)
        wp.synchronize_device(self.device)
        total, count = (float(v) for v in self._plane_radius_stats_host.numpy())
        self._radius_sum = 0.5 * self._radius_sum + total
        self._radius_count = 0.5 * self._radius_count + count
