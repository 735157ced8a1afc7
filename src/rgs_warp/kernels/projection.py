"""Per-Gaussian stages of the rasterizer: EWA projection, SH colour, tile binning, and their backward.

Every adjoint here is written by hand (the pose gradient is the analytic one of supplement §4.2 and
must be reduced per block, which auto-generated adjoints cannot do), so the module compiles no
backward code.

Projection (3DGS, Zwicker et al. EWA splatting), for a Gaussian with mean m, unit quaternion q,
scales s = exp(log_s), camera-from-world rotation W and translation t:
    X = W m + t,  Sigma = R(q) S S^T R(q)^T,  Sigma_c = W Sigma W^T,
    J = [[fx/z, 0, -fx x/z^2], [0, fy/z, -fy y/z^2]]  (x/z, y/z clamped to the widened frustum),
    Sigma_2d = J Sigma_c J^T + 0.3 I  (low-pass dilation),  conic = Sigma_2d^-1,
    mean2d = (fx x/z + cx, fy y/z + cy)  (pixel centres at integer coordinates, see types.py).
"""

import math

import warp as wp

from rgs_warp.kernels.math import (
    ALPHA_MIN,
    COV2D_DILATION,
    POSE_JAC_COLOR,
    POSE_JAC_CONIC,
    POSE_JAC_X,
    SH_C0,
    SH_C1,
    SH_C2_0,
    SH_C2_1,
    SH_C2_2,
    SH_C2_3,
    SH_C2_4,
    SH_C3_0,
    SH_C3_1,
    SH_C3_2,
    SH_C3_3,
    SH_C3_4,
    SH_C3_5,
    SH_C3_6,
    TILE_SIZE,
    CameraParams,
    block_sum,
    exp3,
    mat23,
    projection_jacobian,
    quat_to_rot,
    vec6,
    vec10,
    vec32,
)

wp.set_module_options({"enable_backward": False})

PROJECT_BLOCK = 256


@wp.func
def quat_to_rot_vjp(q: wp.quat, g: wp.mat33):
    """Gradient w.r.t. the (unit) quaternion of <g, quat_to_rot(q)>."""
    x = q[0]
    y = q[1]
    z = q[2]
    w = q[3]
    gx = 2.0 * (y * (g[0, 1] + g[1, 0]) + z * (g[0, 2] + g[2, 0]) + w * (g[2, 1] - g[1, 2])) - 4.0 * x * (
        g[1, 1] + g[2, 2]
    )
    gy = 2.0 * (x * (g[0, 1] + g[1, 0]) + z * (g[1, 2] + g[2, 1]) + w * (g[0, 2] - g[2, 0])) - 4.0 * y * (
        g[0, 0] + g[2, 2]
    )
    gz = 2.0 * (x * (g[0, 2] + g[2, 0]) + y * (g[1, 2] + g[2, 1]) + w * (g[1, 0] - g[0, 1])) - 4.0 * z * (
        g[0, 0] + g[1, 1]
    )
    gw = 2.0 * (z * (g[1, 0] - g[0, 1]) + y * (g[0, 2] - g[2, 0]) + x * (g[2, 1] - g[1, 2]))
    return wp.quat(gx, gy, gz, gw)


