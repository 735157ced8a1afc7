"""Batched homogeneous DLT triangulation in float64, one point per thread (supplement §4.4).

The construction, shared with the NumPy reference of ``tests/test_triangulation.py``:

* World normalisation.  With c the centroid of the centres of the views used and s their RMS
  distance to c (1 when they coincide), X = s X' + c, i.e. P'_v = P_v [[s I, c], [0, 1]].  The solve
  is then independent of the world's origin and unit (a monocular map has an arbitrary scale, and a
  world origin far from the cameras would otherwise dominate the fourth column of A).
* Rows.  u p'_3 - p'_1 and v p'_3 - p'_2 for each view, each scaled to unit norm so that every
  view weighs the same whatever its intrinsics and pixel coordinates (the "unit-norm rows"
  conditioning; pixel scaling is then irrelevant).
* Solve.  The smallest right singular vector of A (2V x 4): the rows are rotated into a 4x4 upper
  triangle R as they are produced (streaming Givens QR, A = QR, nothing of A is stored), then R's
  SVD by one-sided (Hestenes) Jacobi.  This never forms A^T A, so its error stays that of an SVD
  of A (~eps * sigma_1 / sigma_3) where the normal equations' is ~eps * (sigma_1 / sigma_3)^2.
  Measured against ``numpy.linalg.svd`` (rays 0.05 deg apart, 300 points): without the world
  normalisation (origin 100 m away) a Jacobi eigen-solve of A^T A is off by 1.2e-8 relative, the
  QR route by 1.2e-13; with the normalisation both agree to ~1e-11 (the remaining error is the
  dehomogenisation of far points, ~eps * distance / baseline).  The normalisation is what makes the
  problem well conditioned; the QR route is the margin for the cases it does not cover.

A solution is degenerate when its homogeneous w vanishes (the point lies at more than 1e12
baselines, i.e. the rays are parallel) or when it lies behind one of the cameras used.
"""

import warp as wp

wp.set_module_options({"enable_backward": False})

mat34d = wp.types.matrix(shape=(3, 4), dtype=wp.float64)

# One-sided Jacobi stops when every column pair is orthogonal to machine precision; 4 columns
# converge quadratically in 3-5 sweeps, 12 only bounds pathological (NaN) input.
JACOBI_SWEEPS = 12
JACOBI_TOL = wp.constant(wp.float64(1.0e-15))
# |w| / |h| below this puts the point beyond 1e12 normalised units (baselines) from the cameras.
MIN_W = wp.constant(wp.float64(1.0e-12))
RAD_TO_DEG = wp.constant(wp.float64(57.29577951308232))


@wp.func
def camera_centre(P: mat34d) -> wp.vec3d:
    """Centre C of a finite camera: P (C, 1) = 0, C = -M^-1 p4."""
    M = wp.mat33d(P[0, 0], P[0, 1], P[0, 2], P[1, 0], P[1, 1], P[1, 2], P[2, 0], P[2, 1], P[2, 2])
    return -(wp.inverse(M) @ wp.vec3d(P[0, 3], P[1, 3], P[2, 3]))


@wp.func
def depth_sign(P: mat34d) -> wp.float64:
    """+1 when P = K [R | t] with det(M) > 0; makes (P X)_3 a depth of either sign convention."""
    M = wp.mat33d(P[0, 0], P[0, 1], P[0, 2], P[1, 0], P[1, 1], P[1, 2], P[2, 0], P[2, 1], P[2, 2])
    return wp.where(wp.determinant(M) < wp.float64(0.0), wp.float64(-1.0), wp.float64(1.0))


@wp.func
def project(P: mat34d, X: wp.vec3d) -> wp.vec3d:
    """(u, v, depth) of world point X."""
    y = P @ wp.vec4d(X[0], X[1], X[2], wp.float64(1.0))
    return wp.vec3d(y[0] / y[2], y[1] / y[2], y[2] * depth_sign(P))


