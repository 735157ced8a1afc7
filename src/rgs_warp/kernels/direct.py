"""Kernels of tracking's direct alignment (direct_align.py): Gauss-Newton of a frame
against one render of the map, coarse to fine on an image pyramid, before the Adam steps.

The render at the start pose is the reference: its colour and depth (divided by the opacity) give a 3D
point for every pixel the map covers.  The point goes through the relative pose ``T_rel`` (this frame's
camera from the render's) into the frame, whose grey level (and measured depth, RGB-D) there is compared
with the reference's: r_c = I(u') - (g I_ref(u) + b) and r_d = D(u') - z'.  The unknowns are the twist of
``T_rel`` (left update, as the Adam steps) and the affine brightness (g, b) of Eq. 3.  Residuals are
scaled by their noise (``SIGMA_COLOUR``; depth: ``SIGMA_DEPTH`` x the reference's depth) and weighted
by Huber's function (``HUBER``); pixels whose measured depth is far from the point (``MAX_DEPTH_GAP``) are taken
for occlusions and left out.  The normal equations go to ``N_COLUMNS`` float64 sums (one atomic per block
and column); one thread solves them and moves the pose on the device, so no step reads back to the host.

Geometric mode (``DEPTH_GEOMETRIC``, ``tracking.geometric``): the depth enters point to plane instead
(``geometric_equations``): every frame pixel's measured point, through ``T_rel``'s inverse into the
reference, against the plane of the reference pixel it projects to (normal from the reference's depth by
central differences), r_g = n . (T_rel^-1 q - p), scaled by the measured depth's noise sigma(z)
(``math.depth_sigma``) and down-weighted at depth edges (``edge_weight``).  Both terms' residuals are then
counted in a histogram, whose median gives each term's noise scale (``solve_scales``, MAD): the colour's
sigma and the geometric residuals' scale in units of sigma(z), so the two terms weigh by their noise.
"""

import warp as wp

from rgs_warp.kernels.math import (
    TERM_COLOUR,
    TERM_GEOMETRIC,
    block_sum,
    depth_sigma,
    grey_bilinear,
    grey_level,
    rigid_inverse_f32,
    sample_depth,
    se3_exp,
)

# threads a block of ``normal_equations`` (launch_tiled): 46 float32 sums a thread stay within shared memory.
# The module's default too, so that the run's preload (rgs_warp.compile) compiles this variant, and every
# launch of the module's kernels passes it (wp.launch's own default is 256 on CUDA, which compiled the
# module a second time in the first tracked frame: 3.3 s on an H100)
BLOCK = 128

wp.set_module_options({"enable_backward": False, "block_dim": BLOCK})

# Unknowns: twist (rho, phi) of T_rel, then gain g and bias b.  Sums: the upper triangle of J^T W J (36),
# J^T W r (8), the robust cost, the pixels used.
N_PARAMS = 8
N_UPPER = N_PARAMS * (N_PARAMS + 1) // 2
S_GRAD = N_UPPER
S_COST = 44
S_COUNT = 45
N_COLUMNS = 46
# Residual noise: grey levels (0..1), and depth relative to the depth (1 % at 1 m: the office's exact depth
# and a Kinect's both sit within it); Huber's threshold in units of the noise
SIGMA_COLOUR = 0.02
SIGMA_DEPTH = 0.01
HUBER = 2.0
# a measured depth further than this fraction from the warped point's: another surface (occlusion) there
MAX_DEPTH_GAP = 0.1
# a depth sample whose 2x2 neighbourhood spreads more than this fraction of its mean is on an edge: not
# interpolated (math.sample_depth, as the matcher's)
DEPTH_EDGE_SPREAD = 0.05
# fewer pixels than this, or a non-finite system: the step is not taken
MIN_PIXELS = 64
# Levenberg-Marquardt damping of the diagonal (a GN step where the data constrain it)
DAMPING = 1.0e-4
# the largest step one iteration takes (the prediction is millimetres off; a pyramid level's few steps
# must not run away on a bad linearisation)
MAX_STEP_M = 0.05
MAX_STEP_RAD = 0.05