@wp.func
def sh_basis(k: int, d: wp.vec3):
    """Real SH basis function k (3DGS constants and signs) at unit direction d, and its gradient in d
    (taken with x, y, z independent; the caller projects out the radial part)."""
    x = d[0]
    y = d[1]
    z = d[2]
    if k == 0:
        return SH_C0, wp.vec3(0.0)
    if k == 1:
        return -SH_C1 * y, wp.vec3(0.0, -SH_C1, 0.0)
    if k == 2:
        return SH_C1 * z, wp.vec3(0.0, 0.0, SH_C1)
    if k == 3:
        return -SH_C1 * x, wp.vec3(-SH_C1, 0.0, 0.0)
    if k == 4:
        return SH_C2_0 * x * y, SH_C2_0 * wp.vec3(y, x, 0.0)
    if k == 5:
        return SH_C2_1 * y * z, SH_C2_1 * wp.vec3(0.0, z, y)
    if k == 6:
        return SH_C2_2 * (2.0 * z * z - x * x - y * y), SH_C2_2 * wp.vec3(-2.0 * x, -2.0 * y, 4.0 * z)
    if k == 7:
        return SH_C2_3 * x * z, SH_C2_3 * wp.vec3(z, 0.0, x)
    if k == 8:
        return SH_C2_4 * (x * x - y * y), SH_C2_4 * wp.vec3(2.0 * x, -2.0 * y, 0.0)
    if k == 9:
        return SH_C3_0 * y * (3.0 * x * x - y * y), SH_C3_0 * wp.vec3(6.0 * x * y, 3.0 * (x * x - y * y), 0.0)
    if k == 10:
        return SH_C3_1 * x * y * z, SH_C3_1 * wp.vec3(y * z, x * z, x * y)
    if k == 11:
        return SH_C3_2 * y * (4.0 * z * z - x * x - y * y), SH_C3_2 * wp.vec3(
            -2.0 * x * y, 4.0 * z * z - x * x - 3.0 * y * y, 8.0 * y * z
        )
    if k == 12:
        return SH_C3_3 * z * (2.0 * z * z - 3.0 * x * x - 3.0 * y * y), SH_C3_3 * wp.vec3(
            -6.0 * x * z, -6.0 * y * z, 6.0 * z * z - 3.0 * x * x - 3.0 * y * y
        )
    if k == 13:
        return SH_C3_4 * x * (4.0 * z * z - x * x - y * y), SH_C3_4 * wp.vec3(
            4.0 * z * z - 3.0 * x * x - y * y, -2.0 * x * y, 8.0 * x * z
        )
    if k == 14:
        return SH_C3_5 * z * (x * x - y * y), SH_C3_5 * wp.vec3(2.0 * x * z, -2.0 * y * z, x * x - y * y)
    return SH_C3_6 * x * (x * x - 3.0 * y * y), SH_C3_6 * wp.vec3(3.0 * (x * x - y * y), -6.0 * x * y, 0.0)


@wp.func
def tile_rect(mean2d: wp.vec2, radii: wp.vec2i, cam: CameraParams):
    """Tiles [x0, x1) x [y0, y1) holding the pixels within radii of mean2d (pixel px is in tile px // 16)."""
    ts = float(TILE_SIZE)
    fx0 = wp.clamp((mean2d[0] - float(radii[0])) / ts, -1.0, float(cam.tiles_x))
    fx1 = wp.clamp((mean2d[0] + float(radii[0])) / ts, -1.0, float(cam.tiles_x))
    fy0 = wp.clamp((mean2d[1] - float(radii[1])) / ts, -1.0, float(cam.tiles_y))
    fy1 = wp.clamp((mean2d[1] + float(radii[1])) / ts, -1.0, float(cam.tiles_y))
    x0 = wp.clamp(int(wp.floor(fx0)), 0, cam.tiles_x)
    x1 = wp.clamp(int(wp.floor(fx1)) + 1, 0, cam.tiles_x)
    y0 = wp.clamp(int(wp.floor(fy0)), 0, cam.tiles_y)
    y1 = wp.clamp(int(wp.floor(fy1)) + 1, 0, cam.tiles_y)
    return wp.vec4i(x0, x1, y0, y1)


@wp.func
def alpha_extent2(opacity: float):
    """Squared Mahalanobis radius of the ellipse where opacity * G = 1/255 (the compositing's skip rule)."""
    return 2.0 * wp.log(opacity / ALPHA_MIN)


