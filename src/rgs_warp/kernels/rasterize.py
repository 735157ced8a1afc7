"""Front-to-back alpha compositing of depth-sorted screen-space Gaussians, and its hand-written adjoint.

Per pixel p and Gaussian i (sorted by depth within the pixel's 16x16 tile):
    alpha_i = min(0.99, o_i exp(-0.5 d^T Q_i d)),  d = mean2d_i - p,
    skipped when alpha_i < 1/255; compositing stops before the Gaussian that would bring the
    transmittance T below 1e-4 (3DGS's rules), w_i = alpha_i T_i, T_{i+1} = T_i (1 - alpha_i):
    colour = sum_i w_i c_i + T_final * background,  depth = sum_i w_i z_i,  alpha = 1 - T_final.

The backward walks the same list back to front, recovering T_i = T_{i+1} / (1 - alpha_i) (the
3DGS/gsplat scheme), so no per-pixel list is stored: only T_final and the number of entries up to
the last contributor. wp.Tape cannot differentiate these loops (loop-carried transmittance in a
dynamic loop comes out wrong), hence the explicit adjoint.

Two implementations share the per-splat math: a tiled one (one 256-thread block per image tile,
batches of Gaussians gathered into shared memory, per-Gaussian gradients reduced over each warp
before global atomics) for speed, and a plain per-pixel one used as a second reference.
"""

import warp as wp

from rgs_warp.kernels.math import (
    ALPHA_MIN,
    POSE_JAC_COLOR,
    POSE_JAC_CONIC,
    POSE_JAC_X,
    TILE_SIZE,
    block_sum,
    vec6,
    vec10,
    vec32,
)

# Fast math (approximate exp and division) as gsplat builds its kernels (-use_fast_math): measured on an
# H100 it cuts the compositing backward by a third (experiments/results/raster.md); the projection and
# its pose Jacobians, where precision matters more, stay in a module without it.
wp.set_module_options({"enable_backward": False, "fast_math": True})

BLOCK = TILE_SIZE * TILE_SIZE
ALPHA_MAX = 0.99
# Transmittance at which a pixel is saturated (3DGS): later Gaussians change it by < 1e-4.
T_MIN = 1.0e-4


# Warp-level reduction of the backward's per-splat gradients (gsplat's scheme, with fewer shuffles): the
# 32 lanes' vec10 (padded to 16 slots) are summed by recursive halving, each round a lane keeping half of
# its slots and adding its partner's copy of them, so 8 + 4 + 2 + 1 + 1 = 16 shuffles instead of 10 x 5;
# then lane 2s holds the warp's sum of slot s (s = 0..9 are the vec10 components) and adds it to global
# memory: 10 lanes, one atomic each, instead of one lane's 10.  On the CPU (lanes run as fibers, no
# shuffles) the sum is the lane's own vec10 and every lane adds all of it: the same result.
_WARP_REDUCE_SCATTER = """
#if defined(__CUDA_ARCH__)
    float s[16];
#pragma unroll
    for (int c = 0; c < 10; ++c) s[c] = v.c[c];
#pragma unroll
    for (int c = 10; c < 16; ++c) s[c] = 0.0f;
#define RGS_HALVE(OFFSET, HALF)                                                   \
    {                                                                             \
        const bool upper = (lane & OFFSET) != 0;                                  \
        _Pragma("unroll") for (int c = 0; c < HALF; ++c) {                        \
            const float send = upper ? s[c] : s[c + HALF];                        \
            const float keep = upper ? s[c + HALF] : s[c];                        \
            s[c] = keep + __shfl_xor_sync(0xffffffffu, send, OFFSET);             \
        }                                                                         \
    }
    RGS_HALVE(16, 8)
    RGS_HALVE(8, 4)
    RGS_HALVE(4, 2)
    RGS_HALVE(2, 1)
#undef RGS_HALVE
    s[0] += __shfl_xor_sync(0xffffffffu, s[0], 1);
    auto out = v;
    out.c[0] = s[0];
    return out;
#else
    return v;
#endif
"""
# The vec10 component whose warp sum this lane holds after warp_reduce_scatter, 10 and above for none
# (odd lanes and padding slots); -1 on the CPU: the lane holds all ten.
_SCATTER_SLOT = """
#if defined(__CUDA_ARCH__)
    return (lane & 1) == 0 ? ((lane >> 1) & 15) : 16;
#else
    return -1;
#endif
"""
_WARP_ANY = """
#if defined(__CUDA_ARCH__)
    return __any_sync(0xffffffffu, flag) ? 1 : 0;
#else
    return flag;
#endif
"""


