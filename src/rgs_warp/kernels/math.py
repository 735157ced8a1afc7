"""Kernel math shared by the stages' kernel files: constants and types of the Gaussian and rasterizer
layout, quaternions, SH constants, SE(3) in float64, the pinhole projection's Jacobian, the block size
of the per-pixel reductions, tracking's depth noise model, and the descriptor similarity, patch ZNCC and
sub-pixel fits of the matching searches.  Stage kernel files import from here and never from each other."""

from typing import Any

import warp as wp

from rgs_warp.config import MAX_PATCH_RADIUS

# ---- per-pixel reductions ------------------------------------------------------------------------
# Reductions over pixels sum REDUCE_BLOCK values in a block tile and issue one float64 atomic per
# block and column, so nothing is read back to the host inside an optimisation loop.
REDUCE_BLOCK = 256


def reduce_blocks(count: int) -> int:
    """Blocks of REDUCE_BLOCK threads that cover ``count`` items (one thread each)."""
    return (int(count) + REDUCE_BLOCK - 1) // REDUCE_BLOCK


# ---- noise of tracking's residuals (kernels/direct.py, kernels/tracking.py) ------------------------
# Axial noise of a structured-light depth camera (Kinect v1; Nguyen, Izadi & Lovell 2012):
# sigma(z) = DEPTH_NOISE_A + DEPTH_NOISE_B (z - DEPTH_NOISE_Z0)^2 metres
DEPTH_NOISE_A = 0.0012
DEPTH_NOISE_B = 0.0019
DEPTH_NOISE_Z0 = 0.4
# The noise scales the direct alignment estimates from its residuals (arrays of N_TERMS): the colour
# residuals' sigma (grey levels) and the depth residuals' in units of sigma(z)
N_TERMS = 2
TERM_COLOUR = 0
TERM_GEOMETRIC = 1


@wp.func
def depth_sigma(z: float) -> float:
    """sigma(z) of the depth noise model (``DEPTH_NOISE_*``), metres."""
    dz = z - DEPTH_NOISE_Z0
    return DEPTH_NOISE_A + DEPTH_NOISE_B * dz * dz


# ---- points out of play in a hash grid ------------------------------------------------------------
# wp.HashGrid wraps cell coordinates modulo its dimensions (128^3 here) and a query walks whole cells,
# so points that take no part in the queries must not share a cell: one shared point made a merge kernel
# walk 600k of them per query (41 ms of an office keyframe on an H100).  They go on this lattice.
HASH_LATTICE = 128