# What the frame's depth does in ``normal_equations``: nothing (colour only); the projective residual
# r_d = D(u') - z' and the occlusion test; the occlusion test only (the depth enters point to plane,
# ``geometric_equations``, and the colour residuals' noise is estimated, ``solve_scales``)
DEPTH_NONE = 0
DEPTH_PROJECTIVE = 1
DEPTH_GEOMETRIC = 2
# A surface sloping more than this (|grad D| f / D, about tan of the incidence angle: 63 deg) or a depth
# edge (a jump of many footprints) loses its weight: 1 / (1 + (slope / (EDGE_SLOPE + noise slope))^2)
EDGE_SLOPE = 2.0
# Noise scales (``scales``, math.TERM_*): estimated from a histogram of |r| per term, HIST_BINS bins
# HIST_PER_OCTAVE a factor of 2 from 2^HIST_MIN_LOG2 (1e-6 .. 4096): sigma = MAD_TO_SIGMA x the median,
# at least the floors (half an 8-bit grey level; a tenth of the depth noise model's)
HIST_BINS = 128
HIST_PER_OCTAVE = 4.0
HIST_MIN_LOG2 = -20.0
MAD_TO_SIGMA = 1.4826
SIGMA_COLOUR_MIN = 0.002
GEOMETRIC_SCALE_MIN = 0.1

vec46 = wp.types.vector(length=N_COLUMNS, dtype=wp.float32)
vec8 = wp.types.vector(length=N_PARAMS, dtype=wp.float32)
vec8d = wp.types.vector(length=N_PARAMS, dtype=wp.float64)
mat88d = wp.types.matrix(shape=(N_PARAMS, N_PARAMS), dtype=wp.float64)


@wp.kernel
def reference_image(
    # in: the map's render (colour and depth accumulated over opacity, not normalised)
    color: wp.array2d(dtype=wp.vec3),
    depth: wp.array2d(dtype=wp.float32),
    alpha: wp.array2d(dtype=wp.float32),
    min_alpha: float,
    # out: colour and depth per opacity where the opacity reaches min_alpha, else 0 (no reference there)
    rgb_out: wp.array2d(dtype=wp.vec3),
    depth_out: wp.array2d(dtype=wp.float32),
):
    y, x = wp.tid()
    a = alpha[y, x]
    if a >= min_alpha and a > 0.0:
        rgb_out[y, x] = color[y, x] / a
        depth_out[y, x] = depth[y, x] / a
    else:
        rgb_out[y, x] = wp.vec3(0.0)
        depth_out[y, x] = 0.0


@wp.func
def robust_weight(e: float) -> float:
    """Huber's weight of a residual ``e`` in units of its noise (IRLS)."""
    a = wp.abs(e)
    return wp.where(a <= HUBER, 1.0, HUBER / a)


@wp.func
def robust_cost(e: float) -> float:
    a = wp.abs(e)
    return wp.where(a <= HUBER, 0.5 * a * a, HUBER * (a - 0.5 * HUBER))


@wp.func
def add_residual(s: vec46, J: vec8, r: float, sigma: float, weight: float) -> vec46:
    """``s`` plus one residual's share of the normal equations: J^T w J (upper triangle), J^T w r, cost;
    ``weight`` multiplies its IRLS weight and cost (1: a full residual)."""
    e = r / sigma
    w = weight * robust_weight(e) / (sigma * sigma)
    out = s
    k = int(0)
    for i in range(N_PARAMS):
        for j in range(i, N_PARAMS):
            out[k] = out[k] + w * J[i] * J[j]
            k += 1
    for i in range(N_PARAMS):
        out[S_GRAD + i] = out[S_GRAD + i] + w * J[i] * r
    out[S_COST] = out[S_COST] + weight * robust_cost(e)
    return out


@wp.func
def count_residual(histogram: wp.array2d(dtype=wp.int32), term: int, r: float):
    """One residual of ``term`` into its row of the |r| histogram (log2 bins, ``solve_scales``)."""
    a = wp.abs(r)
    k = int(0)
    if a > 0.0:
        k = int(wp.clamp(wp.floor((wp.log2(a) - HIST_MIN_LOG2) * HIST_PER_OCTAVE), 0.0, float(HIST_BINS - 1)))
    wp.atomic_add(histogram, term, k, 1)


