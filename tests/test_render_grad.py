"""Gradients of the rasterizer against central finite differences of the float64 reference.

The loss is L = <Wc, color> + <Wd, depth> + <Wa, alpha> with random weights, so dL/dimage = W.
Finite differences run with the reference's discrete decisions (depth order, which splat
contributes where, alpha clamping) frozen at the nominal point: the analytic gradient is that of
the current smooth piece, and a step across the 1/255 threshold would add a jump, not a slope.
"""

import numpy as np
import pytest
import torch
import warp as wp

from helpers_render import BACKGROUND, T_WC, to_map
from reference_render import random_scene, render_reference
from rgs_warp.render import GaussianGrads, Renderer
from rgs_warp.render_torch import rasterize
from rgs_warp.types import Camera

CAM = Camera(fx=30.0, fy=30.0, cx=15.5, cy=11.5, width=32, height=24)
STEP = 1e-6
FIELDS = {
    "means": "means",
    "quats": "rotations",
    "log_scales": "log_scales",
    "opacity_logits": "opacity_logits",
    "sh": "sh",
}


@pytest.fixture(scope="module")
def problem():
    rng = np.random.default_rng(11)
    scene = random_scene(rng, 40, T_WC, sh_degree=3)
    scene["log_scales"] += 1.0  # larger splats at the small resolution: more pixels per Gaussian
    H, W = CAM.height, CAM.width
    weights = (rng.normal(size=(H, W, 3)), rng.normal(size=(H, W)), rng.normal(size=(H, W)))
    decisions = render_reference(scene, CAM, T_WC, BACKGROUND)[3]

    def loss(s, xi=None):
        c, d, a, _ = render_reference(s, CAM, T_WC, BACKGROUND, xi=xi, decisions=decisions)
        return (weights[0] * c).sum() + (weights[1] * d).sum() + (weights[2] * a).sum()

    return scene, weights, loss, rng


def _image_grads(weights, device):
    return (
        wp.array(weights[0].astype(np.float32), dtype=wp.vec3, device=device),
        wp.array(weights[1].astype(np.float32), device=device),
        wp.array(weights[2].astype(np.float32), device=device),
    )


def _fd(loss, scene, key, idx):
    plus = {k: v.copy() for k, v in scene.items()}
    minus = {k: v.copy() for k, v in scene.items()}
    plus[key][idx] += STEP
    minus[key][idx] -= STEP
    return (loss(plus) - loss(minus)) / (2 * STEP)


def _fd_pose(loss, scene):
    out = np.zeros(6)
    for j in range(6):
        e = np.zeros(6)
        e[j] = STEP
        out[j] = (loss(scene, e) - loss(scene, -e)) / (2 * STEP)
    return out


def _assert_close(analytic, numeric):
    analytic, numeric = np.asarray(analytic, np.float64), np.asarray(numeric, np.float64)
    scale = np.abs(numeric).max()
    assert scale > 1e-3
    # relative error where the gradient is not tiny (1% of the largest), absolute below that
    big = np.abs(numeric) > 1e-2 * scale
    assert big.sum() >= 1
    rel = np.abs(analytic[big] - numeric[big]) / np.abs(numeric[big])
    assert rel.max() < 1e-2, (analytic, numeric)
    assert np.abs(analytic[~big] - numeric[~big]).max(initial=0.0) < 1e-3 * scale


@pytest.mark.parametrize("tiled", [True, False])
def test_parameter_and_pose_gradients(device, problem, tiled):
    scene, weights, loss, rng = problem
    renderer = Renderer(device, tiled=tiled)
    gmap = to_map(scene, device)
    renderer.forward(gmap, CAM, T_WC, BACKGROUND)
    grads, pose_grad = renderer.backward(*_image_grads(weights, device))
    analytic = grads.to_numpy(len(gmap))
    _assert_close(pose_grad.numpy(), _fd_pose(loss, scene))

    visible = np.flatnonzero(renderer.radii.numpy()[: len(gmap), 0] > 0)
    for key, name in FIELDS.items():
        entries = [
            (int(rng.choice(visible)),) + tuple(int(rng.integers(0, s)) for s in scene[key].shape[1:])
            for _ in range(12)
        ]
        numeric = [_fd(loss, scene, key, idx) for idx in entries]
        _assert_close([analytic[name][idx] for idx in entries], numeric)
    # culled Gaussians get exactly zero
    culled = renderer.radii.numpy()[: len(gmap), 0] == 0
    assert culled.any() and not analytic["means"][culled].any()