@wp.func
def hash_lattice(i: int) -> wp.vec3:
    """Integer coordinates of point ``i`` on a HASH_LATTICE^3 lattice (unit spacing), one point per
    index up to HASH_LATTICE^3: spaced a few cells apart, they fall in different wrapped cells."""
    return wp.vec3(
        float(i % HASH_LATTICE),
        float((i // HASH_LATTICE) % HASH_LATTICE),
        float((i // (HASH_LATTICE * HASH_LATTICE)) % HASH_LATTICE),
    )


@wp.func
def block_sum(x: Any):
    """Sum of ``x`` (a scalar, vector or matrix) over the threads of the block, as a block tile;
    every thread gets the total.  Launch with ``wp.launch_tiled`` (``block_dim`` threads a block)."""
    return wp.tile_extract(wp.tile_sum(wp.tile(x, preserve_type=True)), 0)


# ---- rasterizer layout (projection.py and rasterize.py) ------------------------------------------
TILE_SIZE = 16
# Skip threshold of the compositing (3DGS): contributions with alpha below 1/255 are invisible in
# 8-bit output and are dropped; the projection's radius is derived from the same threshold.
ALPHA_MIN = 1.0 / 255.0
COV2D_DILATION = 0.3
# Frustum widening for the Jacobian clamp (3DGS/gsplat: 1.3 x the half field of view): bounds the
# linearisation error of Gaussians far outside the image, whose x/z would otherwise explode J.
FRUSTUM_MARGIN = 0.3

# Per-Gaussian screen-space gradient accumulated by the compositing backward:
# (d/du, d/dv, d/dconic_a, d/dconic_b, d/dconic_c, d/dopacity, d/dr, d/dg, d/db, d/ddepth).
vec10 = wp.types.vector(length=10, dtype=wp.float32)
vec6 = wp.types.vector(length=6, dtype=wp.float32)
mat23 = wp.types.matrix(shape=(2, 3), dtype=wp.float32)
# Per-Gaussian pose Jacobian for the pose-only backward, d(screen-space Gaussian)/d(twist):
# [0:3] X (camera frame), [3] 1/z (mean2d and depth follow from these), [4:22] rows of d(conic a, b, c)/dxi,
# [22:31] rows of d(colour r, g, b)/drho (the view direction depends on the camera centre only), [31] unused.
vec32 = wp.types.vector(length=32, dtype=wp.float32)
POSE_JAC_X = 0
POSE_JAC_CONIC = 4
POSE_JAC_COLOR = 22

# ---- spherical harmonics (3DGS's real SH constants and band order) --------------------------------
SH_C0 = 0.28209479177387814
SH_C1 = 0.4886025119029199
SH_C2_0 = 1.0925484305920792
SH_C2_1 = -1.0925484305920792
SH_C2_2 = 0.31539156525252005
SH_C2_3 = -1.0925484305920792
SH_C2_4 = 0.5462742152960396
SH_C3_0 = -0.5900435899266435
SH_C3_1 = 2.890611442640554
SH_C3_2 = -0.4570457994644658
SH_C3_3 = 0.3731763325901154
SH_C3_4 = -0.4570457994644658
SH_C3_5 = 1.445305721320277
SH_C3_6 = -0.5900435899266435


@wp.struct
class CameraParams:
    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    tiles_x: int
    tiles_y: int
    near: float
    # clamp range of x/z and y/z in the projection Jacobian
    tan_x_min: float
    tan_x_max: float
    tan_y_min: float
    tan_y_max: float


def camera_params(camera, near_m: float = 0.0, frustum_margin: float = 0.0) -> CameraParams:
    """The kernels' ``CameraParams`` of a ``types.Camera``: its intrinsics and tile grid, the near
    plane ``near_m``, and the Jacobian's clamp range, the image edges (pixel centres -0.5 .. W-0.5)
    widened by ``frustum_margin`` of the image size (the renderer's FRUSTUM_MARGIN; 0: the image)."""
    p = CameraParams()
    p.fx, p.fy, p.cx, p.cy = camera.fx, camera.fy, camera.cx, camera.cy
    p.width, p.height = camera.width, camera.height
    p.tiles_x = (camera.width + TILE_SIZE - 1) // TILE_SIZE
    p.tiles_y = (camera.height + TILE_SIZE - 1) // TILE_SIZE
    p.near = near_m
    mx = frustum_margin * camera.width
    my = frustum_margin * camera.height
    p.tan_x_min = (-0.5 - mx - camera.cx) / camera.fx
    p.tan_x_max = (camera.width - 0.5 + mx - camera.cx) / camera.fx
    p.tan_y_min = (-0.5 - my - camera.cy) / camera.fy
    p.tan_y_max = (camera.height - 0.5 + my - camera.cy) / camera.fy
    return p


@wp.func
def quat_to_rot(q: wp.quat):
    x = q[0]
    y = q[1]
    z = q[2]
    w = q[3]
    return wp.mat33(
        1.0 - 2.0 * (y * y + z * z),
        2.0 * (x * y - z * w),
        2.0 * (x * z + y * w),
        2.0 * (x * y + z * w),
        1.0 - 2.0 * (x * x + z * z),
        2.0 * (y * z - x * w),
        2.0 * (x * z - y * w),
        2.0 * (y * z + x * w),
        1.0 - 2.0 * (x * x + y * y),
    )


@wp.func
def exp3(v: wp.vec3):
    return wp.vec3(wp.exp(v[0]), wp.exp(v[1]), wp.exp(v[2]))


@wp.func
def grey_level(c: wp.vec3) -> float:
    """Grey level of an RGB colour: the channel mean."""
    return (c[0] + c[1] + c[2]) / 3.0


@wp.func
def bilinear_corner(u: float, v: float, width: int, height: int):
    """Bilinear interpolation at (u, v) on a width x height grid of samples at integer coordinates
    (pixel centres, types.py), (u, v) clamped into the grid (width, height >= 2): the top-left sample
    (x0, y0) and the weights (fx, fy) of ``bilerp``."""
    uc = wp.clamp(u, 0.0, float(width - 1))
    vc = wp.clamp(v, 0.0, float(height - 1))
    x0 = wp.min(int(uc), width - 2)
    y0 = wp.min(int(vc), height - 2)
    return x0, y0, uc - float(x0), vc - float(y0)


@wp.func
def bilerp(p00: Any, p01: Any, p10: Any, p11: Any, fx: float, fy: float):
    """Bilinear blend of the samples at (x0, y0), (x0 + 1, y0), (x0, y0 + 1), (x0 + 1, y0 + 1)."""
    return (1.0 - fy) * ((1.0 - fx) * p00 + fx * p01) + fy * ((1.0 - fx) * p10 + fx * p11)


@wp.func
def grey_bilinear(rgb: wp.array2d(dtype=wp.vec3), u: float, v: float) -> float:
    """Grey level of the bilinear colour at image point (u, v) (clamped into the image)."""
    x0, y0, fx, fy = bilinear_corner(u, v, rgb.shape[1], rgb.shape[0])
    return grey_level(bilerp(rgb[y0, x0], rgb[y0, x0 + 1], rgb[y0 + 1, x0], rgb[y0 + 1, x0 + 1], fx, fy))


@wp.func
def grey_sample(grey: wp.array2d(dtype=wp.float32), u: float, v: float) -> float:
    """Bilinear grey level at image point (u, v) of a grey image (clamped into the image)."""
    x0, y0, fx, fy = bilinear_corner(u, v, grey.shape[1], grey.shape[0])
    return bilerp(grey[y0, x0], grey[y0, x0 + 1], grey[y0 + 1, x0], grey[y0 + 1, x0 + 1], fx, fy)


@wp.func
def sample_depth(depth: wp.array2d(dtype=wp.float32), u: float, v: float, max_rel_spread: float) -> float:
    """Bilinear depth at image point (u, v); 0 where any of the 4 pixels is invalid or they spread by
    more than ``max_rel_spread`` of their mean (a depth edge: interpolating there invents depth)."""
    H = depth.shape[0]
    W = depth.shape[1]
    if u < 0.0 or v < 0.0 or u > float(W - 1) or v > float(H - 1):
        return 0.0
    x0, y0, fx, fy = bilinear_corner(u, v, W, H)
    d00 = depth[y0, x0]
    d01 = depth[y0, x0 + 1]
    d10 = depth[y0 + 1, x0]
    d11 = depth[y0 + 1, x0 + 1]
    lo = wp.min(wp.min(d00, d01), wp.min(d10, d11))
    hi = wp.max(wp.max(d00, d01), wp.max(d10, d11))
    if lo <= 0.0 or hi - lo > max_rel_spread * 0.5 * (hi + lo):
        return 0.0
    return bilerp(d00, d01, d10, d11, fx, fy)


@wp.func
def projection_jacobian(X: wp.vec3, cam: CameraParams):
    z = X[2]
    u = wp.clamp(X[0] / z, cam.tan_x_min, cam.tan_x_max)
    v = wp.clamp(X[1] / z, cam.tan_y_min, cam.tan_y_max)
    return mat23(cam.fx / z, 0.0, -cam.fx * u / z, 0.0, cam.fy / z, -cam.fy * v / z)


@wp.func
def skew_d(v: wp.vec3d):
    z = wp.float64(0.0)
    return wp.mat33d(z, -v[2], v[1], v[2], z, -v[0], -v[1], v[0], z)


@wp.func
def se3_exp(rho: wp.vec3d, phi: wp.vec3d):
    """4x4 exponential of the twist (rho, phi), float64: R = I + A K + B K^2, t = (I + B K + C K^2) rho."""
    theta = wp.length(phi)
    K = skew_d(phi)
    K2 = K @ K
    t2 = theta * theta
    A = wp.float64(1.0) - t2 / wp.float64(6.0)
    B = wp.float64(0.5) - t2 / wp.float64(24.0)
    C = wp.float64(1.0) / wp.float64(6.0) - t2 / wp.float64(120.0)
    if theta > wp.float64(1.0e-3):  # below, the series' next terms are < 1e-16
        A = wp.sin(theta) / theta
        B = (wp.float64(1.0) - wp.cos(theta)) / t2
        C = (theta - wp.sin(theta)) / (t2 * theta)
    eye = wp.identity(n=3, dtype=wp.float64)
    R = eye + A * K + B * K2
    t = (eye + B * K + C * K2) @ rho
    z = wp.float64(0.0)
    o = wp.float64(1.0)
    return wp.mat44d(
        R[0, 0], R[0, 1], R[0, 2], t[0],
        R[1, 0], R[1, 1], R[1, 2], t[1],
        R[2, 0], R[2, 1], R[2, 2], t[2],
        z, z, z, o,
    )  # fmt: skip


@wp.func
def rigid_inverse_f32(T: wp.mat44d):
    """Inverse of a rigid float64 transform, as the float32 matrix the renderer takes."""
    R = wp.mat33d(T[0, 0], T[0, 1], T[0, 2], T[1, 0], T[1, 1], T[1, 2], T[2, 0], T[2, 1], T[2, 2])
    Rt = wp.transpose(R)
    t = -(Rt @ wp.vec3d(T[0, 3], T[1, 3], T[2, 3]))
    return wp.mat44(
        float(Rt[0, 0]), float(Rt[0, 1]), float(Rt[0, 2]), float(t[0]),
        float(Rt[1, 0]), float(Rt[1, 1]), float(Rt[1, 2]), float(t[1]),
        float(Rt[2, 0]), float(Rt[2, 1]), float(Rt[2, 2]), float(t[2]),
        0.0, 0.0, 0.0, 1.0,
    )  # fmt: skip


# ---- descriptor search (kernels/matching.py, kernels/bootstrap.py) ----------------------------------
# Feature pixel (i, j) of stride s is centred at image coordinates (s*j + (s-1)/2, s*i + (s-1)/2);
# searches run on the feature grid and return image pixels.
# Similarity of a query without a match (its segment leaves the image, or it was skipped).
NO_MATCH = wp.constant(-2.0)
# A ZNCC query patch, read once per query (``query_patch``): patch radii up to MAX_PATCH_RADIUS
patch_values = wp.types.vector(length=(2 * MAX_PATCH_RADIUS + 1) ** 2, dtype=wp.float32)


@wp.func
def to_grid(u: float, stride: int) -> float:
    return (u - 0.5 * float(stride - 1)) / float(stride)


@wp.func
def to_image(g: float, stride: int) -> float:
    return g * float(stride) + 0.5 * float(stride - 1)


@wp.func
def similarity(
    query: wp.array2d(dtype=wp.float32), row: int, target: wp.array3d(dtype=wp.float32), y: int, x: int
) -> float:
    """Eq. 10: inner product of L2-normalised descriptors."""
    s = float(0.0)
    for k in range(query.shape[1]):
        s += query[row, k] * target[y, x, k]
    return s


@wp.func
def parabola_peak(s_minus: float, s0: float, s_plus: float) -> float:
    """Offset in [-0.5, 0.5] of the vertex of the parabola through (-1, s-), (0, s0), (1, s+)."""
    curvature = s_minus - 2.0 * s0 + s_plus
    if curvature >= 0.0:
        return 0.0
    return wp.clamp(0.5 * (s_minus - s_plus) / curvature, -0.5, 0.5)


@wp.func
def query_patch(grey: wp.array2d(dtype=wp.float32), q: wp.vec2, radius: int):
    """The (2r+1)^2 grey patch at q (bilinear, row by row; r <= MAX_PATCH_RADIUS), its sum and n
    times its variance: what ``patch_zncc`` needs of the query, read once for all its shifts."""
    a = patch_values()
    sa = float(0.0)
    saa = float(0.0)
    k = int(0)
    for dy in range(-radius, radius + 1):
        for dx in range(-radius, radius + 1):
            v = grey_sample(grey, q[0] + float(dx), q[1] + float(dy))
            a[k] = v
            sa += v
            saa += v * v
            k += 1
    n = float((2 * radius + 1) * (2 * radius + 1))
    return a, sa, saa - sa * sa / n


@wp.func
def patch_zncc(
    a: patch_values,
    sa: float,
    va: float,
    target_grey: wp.array2d(dtype=wp.float32),
    t: wp.vec2,
    radius: int,
) -> float:
    """Zero-mean normalised cross-correlation of the query patch (``query_patch``: values ``a``,
    sum ``sa``, n times its variance ``va``) with the grey (2r+1)^2 patch at t (bilinear); NO_MATCH
    when either patch is flat (below 1e-4 grey-level variance: JPEG noise)."""
    sb = float(0.0)
    sbb = float(0.0)
    sab = float(0.0)
    k = int(0)
    for dy in range(-radius, radius + 1):
        for dx in range(-radius, radius + 1):
            b = grey_sample(target_grey, t[0] + float(dx), t[1] + float(dy))
            sb += b
            sbb += b * b
            sab += a[k] * b
            k += 1
    n = float((2 * radius + 1) * (2 * radius + 1))
    vb = sbb - sb * sb / n
    if va < 1e-4 * n or vb < 1e-4 * n:
        return NO_MATCH
    return (sab - sa * sb / n) / wp.sqrt(va * vb)


@wp.func
def refine_zncc(
    query_grey: wp.array2d(dtype=wp.float32),
    q: wp.vec2,
    target_grey: wp.array2d(dtype=wp.float32),
    coarse: wp.vec2,
    refine_radius: int,
    patch_radius: int,
) -> wp.vec2:
    """Image-resolution refinement of a match around ``coarse`` by patch ZNCC (see
    ``kernels.matching.epipolar_search``) on the grey images (``kernels.matching.grey_image``)."""
    a, sa, va = query_patch(query_grey, q, patch_radius)
    if va < 1e-4 * float((2 * patch_radius + 1) * (2 * patch_radius + 1)):
        return coarse  # a flat query patch: no shift correlates
    best = float(NO_MATCH)
    bx = int(0)
    by = int(0)
    for dy in range(-refine_radius, refine_radius + 1):
        for dx in range(-refine_radius, refine_radius + 1):
            c = patch_zncc(a, sa, va, target_grey, coarse + wp.vec2(float(dx), float(dy)), patch_radius)
            if c > best:
                best = c
                bx = dx
                by = dy
    if best <= NO_MATCH:
        return coarse
    off_x = float(0.0)
    off_y = float(0.0)
    r = patch_radius
    if wp.abs(bx) < refine_radius:
        left = patch_zncc(a, sa, va, target_grey, coarse + wp.vec2(float(bx - 1), float(by)), r)
        right = patch_zncc(a, sa, va, target_grey, coarse + wp.vec2(float(bx + 1), float(by)), r)
        off_x = parabola_peak(left, best, right)
    if wp.abs(by) < refine_radius:
        up = patch_zncc(a, sa, va, target_grey, coarse + wp.vec2(float(bx), float(by - 1)), r)
        down = patch_zncc(a, sa, va, target_grey, coarse + wp.vec2(float(bx), float(by + 1)), r)
        off_y = parabola_peak(up, best, down)
    return coarse + wp.vec2(float(bx) + off_x, float(by) + off_y)