@wp.kernel
def normal_equations(
    # in: the reference (render per opacity; depth 0 = no reference) and the frame at this level
    ref_rgb: wp.array2d(dtype=wp.vec3),
    ref_depth: wp.array2d(dtype=wp.float32),
    rgb: wp.array2d(dtype=wp.vec3),
    depth: wp.array2d(dtype=wp.float32),
    depth_mode: int,  # DEPTH_NONE, DEPTH_PROJECTIVE or DEPTH_GEOMETRIC
    # intrinsics (fx, fy, cx, cy) of this level, shared by reference and frame
    intrinsics: wp.vec4,
    # the frame's camera from the reference's, and (g, b)
    T_rel: wp.array(dtype=wp.mat44d),
    affine: wp.array(dtype=wp.float64),
    # noise scales (math.N_TERMS): the colour residuals' sigma at TERM_COLOUR
    scales: wp.array(dtype=wp.float32),
    # out: N_COLUMNS sums (zeroed beforehand); DEPTH_GEOMETRIC: the colour residuals' |r| histogram row
    sums: wp.array(dtype=wp.float64),
    histogram_out: wp.array2d(dtype=wp.int32),
):
    block, lane = wp.tid()
    width = ref_rgb.shape[1]
    height = ref_rgb.shape[0]
    i = block * BLOCK + lane
    s = vec46()
    if i < width * height:
        y = i // width
        x = i - y * width
        d = ref_depth[y, x]
        fx = intrinsics[0]
        fy = intrinsics[1]
        cx = intrinsics[2]
        cy = intrinsics[3]
        if d > 0.0:
            T = T_rel[0]
            p = wp.vec3(d * (float(x) - cx) / fx, d * (float(y) - cy) / fy, d)
            q = wp.vec3(
                float(T[0, 0]) * p[0] + float(T[0, 1]) * p[1] + float(T[0, 2]) * p[2] + float(T[0, 3]),
                float(T[1, 0]) * p[0] + float(T[1, 1]) * p[1] + float(T[1, 2]) * p[2] + float(T[1, 3]),
                float(T[2, 0]) * p[0] + float(T[2, 1]) * p[1] + float(T[2, 2]) * p[2] + float(T[2, 3]),
            )
            z = q[2]
            if z > 1.0e-3:
                u = fx * q[0] / z + cx
                v = fy * q[1] / z + cy
                # central differences one pixel either side: the sample and its neighbours stay inside
                if u >= 1.0 and u <= float(width - 2) and v >= 1.0 and v <= float(height - 2):
                    # d(u, v) / dq
                    du = wp.vec3(fx / z, 0.0, -fx * q[0] / (z * z))
                    dv = wp.vec3(0.0, fy / z, -fy * q[1] / (z * z))
                    use = int(1)
                    if depth_mode != DEPTH_NONE:
                        dz = sample_depth(depth, u, v, DEPTH_EDGE_SPREAD)
                        if dz > 0.0 and wp.abs(dz - z) > MAX_DEPTH_GAP * z:
                            use = 0  # another surface in front of (or behind) the point: occluded
                        if depth_mode == DEPTH_PROJECTIVE:
                            right = sample_depth(depth, u + 1.0, v, DEPTH_EDGE_SPREAD)
                            left = sample_depth(depth, u - 1.0, v, DEPTH_EDGE_SPREAD)
                            down = sample_depth(depth, u, v + 1.0, DEPTH_EDGE_SPREAD)
                            up = sample_depth(depth, u, v - 1.0, DEPTH_EDGE_SPREAD)
                            if use != 0 and dz > 0.0 and wp.min(wp.min(right, left), wp.min(down, up)) > 0.0:
                                a = 0.5 * (right - left) * du + 0.5 * (down - up) * dv - wp.vec3(0.0, 0.0, 1.0)
                                b = wp.cross(q, a)
                                J = vec8(a[0], a[1], a[2], b[0], b[1], b[2], 0.0, 0.0)
                                s = add_residual(s, J, dz - z, SIGMA_DEPTH * d, 1.0)
                    if use != 0:
                        g = float(affine[0])
                        bias = float(affine[1])
                        i_ref = grey_level(ref_rgb[y, x])
                        gx = 0.5 * (grey_bilinear(rgb, u + 1.0, v) - grey_bilinear(rgb, u - 1.0, v))
                        gy = 0.5 * (grey_bilinear(rgb, u, v + 1.0) - grey_bilinear(rgb, u, v - 1.0))
                        a = gx * du + gy * dv
                        b = wp.cross(q, a)
                        J = vec8(a[0], a[1], a[2], b[0], b[1], b[2], -i_ref, -1.0)
                        r = grey_bilinear(rgb, u, v) - (g * i_ref + bias)
                        s = add_residual(s, J, r, scales[TERM_COLOUR], 1.0)
                        s[S_COUNT] = 1.0
                        if depth_mode == DEPTH_GEOMETRIC:
                            count_residual(histogram_out, TERM_COLOUR, r)
    total = block_sum(s)
    if lane == 0:
        for c in range(N_COLUMNS):
            wp.atomic_add(sums, c, wp.float64(total[c]))