@wp.func_native(_WARP_REDUCE_SCATTER)
def warp_reduce_scatter(v: vec10, lane: int) -> vec10: ...


@wp.func_native(_SCATTER_SLOT)
def scatter_slot(lane: int) -> int: ...


@wp.func_native(_WARP_ANY)
def warp_any(flag: int) -> int: ...


@wp.func
def splat_alpha(xyod: wp.vec4, con: wp.vec3, px: float, py: float):
    dx = xyod[0] - px
    dy = xyod[1] - py
    power = -0.5 * (con[0] * dx * dx + con[2] * dy * dy) - con[1] * dx * dy
    return wp.min(ALPHA_MAX, xyod[2] * wp.exp(power)), dx, dy


@wp.func
def splat_grad(
    xyod: wp.vec4,
    con: wp.vec3,
    col: wp.vec3,
    dx: float,
    dy: float,
    alpha: float,
    t_i: float,
    t_final: float,
    acc_color: wp.vec3,
    acc_depth: float,
    g_color: wp.vec3,
    g_depth: float,
    g_alpha: float,
):
    """Screen-space gradient (vec10 layout of projection.vec10) of one splat at one pixel.

    acc_color / acc_depth hold what lies behind splat i (sum_{j>i} w_j c_j + T_final bg, and
    sum_{j>i} w_j z_j); every w_j behind i carries a factor (1 - alpha_i).
    """
    one_minus = 1.0 - alpha
    w = alpha * t_i
    g_a = (
        wp.dot(g_color, t_i * col - acc_color / one_minus)
        + g_depth * (t_i * xyod[3] - acc_depth / one_minus)
        + g_alpha * t_final / one_minus
    )
    out = vec10()
    out[6] = w * g_color[0]
    out[7] = w * g_color[1]
    out[8] = w * g_color[2]
    out[9] = w * g_depth
    opacity = xyod[2]
    if alpha < ALPHA_MAX:
        out[5] = g_a * alpha / opacity
        # alpha = o exp(power): dL/dpower = dL/dalpha * alpha
        g_power = g_a * alpha
        out[0] = -g_power * (con[0] * dx + con[1] * dy)
        out[1] = -g_power * (con[1] * dx + con[2] * dy)
        out[2] = -0.5 * g_power * dx * dx
        out[3] = -g_power * dx * dy
        out[4] = -0.5 * g_power * dy * dy
    return out


@wp.kernel
def rasterize_tiles(
    # in: per-tile [start, end) into the depth-sorted Gaussian ids
    ranges: wp.array2d(dtype=wp.int32),
    sorted_ids: wp.array(dtype=wp.int32),
    # in: screen-space Gaussians
    xy_opacity_depth: wp.array(dtype=wp.vec4),
    conic: wp.array(dtype=wp.vec3),
    color: wp.array(dtype=wp.vec3),
    # in: image
    background: wp.vec3,
    width: int,
    height: int,
    tiles_x: int,
    # out: images and the per-pixel state the backward needs
    color_out: wp.array2d(dtype=wp.vec3),
    depth_out: wp.array2d(dtype=float),
    alpha_out: wp.array2d(dtype=float),
    final_t_out: wp.array2d(dtype=float),
    n_contrib_out: wp.array2d(dtype=wp.int32),
):
    tile, lane = wp.tid()
    ty = tile // tiles_x
    px_i = (tile - ty * tiles_x) * TILE_SIZE + lane % TILE_SIZE
    py_i = ty * TILE_SIZE + lane // TILE_SIZE
    inside = px_i < width and py_i < height
    px = float(px_i)
    py = float(py_i)
    start = ranges[tile, 0]
    end = ranges[tile, 1]
    n_batches = (end - start + BLOCK - 1) // BLOCK

    T = wp.float32(1.0)
    acc_color = wp.vec3(0.0)
    acc_depth = wp.float32(0.0)
    last = wp.int32(0)
    done = not inside
    for b in range(n_batches):
        # Block-wide early exit; the reduction is also the barrier before the shared tiles are reused.
        n_done = block_sum(wp.where(done, 1, 0))
        if n_done == BLOCK:
            break
        batch_start = start + b * BLOCK
        ids = wp.tile_load(sorted_ids, shape=BLOCK, offset=batch_start, storage="shared")
        s_xyod = wp.tile_load_indexed(xy_opacity_depth, ids, shape=(BLOCK,), storage="shared")
        s_conic = wp.tile_load_indexed(conic, ids, shape=(BLOCK,), storage="shared")
        s_color = wp.tile_load_indexed(color, ids, shape=(BLOCK,), storage="shared")
        count = wp.min(BLOCK, end - batch_start)
        for k in range(count):
            if done:
                break
            xyod = wp.tile_extract(s_xyod, k)
            alpha, dx, dy = splat_alpha(xyod, wp.tile_extract(s_conic, k), px, py)
            if alpha < ALPHA_MIN:
                continue
            t_next = T * (1.0 - alpha)
            if t_next < T_MIN:
                done = True
                break
            w = alpha * T
            acc_color += w * wp.tile_extract(s_color, k)
            acc_depth += w * xyod[3]
            T = t_next
            last = batch_start + k + 1 - start

    if inside:
        color_out[py_i, px_i] = acc_color + T * background
        depth_out[py_i, px_i] = acc_depth
        alpha_out[py_i, px_i] = 1.0 - T
        final_t_out[py_i, px_i] = T
        n_contrib_out[py_i, px_i] = last


