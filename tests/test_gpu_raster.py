"""On a GPU only (skipped without CUDA; run it on a GPU machine with ``pytest -m gpu``): the tiled
compositing backward's CUDA-only code, the warp shuffles that sum each splat's screen-space gradient
over a warp and scatter its ten components to ten lanes (``kernels/rasterize.py``,
``warp_reduce_scatter``), against the per-pixel backward, which adds every pixel's gradient with its
own atomics.  On the CPU the tiled kernel takes the per-lane branch, so the CPU tests do not see this
code."""

import numpy as np
import pytest
import warp as wp

from helpers_render import BACKGROUND, CAMERA, T_WC, to_map
from reference_render import random_scene
from rgs_warp.render import Renderer

pytestmark = [pytest.mark.gpu, pytest.mark.skipif(not wp.is_cuda_available(), reason="needs a CUDA GPU")]


def test_tiled_backward_sums_every_component_over_the_warp():
    device = "cuda:0"
    rng = np.random.default_rng(5)
    scene = random_scene(rng, 600, T_WC, sh_degree=1)
    scene["log_scales"] += 1.0  # splats over many pixels: whole warps hit each of them
    gmap = to_map(scene, device)
    H, W = CAMERA.height, CAMERA.width
    image_grads = (
        wp.array(rng.normal(size=(H, W, 3)).astype(np.float32), dtype=wp.vec3, device=device),
        wp.array(rng.normal(size=(H, W)).astype(np.float32), device=device),
        wp.array(rng.normal(size=(H, W)).astype(np.float32), device=device),
    )
    out = []
    for tiled in (True, False):
        renderer = Renderer(device, tiled=tiled)
        renderer.forward(gmap, CAMERA, T_WC, BACKGROUND)
        grads, pose = renderer.backward(*image_grads)
        out.append((renderer.grad2d.numpy()[: len(gmap)].astype(np.float64), grads.to_numpy(len(gmap)), pose.numpy()))
    (g2_tiled, grads_tiled, pose_tiled), (g2_pixel, grads_pixel, pose_pixel) = out
    hit = np.abs(g2_pixel).sum(axis=1) > 0
    assert hit.sum() > 100
    for c in range(10):  # each component is summed by its own lane
        scale = np.abs(g2_pixel[:, c]).max()
        assert scale > 0, c
        np.testing.assert_allclose(g2_tiled[:, c], g2_pixel[:, c], rtol=0, atol=1e-4 * scale, err_msg=f"component {c}")
    for name, value in grads_pixel.items():
        np.testing.assert_allclose(grads_tiled[name], value, rtol=0, atol=1e-4 * np.abs(value).max(), err_msg=name)
    np.testing.assert_allclose(pose_tiled, pose_pixel, rtol=1e-4, atol=1e-4 * np.abs(pose_pixel).max())