@wp.func
def backproject(x: float, y: float, z: float, intrinsics: wp.vec4) -> wp.vec3:
    """The camera-frame point at depth ``z`` on the ray of image point (x, y)."""
    return wp.vec3(z * (x - intrinsics[2]) / intrinsics[0], z * (y - intrinsics[3]) / intrinsics[1], z)


@wp.func
def edge_weight(depth: wp.array2d(dtype=wp.float32), x: int, y: int, intrinsics: wp.vec4, noise: float) -> float:
    """1 / (1 + (s / (EDGE_SLOPE + s_noise))^2) of the slope s = |grad D| f / D at pixel (x, y) (central
    differences), s_noise = noise f / D the slope a depth noise ``noise`` (m) alone shows; 0 on the border,
    without depth or next to a pixel without depth (missing depth gathers at edges and in shadows)."""
    h = depth.shape[0]
    w = depth.shape[1]
    weight = float(0.0)
    if x >= 1 and y >= 1 and x <= w - 2 and y <= h - 2:
        d = depth[y, x]
        left = depth[y, x - 1]
        right = depth[y, x + 1]
        up = depth[y - 1, x]
        down = depth[y + 1, x]
        if d > 0.0 and wp.min(wp.min(left, right), wp.min(up, down)) > 0.0:
            sx = 0.5 * (right - left) * intrinsics[0] / d
            sy = 0.5 * (down - up) * intrinsics[1] / d
            limit = EDGE_SLOPE + noise * 0.5 * (intrinsics[0] + intrinsics[1]) / d
            weight = 1.0 / (1.0 + (sx * sx + sy * sy) / (limit * limit))
    return weight


@wp.func
def depth_normal(depth: wp.array2d(dtype=wp.float32), x: int, y: int, intrinsics: wp.vec4) -> wp.vec3:
    """Unit normal at pixel (x, y) of the surface back-projected from ``depth``: the cross product of central
    differences of its 4-neighbours' points (which the caller has checked have depth)."""
    u = float(x)
    v = float(y)
    tx = backproject(u + 1.0, v, depth[y, x + 1], intrinsics) - backproject(u - 1.0, v, depth[y, x - 1], intrinsics)
    ty = backproject(u, v + 1.0, depth[y + 1, x], intrinsics) - backproject(u, v - 1.0, depth[y - 1, x], intrinsics)
    return wp.normalize(wp.cross(tx, ty))