@wp.func
def tile_reached(mean2d: wp.vec2, conic: wp.vec3, extent2: float, tx: int, ty: int):
    """Whether the ellipse d^T Q d <= extent2 (d = mean2d - p, Q the conic) reaches the rectangle of pixel
    centres of tile (tx, ty), [16 tx, 16 tx + 15] x [16 ty, 16 ty + 15].  Its minimum over the (continuous)
    rectangle: 0 when it holds mean2d, else on an edge, where the quadratic in the free coordinate is least
    at its clamped stationary point; never above the minimum over the tile's pixels, so a tile with a pixel
    the compositing would not skip is always reached (and a little slack covers fast-math exp)."""
    span = float(TILE_SIZE - 1)
    dx0 = mean2d[0] - (float(tx * TILE_SIZE) + span)
    dx1 = mean2d[0] - float(tx * TILE_SIZE)
    dy0 = mean2d[1] - (float(ty * TILE_SIZE) + span)
    dy1 = mean2d[1] - float(ty * TILE_SIZE)
    if dx0 <= 0.0 and dx1 >= 0.0 and dy0 <= 0.0 and dy1 >= 0.0:
        return True
    a = conic[0]
    b = conic[1]
    c = conic[2]
    best = float(1.0e30)
    for k in range(2):
        dx = wp.where(k == 0, dx0, dx1)  # a vertical edge: dy free
        dy = wp.clamp(-b * dx / c, dy0, dy1)
        best = wp.min(best, a * dx * dx + 2.0 * b * dx * dy + c * dy * dy)
        dy = wp.where(k == 0, dy0, dy1)  # a horizontal edge: dx free
        dx = wp.clamp(-b * dy / a, dx0, dx1)
        best = wp.min(best, a * dx * dx + 2.0 * b * dx * dy + c * dy * dy)
    return best <= extent2 * 1.001 + 1.0e-3


@wp.func
def tiles_reached(mean2d: wp.vec2, conic: wp.vec3, extent2: float, rect: wp.vec4i):
    """How many tiles of ``rect`` (``tile_rect``) the ellipse reaches (``tile_reached``)."""
    n = int(0)
    for ty in range(rect[2], rect[3]):
        for tx in range(rect[0], rect[1]):
            if tile_reached(mean2d, conic, extent2, tx, ty):
                n += 1
    return n


@wp.func
def view_direction(mean: wp.vec3, view: wp.mat44):
    """Unnormalised direction from the camera centre C = -W^T t to the mean, and W, t."""
    W = wp.mat33(
        view[0, 0], view[0, 1], view[0, 2], view[1, 0], view[1, 1], view[1, 2], view[2, 0], view[2, 1], view[2, 2]
    )
    t = wp.vec3(view[0, 3], view[1, 3], view[2, 3])
    return mean + wp.transpose(W) @ t, W, t


@wp.func
def conic_backward(cn: wp.vec3, g_con: wp.vec3, J: mat23, cov_c: wp.mat33):
    """(dL/dSigma_c, dL/dJ) from the gradient g_con of the stored conic (a, b, c) = Sigma2d^-1 entries.

    dL/dSigma2d = -Q G Q with G the symmetric gradient of the conic matrix (the stored off-diagonal b
    enters the quadratic form twice, hence g_b / 2 per entry); Sigma2d = J Sigma_c J^T + 0.3 I.
    """
    Q = wp.mat22(cn[0], cn[1], cn[1], cn[2])
    G = wp.mat22(g_con[0], 0.5 * g_con[1], 0.5 * g_con[1], g_con[2])
    g_cov2d = -(Q @ G @ Q)
    return wp.transpose(J) @ g_cov2d @ J, 2.0 * (g_cov2d @ J @ cov_c)


@wp.func
def jacobian_backward(g_J: mat23, X: wp.vec3, cam: CameraParams):
    """dL/dX through J(X) (projection_jacobian, with its clamped tangents u = x/z, v = y/z)."""
    z = X[2]
    ux = X[0] / z
    vy = X[1] / z
    u = wp.clamp(ux, cam.tan_x_min, cam.tan_x_max)
    v = wp.clamp(vy, cam.tan_y_min, cam.tan_y_max)
    du_dx = wp.where(ux == u, 1.0 / z, 0.0)
    dv_dy = wp.where(vy == v, 1.0 / z, 0.0)
    du_dz = wp.where(ux == u, -ux / z, 0.0)
    dv_dz = wp.where(vy == v, -vy / z, 0.0)
    z2 = z * z
    return wp.vec3(
        g_J[0, 2] * (-cam.fx / z) * du_dx,
        g_J[1, 2] * (-cam.fy / z) * dv_dy,
        -g_J[0, 0] * cam.fx / z2
        - g_J[1, 1] * cam.fy / z2
        + g_J[0, 2] * cam.fx * (u / z2 - du_dz / z)
        + g_J[1, 2] * cam.fy * (v / z2 - dv_dz / z),
    )