def test_pose_only_path(device, problem):
    scene, weights, loss, _ = problem
    renderer = Renderer(device)
    gmap = to_map(scene, device)
    renderer.forward(gmap, CAM, T_WC, BACKGROUND)
    _, full_pose = renderer.backward(*_image_grads(weights, device))
    full_pose = full_pose.numpy().copy()
    renderer.grads.means.fill_(wp.vec3(7.0, 7.0, 7.0))
    grads, pose_grad = renderer.backward(*_image_grads(weights, device), pose_only=True)
    assert grads is None
    np.testing.assert_allclose(pose_grad.numpy(), full_pose, rtol=1e-5, atol=1e-5)
    assert (renderer.grads.means.numpy() == 7.0).all()  # per-Gaussian storage untouched


def test_mapping_path_without_pose(device, problem):
    """``with_pose=False`` (the mapper's backward) gives the same per-Gaussian gradients, computes no
    twist gradient and leaves the renderer's one as it was."""
    scene, weights, _, _ = problem
    renderer = Renderer(device)
    gmap = to_map(scene, device)
    renderer.forward(gmap, CAM, T_WC, BACKGROUND)
    grads, _ = renderer.backward(*_image_grads(weights, device))
    full = grads.to_numpy(len(gmap))
    renderer.pose_grad.fill_(3.0)
    grads, pose_grad = renderer.backward(*_image_grads(weights, device), with_pose=False)
    assert pose_grad is None
    assert (renderer.pose_grad.numpy() == 3.0).all()
    for name, values in grads.to_numpy(len(gmap)).items():
        np.testing.assert_array_equal(values, full[name], err_msg=name)


@pytest.mark.parametrize("jacobians_in_forward", [True, False])
def test_pose_only_fast_path(device, problem, jacobians_in_forward):
    """The pose-only compositing backward (per-Gaussian pose Jacobians, no per-Gaussian gradients)
    against finite differences and against the general path of the per-pixel implementation."""
    scene, weights, loss, _ = problem
    gmap = to_map(scene, device)
    reference = Renderer(device, tiled=False)
    reference.forward(gmap, CAM, T_WC, BACKGROUND)
    expected = reference.backward(*_image_grads(weights, device))[1].numpy().copy()

    renderer = Renderer(device)
    renderer.forward(gmap, CAM, T_WC, BACKGROUND, pose_jacobians=jacobians_in_forward)
    grads, pose_grad = renderer.backward(*_image_grads(weights, device), pose_only=True)
    assert grads is None
    assert not renderer.grad2d.numpy().any()  # no per-Gaussian gradient buffer touched
    np.testing.assert_allclose(pose_grad.numpy(), expected, rtol=1e-4, atol=1e-4 * np.abs(expected).max())
    _assert_close(pose_grad.numpy(), _fd_pose(loss, scene))

    # accumulate adds
    renderer.backward(*_image_grads(weights, device), pose_only=True, accumulate=True)
    np.testing.assert_allclose(pose_grad.numpy(), 2 * expected, rtol=1e-4, atol=2e-4 * np.abs(expected).max())


def test_tape_backward_through_warp_loss(device, problem):
    """Forward recorded on a wp.Tape, a loss written as a Warp kernel, tape.backward runs the chain."""
    scene, weights, _, _ = problem

    @wp.kernel
    def weighted_sum(
        color: wp.array2d(dtype=wp.vec3),
        depth: wp.array2d(dtype=float),
        alpha: wp.array2d(dtype=float),
        wc: wp.array2d(dtype=wp.vec3),
        wd: wp.array2d(dtype=float),
        wa: wp.array2d(dtype=float),
        loss_out: wp.array(dtype=float),
    ):
        v, u = wp.tid()
        wp.atomic_add(loss_out, 0, wp.dot(wc[v, u], color[v, u]) + wd[v, u] * depth[v, u] + wa[v, u] * alpha[v, u])

    renderer = Renderer(device)
    gmap = to_map(scene, device, requires_grad=True)
    wc, wd, wa = _image_grads(weights, device)
    loss = wp.zeros(1, dtype=float, device=device, requires_grad=True)
    tape = wp.Tape()
    with tape:
        result = renderer.forward(gmap, CAM, T_WC, BACKGROUND, tape=tape)
        wp.launch(
            weighted_sum,
            dim=(CAM.height, CAM.width),
            inputs=[result.color, result.depth, result.alpha, wc, wd, wa],
            outputs=[loss],
            device=device,
        )
    tape.backward(loss)
    via_tape = GaussianGrads.of_map_grads(gmap).to_numpy(len(gmap))
    pose_via_tape = renderer.pose_grad.numpy().copy()

    direct = Renderer(device)
    direct.forward(to_map(scene, device), CAM, T_WC, BACKGROUND)
    grads, pose_grad = direct.backward(wc, wd, wa)
    expected = grads.to_numpy(len(gmap))
    for name in expected:
        # GPU atomics sum in a different order each run: allow float noise relative to the field's scale
        atol = 1e-5 * max(np.abs(expected[name]).max(), 1e-3)
        np.testing.assert_allclose(via_tape[name], expected[name], rtol=1e-4, atol=atol)
    np.testing.assert_allclose(pose_via_tape, pose_grad.numpy(), rtol=1e-4, atol=1e-5)
    assert np.abs(via_tape["means"]).max() > 1e-3
    tape.zero()
    assert not gmap.means.grad.numpy().any()


