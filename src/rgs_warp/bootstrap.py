"""Monocular two-view bootstrap: the first map of a monocular run from frame 0 and a later frame k.

A monocular map cannot start from one image: it needs a second view with parallax.  ``MonoBootstrap``
tries a pair (frame 0, frame k) and either returns their relative pose and the triangulated points,
or None when the pair cannot fix them (too little parallax, too few consistent matches); the caller
then tries a later k, up to ``BootstrapConfig.max_wait_frames``.

``try_init`` steps:

1. Dense descriptors of both images with the project's backbone (``features.make_backbone``).
2. An unconstrained search (no pose yet, so no epipolar line) of every feature pixel of frame 0 in a
   window of +/- ``search_radius`` feature px of frame k, centred by the global image motion that a
   coarse whole-image pass finds, refined to sub-pixel (parabola, then image-resolution patch ZNCC
   as in the DenseMatcher), searched back from k into 0; kept when similar enough, distinctive
   (Lowe's ratio against the best match outside the immediate neighbourhood) and mutual
   (``kernels/bootstrap.py``).
3. On the host, once per attempt: the essential matrix and the relative pose by OpenCV
   (``relative_pose``: ``findEssentialMat`` with USAC, Sampson error in image px, deterministic;
   ``recoverPose`` picks the (R, t) that puts the most inliers in front of both cameras).  Rejected
   when the inliers are too few or too small a part of the matches, too few of them are in front
   of both cameras (a wrong pose puts several % behind one), or their median parallax angle is
   below ``min_parallax_deg``.
4. The inliers triangulated with the project's batched DLT (``triangulation.triangulate_dlt``) and
   the gauge fixed: frame 0 is the origin and the median depth of the points in frame 0 is
   ``matching.scene_depth_m`` (the unit the rest of a monocular run measures in).
5. Each point's confidence is Eq. 11-12 of the DenseMatcher (similarity, forward-backward error,
   distance to the epipolar line of the estimated pose), so the Seeder's Eq. 14 opacities mean the
   same as for later keyframes.

``to_triangulated_points`` turns a result into the Seeder's input for the two keyframes (0, k):
``seeder.seed(points, wp.array(result.confidence), keyframes, [slot_0, slot_k], gmap)`` with the
keyframes' poses ``T_W0`` and ``T_W0 @ result.T_0k``.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
import warp as wp

from rgs_warp.config import BootstrapConfig, MatchingConfig
from rgs_warp.features import feature_centres, make_backbone
from rgs_warp.geometry import invert_pose, skew
from rgs_warp.kernels.bootstrap import (
    select_matches,
    window_search,
    window_search_best,
    window_search_finish,
    window_search_rows,
)
from rgs_warp.kernels.matching import grey_image, sample_descriptors, score_matches
from rgs_warp.triangulation import TriangulatedPoints, baseline_angle_deg, projection_matrices, triangulate_dlt
from rgs_warp.types import Camera


class BandedWindowSearch:
    """``kernels.bootstrap.window_search`` for windows as large as the image (the bootstrap's coarse
    pass): each query's window rows are split over ``bands`` threads, whose bests are reduced in row
    order, so the result is the same (tests/test_bootstrap.py) while one thread per query would
    leave the GPU nearly idle (a few thousand queries, each scanning the whole grid: 0.76 s of a
    1.0 s bootstrap attempt at 1200x680 on an H100).  Buffers for ``queries`` queries."""

    def __init__(self, queries: int, bands: int, device=None):
        kw = {"device": wp.get_device(device)}
        self.device = kw["device"]
        self._band_sim = wp.zeros((queries, bands), dtype=wp.float32, **kw)
        self._band_xy = wp.zeros((queries, bands), dtype=wp.vec2i, **kw)
        self._best_xy = wp.zeros(queries, dtype=wp.vec2i, **kw)

    def __call__(
        self, query_desc, query_uv, query_grey, target_desc, target_grey, stride, offset, radius, exclusion, refine, out
    ) -> None:
        """As ``window_search`` with the same arguments (``refine``: [refine_radius, patch_radius];
        ``out``: [match_uv, sim, second_sim])."""
        match_uv, sim, second = out
        n, bands = self._band_sim.shape
        geometry = [query_uv, target_desc, stride, offset, radius]
        rows = [query_desc, query_uv, target_desc, stride, offset, radius, exclusion, self._best_xy]
        d = self.device
        wp.launch(window_search_rows, dim=(n, bands), inputs=rows, outputs=[self._band_sim, self._band_xy, 0], device=d)
        best = [self._band_sim, self._band_xy]
        wp.launch(window_search_best, dim=n, inputs=geometry + best, outputs=[self._best_xy, sim], device=d)
        if exclusion >= 0:
            bands_out = [self._band_sim, self._band_xy, 1]
            wp.launch(window_search_rows, dim=(n, bands), inputs=rows, outputs=bands_out, device=d)
        wp.launch(
            window_search_finish,
            dim=n,
            inputs=[query_desc, query_uv, query_grey, target_desc, target_grey, stride, self._best_xy, self._band_sim]
            + [exclusion, *refine, sim],
            outputs=[match_uv, second],
            device=d,
        )


@dataclass
class BootstrapResult:
    """A successful bootstrap of frames 0 and k, in frame 0's camera coordinates at the fixed scale.

    T_0k: (4, 4) camera k to camera 0; points: (N, 3) float64 points in camera 0; ref_uv / match_uv:
    (N, 2) their pixels in frame 0 (feature-pixel centres) and frame k; residual_px: (N,) RMS
    reprojection error over both views; parallax_deg: (N,) angle between the two rays;
    confidence: (N,) float32 Eq. 12; inlier_ratio: essential-matrix inliers / selected matches;
    median_parallax_deg: over the inliers; scale: the factor applied to the unit-baseline solution
    (``|t|`` in map units).
    """

    T_0k: np.ndarray
    points: np.ndarray
    ref_uv: np.ndarray
    match_uv: np.ndarray
    residual_px: np.ndarray
    parallax_deg: np.ndarray
    confidence: np.ndarray
    inlier_ratio: float
    median_parallax_deg: float
    scale: float


class MonoBootstrap:
    """Two-view initialisation of a monocular map (module docstring).  Buffers are sized by the
    camera; ``matching`` supplies the backbone (when none is given) and Eq. 11-12's constants.
    ``last_rejection`` says why the last ``try_init`` returned None."""

    def __init__(
        self,
        cfg: BootstrapConfig,
        camera: Camera,
        device=None,
        backbone=None,
        matching: MatchingConfig | None = None,
    ):
        self.cfg = cfg
        self.camera = camera
        self.device = wp.get_device(device)
        self.matching = matching if matching is not None else MatchingConfig()
        self.backbone = backbone if backbone is not None else make_backbone(self.matching, self.device)
        self.stride = s = self.backbone.stride
        hf, wf = self.grid = self.backbone.grid_shape(camera.height, camera.width)
        n = hf * wf
        centres = feature_centres(self.grid, s)
        self._ref_uv_host = centres
        kw = {"device": self.device}
        self._rgb = [wp.zeros((camera.height, camera.width), dtype=wp.vec3, **kw) for _ in range(2)]
        self._grey = [wp.zeros((camera.height, camera.width), dtype=wp.float32, **kw) for _ in range(2)]
        self._desc = [wp.zeros((hf, wf, self.backbone.dim), dtype=wp.float32, **kw) for _ in range(2)]
        self._ref_uv = wp.array(centres.astype(np.float32), dtype=wp.vec2, **kw)
        self._query = wp.zeros((n, self.backbone.dim), dtype=wp.float32, **kw)
        self._fwd_uv, self._bwd_uv = wp.zeros(n, dtype=wp.vec2, **kw), wp.zeros(n, dtype=wp.vec2, **kw)
        self._fwd_sim, self._fwd_second = wp.zeros(n, dtype=wp.float32, **kw), wp.zeros(n, dtype=wp.float32, **kw)
        self._bwd_sim, self._bwd_second = wp.zeros(n, dtype=wp.float32, **kw), wp.zeros(n, dtype=wp.float32, **kw)
        self._fb_err = wp.zeros(n, dtype=wp.float32, **kw)
        self._valid = wp.zeros(n, dtype=wp.int32, **kw)
        self._epi_dist = wp.zeros(n, dtype=wp.float32, **kw)
        self._match_uv = wp.zeros((n, 1), dtype=wp.vec2d, **kw)
        self._confidence = wp.zeros((n, 1), dtype=wp.float32, **kw)
        step = max(cfg.coarse_step, 1)
        self._coarse_uv_host = centres.reshape(hf, wf, 2)[step // 2 :: step, step // 2 :: step].reshape(-1, 2)
        m = len(self._coarse_uv_host)
        self._coarse_uv = wp.array(self._coarse_uv_host.astype(np.float32), dtype=wp.vec2, **kw)
        self._coarse_query = wp.zeros((m, self.backbone.dim), dtype=wp.float32, **kw)
        self._coarse_match = wp.zeros(m, dtype=wp.vec2, **kw)
        self._coarse_sim, self._coarse_second = wp.zeros(m, dtype=wp.float32, **kw), wp.zeros(m, dtype=wp.float32, **kw)
        self._coarse_fb_err, self._coarse_valid = wp.zeros(m, dtype=wp.float32, **kw), wp.zeros(m, dtype=wp.int32, **kw)
        self._coarse_search = BandedWindowSearch(m, hf, self.device)  # a thread per query and row
        self.last_motion_px = np.zeros(2)  # the global image motion the last search assumed
        self.last_rejection: str | None = None

    def match(self, rgb0, rgbk) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Selected matches of frame 0's feature pixels in frame k: (ref_uv (N, 2), match_uv (N, 2),
        valid (N,) bool) over the whole feature grid, image px."""
        cfg, s, d = self.cfg, self.stride, self.device
        n = self.grid[0] * self.grid[1]
        for buf, img in zip(self._rgb, (rgb0, rgbk), strict=True):
            if isinstance(img, wp.array):
                wp.copy(buf, img)
            else:
                buf.assign(np.ascontiguousarray(img, dtype=np.float32))
        rgb0_d, rgbk_d = self._rgb
        grey0, greyk = self._grey
        for rgb, grey in zip(self._rgb, self._grey, strict=True):
            wp.launch(grey_image, dim=grey.shape, inputs=[rgb], outputs=[grey], device=d)
        desc0 = self.backbone.describe(rgb0_d, out=self._desc[0])
        desck = self.backbone.describe(rgbk_d, out=self._desc[1])
        self.last_motion_px = motion = self._global_motion(desc0, desck) if cfg.coarse_step > 0 else np.zeros(2)
        fwd_offset, bwd_offset = wp.vec2(*(motion / s)), wp.vec2(*(-motion / s))
        refine = [cfg.refine_radius_px, cfg.patch_radius_px]
        wp.launch(
            window_search,
            dim=n,
            inputs=[desc0.reshape((n, self.backbone.dim)), self._ref_uv, grey0, desck, greyk, s, fwd_offset]
            + [cfg.search_radius, cfg.ratio_exclusion, *refine],
            outputs=[self._fwd_uv, self._fwd_sim, self._fwd_second],
            device=d,
        )
        wp.launch(sample_descriptors, dim=n, inputs=[desck, self._fwd_uv, s], outputs=[self._query], device=d)
        wp.launch(  # back from k into 0: only its best match matters (exclusion -1: no second best)
            window_search,
            dim=n,
            inputs=[self._query, self._fwd_uv, greyk, desc0, grey0, s, bwd_offset, cfg.search_radius, -1, *refine],
            outputs=[self._bwd_uv, self._bwd_sim, self._bwd_second],
            device=d,
        )
        wp.launch(
            select_matches,
            dim=n,
            inputs=[self._ref_uv, self._fwd_uv, self._fwd_sim, self._fwd_second, self._bwd_uv]
            + [cfg.min_similarity, cfg.max_ratio, cfg.max_fb_px],
            outputs=[self._fb_err, self._valid],
            device=d,
        )
        return self._ref_uv_host, self._fwd_uv.numpy().astype(np.float64), self._valid.numpy().astype(bool)

    def _global_motion(self, desc0: wp.array, desck: wp.array) -> np.ndarray:
        """Median image motion (px) from frame 0 to k of the coarse queries' distinctive matches
        over the whole image (0 when fewer than 8 are)."""
        cfg, s, d = self.cfg, self.stride, self.device
        m = self._coarse_uv.shape[0]
        wp.launch(sample_descriptors, dim=m, inputs=[desc0, self._coarse_uv, s], outputs=[self._coarse_query], device=d)
        self._coarse_search(
            self._coarse_query,
            self._coarse_uv,
            self._grey[0],
            desck,
            self._grey[1],
            s,
            wp.vec2(0.0, 0.0),
            max(self.grid),
            cfg.ratio_exclusion,
            [0, 0],
            [self._coarse_match, self._coarse_sim, self._coarse_second],
        )
        wp.launch(  # similarity and ratio tests only: the query stands in for its backward match
            select_matches,
            dim=m,
            inputs=[self._coarse_uv, self._coarse_match, self._coarse_sim, self._coarse_second, self._coarse_uv]
            + [cfg.min_similarity, cfg.max_ratio, 0.0],
            outputs=[self._coarse_fb_err, self._coarse_valid],
            device=d,
        )
        distinct = self._coarse_valid.numpy().astype(bool)
        if distinct.sum() < 8:
            return np.zeros(2)
        return np.median(self._coarse_match.numpy()[distinct] - self._coarse_uv_host[distinct], axis=0)

    def try_init(self, rgb0, rgbk) -> BootstrapResult | None:
        """Bootstrap from frame 0 and frame k (HxWx3 float32 NumPy in [0, 1], or (H, W) ``wp.vec3``
        arrays on any device); None when the pair cannot (``last_rejection`` says why)."""
        cfg, cam = self.cfg, self.camera
        K = cam.K
        ref_uv, match_uv, valid = self.match(rgb0, rgbk)
        selected = np.flatnonzero(valid)
        self.last_rejection = None
        if len(selected) < max(cfg.min_inliers, 8):
            return self._reject(f"{len(selected)} selected matches < {cfg.min_inliers}")
        pose = relative_pose(
            ref_uv[selected], match_uv[selected], K, cfg.ransac_threshold_px, cfg.ransac_confidence, cfg.ransac_iters
        )
        if pose is None:
            return self._reject("no essential matrix")
        R, t, inliers, in_front = pose
        if inliers.sum() < cfg.min_inliers:
            return self._reject(f"{inliers.sum()} essential-matrix inliers < {cfg.min_inliers}")
        if inliers.mean() < cfg.min_inlier_ratio:
            return self._reject(f"inlier ratio {inliers.mean():.2f} < {cfg.min_inlier_ratio}")
        if in_front.mean() < cfg.min_cheirality_ratio:
            return self._reject(f"cheirality {in_front.mean():.2f} < {cfg.min_cheirality_ratio} (ambiguous pose)")
        T_0k = invert_pose(_transform(R, t))  # unit baseline
        keep = selected[inliers][in_front]
        P = projection_matrices(K, np.stack([np.eye(4), T_0k]))
        x = np.stack([ref_uv[keep], match_uv[keep]], 1)
        X, residual = triangulate_dlt(P, x, np.ones((len(keep), 2), bool), self.device)
        parallax = baseline_angle_deg(P, X, np.ones((len(keep), 2), bool), self.device).numpy()
        X, residual = X.numpy(), residual.numpy()
        finite = np.isfinite(residual)
        median_parallax = float(np.median(parallax[finite])) if finite.any() else 0.0
        if finite.sum() < cfg.min_inliers:
            return self._reject(f"{finite.sum()} points in front of both cameras < {cfg.min_inliers}")
        if median_parallax < cfg.min_parallax_deg:
            return self._reject(f"median parallax {median_parallax:.2f} deg < {cfg.min_parallax_deg}")
        good = finite & (residual <= cfg.max_reproj_px) & (parallax >= cfg.min_point_parallax_deg)
        if not good.any():
            return self._reject("no point passes the reprojection and parallax tests")
        scale = self.matching.scene_depth_m / float(np.median(X[good, 2]))
        T_0k[:3, 3] *= scale
        confidence = self._confidence_of(skew(t) @ R, ref_uv, match_uv)[keep[good]]
        return BootstrapResult(
            T_0k=T_0k,
            points=X[good] * scale,
            ref_uv=ref_uv[keep[good]],
            match_uv=match_uv[keep[good]],
            residual_px=residual[good],
            parallax_deg=parallax[good],
            confidence=confidence,
            inlier_ratio=float(inliers.mean()),
            median_parallax_deg=median_parallax,
            scale=scale,
        )

    def _reject(self, reason: str) -> None:
        self.last_rejection = reason
        return None

    def _confidence_of(self, E: np.ndarray, ref_uv: np.ndarray, match_uv: np.ndarray) -> np.ndarray:
        """(N,) Eq. 12 confidence of every forward match given the pose's epipolar geometry."""
        m = self.matching
        self._epi_dist.assign(epipolar_distance_px(E, ref_uv, match_uv, self.camera.K).astype(np.float32))
        wp.launch(
            score_matches,
            dim=self._epi_dist.shape[0],
            inputs=[self._ref_uv, self._fwd_uv, self._fwd_sim, self._epi_dist, self._bwd_uv, self._bwd_sim, 0]
            + [wp.vec3(m.w_sim, m.w_fb, m.w_epi), m.sigma_fb_px, m.sigma_epi_px, m.gamma0, m.gamma1],
            outputs=[self._match_uv, self._confidence],
            device=self.device,
        )
        return self._confidence.numpy()[:, 0]