@wp.func
def covariance_twist_grad(g_cov_c: wp.mat33, cov_c: wp.mat33):
    """Rotation part of the twist gradient through Sigma_c = W Sigma W^T: dW = [phi]x W gives
    dSigma_c = [phi]x Sigma_c - Sigma_c [phi]x."""
    A = g_cov_c @ cov_c
    return 2.0 * wp.vec3(A[2, 1] - A[1, 2], A[0, 2] - A[2, 0], A[1, 0] - A[0, 1])


@wp.func
def direction_backward(g_d: wp.vec3, d: wp.vec3, dir_raw: wp.vec3):
    """dL/d(dir_raw) from dL/dd with d = dir_raw / |dir_raw| (the radial part drops out)."""
    return (g_d - d * wp.dot(d, g_d)) / wp.length(dir_raw)


@wp.func
def conic_twist_jacobian(cn: wp.vec3, J: mat23, cov_c: wp.mat33, X: wp.vec3, cam: CameraParams, e: wp.vec3):
    """d<e, conic>/dxi = (rho, phi): the twist gradient of a unit gradient e on the stored conic.

    Xi moves X by rho + phi x X (through J) and rotates Sigma_c (covariance_twist_grad).
    """
    g_cov_c, g_J = conic_backward(cn, e, J, cov_c)
    g_X = jacobian_backward(g_J, X, cam)
    g_phi = wp.cross(X, g_X) + covariance_twist_grad(g_cov_c, cov_c)
    return vec6(g_X[0], g_X[1], g_X[2], g_phi[0], g_phi[1], g_phi[2])