@wp.func
def _givens_add_row(R: wp.mat44d, r: wp.vec4d) -> wp.mat44d:
    """Rotate one more row of A into the upper triangle R (R^T R stays A^T A)."""
    for k in range(4):
        b = r[k]
        if b != wp.float64(0.0):
            a = R[k, k]
            rho = wp.sqrt(a * a + b * b)
            c = a / rho
            s = b / rho
            for j in range(k, 4):
                rk = R[k, j]
                rj = r[j]
                R[k, j] = c * rk + s * rj
                r[j] = c * rj - s * rk
    return R


@wp.func
def dlt_add_view(R: wp.mat44d, P: mat34d, c: wp.vec3d, s: wp.float64, uv: wp.vec2d) -> wp.mat44d:
    """Append the two unit-norm DLT rows of one view, in the normalised world X = s X' + c."""
    for k in range(2):
        r = wp.vec4d(
            uv[k] * P[2, 0] - P[k, 0],
            uv[k] * P[2, 1] - P[k, 1],
            uv[k] * P[2, 2] - P[k, 2],
            uv[k] * P[2, 3] - P[k, 3],
        )
        # (r_xyz, r_w) [[s I, c], [0, 1]] = (s r_xyz, r_xyz . c + r_w)
        rn = wp.vec4d(s * r[0], s * r[1], s * r[2], r[0] * c[0] + r[1] * c[1] + r[2] * c[2] + r[3])
        R = _givens_add_row(R, rn / wp.length(rn))
    return R


@wp.func
def smallest_right_singular_vector(R: wp.mat44d) -> wp.vec4d:
    """Unit right singular vector of R for its smallest singular value (one-sided Jacobi)."""
    Vm = wp.identity(n=4, dtype=wp.float64)
    for _sweep in range(JACOBI_SWEEPS):
        rotated = int(0)
        for p in range(3):
            for q in range(p + 1, 4):
                alpha = wp.float64(0.0)
                beta = wp.float64(0.0)
                gamma = wp.float64(0.0)
                for i in range(4):
                    alpha += R[i, p] * R[i, p]
                    beta += R[i, q] * R[i, q]
                    gamma += R[i, p] * R[i, q]
                if wp.abs(gamma) > JACOBI_TOL * wp.sqrt(alpha * beta):
                    rotated = 1
                    zeta = (beta - alpha) / (wp.float64(2.0) * gamma)
                    t = wp.float64(1.0) / (wp.abs(zeta) + wp.sqrt(wp.float64(1.0) + zeta * zeta))
                    if zeta < wp.float64(0.0):
                        t = -t
                    cs = wp.float64(1.0) / wp.sqrt(wp.float64(1.0) + t * t)
                    sn = cs * t
                    for i in range(4):
                        a = R[i, p]
                        b = R[i, q]
                        R[i, p] = cs * a - sn * b
                        R[i, q] = sn * a + cs * b
                        a = Vm[i, p]
                        b = Vm[i, q]
                        Vm[i, p] = cs * a - sn * b
                        Vm[i, q] = sn * a + cs * b
        if rotated == 0:
            break
    best = int(0)
    best_norm = wp.float64(0.0)
    for j in range(4):
        norm = R[0, j] * R[0, j] + R[1, j] * R[1, j] + R[2, j] * R[2, j] + R[3, j] * R[3, j]
        if j == 0 or norm < best_norm:
            best = j
            best_norm = norm
    return wp.vec4d(Vm[0, best], Vm[1, best], Vm[2, best], Vm[3, best])


@wp.func
def normaliser(P: wp.array(dtype=mat34d), views: int):
    """(c, s) of the world normalisation over the views whose bits are set in ``views``."""
    c = wp.vec3d()
    n = int(0)
    for v in range(P.shape[0]):
        if (views >> v) & 1:
            c += camera_centre(P[v])
            n += 1
    c = c / wp.float64(n)
    ss = wp.float64(0.0)
    for v in range(P.shape[0]):
        if (views >> v) & 1:
            d = camera_centre(P[v]) - c
            ss += wp.dot(d, d)
    s = wp.sqrt(ss / wp.float64(n))
    # Views sharing one centre (pure rotation) triangulate nothing; any unit keeps the algebra finite.
    if s <= wp.float64(0.0):
        s = wp.float64(1.0)
    return c, s


