"""Kernels of the ``classic`` dense descriptor (``rgs_warp.features.classic`` describes the design):
gradient orientation cells, box pooling at two scales, DAISY-like sampling and normalisation."""

import warp as wp

from rgs_warp.kernels.math import bilerp, bilinear_corner, grey_level

wp.set_module_options({"enable_backward": False})

N_ORIENT = wp.constant(8)
N_SAMPLES = wp.constant(17)  # centre + two rings of 8
DIM = 8 * 17
POOL1 = 1  # fine pooling half-width, cells
POOL2 = 2  # coarse pooling half-width, cells
RING1 = wp.constant(2.0)  # ring radii, cells
RING2 = wp.constant(4.0)
# Below this norm (after the square root and mean removal) a patch counts as textureless: a flat
# patch gives 0 up to float rounding.
MIN_ENERGY = wp.constant(1e-3)


@wp.func
def grey(rgb: wp.array2d(dtype=wp.vec3), y: int, x: int) -> float:
    H = rgb.shape[0]
    W = rgb.shape[1]
    return grey_level(rgb[wp.clamp(y, 0, H - 1), wp.clamp(x, 0, W - 1)])


@wp.kernel
def orientation_cells(
    # in:
    rgb: wp.array2d(dtype=wp.vec3),
    stride: int,
    # out:
    cells_out: wp.array3d(dtype=wp.float32),
):
    cy, cx = wp.tid()
    for o in range(N_ORIENT):
        cells_out[cy, cx, o] = 0.0
    for dy in range(stride):
        for dx in range(stride):
            y = cy * stride + dy
            x = cx * stride + dx
            gx = 0.5 * (grey(rgb, y, x + 1) - grey(rgb, y, x - 1))
            gy = 0.5 * (grey(rgb, y + 1, x) - grey(rgb, y - 1, x))
            for o in range(N_ORIENT):
                theta = float(o) * (wp.pi / 4.0)
                g = wp.max(gx * wp.cos(theta) + gy * wp.sin(theta), 0.0)
                cells_out[cy, cx, o] += g / float(stride * stride)


@wp.kernel
def box_pool(
    # in:
    cells: wp.array3d(dtype=wp.float32),
    half_width: int,
    # out:
    pooled_out: wp.array3d(dtype=wp.float32),
):
    y, x = wp.tid()
    H = cells.shape[0]
    W = cells.shape[1]
    norm = 1.0 / float((2 * half_width + 1) * (2 * half_width + 1))
    for o in range(N_ORIENT):
        acc = float(0.0)
        for dy in range(-half_width, half_width + 1):
            for dx in range(-half_width, half_width + 1):
                acc += cells[wp.clamp(y + dy, 0, H - 1), wp.clamp(x + dx, 0, W - 1), o]
        pooled_out[y, x, o] = acc * norm


@wp.func
def bilinear_cell(pooled: wp.array3d(dtype=wp.float32), y: float, x: float, o: int) -> float:
    x0, y0, fx, fy = bilinear_corner(x, y, pooled.shape[1], pooled.shape[0])
    return bilerp(pooled[y0, x0, o], pooled[y0, x0 + 1, o], pooled[y0 + 1, x0, o], pooled[y0 + 1, x0 + 1, o], fx, fy)


@wp.kernel
def daisy_descriptor(
    # in:
    pooled_fine: wp.array3d(dtype=wp.float32),
    pooled_coarse: wp.array3d(dtype=wp.float32),
    # out:
    desc_out: wp.array3d(dtype=wp.float32),
):
    y, x = wp.tid()
    total = float(0.0)
    for s in range(N_SAMPLES):
        sy = float(y)
        sx = float(x)
        if s > 0:
            ring = (s - 1) // 8
            angle = float((s - 1) % 8) * (wp.pi / 4.0)
            radius = wp.where(ring == 0, RING1, RING2)
            sy = sy + radius * wp.sin(angle)
            sx = sx + radius * wp.cos(angle)
        for o in range(N_ORIENT):
            v = float(0.0)
            if s <= 8:
                v = bilinear_cell(pooled_fine, sy, sx, o)
            else:
                v = bilinear_cell(pooled_coarse, sy, sx, o)
            v = wp.sqrt(wp.max(v, 0.0))
            desc_out[y, x, s * N_ORIENT + o] = v
            total += v
    D = desc_out.shape[2]
    mean = total / float(D)
    sq = float(0.0)
    for k in range(D):
        v = desc_out[y, x, k] - mean
        desc_out[y, x, k] = v
        sq += v * v
    norm = wp.sqrt(sq)
    scale = wp.where(norm > MIN_ENERGY, 1.0 / wp.max(norm, MIN_ENERGY), 0.0)
    for k in range(D):
        desc_out[y, x, k] = desc_out[y, x, k] * scale