@wp.func
def fold_pose(jac: vec32, g: vec10, fx: float, fy: float):
    """Twist gradient (rho, phi) of one splat-pixel screen-space gradient g through the splat's pose
    Jacobian (projection.vec32 layout): mean2d = (fx x / z + cx, fy y / z + cy) and depth z move with
    dX = rho + phi x X; the conic and colour rows are precomputed per Gaussian."""
    iz = jac[POSE_JAC_X + 3]
    X = wp.vec3(jac[POSE_JAC_X + 0], jac[POSE_JAC_X + 1], jac[POSE_JAC_X + 2])
    gx = fx * iz * g[0]
    gy = fy * iz * g[1]
    g_X = wp.vec3(gx, gy, g[9] - iz * (X[0] * gx + X[1] * gy))
    g_rho = g_X
    for c in range(3):
        o = POSE_JAC_COLOR + 3 * c
        g_rho += g[6 + c] * wp.vec3(jac[o], jac[o + 1], jac[o + 2])
    g_phi = wp.cross(X, g_X)
    out = vec6(g_rho[0], g_rho[1], g_rho[2], g_phi[0], g_phi[1], g_phi[2])
    for r in range(3):
        o = POSE_JAC_CONIC + 6 * r
        out += g[2 + r] * vec6(jac[o], jac[o + 1], jac[o + 2], jac[o + 3], jac[o + 4], jac[o + 5])
    return out


@wp.func
def splat_back(
    xyod: wp.vec4,
    con: wp.vec3,
    col: wp.vec3,
    px: float,
    py: float,
    t_after: float,
    t_final: float,
    acc_color: wp.vec3,
    acc_depth: float,
    g_color: wp.vec3,
    g_depth: float,
    g_alpha: float,
):
    """One pixel's step back over one splat of its list: (1 if the splat contributes to the pixel else 0,
    the transmittance in front of it, what lies behind the splat before it: colour and depth, and the
    splat's screen-space gradient at the pixel); ``t_after`` is the transmittance behind the splat."""
    g = vec10()
    hit = wp.int32(0)
    t_before = t_after
    behind_color = acc_color
    behind_depth = acc_depth
    alpha, dx, dy = splat_alpha(xyod, con, px, py)
    if alpha >= ALPHA_MIN:
        t_before = t_after / (1.0 - alpha)
        g = splat_grad(
            xyod, con, col, dx, dy, alpha, t_before, t_final, acc_color, acc_depth, g_color, g_depth, g_alpha
        )
        w = alpha * t_before
        behind_color = acc_color + w * col
        behind_depth = acc_depth + w * xyod[3]
        hit = 1
    return hit, t_before, behind_color, behind_depth, g