@wp.kernel
def project_gaussians(
    # in: Gaussian map
    means: wp.array(dtype=wp.vec3),
    rotations: wp.array(dtype=wp.quat),
    log_scales: wp.array(dtype=wp.vec3),
    opacity_logits: wp.array(dtype=float),
    sh: wp.array2d(dtype=wp.vec3),
    num_sh: int,
    # in: camera-from-world pose (1 element) and intrinsics
    view: wp.array(dtype=wp.mat44),
    cam: CameraParams,
    # in: whether to write pose_jac_out (for the pose-only backward)
    with_pose_jac: int,
    # out: screen-space Gaussians (xy_opacity_depth = u, v, opacity, z)
    xy_opacity_depth_out: wp.array(dtype=wp.vec4),
    depth_out: wp.array(dtype=float),
    conic_out: wp.array(dtype=wp.vec3),
    color_out: wp.array(dtype=wp.vec3),
    radii_out: wp.array(dtype=wp.vec2i),
    tiles_touched_out: wp.array(dtype=wp.int32),
    pose_jac_out: wp.array(dtype=vec32),
):
    i = wp.tid()
    radii_out[i] = wp.vec2i(0, 0)
    tiles_touched_out[i] = 0

    mean = means[i]
    V = view[0]
    dir_raw, W, t = view_direction(mean, V)
    X = W @ mean + t
    z = X[2]
    if z < cam.near:
        return
    opacity = 1.0 / (1.0 + wp.exp(-opacity_logits[i]))
    if opacity < ALPHA_MIN:
        return

    q = wp.normalize(rotations[i])
    R = quat_to_rot(q)
    s = exp3(log_scales[i])
    M = R @ wp.diag(s)
    cov_c = W @ (M @ wp.transpose(M)) @ wp.transpose(W)
    J = projection_jacobian(X, cam)
    cov2d = J @ cov_c @ wp.transpose(J)
    a = cov2d[0, 0] + COV2D_DILATION
    b = cov2d[0, 1]
    c = cov2d[1, 1] + COV2D_DILATION
    det = a * c - b * b
    if det <= 0.0:
        return

    # Axis-aligned half extent of the ellipse where opacity * G = 1/255: outside it the compositing
    # skips the Gaussian anyway, so tile culling drops nothing the dense composite would keep
    # (3 sigma in 3DGS; here sqrt(2 ln(255 o)) <= 3.33 sigma, exact for the 1/255 rule).  Of the tiles
    # that box covers, only those the ellipse itself reaches get the Gaussian (``tile_reached``): an
    # elongated or tilted one misses the box's corners.
    extent2 = alpha_extent2(opacity)
    extent = wp.sqrt(extent2)
    rx = int(wp.ceil(wp.min(extent * wp.sqrt(a), 1.0e6)))
    ry = int(wp.ceil(wp.min(extent * wp.sqrt(c), 1.0e6)))
    mean2d = wp.vec2(cam.fx * X[0] / z + cam.cx, cam.fy * X[1] / z + cam.cy)
    radii = wp.vec2i(rx, ry)
    rect = tile_rect(mean2d, radii, cam)
    if (rect[1] - rect[0]) * (rect[3] - rect[2]) <= 0:
        return
    conic = wp.vec3(c / det, -b / det, a / det)
    touched = tiles_reached(mean2d, conic, extent2, rect)
    if touched == 0:
        return

    d = wp.normalize(dir_raw)
    raw = wp.vec3(0.0)
    # gradients of the three raw colour channels in d, for the pose Jacobian
    g_dr = wp.vec3(0.0)
    g_dg = wp.vec3(0.0)
    g_db = wp.vec3(0.0)
    for k in range(num_sh):
        y, dy = sh_basis(k, d)
        coeff = sh[i, k]
        raw += y * coeff
        if with_pose_jac != 0:
            g_dr += coeff[0] * dy
            g_dg += coeff[1] * dy
            g_db += coeff[2] * dy
    # 3DGS: the SH value is offset by 0.5 and clamped at 0 (no upper clamp).
    color = wp.vec3(wp.max(raw[0] + 0.5, 0.0), wp.max(raw[1] + 0.5, 0.0), wp.max(raw[2] + 0.5, 0.0))

    xy_opacity_depth_out[i] = wp.vec4(mean2d[0], mean2d[1], opacity, z)
    depth_out[i] = z
    conic_out[i] = conic
    color_out[i] = color
    radii_out[i] = radii
    tiles_touched_out[i] = touched

    if with_pose_jac != 0:
        jac = vec32()
        jac[POSE_JAC_X + 0] = X[0]
        jac[POSE_JAC_X + 1] = X[1]
        jac[POSE_JAC_X + 2] = X[2]
        jac[POSE_JAC_X + 3] = 1.0 / z
        for r in range(3):
            e = wp.vec3(0.0)
            e[r] = 1.0
            row = conic_twist_jacobian(conic, J, cov_c, X, cam, e)
            for j in range(6):
                jac[POSE_JAC_CONIC + 6 * r + j] = row[j]
        # colour moves with the camera centre C = -W^T t only: dC = -W^T rho, so d(dir_raw) = W^T rho
        col_r = wp.where(raw[0] + 0.5 > 0.0, 1.0, 0.0) * (W @ direction_backward(g_dr, d, dir_raw))
        col_g = wp.where(raw[1] + 0.5 > 0.0, 1.0, 0.0) * (W @ direction_backward(g_dg, d, dir_raw))
        col_b = wp.where(raw[2] + 0.5 > 0.0, 1.0, 0.0) * (W @ direction_backward(g_db, d, dir_raw))
        for j in range(3):
            jac[POSE_JAC_COLOR + j] = col_r[j]
            jac[POSE_JAC_COLOR + 3 + j] = col_g[j]
            jac[POSE_JAC_COLOR + 6 + j] = col_b[j]
        pose_jac_out[i] = jac


# Intersection keys are 32 bits: the tile id in the high ``32 - depth_key_bits`` bits and the Gaussian's
# depth, quantized, in the low ``depth_key_bits``.  Positive IEEE floats order like their bit patterns, so
# the key's depth part is the depth's bit pattern less the near plane's, shifted right: over the depths
# [near, near x 2^DEPTH_KEY_OCTAVES) it orders exactly up to the mantissa bits it drops (relative steps of
# 2^-(depth_key_bits - 5): 3e-5 with 4,096 tiles, 0.1 mm at 4 m); deeper ones share the last key, and
# Gaussians of equal keys keep their index order (the sort is stable).  The
# sort then takes 4 radix passes over 8 bytes a pair instead of 6 over 12 (tile << 32 | float bits).
DEPTH_KEY_OCTAVES = 32  # 5 bits of exponent
MAX_TILE_KEY_BITS = 16