def test_torch_wrapper(device, problem):
    scene, weights, _, _ = problem
    renderer = Renderer(device)
    tdev = wp.device_to_torch(device)
    tensors = [
        torch.tensor(scene[k], dtype=torch.float32, device=tdev, requires_grad=True)
        for k in ("means", "quats", "log_scales", "opacity_logits", "sh")
    ]
    if tdev != "cpu":  # tensors elsewhere than the renderer are refused, not launched on
        with pytest.raises(ValueError, match="is on cpu, the renderer on"):
            rasterize(renderer, CAM, T_WC, *[t.detach().cpu() for t in tensors])
    xi = torch.zeros(6, device=tdev, requires_grad=True)
    color, depth, alpha = rasterize(renderer, CAM, T_WC, *tensors, xi=xi, background=BACKGROUND)
    ref = render_reference(scene, CAM, T_WC, BACKGROUND)
    assert np.abs(color.detach().cpu().numpy() - ref[0]).max() < 1e-4
    loss = (
        (torch.tensor(weights[0], dtype=torch.float32, device=tdev) * color).sum()
        + (torch.tensor(weights[1], dtype=torch.float32, device=tdev) * depth).sum()
        + (torch.tensor(weights[2], dtype=torch.float32, device=tdev) * alpha).sum()
    )
    loss.backward()

    direct = Renderer(device)
    direct.forward(to_map(scene, device), CAM, T_WC, BACKGROUND)
    grads, pose_grad = direct.backward(*_image_grads(weights, device))
    expected = grads.to_numpy(len(scene["means"]))
    for tensor, name in zip(tensors, FIELDS.values(), strict=True):
        atol = 1e-5 * max(np.abs(expected[name]).max(), 1e-3)
        np.testing.assert_allclose(tensor.grad.cpu().numpy(), expected[name], rtol=1e-4, atol=atol)
    np.testing.assert_allclose(xi.grad.cpu().numpy(), pose_grad.numpy(), rtol=1e-4, atol=1e-5)


@pytest.mark.parametrize("phase", [0, 1])
def test_tile_stride_renders_and_differentiates_one_tile_in_two(device, problem, phase):
    """``forward(tile_stride=2)`` (the tracker's cheaper steps): the checkerboard of tiles it keeps renders
    exactly as the full render, the others as nothing; its pose-only backward is the full render's with
    the image gradients zeroed outside the kept tiles (the skipped tiles add nothing, not even a
    rounding)."""
    scene, weights, _, _ = problem
    gmap = to_map(scene, device)
    renderer = Renderer(device)
    full = renderer.forward(gmap, CAM, T_WC, BACKGROUND)
    color, depth, alpha = full.color.numpy().copy(), full.depth.numpy().copy(), full.alpha.numpy().copy()
    ty, tx = np.mgrid[: CAM.height, : CAM.width] // 16
    kept = (tx + ty + phase) % 2 == 0
    assert 0 < kept.mean() < 1 and (alpha[kept] > 0.5).any() and (alpha[~kept] > 0.5).any()
    masked = [w * (kept[..., None] if w.ndim == 3 else kept) for w in weights]
    renderer.forward(gmap, CAM, T_WC, BACKGROUND, pose_jacobians=True)
    expected = renderer.backward(*_image_grads(masked, device), pose_only=True)[1].numpy().copy()

    half = renderer.forward(gmap, CAM, T_WC, BACKGROUND, pose_jacobians=True, tile_stride=2, tile_phase=phase)
    np.testing.assert_array_equal(half.color.numpy()[kept], color[kept])
    np.testing.assert_array_equal(half.depth.numpy()[kept], depth[kept])
    np.testing.assert_array_equal(half.alpha.numpy()[kept], alpha[kept])
    background = np.broadcast_to(np.float32(BACKGROUND), color[~kept].shape)
    np.testing.assert_array_equal(half.color.numpy()[~kept], background)
    assert not half.alpha.numpy()[~kept].any() and not half.depth.numpy()[~kept].any()
    got = renderer.backward(*_image_grads(weights, device), pose_only=True)[1].numpy()
    np.testing.assert_allclose(got, expected, rtol=1e-6, atol=1e-7 * np.abs(expected).max())
    assert np.abs(expected).max() > 0