@wp.func
def point_to_plane(
    ref_depth: wp.array2d(dtype=wp.float32),
    depth: wp.array2d(dtype=wp.float32),
    x: int,
    y: int,
    intrinsics: wp.vec4,
    T: wp.mat44d,
):
    """Frame pixel (x, y) against the reference: r = n . (T^-1 q - p), q the frame's measured point, p and n the
    point and normal of the reference pixel nearest to where T^-1 q projects (projective association, held
    in the derivative); J = (-m, m x q, 0, 0) its derivative under the left twist T -> Exp(xi) T, m = R n
    the normal in the frame's camera; sigma(z) of the measured depth; the pair's weight (the frame's and the
    reference's ``edge_weight``), 0 for no residual: no depth or an edge, outside the reference or none
    there, or points further apart in depth than MAX_DEPTH_GAP (an occlusion)."""
    r = float(0.0)
    J = vec8()
    weight = float(0.0)
    z = depth[y, x]
    sigma = depth_sigma(z)
    w_frame = edge_weight(depth, x, y, intrinsics, sigma)
    if w_frame > 0.0:
        q = backproject(float(x), float(y), z, intrinsics)
        R = wp.mat33(
            float(T[0, 0]), float(T[0, 1]), float(T[0, 2]),
            float(T[1, 0]), float(T[1, 1]), float(T[1, 2]),
            float(T[2, 0]), float(T[2, 1]), float(T[2, 2]),
        )  # fmt: skip
        t = wp.vec3(float(T[0, 3]), float(T[1, 3]), float(T[2, 3]))
        p_frame = wp.transpose(R) @ (q - t)  # the measured point in the reference's camera
        if p_frame[2] > 1.0e-3:
            u = intrinsics[0] * p_frame[0] / p_frame[2] + intrinsics[2]
            v = intrinsics[1] * p_frame[1] / p_frame[2] + intrinsics[3]
            if u > -1.0 and v > -1.0 and u < float(ref_depth.shape[1]) and v < float(ref_depth.shape[0]):
                xr = int(wp.floor(u + 0.5))
                yr = int(wp.floor(v + 0.5))
                w_ref = edge_weight(ref_depth, xr, yr, intrinsics, 0.0)
                if w_ref > 0.0:
                    p = backproject(float(xr), float(yr), ref_depth[yr, xr], intrinsics)
                    if wp.abs(p_frame[2] - p[2]) <= MAX_DEPTH_GAP * p[2]:
                        n = depth_normal(ref_depth, xr, yr, intrinsics)
                        r = wp.dot(n, p_frame - p)
                        m = R @ n
                        b = wp.cross(m, q)
                        J = vec8(-m[0], -m[1], -m[2], b[0], b[1], b[2], 0.0, 0.0)
                        weight = w_frame * w_ref
    return r, J, sigma, weight


@wp.kernel
def geometric_equations(
    # in: the reference's depth (render per opacity; 0 = no reference) and the frame's measured depth at
    # this level
    ref_depth: wp.array2d(dtype=wp.float32),
    depth: wp.array2d(dtype=wp.float32),
    # intrinsics (fx, fy, cx, cy) of this level, shared by reference and frame
    intrinsics: wp.vec4,
    # the frame's camera from the reference's
    T_rel: wp.array(dtype=wp.mat44d),
    # noise scales (math.N_TERMS): the geometric residuals' in units of sigma(z) at TERM_GEOMETRIC
    scales: wp.array(dtype=wp.float32),
    # out: the point-to-plane residuals' share added to the N_COLUMNS sums; their |r| / sigma(z) histogram row
    sums: wp.array(dtype=wp.float64),
    histogram_out: wp.array2d(dtype=wp.int32),
):
    # residual r / (sigma(z) scale) under Huber's weight, times the pair's edge weight
    block, lane = wp.tid()
    width = depth.shape[1]
    i = block * BLOCK + lane
    s = vec46()
    if i < width * depth.shape[0]:
        y = i // width
        x = i - y * width
        r, J, sigma, weight = point_to_plane(ref_depth, depth, x, y, intrinsics, T_rel[0])
        if weight > 0.0:
            s = add_residual(s, J, r, sigma * scales[TERM_GEOMETRIC], weight)
            s[S_COUNT] = 1.0
            count_residual(histogram_out, TERM_GEOMETRIC, r / sigma)
    total = block_sum(s)
    if lane == 0:
        for c in range(N_COLUMNS):
            wp.atomic_add(sums, c, wp.float64(total[c]))


@wp.kernel
def solve_scales(
    # in: the |r| histograms of ``normal_equations`` and ``geometric_equations``, a row a term
    histogram: wp.array2d(dtype=wp.int32),
    # in/out: noise scales (math.N_TERMS); a term with fewer than MIN_PIXELS residuals keeps its scale
    scales: wp.array(dtype=wp.float32),
):
    # MAD: the median of |r| (log-uniform within its bin) x MAD_TO_SIGMA, Gaussian-consistent and robust to
    # the outliers that Huber's weights then cut down; at least the term's floor
    term = wp.tid()
    total = int(0)
    for k in range(HIST_BINS):
        total += histogram[term, k]
    if total >= MIN_PIXELS:
        half = 0.5 * float(total)
        below = float(0.0)
        median_log2 = float(0.0)
        found = int(0)
        for k in range(HIST_BINS):
            c = float(histogram[term, k])
            if found == 0 and below + c >= half:
                median_log2 = HIST_MIN_LOG2 + (float(k) + (half - below) / c) / HIST_PER_OCTAVE
                found = 1
            below += c
        floor = wp.where(term == TERM_COLOUR, SIGMA_COLOUR_MIN, GEOMETRIC_SCALE_MIN)
        scales[term] = wp.max(MAD_TO_SIGMA * wp.pow(2.0, median_log2), floor)


