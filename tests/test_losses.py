"""Differentiable SSIM against the evaluation SSIM (float64 host reference) and finite differences."""

import numpy as np
import pytest
import warp as wp

from rgs_warp.eval import ssim as ssim_reference
from rgs_warp.losses import DSSIMLoss, gaussian_window


def _images(rng, h, w):
    base = rng.random((h, w, 3))
    x = np.clip(base + 0.15 * rng.standard_normal((h, w, 3)), 0, 1)
    return x, base


def test_window_is_normalised_gaussian():
    w = gaussian_window()
    assert w.shape == (11,) and abs(w.sum() - 1) < 1e-6 and w[5] == w.max()
    assert w[4] / w[5] == pytest.approx(np.exp(-1 / (2 * 1.5**2)), rel=1e-6)


def test_value_matches_reference(device):
    rng = np.random.default_rng(0)
    x, y = _images(rng, 37, 52)
    loss = DSSIMLoss(37, 52, device)
    grad = wp.zeros((37, 52), dtype=wp.vec3, device=device)
    xw, yw = (
        wp.array(x.astype(np.float32), dtype=wp.vec3, device=device),
        wp.array(y.astype(np.float32), dtype=wp.vec3, device=device),
    )
    loss.accumulate_grad(xw, yw, 1.0, grad)
    assert loss.ssim() == pytest.approx(ssim_reference(x, y), abs=2e-6)
    loss.accumulate_grad(yw, yw, 1.0, grad)
    assert loss.ssim() == pytest.approx(1.0, abs=1e-6)


def test_gradient_matches_finite_differences(device):
    rng = np.random.default_rng(1)
    h, w = 19, 23
    x, y = _images(rng, h, w)
    weight = 0.2
    loss = DSSIMLoss(h, w, device)
    grad = wp.array(np.full((h, w, 3), 0.5, np.float32), dtype=wp.vec3, device=device)  # accumulates onto this
    loss.accumulate_grad(
        wp.array(x.astype(np.float32), dtype=wp.vec3, device=device),
        wp.array(y.astype(np.float32), dtype=wp.vec3, device=device),
        weight,
        grad,
    )
    g = grad.numpy() - 0.5

    def f(img):
        return weight * (1.0 - ssim_reference(img, y))

    eps = 1e-5
    checked = 0
    for p in [(0, 0, 0), (3, 7, 1), (9, 11, 2), (18, 22, 0), (10, 0, 1), (5, 15, 2), (12, 20, 0), (7, 3, 1)]:
        xp, xm = x.copy(), x.copy()
        xp[p] += eps
        xm[p] -= eps
        fd = (f(xp) - f(xm)) / (2 * eps)
        assert g[p] == pytest.approx(fd, rel=1e-2, abs=1e-7), p
        checked += abs(fd) > 1e-5
    assert checked >= 5  # most probes have a gradient that is not tiny