@wp.func
def dehomogenise(h: wp.vec4d, c: wp.vec3d, s: wp.float64):
    """World point of the normalised homogeneous solution h, and whether w is usable."""
    ok = wp.abs(h[3]) > MIN_W
    w = wp.where(ok, h[3], wp.float64(1.0))
    return wp.vec3d(h[0] / w, h[1] / w, h[2] / w) * s + c, ok


@wp.func
def ray_angle_deg(Ca: wp.vec3d, Cb: wp.vec3d, X: wp.vec3d) -> wp.float64:
    """Angle at X between the rays from camera centres Ca and Cb (atan2: accurate when tiny)."""
    a = X - Ca
    b = X - Cb
    return wp.atan2(wp.length(wp.cross(a, b)), wp.dot(a, b)) * RAD_TO_DEG


@wp.func
def max_ray_angle_deg(P: wp.array(dtype=mat34d), views: int, X: wp.vec3d) -> wp.float64:
    """Baseline angle of X: the largest angle between rays from the centres of the views used."""
    best = wp.float64(0.0)
    for a in range(P.shape[0]):
        if (views >> a) & 1:
            Ca = camera_centre(P[a])
            for b in range(a + 1, P.shape[0]):
                if (views >> b) & 1:
                    best = wp.max(best, ray_angle_deg(Ca, camera_centre(P[b]), X))
    return best


@wp.func
def observed_views(valid: wp.array2d(dtype=wp.bool), i: int, n_views: int):
    """Bit mask of the views (of ``n_views``) that observe point i, and their number."""
    views = int(0)
    n = int(0)
    for v in range(n_views):
        if valid[i, v]:
            views = views | (1 << v)
            n += 1
    return views, n


@wp.kernel
def triangulate_points(
    # in:
    P: wp.array(dtype=mat34d),
    x: wp.array2d(dtype=wp.vec2d),
    valid: wp.array2d(dtype=wp.bool),
    # out:
    X_out: wp.array(dtype=wp.vec3d),
    residual_px_out: wp.array(dtype=wp.float64),
):
    """One point per thread: joint DLT over its valid views and the RMS reprojection error over
    them; the residual is +inf when fewer than two views or the solution is degenerate, and X is
    NaN when it is undefined (fewer than two views, w ~ 0)."""
    i = wp.tid()
    views, n = observed_views(valid, i, P.shape[0])
    nan = wp.float64(wp.nan)
    X = wp.vec3d(nan, nan, nan)
    residual = wp.float64(wp.inf)
    if n >= 2:
        c, s = normaliser(P, views)
        R = wp.mat44d()
        for v in range(P.shape[0]):
            if (views >> v) & 1:
                R = dlt_add_view(R, P[v], c, s, x[i, v])
        Xh, w_ok = dehomogenise(smallest_right_singular_vector(R), c, s)
        # The depth test gets its own flag: when an ``if``'s condition variable is reassigned in a
        # loop inside its body, Warp 1.19 discards the branch's assignments (checked).
        in_front = w_ok
        sq = wp.float64(0.0)
        for v in range(P.shape[0]):
            if (views >> v) & 1:
                q = project(P[v], Xh)
                in_front = in_front and q[2] > wp.float64(0.0)
                d = wp.vec2d(q[0], q[1]) - x[i, v]
                sq += wp.dot(d, d)
        X = wp.where(w_ok, Xh, X)
        residual = wp.where(in_front, wp.sqrt(sq / wp.float64(n)), residual)
    X_out[i] = X
    residual_px_out[i] = residual


@wp.kernel
def baseline_angles(
    # in:
    P: wp.array(dtype=mat34d),
    X: wp.array(dtype=wp.vec3d),
    valid: wp.array2d(dtype=wp.bool),
    # out:
    parallax_deg_out: wp.array(dtype=wp.float64),
):
    i = wp.tid()
    views, _n = observed_views(valid, i, P.shape[0])
    parallax_deg_out[i] = max_ray_angle_deg(P, views, X[i])


@wp.func
def _observation(ref_uv: wp.array(dtype=wp.vec2d), match_uv: wp.array2d(dtype=wp.vec2d), i: int, v: int):
    """Pixel of point i in view v of the Triangulator's layout (view 0 = reference, v = neighbour v-1)."""
    if v == 0:
        return ref_uv[i]
    return match_uv[i, v - 1]