def intersection_key_layout(num_tiles: int) -> tuple[int, int]:
    """(depth_key_bits, depth_shift) of the 32-bit keys for ``num_tiles`` tiles plus the padding's id
    ``num_tiles``: the tile id takes the high bits it needs, the depth the rest, dropping ``depth_shift``
    low bits of the float's offset from the near plane (5 exponent bits + 23 mantissa bits = 28)."""
    tile_bits = max(1, math.ceil(math.log2(num_tiles + 1)))
    if tile_bits > MAX_TILE_KEY_BITS:
        raise ValueError(
            f"{num_tiles} image tiles need {tile_bits} bits of the 32-bit intersection keys, more than "
            f"{MAX_TILE_KEY_BITS}: images are limited to {2**MAX_TILE_KEY_BITS - 1} tiles of 16x16 pixels"
        )
    depth_bits = min(28, 32 - tile_bits)
    return depth_bits, 28 - depth_bits


@wp.func
def depth_key(depth_bits: wp.int32, near_bits: wp.int32, shift: wp.int32, depth_key_bits: wp.int32):
    """The quantized depth of an intersection key (see DEPTH_KEY_OCTAVES)."""
    q = (depth_bits - near_bits) >> shift
    return wp.uint32(wp.clamp(q, 0, (1 << depth_key_bits) - 1))


@wp.kernel
def emit_intersections(
    # in: projected Gaussians (depth_bits: the float32 depths reinterpreted as int32)
    xy_opacity_depth: wp.array(dtype=wp.vec4),
    depth_bits: wp.array(dtype=wp.int32),
    conic: wp.array(dtype=wp.vec3),
    radii: wp.array(dtype=wp.vec2i),
    tiles_touched: wp.array(dtype=wp.int32),
    offsets_inclusive: wp.array(dtype=wp.int32),
    cam: CameraParams,
    capacity: int,
    # in: the key layout (intersection_key_layout) and the near plane's float bits
    depth_key_bits: int,
    depth_shift: int,
    near_bits: int,
    # out: unsorted (tile << depth_key_bits | quantized depth) keys and Gaussian ids; entries past
    # capacity are dropped (the caller sees the overflow in the total count and grows the buffers)
    keys_out: wp.array(dtype=wp.uint32),
    ids_out: wp.array(dtype=wp.int32),
):
    i = wp.tid()
    n = tiles_touched[i]
    if n == 0:
        return
    j = offsets_inclusive[i] - n
    if j >= capacity:
        return
    xyod = xy_opacity_depth[i]
    mean2d = wp.vec2(xyod[0], xyod[1])
    rect = tile_rect(mean2d, radii[i], cam)
    extent2 = alpha_extent2(xyod[2])
    con = conic[i]
    end = j + n  # the tiles the projection counted, with the same test
    zkey = depth_key(depth_bits[i], near_bits, depth_shift, depth_key_bits)
    for ty in range(rect[2], rect[3]):
        for tx in range(rect[0], rect[1]):
            if j < end and tile_reached(mean2d, con, extent2, tx, ty):
                if j < capacity:
                    keys_out[j] = (wp.uint32(ty * cam.tiles_x + tx) << wp.uint32(depth_key_bits)) | zkey
                    ids_out[j] = wp.int32(i)
                j += 1


@wp.kernel
def pad_intersection_keys(
    # in: number of intersections (1 element), the tile id past the last tile, the keys' depth bits
    total: wp.array(dtype=wp.int32),
    end_tile: int,
    depth_key_bits: int,
    # out: keys past the total, set to sort behind every real key
    keys_out: wp.array(dtype=wp.uint32),
):
    j = wp.tid()
    if j >= total[0]:
        keys_out[j] = wp.uint32(end_tile) << wp.uint32(depth_key_bits)


@wp.kernel
def tile_ranges_from_keys(
    # in: sorted keys, their number (1 element, may exceed the buffer's capacity), that capacity, and
    # the keys' depth bits
    keys: wp.array(dtype=wp.uint32),
    total: wp.array(dtype=wp.int32),
    capacity: int,
    depth_key_bits: int,
    # out: [start, end) of each tile's run in the sorted list (zeroed beforehand)
    ranges_out: wp.array2d(dtype=wp.int32),
):
    j = wp.tid()
    count = wp.min(total[0], capacity)
    if j >= count:
        return
    tile = int(keys[j] >> wp.uint32(depth_key_bits))
    if j == 0:
        ranges_out[tile, 0] = 0
    else:
        prev = int(keys[j - 1] >> wp.uint32(depth_key_bits))
        if prev != tile:
            ranges_out[prev, 1] = j
            ranges_out[tile, 0] = j
    if j == count - 1:
        ranges_out[tile, 1] = count


