"""Triangulation (supplement §4.4): batched float64 DLT and the Triangulator stage.

Projection matrices map world points to pixels, ``P = K [R_CW | t_CW]`` (pixel centres at integer
coordinates, see ``types.py``); ``projection_matrices`` builds them from camera-to-world poses.
The DLT construction and solver are described in ``kernels/dlt.py``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import warp as wp

from rgs_warp.config import TriangulationConfig
from rgs_warp.geometry import invert_pose
from rgs_warp.kernels.dlt import baseline_angles, mat34d, triangulate_hypotheses, triangulate_points
from rgs_warp.types import grown_capacity


def projection_matrices(K: np.ndarray, T_WC: np.ndarray) -> np.ndarray:
    """(V, 3, 4) float64 ``K [R_CW | t_CW]`` of camera-to-world poses ``T_WC`` (V, 4, 4)."""
    T_WC = np.asarray(T_WC, dtype=np.float64).reshape(-1, 4, 4)
    return np.stack([np.asarray(K, dtype=np.float64) @ invert_pose(T)[:3] for T in T_WC])


def _as_array(a, dtype, ndim: int, device) -> wp.array:
    """A ``wp.array`` of ``dtype`` on ``device``: NumPy input is converted (the trailing axes fold
    into the vector/matrix dtype), a ``wp.array`` must already have that dtype."""
    if isinstance(a, wp.array):
        if a.dtype != dtype or a.ndim != ndim:
            raise TypeError(f"expected a {ndim}-d wp.array of {dtype.__name__}, got {a.ndim}-d of {a.dtype.__name__}")
        return a if a.device == device else a.to(device)
    return wp.array(np.ascontiguousarray(a), dtype=dtype, device=device)


def triangulate_dlt(P, x, valid, device=None, X_out=None, residual_px_out=None) -> tuple[wp.array, wp.array]:
    """Homogeneous DLT of N points seen in V views, one point per thread, float64 throughout.

    P: (V, 3, 4) float64 NumPy, or a (V,) ``wp.array`` of ``mat34d``.
    x: (N, V, 2) float64 pixel observations (NumPy), or an (N, V) ``wp.array`` of ``wp.vec2d``.
    valid: (N, V) bool (NumPy, any dtype: nonzero = observed), or an (N, V) ``wp.array`` of ``wp.bool``.
    Returns ``X`` (N,) ``wp.vec3d`` (``.numpy()`` is (N, 3) float64) and ``residual_px`` (N,)
    float64, the RMS reprojection error over the valid views: +inf for points with fewer than two
    valid views or a degenerate solution (w ~ 0, behind a camera); X is NaN where undefined.
    ``X_out``/``residual_px_out`` are optional preallocated outputs.
    """
    device = wp.get_device(device)
    P = _as_array(P, mat34d, 1, device)
    x = _as_array(x, wp.vec2d, 2, device)
    valid = _as_array(np.asarray(valid).astype(bool) if not isinstance(valid, wp.array) else valid, wp.bool, 2, device)
    n = x.shape[0]
    if X_out is None:
        X_out = wp.empty(n, dtype=wp.vec3d, device=device)
    if residual_px_out is None:
        residual_px_out = wp.empty(n, dtype=wp.float64, device=device)
    wp.launch(triangulate_points, dim=n, inputs=[P, x, valid], outputs=[X_out, residual_px_out], device=device)
    return X_out, residual_px_out


def baseline_angle_deg(P, X, valid, device=None, parallax_deg_out=None) -> wp.array:
    """Per point, the largest angle (degrees) between the rays from the centres of its valid views
    to X: (N,) float64.  Inputs as for ``triangulate_dlt``; ``X`` as it returns (or (N, 3) NumPy)."""
    device = wp.get_device(device)
    P = _as_array(P, mat34d, 1, device)
    X = _as_array(X, wp.vec3d, 1, device)
    valid = _as_array(np.asarray(valid).astype(bool) if not isinstance(valid, wp.array) else valid, wp.bool, 2, device)
    if parallax_deg_out is None:
        parallax_deg_out = wp.empty(X.shape[0], dtype=wp.float64, device=device)
    wp.launch(baseline_angles, dim=X.shape[0], inputs=[P, X, valid], outputs=[parallax_deg_out], device=device)
    return parallax_deg_out


@dataclass
class TriangulatedPoints:
    """Views of the Triangulator's buffers for the N reference pixels of the last call (valid
    until the next call).

    X: (N,) vec3d world points; residual_px: (N,) float64 RMS reprojection error over the views
    used; parallax_deg: (N,) float64 baseline angle over them; support: (N,) int32 bit mask of the
    views used (bit 0 the reference, bit n + 1 neighbour n; the Seeder samples colours there);
    valid: (N,) int32, 1 where a hypothesis passed the parallax and reprojection tests.
    """

    X: wp.array
    residual_px: wp.array
    parallax_deg: wp.array
    support: wp.array
    valid: wp.array

    @classmethod
    def zeros(cls, n: int, device) -> TriangulatedPoints:
        """N zeroed points on ``device`` (none valid)."""
        kw = {"device": device}
        return cls(
            wp.zeros(n, dtype=wp.vec3d, **kw),
            wp.zeros(n, dtype=wp.float64, **kw),
            wp.zeros(n, dtype=wp.float64, **kw),
            wp.zeros(n, dtype=wp.int32, **kw),
            wp.zeros(n, dtype=wp.int32, **kw),
        )


class Triangulator:
    """Triangulates the dense matches of a reference keyframe against its neighbours.

    Each neighbour n with a confident match gives one two-view hypothesis (reference + n).  It is
    rejected when its baseline angle is below ``min_parallax_deg`` or its reprojection error in
    either view exceeds ``max_reproj_px``.  The other neighbours whose match lies within
    ``max_reproj_px`` of its projection vote for it, and it is re-solved jointly over the reference,
    n and its voters (kept when every view stays within ``max_reproj_px``, else it stays two-view).
    The hypothesis with the most views wins, ties broken by the smallest RMS reprojection error:
    the supplement's rule, to which this reduces when no neighbour votes.

    Why two-view hypotheses rather than one joint DLT over all matches: the DLT is least squares,
    so one wrong match among M spoils the joint solution, whereas it only spoils its own
    hypothesis here; the votes catch the wrong matches that slide along their epipolar line (a
    two-view residual cannot see them), and the joint re-solve recovers the accuracy of all views.
    Cost: at most 2M small solves per pixel.
    """

    def __init__(self, cfg: TriangulationConfig, device=None):
        self.cfg = cfg
        self.device = wp.get_device(device)
        self._capacity = 0
        self._ensure(1)

    def _ensure(self, n: int) -> None:
        if n <= self._capacity:
            return
        cap = grown_capacity(self._capacity, n, minimum=1024)
        self._points = TriangulatedPoints.zeros(cap, self.device)
        self._capacity = cap

    def triangulate(
        self, P: wp.array, ref_uv: wp.array, match_uv: wp.array, confidence: wp.array
    ) -> TriangulatedPoints:
        """P: (1 + M,) ``mat34d`` projection matrices, the reference first, then the M neighbours;
        ref_uv: (N,) ``wp.vec2d`` reference pixels; match_uv: (N, M) ``wp.vec2d`` their matches in
        each neighbour; confidence: (N, M) float32 match confidence (Eq. 12), 0 = no match.
        All on this stage's device.  M <= 30 (views are bits of an int32)."""
        n, m = match_uv.shape
        if P.shape[0] != m + 1 or m > 30:
            raise ValueError(f"P must hold the reference and the {m} neighbours (M <= 30), got {P.shape[0]} matrices")
        self._ensure(n)
        p = self._points
        out = TriangulatedPoints(p.X[:n], p.residual_px[:n], p.parallax_deg[:n], p.support[:n], p.valid[:n])
        wp.launch(
            triangulate_hypotheses,
            dim=n,
            inputs=[P, ref_uv, match_uv, confidence, self.cfg.min_parallax_deg, self.cfg.max_reproj_px],
            outputs=[out.X, out.residual_px, out.parallax_deg, out.support, out.valid],
            device=self.device,
        )
        return out