@wp.func
def _triangulate_views(
    P: wp.array(dtype=mat34d),
    views: int,
    ref_uv: wp.array(dtype=wp.vec2d),
    match_uv: wp.array2d(dtype=wp.vec2d),
    i: int,
):
    """DLT over ``views``: (X, RMS error px, largest per-view error px); errors +inf if degenerate."""
    c, s = normaliser(P, views)
    R = wp.mat44d()
    for v in range(P.shape[0]):
        if (views >> v) & 1:
            R = dlt_add_view(R, P[v], c, s, _observation(ref_uv, match_uv, i, v))
    X, ok = dehomogenise(smallest_right_singular_vector(R), c, s)
    sq = wp.float64(0.0)
    worst = wp.float64(0.0)
    n = int(0)
    for v in range(P.shape[0]):
        if (views >> v) & 1:
            q = project(P[v], X)
            ok = ok and q[2] > wp.float64(0.0)
            e = wp.length(wp.vec2d(q[0], q[1]) - _observation(ref_uv, match_uv, i, v))
            sq += e * e
            worst = wp.max(worst, e)
            n += 1
    inf = wp.float64(wp.inf)
    return X, wp.where(ok, wp.sqrt(sq / wp.float64(n)), inf), wp.where(ok, worst, inf)


@wp.kernel
def triangulate_hypotheses(
    # in:
    P: wp.array(dtype=mat34d),
    ref_uv: wp.array(dtype=wp.vec2d),
    match_uv: wp.array2d(dtype=wp.vec2d),
    confidence: wp.array2d(dtype=wp.float32),
    min_parallax_deg: wp.float64,
    max_reproj_px: wp.float64,
    # out:
    X_out: wp.array(dtype=wp.vec3d),
    residual_px_out: wp.array(dtype=wp.float64),
    parallax_deg_out: wp.array(dtype=wp.float64),
    support_out: wp.array(dtype=wp.int32),
    valid_out: wp.array(dtype=wp.int32),
):
    """Per reference pixel: one two-view hypothesis per matched neighbour, each grown into the
    joint solution over the neighbours that agree with it, the best kept (see ``Triangulator``)."""
    i = wp.tid()
    M = match_uv.shape[1]
    best_views = int(0)
    best_count = int(0)
    best_X = wp.vec3d()
    best_rms = wp.float64(wp.inf)
    C0 = camera_centre(P[0])
    for n in range(M):
        if confidence[i, n] > wp.float32(0.0):
            views = 1 | (1 << (n + 1))
            X, rms, worst = _triangulate_views(P, views, ref_uv, match_uv, i)
            if worst <= max_reproj_px and ray_angle_deg(C0, camera_centre(P[n + 1]), X) >= min_parallax_deg:
                # Other neighbours whose match lands where this X projects vote for it: a wrong
                # match sliding along its epipolar line has a tiny two-view residual but no votes.
                support = views
                count = int(2)
                for m in range(M):
                    if m != n and confidence[i, m] > wp.float32(0.0):
                        q = project(P[m + 1], X)
                        if q[2] > wp.float64(0.0):
                            if wp.length(wp.vec2d(q[0], q[1]) - match_uv[i, m]) <= max_reproj_px:
                                support = support | (1 << (m + 1))
                                count += 1
                if count > 2:
                    # The joint solution must itself fit every view it uses; a hypothesis whose
                    # voters only agree with it approximately stays a two-view one.
                    Xj, rms_j, worst_j = _triangulate_views(P, support, ref_uv, match_uv, i)
                    if worst_j <= max_reproj_px:
                        X = Xj
                        rms = rms_j
                        views = support
                    else:
                        count = 2
                if count > best_count or (count == best_count and rms < best_rms):
                    best_views = views
                    best_count = count
                    best_X = X
                    best_rms = rms
    X_out[i] = best_X
    residual_px_out[i] = best_rms
    parallax_deg_out[i] = wp.where(best_count > 0, max_ray_angle_deg(P, best_views, best_X), wp.float64(0.0))
    support_out[i] = best_views
    valid_out[i] = wp.where(best_count > 0, 1, 0)