def to_triangulated_points(result: BootstrapResult, T_W0: np.ndarray, device=None) -> TriangulatedPoints:
    """The Seeder's input for the two keyframes of a bootstrap: points in world coordinates (frame 0
    at camera-to-world pose ``T_W0``, frame k at ``T_W0 @ result.T_0k``), every point valid and
    supported by both views (bits 0 and 1: pass ``view_slots = [slot_0, slot_k]``)."""
    device = wp.get_device(device)
    T_W0 = np.asarray(T_W0, dtype=np.float64)
    X = result.points @ T_W0[:3, :3].T + T_W0[:3, 3]
    n = len(X)
    return TriangulatedPoints(
        X=wp.array(X, dtype=wp.vec3d, device=device),
        residual_px=wp.array(result.residual_px.astype(np.float64), dtype=wp.float64, device=device),
        parallax_deg=wp.array(result.parallax_deg.astype(np.float64), dtype=wp.float64, device=device),
        support=wp.full(n, 0b11, dtype=wp.int32, device=device),
        valid=wp.full(n, 1, dtype=wp.int32, device=device),
    )


# ---------------------------------------------------------------------------- two-view geometry (host)


def relative_pose(
    uv0: np.ndarray,
    uvk: np.ndarray,
    K: np.ndarray,
    threshold_px: float = 1.0,
    confidence: float = 0.999999999,
    max_iters: int = 1000,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None:
    """Relative pose of pixel correspondences uv0 <-> uvk (n, 2), both seen by the camera K, by
    OpenCV: ``findEssentialMat`` with USAC_DEFAULT (5-point samples, MSAC score on the Sampson error
    in image px, local optimisation; OpenCV seeds it with a fixed state, so the same input gives the
    same pose) and ``recoverPose`` on its inliers (the one of E's four (R, t) with the most inliers
    in front of both cameras; no far limit on the points).

    Returns (R, t, inliers (n,) bool, in_front (number of inliers,) bool) with camera-0 points
    mapping into camera k as X_k = R X_0 + t, |t| = 1; None when OpenCV finds no essential matrix."""
    uv0 = np.ascontiguousarray(uv0, dtype=np.float64)
    uvk = np.ascontiguousarray(uvk, dtype=np.float64)
    E, mask = cv2.findEssentialMat(
        uv0, uvk, K, method=cv2.USAC_DEFAULT, prob=confidence, threshold=threshold_px, maxIters=max_iters
    )
    if E is None or mask is None or E.shape != (3, 3):
        return None
    inliers = mask.ravel() > 0
    if inliers.sum() < 5:
        return None
    _, R, t, front, _ = cv2.recoverPose(E, uv0[inliers], uvk[inliers], K, distanceThresh=np.inf)
    return R, t.ravel(), inliers, front.ravel() > 0


def _homogeneous(x: np.ndarray) -> np.ndarray:
    return np.concatenate([x, np.ones(x.shape[:-1] + (1,))], -1)


def epipolar_distance_px(E: np.ndarray, uv0: np.ndarray, uvk: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Distance (image px) of each uvk from the epipolar line of its uv0 in image k under the
    essential matrix E (x_k^T E x_0 = 0 in normalised coordinates): (n,)."""
    Kinv = np.linalg.inv(K)
    F = Kinv.T @ E @ Kinv
    Fx0 = _homogeneous(uv0) @ F.T
    r = np.einsum("ni,ni->n", Fx0, _homogeneous(uvk))
    return np.abs(r) / np.sqrt(np.maximum(Fx0[:, 0] ** 2 + Fx0[:, 1] ** 2, 1e-300))


def _transform(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    return T