@wp.func
def backward_pixel(
    tile: int,
    lane: int,
    tiles_x: int,
    width: int,
    height: int,
    n_contrib: wp.array2d(dtype=wp.int32),
    final_t: wp.array2d(dtype=float),
    grad_color: wp.array2d(dtype=wp.vec3),
    grad_depth: wp.array2d(dtype=float),
    grad_alpha: wp.array2d(dtype=float),
):
    """A backward thread's pixel (lane ``lane`` of tile ``tile``) and its state from the forward and the
    loss: (px, py, entries up to its last contributor, final transmittance, dL/dcolour, dL/ddepth,
    dL/dalpha); a pixel outside the image has no entries and no gradient."""
    ty = tile // tiles_x
    px_i = (tile - ty * tiles_x) * TILE_SIZE + lane % TILE_SIZE
    py_i = ty * TILE_SIZE + lane // TILE_SIZE
    last = wp.int32(0)
    T = wp.float32(1.0)
    g_color = wp.vec3(0.0)
    g_depth = wp.float32(0.0)
    g_alpha = wp.float32(0.0)
    if px_i < width and py_i < height:
        last = n_contrib[py_i, px_i]
        T = final_t[py_i, px_i]
        g_color = grad_color[py_i, px_i]
        g_depth = grad_depth[py_i, px_i]
        g_alpha = grad_alpha[py_i, px_i]
    return float(px_i), float(py_i), last, T, g_color, g_depth, g_alpha


def _tiles_backward(
    # in: per-tile [start, end) into the depth-sorted Gaussian ids
    ranges: wp.array2d(dtype=wp.int32),
    sorted_ids: wp.array(dtype=wp.int32),
    # in: screen-space Gaussians
    xy_opacity_depth: wp.array(dtype=wp.vec4),
    conic: wp.array(dtype=wp.vec3),
    color: wp.array(dtype=wp.vec3),
    # in: image and forward per-pixel state
    background: wp.vec3,
    width: int,
    height: int,
    tiles_x: int,
    final_t: wp.array2d(dtype=float),
    n_contrib: wp.array2d(dtype=wp.int32),
    # in: loss gradients w.r.t. the rendered images
    grad_color: wp.array2d(dtype=wp.vec3),
    grad_depth: wp.array2d(dtype=float),
    grad_alpha: wp.array2d(dtype=float),
    # out: screen-space gradients per Gaussian, (N, 10), added to (the renderer's vec10 buffer seen as
    # floats, zeroed beforehand)
    grad2d_out: wp.array2d(dtype=float),
):
    """The general tiled compositing adjoint: one thread a pixel; each splat's per-pixel gradients summed
    over the warp with shuffles, ten atomics per warp and splat."""
    tile, lane = wp.tid()
    start = ranges[tile, 0]
    px, py, last, T, g_color, g_depth, g_alpha = backward_pixel(
        tile, lane, tiles_x, width, height, n_contrib, final_t, grad_color, grad_depth, grad_alpha
    )
    t_final = T
    acc_color = T * background
    acc_depth = wp.float32(0.0)

    block_last = wp.tile_extract(wp.tile_max(wp.tile(last)), 0)
    n_batches = (block_last + BLOCK - 1) // BLOCK
    for bb in range(n_batches):
        b = n_batches - 1 - bb
        batch_start = start + b * BLOCK
        ids = wp.tile_load(sorted_ids, shape=BLOCK, offset=batch_start, storage="shared")
        s_xyod = wp.tile_load_indexed(xy_opacity_depth, ids, shape=(BLOCK,), storage="shared")
        s_conic = wp.tile_load_indexed(conic, ids, shape=(BLOCK,), storage="shared")
        s_color = wp.tile_load_indexed(color, ids, shape=(BLOCK,), storage="shared")
        count = wp.min(BLOCK, block_last - b * BLOCK)
        for kk in range(count):
            k = count - 1 - kk
            g = vec10()
            hit = wp.int32(0)
            if b * BLOCK + k < last:
                hit, T, acc_color, acc_depth, g = splat_back(
                    wp.tile_extract(s_xyod, k),
                    wp.tile_extract(s_conic, k),
                    wp.tile_extract(s_color, k),
                    px,
                    py,
                    T,
                    t_final,
                    acc_color,
                    acc_depth,
                    g_color,
                    g_depth,
                    g_alpha,
                )
            if warp_any(hit) != 0:
                total = warp_reduce_scatter(g, lane)
                slot = scatter_slot(lane)
                i = wp.tile_extract(ids, k)
                if slot < 0:
                    for c in range(10):
                        wp.atomic_add(grad2d_out, i, c, total[c])
                elif slot < 10:
                    wp.atomic_add(grad2d_out, i, slot, total[0])