@wp.kernel
def skip_tiles(
    tiles_x: int, stride: int, phase: int, step: wp.array(dtype=wp.int32), ranges: wp.array2d(dtype=wp.int32)
):
    """Empty the Gaussian list of every tile but one in ``stride`` (those with (tx + ty + phase +
    step[0]) % stride == 0: a checkerboard for 2, shifting with the phase, the device step counter
    added as the tracker's kernels add it): they then render as nothing (opacity 0) and their backward
    does no work."""
    tile = wp.tid()
    ty = tile // tiles_x
    if (tile - ty * tiles_x + ty + phase + step[0]) % stride != 0:
        ranges[tile, 1] = ranges[tile, 0]


@wp.kernel
def project_gaussians_backward(
    # in: Gaussian map
    means: wp.array(dtype=wp.vec3),
    rotations: wp.array(dtype=wp.quat),
    log_scales: wp.array(dtype=wp.vec3),
    opacity_logits: wp.array(dtype=float),
    sh: wp.array2d(dtype=wp.vec3),
    num_sh: int,
    count: int,
    # in: pose, intrinsics, forward results
    view: wp.array(dtype=wp.mat44),
    cam: CameraParams,
    radii: wp.array(dtype=wp.vec2i),
    conic: wp.array(dtype=wp.vec3),
    # in: screen-space gradients from the compositing backward
    grad2d: wp.array(dtype=vec10),
    # in: what to produce
    pose_only: int,
    with_pose: int,
    accumulate: int,
    # out: parameter gradients (skipped when pose_only) and the twist gradient (rho, phi) (skipped
    # unless with_pose)
    grad_means_out: wp.array(dtype=wp.vec3),
    grad_rotations_out: wp.array(dtype=wp.quat),
    grad_log_scales_out: wp.array(dtype=wp.vec3),
    grad_opacity_logits_out: wp.array(dtype=float),
    grad_sh_out: wp.array2d(dtype=wp.vec3),
    grad_pose_out: wp.array(dtype=float),
):
    block, lane = wp.tid()
    i = block * PROJECT_BLOCK + lane
    g_pose = vec6()
    g_mean = wp.vec3(0.0)
    g_quat = wp.quat(0.0, 0.0, 0.0, 0.0)
    g_log_s = wp.vec3(0.0)
    g_logit = wp.float32(0.0)
    live = i < count
    if live:
        live = radii[i][0] > 0
    if live:
        g = grad2d[i]
        mean = means[i]
        V = view[0]
        dir_raw, W, t = view_direction(mean, V)
        X = W @ mean + t
        z = X[2]

        cn = conic[i]
        q_raw = rotations[i]
        q = wp.normalize(q_raw)
        R = quat_to_rot(q)
        s = exp3(log_scales[i])
        M = R @ wp.diag(s)
        cov_w = M @ wp.transpose(M)
        cov_c = W @ cov_w @ wp.transpose(W)
        J = projection_jacobian(X, cam)
        g_cov_c, g_J = conic_backward(cn, wp.vec3(g[2], g[3], g[4]), J, cov_c)
        g_X = jacobian_backward(g_J, X, cam)
        z2 = z * z
        # mean2d = (fx x / z + cx, fy y / z + cy), depth = z
        g_X += wp.vec3(
            g[0] * cam.fx / z,
            g[1] * cam.fy / z,
            -(g[0] * cam.fx * X[0] + g[1] * cam.fy * X[1]) / z2 + g[9],
        )

        # colour = max(sum_k Y_k(d) sh_k + 0.5, 0), d = dir_raw / |dir_raw|
        d = wp.normalize(dir_raw)
        raw = wp.vec3(0.0)
        for k in range(num_sh):
            y, dy = sh_basis(k, d)
            raw += y * sh[i, k]
        g_col = wp.vec3(
            wp.where(raw[0] + 0.5 > 0.0, g[6], 0.0),
            wp.where(raw[1] + 0.5 > 0.0, g[7], 0.0),
            wp.where(raw[2] + 0.5 > 0.0, g[8], 0.0),
        )
        g_d = wp.vec3(0.0)
        for k in range(num_sh):
            y, dy = sh_basis(k, d)
            g_d += wp.dot(g_col, sh[i, k]) * dy
            if pose_only == 0:
                g_sh_k = y * g_col
                if accumulate != 0:
                    g_sh_k += grad_sh_out[i, k]
                grad_sh_out[i, k] = g_sh_k
        g_dir = direction_backward(g_d, d, dir_raw)

        # Twist xi = (rho, phi), T_CW <- Exp(xi) T_CW: dX = rho + phi x X, dW = [phi]x W, so
        # dSigma_c = [phi]x Sigma_c - Sigma_c [phi]x and the camera centre moves by -W^T rho
        # (the view direction by +W^T rho).
        if with_pose != 0:
            g_phi = wp.cross(X, g_X) + covariance_twist_grad(g_cov_c, cov_c)
            g_rho = g_X + W @ g_dir
            g_pose = vec6(g_rho[0], g_rho[1], g_rho[2], g_phi[0], g_phi[1], g_phi[2])

        if pose_only == 0:
            g_mean = wp.transpose(W) @ g_X + g_dir
            g_cov_w = wp.transpose(W) @ g_cov_c @ W
            g_M = 2.0 * (g_cov_w @ M)
            g_R = g_M @ wp.diag(s)
            g_s = wp.vec3(
                R[0, 0] * g_M[0, 0] + R[1, 0] * g_M[1, 0] + R[2, 0] * g_M[2, 0],
                R[0, 1] * g_M[0, 1] + R[1, 1] * g_M[1, 1] + R[2, 1] * g_M[2, 1],
                R[0, 2] * g_M[0, 2] + R[1, 2] * g_M[1, 2] + R[2, 2] * g_M[2, 2],
            )
            g_log_s = wp.cw_mul(g_s, s)
            g_qn = quat_to_rot_vjp(q, g_R)
            # normalisation q = q_raw / |q_raw|: project out the radial component
            g_quat = (g_qn - q * wp.dot(q, g_qn)) / wp.length(q_raw)
            opacity = 1.0 / (1.0 + wp.exp(-opacity_logits[i]))
            g_logit = g[5] * opacity * (1.0 - opacity)
    elif i < count and pose_only == 0:
        for k in range(num_sh):
            if accumulate == 0:
                grad_sh_out[i, k] = wp.vec3(0.0)

    if i < count and pose_only == 0:
        if accumulate != 0:
            g_mean += grad_means_out[i]
            g_quat += grad_rotations_out[i]
            g_log_s += grad_log_scales_out[i]
            g_logit += grad_opacity_logits_out[i]
        grad_means_out[i] = g_mean
        grad_rotations_out[i] = g_quat
        grad_log_scales_out[i] = g_log_s
        grad_opacity_logits_out[i] = g_logit

    # One atomic per block for the 6-vector shared by all Gaussians (with_pose is uniform over the
    # block, so every thread takes the block reduction or none does).
    if with_pose != 0:
        total = block_sum(g_pose)
        if lane == 0:
            for c in range(6):
                wp.atomic_add(grad_pose_out, c, total[c])


@wp.kernel
def invert_rigid(
    # in: camera-to-world pose
    T_WC: wp.array(dtype=wp.mat44),
    # out: camera-from-world pose
    T_CW_out: wp.array(dtype=wp.mat44),
):
    T = T_WC[0]
    Rt = wp.mat33(T[0, 0], T[1, 0], T[2, 0], T[0, 1], T[1, 1], T[2, 1], T[0, 2], T[1, 2], T[2, 2])
    t = -(Rt @ wp.vec3(T[0, 3], T[1, 3], T[2, 3]))
    T_CW_out[0] = wp.mat44(
        Rt[0, 0], Rt[0, 1], Rt[0, 2], t[0],
        Rt[1, 0], Rt[1, 1], Rt[1, 2], t[1],
        Rt[2, 0], Rt[2, 1], Rt[2, 2], t[2],
        0.0, 0.0, 0.0, 1.0,
    )  # fmt: skip
