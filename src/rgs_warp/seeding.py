"""Seeding (supplement §4.5): the ``Seeder`` stage puts new Gaussians where a keyframe (or a tracked
frame) shows surface the map lacks; ``PointSeeder`` turns points (triangulated, or back-projected
measured depth) into Gaussians (Eq. 13-14), Poisson-disk subsampled in world space
(``rgs_warp.sampling``).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace

import numpy as np
import warp as wp

from rgs_warp.config import SeedingConfig
from rgs_warp.geometry import invert_pose
from rgs_warp.graph_cache import GraphCache, launch_key
from rgs_warp.kernels import seeding as ks
from rgs_warp.kernels.math import camera_params
from rgs_warp.kernels.seeding import MAX_VIEWS, SeedParams, seed_footprint, seed_gaussians
from rgs_warp.keyframes import KeyframeBuffer
from rgs_warp.matching import Matches
from rgs_warp.render import Renderer
from rgs_warp.sampling import compact_mask, poisson_disk_subsample
from rgs_warp.triangulation import TriangulatedPoints
from rgs_warp.types import Camera, GaussianMap, grown_capacity

CELL_PRIOR_POINTS = 1000  # weight of the nominal hash-grid cell size against measured radii


def _view_arrays(**kw) -> tuple[wp.array, wp.array, wp.array]:
    """The per-view inputs of the seeding kernels, ``MAX_VIEWS`` rows each: pose, slot, exposure."""
    return (
        wp.zeros(MAX_VIEWS, dtype=wp.mat44, **kw),
        wp.zeros(MAX_VIEWS, dtype=wp.int32, **kw),
        wp.zeros(MAX_VIEWS, dtype=wp.vec2, **kw),
    )


class PointSeeder:
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
        p.cam = camera_params(camera)
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
        self._graphs = GraphCache(self.device)  # the Poisson-disk rounds' loop of each set of buffers
        self._counters = wp.zeros(2, dtype=wp.int32, **kw)
        self._radius_max = wp.zeros(1, dtype=wp.float32, **kw)
        self._count = wp.zeros(1, dtype=wp.int32, **kw)
        self._plane_radius_stats = wp.zeros(2, dtype=wp.float32, **kw)
        self._count_host = wp.zeros(1, dtype=wp.int32, **host)
        self._plane_radius_stats_host = wp.zeros(2, dtype=wp.float32, **host)
        self._view_T_CW, self._view_slot, self._view_exposure = _view_arrays(**kw)
        self._view_T_CW_host, self._view_slot_host, self._view_exposure_host = _view_arrays(**host)
        # hash grid cell size: running, point-count-weighted mean of the plane-fit radius over the
        # calls so far (halved weight per call), starting from the radius at a nominal 2 m with the
        # weight of CELL_PRIOR_POINTS points: a call with a handful of (possibly outlying) points
        # must not set it, or the next call's queries visit thousands of cells or whole-map cells
        f = 0.5 * (camera.fx + camera.fy)
        self._radius_sum = CELL_PRIOR_POINTS * cfg.plane_radius_px * 2.0 / f
        self._radius_count = float(CELL_PRIOR_POINTS)
        self._capacity = 0
        self._ensure(1024)

    def state_dict(self) -> dict[str, np.ndarray]:
        """The running cell size (sum, count) of the hash grid; ``load_state_dict`` restores it."""
        return {"cell_radius": np.array([self._radius_sum, self._radius_count])}

    def load_state_dict(self, state: dict[str, np.ndarray]) -> None:
        self._radius_sum, self._radius_count = (float(v) for v in state["cell_radius"])

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
            graphs=self._graphs,
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


class Seeder:
    """The seeding stage (§4.5): new Gaussians where a keyframe shows surface the map lacks.

    ``seed_matches``: the keyframe's triangulated matches, minus those whose depth disagrees with the
    measured one (RGB-D, ``depth_consistency_tol``) and those the map already explains (it covers
    their pixel at a consistent depth).  ``seed_depth``: measured-depth seeds where the map still does
    not cover the keyframe (RGB-D with ``depth_fill``: plain walls have no matches; with
    ``depth_extrapolate_px`` also where nothing was measured, at the measured depth nearby), and the
    very first seeds of an empty map (monocular: a plane at ``scene_depth_m``).  ``fill_frame``: the same
    for a tracked frame that is not a keyframe, when it shows more than ``frame_fill_min_uncovered``
    of new surface; those seeds wait in ``pending`` (tracking does not change the map, §4.6, so the
    co-visibility test of the next frames sees the same map) until ``join_pending`` at the next
    keyframe, before its seeding; its mapping refines those it sees.

    ``match_spacing_px``: image pixels between thinned matches (the Poisson radius and tangential
    scale of triangulated seeds are in these units, those of depth seeds in ``depth_stride``).
    ``max_gaussians`` (``mapping.max_gaussians``, 0 = none): a seeding that would take the map (with
    the waiting seeds) over it keeps only its most confident seeds (``_within_cap``).
    ``graphs``: where the depth extrapolation's launches are kept as captured graphs (default: a
    ``GraphCache`` of 16 on ``device``, on with CUDA).
    """

    def __init__(
        self,
        cfg: SeedingConfig,
        camera: Camera,
        device=None,
        *,
        mode: str = "rgbd",
        match_spacing_px: float = 1.0,
        scene_depth_m: float = 2.0,
        sh_degree: int = 2,
        renderer: Renderer | None = None,
        max_gaussians: int = 0,
        graphs: GraphCache | None = None,
    ):
        self.cfg, self.camera, self.mode = cfg, camera, mode
        self.max_gaussians = max_gaussians
        self.device = dev = wp.get_device(device)
        self.renderer = renderer or Renderer(dev)
        radius = cfg.poisson_radius_px
        self._from_matches = PointSeeder(replace(cfg, poisson_radius_px=radius * match_spacing_px), camera, dev)
        self._from_depth = PointSeeder(replace(cfg, poisson_radius_px=radius * cfg.depth_stride), camera, dev)
        self.pending = GaussianMap(1024, sh_degree=sh_degree, device=dev)
        self._fill_frame: KeyframeBuffer | None = None  # the tracked frame of ``fill_frame``
        hg, wg = camera.height // cfg.depth_stride, camera.width // cfg.depth_stride
        n = hg * wg
        self._depth_grid = (hg, wg)
        self._depth_points = TriangulatedPoints.zeros(n, dev)
        # measured depth is certain (Eq. 14 at full confidence); a monocular plane is not
        self._depth_confidence = wp.full(n, 1.0 if mode == "rgbd" else 0.0, dtype=wp.float32, device=dev)
        # detail seeds (seeding.detail_stride): a finer grid of measured depth where the image has detail
        self._from_detail = None
        if mode == "rgbd" and 0 < cfg.detail_stride < cfg.depth_stride:
            self._from_detail = PointSeeder(replace(cfg, poisson_radius_px=radius * cfg.detail_stride), camera, dev)
            self._detail_grid = (camera.height // cfg.detail_stride, camera.width // cfg.detail_stride)
            n_detail = self._detail_grid[0] * self._detail_grid[1]
            self._detail_points = TriangulatedPoints.zeros(n_detail, dev)
            self._detail_confidence = wp.full(n_detail, 1.0, dtype=wp.float32, device=dev)
        shape = (camera.height, camera.width)
        # monocular: the first keyframe's plane at scene_depth_m
        self._plane_depth = wp.full(shape, scene_depth_m, dtype=wp.float32, device=dev) if mode != "rgbd" else None
        self._zero_alpha = wp.zeros(shape, dtype=wp.float32, device=dev)
        # RGB-D: measured depth carried into the pixels without it (depth_extrapolate_px), two buffers
        self._extrapolated = None
        if mode == "rgbd" and cfg.depth_extrapolate_px > 0:
            self._extrapolated = tuple(wp.zeros(shape, dtype=wp.float32, device=dev) for _ in range(2))
        # the extrapolation of each source image (keyframe slots, fills)
        self._graphs = GraphCache(dev, size=16) if graphs is None else graphs
        self._alpha = wp.zeros(shape, dtype=wp.float32, device=dev)

    def _point_seeders(self) -> list[tuple[str, PointSeeder]]:
        seeders = [("matches.", self._from_matches), ("depth.", self._from_depth)]
        return seeders + ([("detail.", self._from_detail)] if self._from_detail is not None else [])

    def state_dict(self) -> dict[str, np.ndarray]:
        """The seeds waiting in ``pending`` and the point seeders' cell sizes; ``load_state_dict``
        restores them."""
        state = {f"pending.{name}": value for name, value in self.pending.to_numpy().items()}
        for prefix, seeder in self._point_seeders():
            state.update({prefix + k: v for k, v in seeder.state_dict().items()})
        return state

    def load_state_dict(self, state: dict[str, np.ndarray]) -> None:
        self.pending.count = 0
        if len(state["pending.means"]):
            self.pending.append(*(state[f"pending.{name}"] for name in GaussianMap.PARAMETERS))
        for prefix, seeder in self._point_seeders():
            seeder.load_state_dict({k[len(prefix) :]: v for k, v in state.items() if k.startswith(prefix)})

    def seed_points(
        self,
        gmap: GaussianMap,
        keyframes: KeyframeBuffer,
        view_slots: Sequence[int],
        points: TriangulatedPoints,
        confidence: wp.array,
    ) -> int:
        """Gaussians from triangulated ``points`` (reference view first in ``view_slots``) with their
        aggregated ``confidence``, as they are; returns how many."""
        row0 = len(gmap)
        added = self._from_matches.seed(points, confidence, keyframes, view_slots, gmap)
        return self._within_cap(gmap, row0, added, self.max_gaussians)

    def seed_matches(
        self,
        gmap: GaussianMap,
        keyframes: KeyframeBuffer,
        slot: int,
        matches: Matches,
        points: TriangulatedPoints,
    ) -> int:
        """Gaussians from keyframe ``slot``'s triangulated ``matches`` where the map does not explain
        the keyframe yet (see the class); returns how many."""
        cfg, dev = self.cfg, self.device
        T_CW = wp.mat44d(invert_pose(keyframes.poses[slot]))
        n = points.X.shape[0]
        if self.mode == "rgbd" and cfg.depth_consistency_tol > 0.0:
            wp.launch(
                ks.reject_depth_inconsistent_points,
                dim=n,
                inputs=[matches.ref_uv, keyframes.depth[slot], points.X, T_CW, cfg.depth_consistency_tol],
                outputs=[points.valid],
                device=dev,
            )
        if len(gmap):
            res = self.renderer.forward(gmap, self.camera, keyframes.poses[slot])
            wp.launch(
                ks.mask_covered_points,
                dim=n,
                inputs=[matches.ref_uv, res.alpha, res.depth, points.X, T_CW, cfg.covered_alpha]
                + [cfg.covered_depth_tol],
                outputs=[points.valid],
                device=dev,
            )
        return self.seed_points(gmap, keyframes, [slot, *matches.neighbours], points, matches.aggregated)

    def seed_depth(self, gmap: GaussianMap, keyframes: KeyframeBuffer, slot: int) -> int:
        """Measured-depth seeds where the map does not cover keyframe ``slot`` (RGB-D with
        ``depth_fill``, and the first seeds of an empty map; monocular: the first keyframe's plane at
        ``scene_depth_m``); returns how many."""
        if len(gmap) == 0:
            alpha = self._zero_alpha
            if self.mode != "rgbd":
                return self._seed_depth(keyframes, slot, alpha, self._plane_depth, gmap, self.max_gaussians)
        elif self.mode == "rgbd" and self.cfg.depth_fill:
            alpha = self.renderer.forward(gmap, self.camera, keyframes.poses[slot]).alpha
        else:
            return 0
        return self._seed_depth(keyframes, slot, alpha, None, gmap, self.max_gaussians)

    def wants_fill(self, coverage: float) -> bool:
        """Whether a tracked frame that is not a keyframe, of which the map covers the fraction
        ``coverage``, gets ``fill_frame`` seeds: RGB-D, and more than ``frame_fill_min_uncovered``
        of it uncovered."""
        fill = self.cfg.frame_fill_min_uncovered
        return self.mode == "rgbd" and fill >= 0.0 and 1.0 - coverage > fill

    def fill_frame(
        self, gmap: GaussianMap, frame_id: int, rgb, depth, T_WC: np.ndarray, exposure, alpha: wp.array | None = None
    ) -> int:
        """Measured-depth seeds into ``pending`` from a tracked frame (``rgb``, ``depth`` on the device)
        that is not a keyframe and that ``wants_fill``, where neither the map nor the pending seeds
        cover it; returns how many.  ``alpha``: ``gmap``'s accumulated opacity at ``T_WC`` at this
        stage's camera size, if the caller has it (tracking's last render: not rendered again); it is
        not written to."""
        dev = self.device
        if self._fill_frame is None:
            self._fill_frame = KeyframeBuffer(1, self.camera.width, self.camera.height, dev)
        self._fill_frame.add(frame_id, T_WC, rgb, depth, exposure)
        if alpha is None:
            alpha = self.renderer.forward(gmap, self.camera, T_WC).alpha
        elif alpha.shape != (self.camera.height, self.camera.width):
            raise ValueError(f"alpha is {alpha.shape}, the Seeder's camera is {self.camera}")
        if len(self.pending):
            wp.copy(self._alpha, alpha)  # the renderer's buffers are reused by the next render
            alpha = self._alpha
            pending = self.renderer.forward(self.pending, self.camera, T_WC).alpha
            wp.launch(ks.union_alpha, dim=alpha.shape, inputs=[alpha, pending], outputs=[alpha], device=dev)
        limit = self.max_gaussians - len(gmap) if self.max_gaussians > 0 else 0
        if self.max_gaussians > 0 and limit <= len(self.pending):
            return 0  # the map and the waiting seeds are at the cap already
        return self._seed_depth(self._fill_frame, 0, alpha, None, self.pending, limit)

    def join_pending(self, gmap: GaussianMap) -> None:
        """The seeds of ``fill_frame`` since the last keyframe join the map (those that fit under
        ``max_gaussians``: the map may have changed since)."""
        if self.max_gaussians > 0 and len(self.pending):
            self._within_cap(self.pending, 0, len(self.pending), max(self.max_gaussians - len(gmap), 0))
        p, n = self.pending, len(self.pending)
        if n:
            gmap.append(p.means[:n], p.rotations[:n], p.log_scales[:n], p.opacity_logits[:n], p.sh[:n])
            p.count = 0

    def _within_cap(self, target: GaussianMap, row0: int, added: int, limit: int) -> int:
        """Keep at most ``limit`` rows in ``target`` (0 = no limit) by dropping some of the ``added``
        rows just seeded from ``row0``: the least confident (lowest opacity, Eq. 14), ties spread
        evenly over the seeds' order (a golden-ratio sequence: dropped seeds do not gather in one part
        of the image).  Returns how many of the added rows stay.  Reads the new opacities back to the
        host, only when the cap is reached."""
        if limit <= 0 or len(target) <= limit:
            return added
        keep = max(limit - row0, 0)
        logits = target.opacity_logits.numpy()[row0 : row0 + added]
        spread = (np.arange(added) * 0.6180339887498949) % 1.0
        order = np.lexsort((spread, -logits))  # most confident first, then the low-discrepancy order
        mask = np.zeros(len(target), dtype=bool)
        mask[row0 + order[keep:]] = True
        target.remove(mask)
        return keep

    def depth_to_seed(self, frames: KeyframeBuffer, slot: int) -> wp.array:
        """The depth image the depth seeds of ``frames`` slot ``slot`` come from: its measured depth,
        carried ``depth_extrapolate_px`` pixels into those without a measurement when that is on (RGB-D)."""
        if self._extrapolated is None:
            return frames.depth[slot]
        src = frames.depth[slot]
        steps = self.cfg.depth_extrapolate_px

        def extrapolate():  # one launch per pixel of reach: replayed as one graph per source image
            image = src
            for k in range(steps):
                dst = self._extrapolated[k % 2]
                wp.launch(ks.extrapolate_depth_step, dim=dst.shape, inputs=[image], outputs=[dst], device=self.device)
                image = dst

        self._graphs.run(("extrapolate",) + launch_key([src, *self._extrapolated, steps]), extrapolate)
        return self._extrapolated[(steps - 1) % 2]

    def _seed_depth(
        self,
        frames: KeyframeBuffer,
        slot: int,
        alpha: wp.array,
        depth: wp.array | None,
        target: GaussianMap,
        limit: int = 0,
    ) -> int:
        """Seeds from the measured depth of ``frames`` slot ``slot`` (carried ``depth_extrapolate_px``
        into the pixels without a measurement; ``depth`` in its place, e.g. the monocular plane) where
        ``alpha`` is below ``covered_alpha``, appended to ``target`` (at most ``limit`` rows in all,
        ``_within_cap``); with ``detail_stride``, measured depth also seeds the finer grid where the
        image has detail (``kernels/seeding.py: keep_detail_points``)."""
        cfg, cam = self.cfg, self.camera
        p = self._depth_points
        wp.launch(
            ks.depth_points,
            dim=self._depth_grid,
            inputs=[self.depth_to_seed(frames, slot) if depth is None else depth]
            + [cam.fx, cam.fy, cam.cx, cam.cy, wp.mat44d(frames.poses[slot]), cfg.depth_stride]
            + [cfg.depth_max_rel_jump, cfg.min_residual_px, 90.0, alpha, cfg.covered_alpha],
            outputs=[p.X, p.residual_px, p.parallax_deg, p.support, p.valid],
            device=self.device,
        )
        row0 = len(target)
        added = self._from_depth.seed(p, self._depth_confidence, frames, [slot], target)
        if self._from_detail is not None and depth is None:  # measured depth: finer where the image has detail
            p = self._detail_points
            wp.launch(
                ks.depth_points,
                dim=self._detail_grid,
                inputs=[frames.depth[slot], cam.fx, cam.fy, cam.cx, cam.cy, wp.mat44d(frames.poses[slot])]
                + [cfg.detail_stride, cfg.depth_max_rel_jump, cfg.min_residual_px, 90.0, alpha, cfg.covered_alpha],
                outputs=[p.X, p.residual_px, p.parallax_deg, p.support, p.valid],
                device=self.device,
            )
            wp.launch(
                ks.keep_detail_points,
                dim=self._detail_grid,
                inputs=[frames.rgb[slot], cfg.detail_stride, cfg.depth_stride, cfg.detail_min_gradient],
                outputs=[p.valid],
                device=self.device,
            )
            added += self._from_detail.seed(p, self._detail_confidence, frames, [slot], target)
        return self._within_cap(target, row0, added, limit)
