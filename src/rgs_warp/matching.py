"""Dense matching (supplement §4.4): the DenseMatcher stage.

For a reference keyframe r and each neighbour n of N_r (chosen by pose proximity and parallax), every
pixel p of the feature grid is matched by a descriptor search along its epipolar segment in n (a
narrow band around the depth reprojection when r has depth there, the segment between
``min_depth_m`` and ``max_depth_m`` otherwise), refined to sub-pixel, then searched back from n into
r.  Eq. 11 scores the match from its similarity (Eq. 10), its forward-backward consistency and its
distance to the epipolar line; Eq. 12 maps the score to a confidence.  The confidences are averaged
over the neighbours (the aggregated confidence), the grid is thinned with blue noise in image space
(``sampling.thin_blue_noise``) and the dropped pixels get confidence 0.

Everything inside ``match`` is kernel launches on buffers sized by the feature grid (no host read
back), so ``DenseMatcher -> Triangulator -> Seeder`` can run as one pass or one CUDA graph.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import warp as wp

from rgs_warp.config import MatchingConfig
from rgs_warp.features import feature_centres, make_backbone
from rgs_warp.geometry import invert_pose, rotation_angle_deg
from rgs_warp.kernels.dlt import mat34d
from rgs_warp.kernels.matching import (
    EpipolarSearch,
    aggregate_confidence,
    apply_thinning,
    epipolar_search,
    epipolar_search_parts,
    grey_image,
    sample_descriptors,
    score_matches,
)
from rgs_warp.keyframes import KeyframeBuffer
from rgs_warp.sampling import thin_blue_noise
from rgs_warp.triangulation import projection_matrices
from rgs_warp.types import Camera

# Threads a query of the epipolar descriptor scan (``epipolar_search_parts``): a segment without depth
# has up to ``max_steps`` samples against a few with depth, and one thread a query left the GPU waiting
# on those (7-Scenes, H100: experiments/results/perf.md)
EPIPOLAR_PARTS = 16


@dataclass
class Matches:
    """Views of the DenseMatcher's buffers for the last call (valid until the next call), for the
    N = Hf * Wf pixels of the reference's feature grid (row-major) and its M neighbours.

    ref_uv: (N,) vec2d reference pixels (image coordinates of the feature-pixel centres);
    match_uv: (N, M) vec2d matches in each neighbour; confidence: (N, M) float32, Eq. 12, 0 = no
    match or thinned away; aggregated: (N,) float32 mean confidence over the neighbours (0 where
    thinned); kept_count: (1,) int32 number of pixels the thinning kept; P: (1 + M,) mat34d
    projection matrices (reference first) for ``Triangulator.triangulate(P, ref_uv, match_uv,
    confidence)``; neighbours: their buffer slots; grid: (Hf, Wf); stride: image px per feature px.
    """

    ref_uv: wp.array
    match_uv: wp.array
    confidence: wp.array
    aggregated: wp.array
    kept_count: wp.array
    P: wp.array
    neighbours: list[int]
    grid: tuple[int, int]
    stride: int


class DenseMatcher:
    """Matches a reference keyframe against its neighbours in a ``KeyframeBuffer``.

    Descriptors of each keyframe are computed once (``describe``) into device slots parallel to
    the buffer's and recorded in ``buffer.descriptors`` (the buffer clears the entry when it
    reuses a slot).
    """

    def __init__(self, cfg: MatchingConfig, camera: Camera, device=None, backbone=None):
        self.cfg = cfg
        self.camera = camera
        self.device = wp.get_device(device)
        self.backbone = backbone if backbone is not None else make_backbone(cfg, self.device)
        self.stride = self.backbone.stride
        hf, wf = self.backbone.grid_shape(camera.height, camera.width)
        self.grid = (hf, wf)
        n = hf * wf
        m = cfg.n_neighbours
        kw = {"device": self.device}
        centres = feature_centres(self.grid, self.stride)
        self._ref_uv = wp.array(centres.astype(np.float32), dtype=wp.vec2, **kw)
        self._ref_uv_d = wp.array(centres, dtype=wp.vec2d, **kw)
        self._always = wp.full(n, 1.0, dtype=wp.float32, **kw)  # forward queries are never skipped
        self._fwd_uv = wp.zeros(n, dtype=wp.vec2, **kw)
        self._fwd_sim = wp.zeros(n, dtype=wp.float32, **kw)
        self._fwd_epi = wp.zeros(n, dtype=wp.float32, **kw)
        self._bwd_uv = wp.zeros(n, dtype=wp.vec2, **kw)
        self._bwd_sim = wp.zeros(n, dtype=wp.float32, **kw)
        self._bwd_epi = wp.zeros(n, dtype=wp.float32, **kw)
        self._match_uv = wp.zeros((n, m), dtype=wp.vec2d, **kw)
        self._confidence = wp.zeros((n, m), dtype=wp.float32, **kw)
        self._aggregated = wp.zeros((hf, wf), dtype=wp.float32, **kw)
        self._keep = wp.zeros((hf, wf), dtype=wp.int32, **kw)
        self._thin_counters = wp.zeros(2, dtype=wp.int32, **kw)
        self._kept_count = wp.zeros(1, dtype=wp.int32, **kw)
        self._P = wp.zeros(m + 1, dtype=mat34d, **kw)
        self._zero_depth = wp.zeros((camera.height, camera.width), dtype=wp.float32, **kw)  # monocular search
        self._part_sim = wp.zeros((n, EPIPOLAR_PARTS), dtype=wp.float32, **kw)
        self._part_cell = wp.zeros((n, EPIPOLAR_PARTS), dtype=wp.vec3i, **kw)
        self._parts = [self._part_sim, self._part_cell]
        self._ref_grey = wp.zeros((camera.height, camera.width), dtype=wp.float32, **kw)  # the ZNCC refinement's
        self._nb_grey = wp.zeros((camera.height, camera.width), dtype=wp.float32, **kw)
        self._desc: wp.array | None = None
        self._query = None  # (N, D) backward-search queries, allocated with the descriptors

    # ------------------------------------------------------------------ neighbours
    def select_neighbours(self, ref_slot: int, buffer: KeyframeBuffer, scene_depth_m: float | None = None) -> list[int]:
        """Up to ``n_neighbours`` slots for ``ref_slot``, by pose proximity and parallax.

        Candidates look the same way as the reference (optical axes within ``max_view_angle_deg``,
        a proxy for overlap); each one's parallax is the angle its baseline subtends at
        ``scene_depth_m`` in front of the reference.  Those closest to ``target_parallax_deg`` (in
        log ratio: 2.5 and 10 deg are equally far from 5) come first; candidates with almost no
        baseline (below 1/10 of the target) only fill remaining places, since they cannot
        triangulate but still confirm matches.
        """
        depth = self.cfg.scene_depth_m if scene_depth_m is None else scene_depth_m
        T_r = buffer.poses[ref_slot]
        target = np.radians(self.cfg.target_parallax_deg)
        ranked = []
        for slot in buffer.slots():
            if slot == ref_slot:
                continue
            T_n = buffer.poses[slot]
            if rotation_angle_deg(T_r[:3, :3].T @ T_n[:3, :3]) > self.cfg.max_view_angle_deg:
                continue
            axis_angle = np.degrees(np.arccos(np.clip(T_r[:3, 2] @ T_n[:3, 2], -1.0, 1.0)))
            if axis_angle > self.cfg.max_view_angle_deg:
                continue
            point = T_r[:3, 3] + depth * T_r[:3, 2]
            a, b = T_r[:3, 3] - point, T_n[:3, 3] - point
            parallax = np.arccos(np.clip(a @ b / (np.linalg.norm(a) * np.linalg.norm(b) + 1e-12), -1.0, 1.0))
            too_small = parallax < 0.1 * target
            ranked.append((too_small, abs(np.log(max(parallax, 1e-9) / target)), slot))
        ranked.sort()
        return [slot for _, _, slot in ranked[: self.cfg.n_neighbours]]

    # ------------------------------------------------------------------ descriptors
    def describe(self, slot: int, buffer: KeyframeBuffer) -> wp.array:
        """(Hf, Wf, D) descriptors of a buffer slot, computed on first use."""
        if self._desc is None or self._desc.shape[0] != buffer.capacity:
            hf, wf = self.grid
            self._desc = wp.zeros((buffer.capacity, hf, wf, self.backbone.dim), dtype=wp.float32, device=self.device)
            self._query = wp.zeros((hf * wf, self.backbone.dim), dtype=wp.float32, device=self.device)
            buffer.descriptors = [None] * buffer.capacity
        if buffer.descriptors[slot] is None:
            buffer.descriptors[slot] = self.backbone.describe(buffer.rgb[slot], out=self._desc[slot])
        return buffer.descriptors[slot]

    # ------------------------------------------------------------------ matching
    def _epipolar(self, T_tq: np.ndarray) -> EpipolarSearch:
        """The search parameters from the query camera into the target camera ``T_tq`` (4x4)."""
        cfg, cam = self.cfg, self.camera
        e = EpipolarSearch()
        e.K = wp.vec4(cam.fx, cam.fy, cam.cx, cam.cy)
        e.R_tq = wp.mat33(*T_tq[:3, :3].astype(np.float32).ravel())
        e.t_tq = wp.vec3(*T_tq[:3, 3].astype(np.float32))
        e.stride, e.depth_range = self.stride, wp.vec2(cfg.min_depth_m, cfg.max_depth_m)
        e.depth_rel_tol, e.min_radius = cfg.depth_rel_tol, cfg.min_search_radius
        e.band, e.max_steps = cfg.band, cfg.max_steps
        return e

    def _search(self, images: list, T_tq: np.ndarray, out: list) -> None:
        """``epipolar_search`` of the queries in ``images`` (query descriptors, points, similarities,
        depth and grey image; target descriptors and grey image) into the target camera ``T_tq`` (from
        the query camera), its descriptor scan spread over EPIPOLAR_PARTS threads a query
        (``epipolar_search_parts``), into ``out`` (match, similarity, epipolar distance)."""
        n, d, cfg = self._part_sim.shape[0], self.device, self.cfg
        desc, uv, sim, depth, query_grey, target_desc, target_grey = images
        e = self._epipolar(T_tq)
        wp.launch(
            epipolar_search_parts,
            dim=self._part_sim.shape,
            inputs=[desc, uv, sim, depth, target_desc, e],
            outputs=self._parts,
            device=d,
        )
        refine = [int(np.ceil(cfg.refine_radius * self.stride)), cfg.patch_radius_px]
        wp.launch(epipolar_search, dim=n, inputs=images + [e, *refine, *self._parts], outputs=out, device=d)

    def match(
        self,
        ref_slot: int,
        buffer: KeyframeBuffer,
        neighbours: list[int] | None = None,
        use_depth: bool = True,
        thin: bool = True,
    ) -> Matches:
        """Dense matches of keyframe ``ref_slot`` in its neighbours (``select_neighbours`` unless
        given).  ``use_depth=False`` ignores the keyframes' depth (monocular search); ``thin=False``
        skips the blue-noise thinning (for measurements)."""
        if neighbours is None:
            neighbours = self.select_neighbours(ref_slot, buffer)
        m = len(neighbours)
        if not 1 <= m <= self.cfg.n_neighbours:
            raise ValueError(f"need 1..{self.cfg.n_neighbours} neighbours, got {neighbours}")
        cfg, s, d = self.cfg, self.stride, self.device
        hf, wf = self.grid
        n = hf * wf
        ref_desc_3d = self.describe(ref_slot, buffer)
        ref_desc = ref_desc_3d.reshape((n, self.backbone.dim))
        ref_grey, nb_grey = self._ref_grey, self._nb_grey
        wp.launch(grey_image, dim=ref_grey.shape, inputs=[buffer.rgb[ref_slot]], outputs=[ref_grey], device=d)
        cam = self.camera
        weights = wp.vec3(cfg.w_sim, cfg.w_fb, cfg.w_epi)
        T_r = buffer.poses[ref_slot]
        for column, slot in enumerate(neighbours):
            nb_desc = self.describe(slot, buffer)
            wp.launch(grey_image, dim=nb_grey.shape, inputs=[buffer.rgb[slot]], outputs=[nb_grey], device=d)
            T_nr = invert_pose(buffer.poses[slot]) @ T_r  # reference camera -> neighbour camera
            T_rn = invert_pose(T_nr)
            ref_depth = buffer.depth[ref_slot] if use_depth else self._zero_depth
            nb_depth = buffer.depth[slot] if use_depth else self._zero_depth
            fwd = [ref_desc, self._ref_uv, self._always, ref_depth, ref_grey, nb_desc, nb_grey]
            self._search(fwd, T_nr, [self._fwd_uv, self._fwd_sim, self._fwd_epi])
            wp.launch(sample_descriptors, dim=n, inputs=[nb_desc, self._fwd_uv, s], outputs=[self._query], device=d)
            bwd = [self._query, self._fwd_uv, self._fwd_sim, nb_depth, nb_grey, ref_desc_3d, ref_grey]
            self._search(bwd, T_rn, [self._bwd_uv, self._bwd_sim, self._bwd_epi])
            wp.launch(
                score_matches,
                dim=n,
                inputs=[self._ref_uv, self._fwd_uv, self._fwd_sim, self._fwd_epi, self._bwd_uv, self._bwd_sim]
                + [column, weights, cfg.sigma_fb_px, cfg.sigma_epi_px, cfg.gamma0, cfg.gamma1],
                outputs=[self._match_uv, self._confidence],
                device=d,
            )
        confidence = self._confidence[:, :m] if m < self.cfg.n_neighbours else self._confidence
        match_uv = self._match_uv[:, :m] if m < self.cfg.n_neighbours else self._match_uv
        aggregated = self._aggregated.flatten()
        wp.launch(aggregate_confidence, dim=n, inputs=[self._confidence, m], outputs=[aggregated], device=d)
        self._kept_count.zero_()
        if thin:
            thin_blue_noise(self._aggregated, cfg.thin_spacing, keep_out=self._keep, counters=self._thin_counters)
        else:
            self._keep.fill_(1)
        wp.launch(
            apply_thinning,
            dim=n,
            inputs=[self._keep.flatten(), m],
            outputs=[self._confidence, aggregated, self._kept_count],
            device=d,
        )
        P = projection_matrices(cam.K, np.stack([T_r] + [buffer.poses[slot] for slot in neighbours]))
        self._P[: m + 1].assign(P)
        return Matches(
            self._ref_uv_d,
            match_uv,
            confidence,
            aggregated,
            self._kept_count,
            self._P[: m + 1],
            list(neighbours),
            self.grid,
            s,
        )