@wp.kernel
def solve_step(
    # in: the normal equations of ``normal_equations`` and the render's camera-from-world pose
    sums: wp.array(dtype=wp.float64),
    T_CW_ref: wp.array(dtype=wp.mat44d),
    # in/out: the frame's camera from the reference's, (g, b)
    T_rel: wp.array(dtype=wp.mat44d),
    affine: wp.array(dtype=wp.float64),
    # out: the frame's camera-from-world pose (float64) and its inverse for the renderer (float32)
    T_CW_out: wp.array(dtype=wp.mat44d),
    T_WC_out: wp.array(dtype=wp.mat44),
):
    # Levenberg-Marquardt step (J^T W J + DAMPING diag) delta = -J^T W r by Cholesky; the twist left-multiplies
    # T_rel (x -> Exp(delta) x, as the linearisation d(Exp(delta) q) = rho + phi x q); a step longer than
    # MAX_STEP_M / MAX_STEP_RAD is shortened to it.  Too few pixels or a system that is not positive
    # definite: no step.
    H = mat88d()
    k = int(0)
    for i in range(N_PARAMS):
        for j in range(i, N_PARAMS):
            H[i, j] = sums[k]
            H[j, i] = sums[k]
            k += 1
    ok = sums[S_COUNT] >= wp.float64(MIN_PIXELS)
    for i in range(N_PARAMS):
        H[i, i] = H[i, i] * wp.float64(1.0 + DAMPING) + wp.float64(1.0e-12)
    # Cholesky H = L L^T, in place in the lower triangle
    L = mat88d()
    for j in range(N_PARAMS):
        acc = H[j, j]
        for m in range(j):
            acc = acc - L[j, m] * L[j, m]
        if not (acc > wp.float64(0.0)):
            ok = False
            acc = wp.float64(1.0)
        L[j, j] = wp.sqrt(acc)
        for i in range(j + 1, N_PARAMS):
            acc2 = H[i, j]
            for m in range(j):
                acc2 = acc2 - L[i, m] * L[j, m]
            L[i, j] = acc2 / L[j, j]
    # L y = -g, L^T delta = y
    y = vec8d()
    for i in range(N_PARAMS):
        acc = -sums[S_GRAD + i]
        for m in range(i):
            acc = acc - L[i, m] * y[m]
        y[i] = acc / L[i, i]
    delta = vec8d()
    for ii in range(N_PARAMS):
        i = N_PARAMS - 1 - ii
        acc = y[i]
        for m in range(i + 1, N_PARAMS):
            acc = acc - L[m, i] * delta[m]
        delta[i] = acc / L[i, i]
    rho = wp.vec3d(delta[0], delta[1], delta[2])
    phi = wp.vec3d(delta[3], delta[4], delta[5])
    scale = wp.min(
        wp.float64(1.0),
        wp.min(
            wp.float64(MAX_STEP_M) / (wp.length(rho) + wp.float64(1.0e-30)),
            wp.float64(MAX_STEP_RAD) / (wp.length(phi) + wp.float64(1.0e-30)),
        ),
    )
    for i in range(N_PARAMS):
        if not wp.isfinite(delta[i]):
            ok = False
    if ok:
        T = se3_exp(scale * rho, scale * phi) @ T_rel[0]
        T_rel[0] = T
        affine[0] = affine[0] + scale * delta[6]
        affine[1] = affine[1] + scale * delta[7]
        T_CW = T @ T_CW_ref[0]
        T_CW_out[0] = T_CW
        T_WC_out[0] = rigid_inverse_f32(T_CW)
