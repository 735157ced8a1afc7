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
3. On the host, once per attempt: the normalised 8-point essential matrix in a MSAC loop (fixed
   seed; Sampson error in image px), refined on its inliers by Levenberg-Marquardt on the Sampson
   error, decomposed into its four (R, t), the one with the most points in front of both cameras
   kept.  Rejected when the inliers are too few or too small a part of the matches, the
   cheirality vote is not clear, or their median parallax angle is below ``min_parallax_deg``.
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

import numpy as np
import warp as wp

from rgs_warp.config import BootstrapConfig, MatchingConfig
from rgs_warp.features import make_backbone
from rgs_warp.geometry import invert_pose, skew, so3_exp
from rgs_warp.kernels.bootstrap import select_matches, window_search
from rgs_warp.kernels.matching import sample_descriptors, score_matches
from rgs_warp.triangulation import TriangulatedPoints, baseline_angle_deg, projection_matrices, triangulate_dlt
from rgs_warp.types import Camera


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
        centres = np.stack(
            np.meshgrid(np.arange(wf) * s + 0.5 * (s - 1), np.arange(hf) * s + 0.5 * (s - 1)), -1
        ).reshape(-1, 2)
        self._ref_uv_host = centres
        kw = {"device": self.device}
        self._rgb = [wp.zeros((camera.height, camera.width), dtype=wp.vec3, **kw) for _ in range(2)]
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
        desc0 = self.backbone.describe(rgb0_d, out=self._desc[0])
        desck = self.backbone.describe(rgbk_d, out=self._desc[1])
        self.last_motion_px = motion = self._global_motion(desc0, desck) if cfg.coarse_step > 0 else np.zeros(2)
        fwd_offset, bwd_offset = wp.vec2(*(motion / s)), wp.vec2(*(-motion / s))
        refine = [cfg.refine_radius_px, cfg.patch_radius_px]
        wp.launch(
            window_search,
            dim=n,
            inputs=[desc0.reshape((n, self.backbone.dim)), self._ref_uv, rgb0_d, desck, rgbk_d, s, fwd_offset]
            + [cfg.search_radius, cfg.ratio_exclusion, *refine],
            outputs=[self._fwd_uv, self._fwd_sim, self._fwd_second],
            device=d,
        )
        wp.launch(sample_descriptors, dim=n, inputs=[desck, self._fwd_uv, s], outputs=[self._query], device=d)
        wp.launch(  # back from k into 0: only its best match matters (exclusion -1: no second best)
            window_search,
            dim=n,
            inputs=[self._query, self._fwd_uv, rgbk_d, desc0, rgb0_d, s, bwd_offset, cfg.search_radius, -1, *refine],
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
        wp.launch(
            window_search,
            dim=m,
            inputs=[self._coarse_query, self._coarse_uv, self._rgb[0], desck, self._rgb[1], s, wp.vec2(0.0, 0.0)]
            + [max(self.grid), cfg.ratio_exclusion, 0, 0],
            outputs=[self._coarse_match, self._coarse_sim, self._coarse_second],
            device=d,
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
        uv0, uvk = ref_uv[selected], match_uv[selected]
        E, inliers = estimate_essential(
            uv0, uvk, K, cfg.ransac_iters, cfg.ransac_threshold_px, cfg.ransac_seed, cfg.refine_rounds
        )
        if inliers.sum() < cfg.min_inliers:
            return self._reject(f"{inliers.sum()} essential-matrix inliers < {cfg.min_inliers}")
        if inliers.mean() < cfg.min_inlier_ratio:
            return self._reject(f"inlier ratio {inliers.mean():.2f} < {cfg.min_inlier_ratio}")
        R, t, in_front = relative_pose_from_essential(E, normalised(uv0[inliers], K), normalised(uvk[inliers], K))
        if in_front.mean() < cfg.min_cheirality_ratio:
            return self._reject(f"cheirality {in_front.mean():.2f} < {cfg.min_cheirality_ratio} (ambiguous pose)")
        T_0k = invert_pose(_rigid(R, t))  # unit baseline
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
        confidence = self._confidence_of(E, ref_uv, match_uv)[keep[good]]
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


def normalised(uv: np.ndarray, K: np.ndarray) -> np.ndarray:
    """(..., 2) pixels to normalised image coordinates K^-1 (u, v, 1), first two components."""
    return (uv - K[:2, 2]) / np.array([K[0, 0], K[1, 1]])


def _homogeneous(x: np.ndarray) -> np.ndarray:
    return np.concatenate([x, np.ones(x.shape[:-1] + (1,))], -1)


def _hartley(x: np.ndarray) -> np.ndarray:
    """(..., 3, 3) similarity moving the points (..., n, 2) to centroid 0, mean distance sqrt(2)."""
    c = x.mean(-2)
    d = np.linalg.norm(x - c[..., None, :], axis=-1).mean(-1)
    s = np.sqrt(2.0) / np.maximum(d, 1e-12)
    T = np.zeros(x.shape[:-2] + (3, 3))
    T[..., 0, 0] = T[..., 1, 1] = s
    T[..., :2, 2] = -s[..., None] * c
    T[..., 2, 2] = 1.0
    return T


def essential_8point(x0: np.ndarray, xk: np.ndarray) -> np.ndarray:
    """Normalised 8-point essential matrix (Hartley) of correspondences in normalised image
    coordinates x0, xk (..., n >= 8, 2), batched over leading axes: the 3x3 matrix minimising the
    algebraic error of ``x_k^T E x_0 = 0`` (in Hartley-normalised coordinates), projected onto the
    essential matrices (singular values (1, 1, 0)) and scaled to unit Frobenius norm.  Camera-0
    points map into camera k as X_k = R X_0 + t, E = [t]x R."""
    T0, Tk = _hartley(x0), _hartley(xk)
    p0 = np.einsum("...ij,...nj->...ni", T0, _homogeneous(x0))
    pk = np.einsum("...ij,...nj->...ni", Tk, _homogeneous(xk))
    A = (pk[..., :, :, None] * p0[..., :, None, :]).reshape(p0.shape[:-1] + (9,))
    e = np.linalg.svd(A, full_matrices=True)[2][..., -1, :]
    E = np.swapaxes(Tk, -1, -2) @ e.reshape(e.shape[:-1] + (3, 3)) @ T0
    U, _, Vt = np.linalg.svd(E)
    E = U @ np.diag([1.0, 1.0, 0.0]) @ Vt
    return E / np.linalg.norm(E, axis=(-2, -1), keepdims=True)


def _epipolar_terms(E: np.ndarray, uv0: np.ndarray, uvk: np.ndarray, K: np.ndarray):
    """Algebraic residual x_k^T F x_0 and the gradients' components (F x_0, F^T x_k) in pixels."""
    Kinv = np.linalg.inv(K)
    F = Kinv.T @ E @ Kinv
    h0, hk = _homogeneous(uv0), _homogeneous(uvk)
    Fx0 = np.einsum("...ij,nj->...ni", F, h0)
    Ftxk = np.einsum("...ji,nj->...ni", F, hk)
    return np.einsum("...ni,ni->...n", Fx0, hk), Fx0, Ftxk


def sampson_error_px(
    E: np.ndarray, uv0: np.ndarray, uvk: np.ndarray, K: np.ndarray, signed: bool = False
) -> np.ndarray:
    """First-order geometric (Sampson) error in image px of pixel correspondences (n, 2) under
    essential matrices E (..., 3, 3): (..., n); ``signed`` keeps the sign of the algebraic residual
    (a least-squares residual)."""
    r, Fx0, Ftxk = _epipolar_terms(E, uv0, uvk, K)
    grad2 = Fx0[..., 0] ** 2 + Fx0[..., 1] ** 2 + Ftxk[..., 0] ** 2 + Ftxk[..., 1] ** 2
    return (r if signed else np.abs(r)) / np.sqrt(np.maximum(grad2, 1e-300))


def epipolar_distance_px(E: np.ndarray, uv0: np.ndarray, uvk: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Distance (image px) of each uvk from the epipolar line of its uv0 in image k: (n,)."""
    r, Fx0, _ = _epipolar_terms(E, uv0, uvk, K)
    return np.abs(r) / np.sqrt(np.maximum(Fx0[:, 0] ** 2 + Fx0[:, 1] ** 2, 1e-300))


def estimate_essential(
    uv0: np.ndarray,
    uvk: np.ndarray,
    K: np.ndarray,
    iters: int = 512,
    threshold_px: float = 1.0,
    seed: int = 0,
    refine_rounds: int = 2,
) -> tuple[np.ndarray, np.ndarray]:
    """Essential matrix of pixel correspondences uv0 <-> uvk (n >= 8, 2) by MSAC over ``iters``
    random 8-point samples (seeded: deterministic), then ``refine_rounds`` rounds of refinement on the
    inliers (``refine_essential``) and re-selection of the inliers, those of Sampson error below
    ``threshold_px``.
    Returns (E, inliers (n,) bool)."""
    n = len(uv0)
    if n < 8:
        raise ValueError(f"the 8-point algorithm needs at least 8 correspondences, got {n}")
    x0, xk = normalised(uv0, K), normalised(uvk, K)
    rng = np.random.default_rng(seed)
    samples = rng.random((iters, n)).argpartition(7, axis=1)[:, :8]  # 8 distinct indices per row
    hypotheses = essential_8point(x0[samples], xk[samples])
    cost = np.empty(iters)
    for lo in range(0, iters, 64):  # bounded memory: 64 hypotheses x n at a time
        err = sampson_error_px(hypotheses[lo : lo + 64], uv0, uvk, K)
        cost[lo : lo + 64] = (np.minimum(err, threshold_px) ** 2).sum(-1)
    E = hypotheses[np.argmin(cost)]
    inliers = sampson_error_px(E, uv0, uvk, K) < threshold_px
    for _ in range(refine_rounds):
        if inliers.sum() < 8:
            break
        E = refine_essential(E, uv0[inliers], uvk[inliers], K)
        inliers = sampson_error_px(E, uv0, uvk, K) < threshold_px
    return E, inliers


def refine_essential(E: np.ndarray, uv0: np.ndarray, uvk: np.ndarray, K: np.ndarray, iters: int = 10) -> np.ndarray:
    """E minimising the squared Sampson error of the correspondences over essential matrices
    (Levenberg-Marquardt on E = [t]x R, 5 degrees of freedom: R <- Exp(w) R, t on the unit sphere).

    Needed because the 8-point solution minimises an algebraic error over all 3x3 matrices and is
    only then projected onto the essential matrices, which at small baselines costs accuracy
    (measured on office0 160x90, frame 0 with frames 6 / 8: rotation 0.69 / 1.19 deg and
    translation direction 12.6 / 15.1 deg off without the refinement, 0.09 / 0.29 and 1.9 / 3.4
    with it)."""
    R, t = decompose_essential(E)[0]

    def residuals(x: np.ndarray) -> np.ndarray:
        t_x = t + x[3] * basis[0] + x[4] * basis[1]
        return sampson_error_px(skew(t_x / np.linalg.norm(t_x)) @ so3_exp(x[:3]) @ R, uv0, uvk, K, signed=True)

    damping = 1e-3
    for _ in range(iters):
        basis = np.linalg.svd(t[None])[2][1:]  # two unit vectors orthogonal to t
        x0 = np.zeros(5)
        r = residuals(x0)
        cost = r @ r
        step = 1e-6
        J = np.stack([(residuals(step * e) - residuals(-step * e)) / (2 * step) for e in np.eye(5)], 1)
        JtJ, Jtr = J.T @ J, J.T @ r
        while damping < 1e8:
            x = np.linalg.solve(JtJ + damping * np.diag(np.diag(JtJ) + 1e-12), -Jtr)
            r_new = residuals(x)
            if r_new @ r_new < cost:
                t_new = t + x[3] * basis[0] + x[4] * basis[1]
                R, t = so3_exp(x[:3]) @ R, t_new / np.linalg.norm(t_new)
                damping = max(damping / 10, 1e-9)
                break
            damping *= 10
        else:
            break
        if cost - r_new @ r_new < 1e-12 * cost:
            break
    E = skew(t) @ R
    return E / np.linalg.norm(E)


def decompose_essential(E: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
    """The four (R, t) of an essential matrix (t unit, X_k = R X_0 + t), the classic
    ``R = U W V^T`` or ``U W^T V^T``, ``t = +/- u_3``."""
    U, _, Vt = np.linalg.svd(E)
    U = U * np.sign(np.linalg.det(U))
    Vt = Vt * np.sign(np.linalg.det(Vt))
    W = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    t = U[:, 2]
    return [(U @ W @ Vt, t), (U @ W @ Vt, -t), (U @ W.T @ Vt, t), (U @ W.T @ Vt, -t)]


def two_view_depths(R: np.ndarray, t: np.ndarray, x0: np.ndarray, xk: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Depths (z0, zk) of the rays through normalised points x0, xk (n, 2) meeting as
    zk xk = z0 R x0 + t (exactly where they intersect, least squares otherwise); NaN for parallel rays."""
    r0 = _homogeneous(x0) @ R.T
    hk = _homogeneous(xk)
    a = np.cross(hk, r0)
    b = np.cross(hk, t)
    with np.errstate(divide="ignore", invalid="ignore"):
        z0 = -(a * b).sum(-1) / (a * a).sum(-1)
        zk = ((z0[:, None] * r0 + t) * hk).sum(-1) / (hk * hk).sum(-1)
    return z0, zk


def relative_pose_from_essential(
    E: np.ndarray, x0: np.ndarray, xk: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The (R, t) of E that puts the most correspondences (normalised coordinates) in front of both
    cameras (cheirality); returns (R, t, in_front (n,) bool)."""
    best = None
    for R, t in decompose_essential(E):
        z0, zk = two_view_depths(R, t, x0, xk)
        in_front = (z0 > 0) & (zk > 0)
        if best is None or in_front.sum() > best[2].sum():
            best = (R, t, in_front)
    return best


def _rigid(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    return T