# 80 -> 64 registers, 4 blocks per SM: 4-6 % faster on an H100 with the warp reduce-scatter, despite
# 56 bytes of spills (experiments/results/raster.md; with the older reduction the cap slowed it).
rasterize_tiles_backward = wp.Kernel(
    _tiles_backward, key="rasterize_tiles_backward", options={"launch_bounds": (BLOCK, 4)}
)


def _tiles_pose_backward(
    # in: per-tile [start, end) into the depth-sorted Gaussian ids
    ranges: wp.array2d(dtype=wp.int32),
    sorted_ids: wp.array(dtype=wp.int32),
    # in: screen-space Gaussians
    xy_opacity_depth: wp.array(dtype=wp.vec4),
    conic: wp.array(dtype=wp.vec3),
    color: wp.array(dtype=wp.vec3),
    # in: image and forward per-pixel state
    background: wp.vec3,
    width: int,
    height: int,
    tiles_x: int,
    final_t: wp.array2d(dtype=float),
    n_contrib: wp.array2d(dtype=wp.int32),
    # in: loss gradients w.r.t. the rendered images
    grad_color: wp.array2d(dtype=wp.vec3),
    grad_depth: wp.array2d(dtype=float),
    grad_alpha: wp.array2d(dtype=float),
    # in: per-Gaussian pose Jacobians, focal lengths
    pose_jac: wp.array(dtype=vec32),
    fx: float,
    fy: float,
    # out: the twist gradient (rho, phi), added to
    grad_pose_out: wp.array(dtype=float),
):
    """The tracker's tiled compositing adjoint: each thread folds its splat gradients straight into a
    twist 6-vector through the per-Gaussian pose Jacobians staged with the batch; the block sums once, one
    atomic per block and component: no per-Gaussian atomics or buffers."""
    tile, lane = wp.tid()
    start = ranges[tile, 0]
    px, py, last, T, g_color, g_depth, g_alpha = backward_pixel(
        tile, lane, tiles_x, width, height, n_contrib, final_t, grad_color, grad_depth, grad_alpha
    )
    t_final = T
    acc_color = T * background
    acc_depth = wp.float32(0.0)
    g_pose = vec6()

    block_last = wp.tile_extract(wp.tile_max(wp.tile(last)), 0)
    n_batches = (block_last + BLOCK - 1) // BLOCK
    for bb in range(n_batches):
        b = n_batches - 1 - bb
        batch_start = start + b * BLOCK
        ids = wp.tile_load(sorted_ids, shape=BLOCK, offset=batch_start, storage="shared")
        s_xyod = wp.tile_load_indexed(xy_opacity_depth, ids, shape=(BLOCK,), storage="shared")
        s_conic = wp.tile_load_indexed(conic, ids, shape=(BLOCK,), storage="shared")
        s_color = wp.tile_load_indexed(color, ids, shape=(BLOCK,), storage="shared")
        s_jac = wp.tile_load_indexed(pose_jac, ids, shape=(BLOCK,), storage="shared")
        count = wp.min(BLOCK, block_last - b * BLOCK)
        for kk in range(count):
            k = count - 1 - kk
            # the per-pixel step written out rather than through splat_back: 2 % faster here (H100)
            if b * BLOCK + k < last:
                xyod = wp.tile_extract(s_xyod, k)
                con = wp.tile_extract(s_conic, k)
                alpha, dx, dy = splat_alpha(xyod, con, px, py)
                if alpha >= ALPHA_MIN:
                    T = T / (1.0 - alpha)
                    col = wp.tile_extract(s_color, k)
                    g = splat_grad(
                        xyod, con, col, dx, dy, alpha, T, t_final, acc_color, acc_depth, g_color, g_depth, g_alpha
                    )
                    w = alpha * T
                    acc_color += w * col
                    acc_depth += w * xyod[3]
                    g_pose += fold_pose(wp.tile_extract(s_jac, k), g, fx, fy)

    pose_total = block_sum(g_pose)
    if lane == 0:
        for c in range(6):
            wp.atomic_add(grad_pose_out, c, pose_total[c])


# Capping registers (102 -> 80) so that 3 blocks fit per SM instead of 2: 15 % faster on an H100 despite a
# few spills.  (Two pixels a thread, a splat's data read once for both and their gradients summed before
# the fold, was 15 % slower: 128 registers, 4 blocks of 128 threads; experiments/results/raster.md.)
rasterize_tiles_pose_backward = wp.Kernel(
    _tiles_pose_backward, key="rasterize_tiles_pose_backward", options={"launch_bounds": (BLOCK, 3)}
)


