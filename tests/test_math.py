"""Shared kernel math (kernels/math.py): the helpers several stages' kernels use (bilinear sampling,
grey level, block reductions, the CameraParams builder) against NumPy references written here."""

import numpy as np
import pytest
import warp as wp

from rgs_warp.kernels.math import (
    FRUSTUM_MARGIN,
    REDUCE_BLOCK,
    TILE_SIZE,
    bilerp,
    bilinear_corner,
    block_sum,
    camera_params,
    grey_level,
)
from rgs_warp.types import Camera

vec8 = wp.types.vector(length=8, dtype=wp.float32)


@wp.kernel
def _sample_grey(
    image: wp.array2d(dtype=wp.vec3),
    uv: wp.array(dtype=wp.vec2),
    grey_out: wp.array(dtype=wp.float32),
):
    i = wp.tid()
    x0, y0, fx, fy = bilinear_corner(uv[i][0], uv[i][1], image.shape[1], image.shape[0])
    c = bilerp(image[y0, x0], image[y0, x0 + 1], image[y0 + 1, x0], image[y0 + 1, x0 + 1], fx, fy)
    grey_out[i] = grey_level(c)


@wp.kernel
def _block_sums(
    values: wp.array(dtype=wp.float32),
    scalar_out: wp.array(dtype=wp.float64),
    vector_out: wp.array2d(dtype=wp.float64),
):
    block, lane = wp.tid()
    i = block * REDUCE_BLOCK + lane
    v = float(0.0)
    if i < values.shape[0]:
        v = values[i]
    total = block_sum(v)
    moments = block_sum(vec8(1.0, v, v * v, 0.0, 0.0, 0.0, 0.0, -v))
    if lane == 0:
        scalar_out[block] = wp.float64(total)
        for c in range(8):
            vector_out[block, c] = wp.float64(moments[c])


def _bilinear_reference(image: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Bilinear sample (float64) with pixel centres at integers, coordinates clamped into the image."""
    h, w = image.shape[:2]
    u = np.clip(u, 0, w - 1)
    v = np.clip(v, 0, h - 1)
    x0 = np.minimum(np.floor(u).astype(int), w - 2)
    y0 = np.minimum(np.floor(v).astype(int), h - 2)
    a, b = (u - x0)[:, None], (v - y0)[:, None]
    top = (1 - a) * image[y0, x0] + a * image[y0, x0 + 1]
    bottom = (1 - a) * image[y0 + 1, x0] + a * image[y0 + 1, x0 + 1]
    return (1 - b) * top + b * bottom


def test_bilinear_grey_matches_numpy(device):
    rng = np.random.default_rng(0)
    image = rng.uniform(0, 1, (7, 9, 3)).astype(np.float32)
    # inside, on the last row/column (the corner is clamped to W-2 / H-2) and outside (clamped)
    uv = np.concatenate(
        [rng.uniform(0, [8, 6], (50, 2)), [[8.0, 6.0], [8.0, 2.5], [3.5, 6.0], [-2.0, 3.0], [11.0, -1.0], [0.0, 0.0]]]
    ).astype(np.float32)
    out = wp.zeros(len(uv), dtype=wp.float32, device=device)
    wp.launch(
        _sample_grey,
        dim=len(uv),
        inputs=[wp.array(image, dtype=wp.vec3, device=device), wp.array(uv, dtype=wp.vec2, device=device)],
        outputs=[out],
        device=device,
    )
    ref = _bilinear_reference(image.astype(np.float64), uv[:, 0].astype(np.float64), uv[:, 1].astype(np.float64))
    np.testing.assert_allclose(out.numpy(), ref.mean(1), atol=1e-6)


@pytest.mark.parametrize("n", [1, REDUCE_BLOCK, 3 * REDUCE_BLOCK + 17])
def test_block_sum_matches_numpy(device, n):
    values = np.random.default_rng(n).standard_normal(n).astype(np.float32)
    blocks = (n + REDUCE_BLOCK - 1) // REDUCE_BLOCK
    scalar = wp.zeros(blocks, dtype=wp.float64, device=device)
    vector = wp.zeros((blocks, 8), dtype=wp.float64, device=device)
    wp.launch_tiled(
        _block_sums,
        dim=[blocks],
        inputs=[wp.array(values, dtype=wp.float32, device=device)],
        outputs=[scalar, vector],
        block_dim=REDUCE_BLOCK,
        device=device,
    )
    padded = np.zeros(blocks * REDUCE_BLOCK)
    padded[:n] = values
    per_block = padded.reshape(blocks, REDUCE_BLOCK)
    np.testing.assert_allclose(scalar.numpy(), per_block.sum(1), rtol=1e-5, atol=1e-5)
    expected = np.stack(
        [np.full(blocks, REDUCE_BLOCK), per_block.sum(1), (per_block**2).sum(1)]
        + [np.zeros(blocks)] * 4
        + [-per_block.sum(1)],
        axis=1,
    )
    np.testing.assert_allclose(vector.numpy(), expected, rtol=1e-5, atol=1e-4)


def test_camera_params():
    camera = Camera(fx=500.0, fy=480.0, cx=319.5, cy=241.0, width=640, height=470)
    image = camera_params(camera, near_m=0.05)
    p = camera_params(camera, near_m=0.05, frustum_margin=FRUSTUM_MARGIN)
    for q in (image, p):
        assert (q.fx, q.fy, q.cx, q.cy, q.width, q.height) == (500.0, 480.0, 319.5, 241.0, 640, 470)
        assert (q.tiles_x, q.tiles_y) == (-(-640 // TILE_SIZE), -(-470 // TILE_SIZE))
        assert q.near == pytest.approx(0.05)
    # margin 0: the clamp range is the image, pixel centres -0.5 .. W-0.5 seen through the pinhole
    np.testing.assert_allclose(
        [image.tan_x_min, image.tan_x_max, image.tan_y_min, image.tan_y_max],
        [-320.0 / 500.0, 320.0 / 500.0, -241.5 / 480.0, 228.5 / 480.0],
        rtol=1e-6,
    )
    mx, my = FRUSTUM_MARGIN * 640, FRUSTUM_MARGIN * 470
    np.testing.assert_allclose(
        [p.tan_x_min, p.tan_x_max, p.tan_y_min, p.tan_y_max],
        [-(320.0 + mx) / 500.0, (320.0 + mx) / 500.0, -(241.5 + my) / 480.0, (228.5 + my) / 480.0],
        rtol=1e-6,
    )
