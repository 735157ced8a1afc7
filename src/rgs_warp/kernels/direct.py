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
"""

import warp as wp

from rgs_warp.kernels.math import block_sum, grey_bilinear, grey_level, rigid_inverse_f32, sample_depth, se3_exp

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
def add_residual(s: vec46, J: vec8, r: float, sigma: float) -> vec46:
    """``s`` plus one residual's share of the normal equations: J^T w J (upper triangle), J^T w r, cost."""
    e = r / sigma
    w = robust_weight(e) / (sigma * sigma)
    out = s
    k = int(0)
    for i in range(N_PARAMS):
        for j in range(i, N_PARAMS):
            out[k] = out[k] + w * J[i] * J[j]
            k += 1
    for i in range(N_PARAMS):
        out[S_GRAD + i] = out[S_GRAD + i] + w * J[i] * r
    out[S_COST] = out[S_COST] + robust_cost(e)
    return out


@wp.kernel
def normal_equations(
    # in: the reference (render per opacity; depth 0 = no reference) and the frame at this level
    ref_rgb: wp.array2d(dtype=wp.vec3),
    ref_depth: wp.array2d(dtype=wp.float32),
    rgb: wp.array2d(dtype=wp.vec3),
    depth: wp.array2d(dtype=wp.float32),
    has_depth: int,
    # intrinsics (fx, fy, cx, cy) of this level, shared by reference and frame
    intrinsics: wp.vec4,
    # the frame's camera from the reference's, and (g, b)
    T_rel: wp.array(dtype=wp.mat44d),
    affine: wp.array(dtype=wp.float64),
    # out: N_COLUMNS sums (zeroed beforehand)
    sums: wp.array(dtype=wp.float64),
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
                    if has_depth != 0:
                        dz = sample_depth(depth, u, v, DEPTH_EDGE_SPREAD)
                        if dz > 0.0 and wp.abs(dz - z) > MAX_DEPTH_GAP * z:
                            use = 0  # another surface in front of (or behind) the point: occluded
                        right = sample_depth(depth, u + 1.0, v, DEPTH_EDGE_SPREAD)
                        left = sample_depth(depth, u - 1.0, v, DEPTH_EDGE_SPREAD)
                        down = sample_depth(depth, u, v + 1.0, DEPTH_EDGE_SPREAD)
                        up = sample_depth(depth, u, v - 1.0, DEPTH_EDGE_SPREAD)
                        if use != 0 and dz > 0.0 and wp.min(wp.min(right, left), wp.min(down, up)) > 0.0:
                            a = 0.5 * (right - left) * du + 0.5 * (down - up) * dv - wp.vec3(0.0, 0.0, 1.0)
                            b = wp.cross(q, a)
                            J = vec8(a[0], a[1], a[2], b[0], b[1], b[2], 0.0, 0.0)
                            s = add_residual(s, J, dz - z, SIGMA_DEPTH * d)
                    if use != 0:
                        g = float(affine[0])
                        bias = float(affine[1])
                        i_ref = grey_level(ref_rgb[y, x])
                        gx = 0.5 * (grey_bilinear(rgb, u + 1.0, v) - grey_bilinear(rgb, u - 1.0, v))
                        gy = 0.5 * (grey_bilinear(rgb, u, v + 1.0) - grey_bilinear(rgb, u, v - 1.0))
                        a = gx * du + gy * dv
                        b = wp.cross(q, a)
                        J = vec8(a[0], a[1], a[2], b[0], b[1], b[2], -i_ref, -1.0)
                        s = add_residual(s, J, grey_bilinear(rgb, u, v) - (g * i_ref + bias), SIGMA_COLOUR)
                        s[S_COUNT] = 1.0
    total = block_sum(s)
    if lane == 0:
        for c in range(N_COLUMNS):
            wp.atomic_add(sums, c, wp.float64(total[c]))


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