@wp.kernel
def rasterize_pixels(
    # in: per-tile [start, end) into the depth-sorted Gaussian ids
    ranges: wp.array2d(dtype=wp.int32),
    sorted_ids: wp.array(dtype=wp.int32),
    # in: screen-space Gaussians
    xy_opacity_depth: wp.array(dtype=wp.vec4),
    conic: wp.array(dtype=wp.vec3),
    color: wp.array(dtype=wp.vec3),
    # in: image
    background: wp.vec3,
    width: int,
    height: int,
    tiles_x: int,
    # out: images and the per-pixel state the backward needs
    color_out: wp.array2d(dtype=wp.vec3),
    depth_out: wp.array2d(dtype=float),
    alpha_out: wp.array2d(dtype=float),
    final_t_out: wp.array2d(dtype=float),
    n_contrib_out: wp.array2d(dtype=wp.int32),
):
    py_i, px_i = wp.tid()
    tile = (py_i // TILE_SIZE) * tiles_x + px_i // TILE_SIZE
    px = float(px_i)
    py = float(py_i)
    start = ranges[tile, 0]
    end = ranges[tile, 1]
    T = wp.float32(1.0)
    acc_color = wp.vec3(0.0)
    acc_depth = wp.float32(0.0)
    last = wp.int32(0)
    for j in range(start, end):
        i = sorted_ids[j]
        xyod = xy_opacity_depth[i]
        alpha, dx, dy = splat_alpha(xyod, conic[i], px, py)
        if alpha < ALPHA_MIN:
            continue
        t_next = T * (1.0 - alpha)
        if t_next < T_MIN:
            break
        w = alpha * T
        acc_color += w * color[i]
        acc_depth += w * xyod[3]
        T = t_next
        last = j + 1 - start
    color_out[py_i, px_i] = acc_color + T * background
    depth_out[py_i, px_i] = acc_depth
    alpha_out[py_i, px_i] = 1.0 - T
    final_t_out[py_i, px_i] = T
    n_contrib_out[py_i, px_i] = last


@wp.kernel
def rasterize_pixels_backward(
    # in: per-tile [start, end) into the depth-sorted Gaussian ids
    ranges: wp.array2d(dtype=wp.int32),
    sorted_ids: wp.array(dtype=wp.int32),
    # in: screen-space Gaussians
    xy_opacity_depth: wp.array(dtype=wp.vec4),
    conic: wp.array(dtype=wp.vec3),
    color: wp.array(dtype=wp.vec3),
    # in: image and forward per-pixel state
    background: wp.vec3,
    width: int,
    height: int,
    tiles_x: int,
    final_t: wp.array2d(dtype=float),
    n_contrib: wp.array2d(dtype=wp.int32),
    # in: loss gradients w.r.t. the rendered images
    grad_color: wp.array2d(dtype=wp.vec3),
    grad_depth: wp.array2d(dtype=float),
    grad_alpha: wp.array2d(dtype=float),
    # out: screen-space gradients per Gaussian (zeroed beforehand)
    grad2d_out: wp.array(dtype=vec10),
):
    py_i, px_i = wp.tid()
    tile = (py_i // TILE_SIZE) * tiles_x + px_i // TILE_SIZE
    px = float(px_i)
    py = float(py_i)
    start = ranges[tile, 0]
    T = final_t[py_i, px_i]
    t_final = T
    acc_color = T * background
    acc_depth = wp.float32(0.0)
    g_color = grad_color[py_i, px_i]
    g_depth = grad_depth[py_i, px_i]
    g_alpha = grad_alpha[py_i, px_i]
    last = n_contrib[py_i, px_i]
    for jj in range(last):
        i = sorted_ids[start + last - 1 - jj]
        xyod = xy_opacity_depth[i]
        con = conic[i]
        alpha, dx, dy = splat_alpha(xyod, con, px, py)
        if alpha < ALPHA_MIN:
            continue
        T = T / (1.0 - alpha)
        col = color[i]
        g = splat_grad(xyod, con, col, dx, dy, alpha, T, t_final, acc_color, acc_depth, g_color, g_depth, g_alpha)
        wp.atomic_add(grad2d_out, i, g)
        w = alpha * T
        acc_color += w * col
        acc_depth += w * xyod[3]
