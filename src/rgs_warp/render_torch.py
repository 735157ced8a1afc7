"""Thin ``torch.autograd.Function`` over the Warp renderer, zero-copy through ``wp.from_torch`` /
``wp.to_torch``.

The returned images are views of the renderer's buffers: valid until its next ``forward``, and one
forward/backward pair may be in flight per ``Renderer``.
"""

from __future__ import annotations

import numpy as np
import torch
import warp as wp

from rgs_warp.geometry import invert_pose, se3_exp
from rgs_warp.render import Renderer
from rgs_warp.types import Camera, GaussianMap


class RasterizeGaussians(torch.autograd.Function):
    @staticmethod
    def forward(ctx, renderer, camera, T_WC, background, means, quats, log_scales, opacity_logits, sh, xi):
        gmap = GaussianMap.from_arrays(
            wp.from_torch(means.detach().contiguous(), dtype=wp.vec3),
            wp.from_torch(quats.detach().contiguous(), dtype=wp.quat),
            wp.from_torch(log_scales.detach().contiguous(), dtype=wp.vec3),
            wp.from_torch(opacity_logits.detach().contiguous()),
            wp.from_torch(sh.detach().contiguous(), dtype=wp.vec3),
        )
        # T_CW <- Exp(xi) T_CW  <=>  T_WC <- T_WC Exp(xi)^-1
        T = np.asarray(T_WC, np.float64) @ invert_pose(se3_exp(xi.detach().double().cpu().numpy()))
        result = renderer.forward(gmap, camera, T, background)
        ctx.renderer = renderer
        ctx.count = len(gmap)
        return wp.to_torch(result.color), wp.to_torch(result.depth), wp.to_torch(result.alpha)

    @staticmethod
    def backward(ctx, g_color, g_depth, g_alpha):
        renderer: Renderer = ctx.renderer
        shape = renderer._image_shape
        dev = wp.device_to_torch(renderer.device)

        def image(g, channels):
            if g is None:
                g = torch.zeros(shape + channels, dtype=torch.float32, device=dev)
            return wp.from_torch(g.contiguous(), dtype=wp.vec3 if channels else wp.float32)

        need_gaussians = any(ctx.needs_input_grad[4:9])
        grads, pose_grad = renderer.backward(
            image(g_color, (3,)), image(g_depth, ()), image(g_alpha, ()), pose_only=not need_gaussians
        )
        n = ctx.count
        out = [None] * 4
        if grads is None:
            out += [None] * 5
        else:
            out += [
                wp.to_torch(a)[:n].clone()
                for a in (grads.means, grads.rotations, grads.log_scales, grads.opacity_logits, grads.sh)
            ]
        out.append(wp.to_torch(pose_grad).clone() if ctx.needs_input_grad[9] else None)
        return tuple(out)


def rasterize(
    renderer: Renderer,
    camera: Camera,
    T_WC: np.ndarray,
    means: torch.Tensor,
    quats_xyzw: torch.Tensor,
    log_scales: torch.Tensor,
    opacity_logits: torch.Tensor,
    sh: torch.Tensor,
    xi: torch.Tensor | None = None,
    background=(0.0, 0.0, 0.0),
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(color (H,W,3), depth (H,W), alpha (H,W)) of float32 tensors (N,3), (N,4), (N,3), (N,), (N,K,3)
    on the renderer's device; ``xi`` (6,) is a pose twist applied as T_CW <- Exp(xi) T_CW whose
    gradient is the analytic one."""
    expected = torch.device(wp.device_to_torch(renderer.device))
    named = {
        "means": means,
        "quats_xyzw": quats_xyzw,
        "log_scales": log_scales,
        "opacity_logits": opacity_logits,
        "sh": sh,
    }
    if xi is not None:
        named["xi"] = xi
    for name, t in named.items():
        if t.device != expected:
            # Warp would launch on the renderer's device with the tensor's pointer: an illegal access.
            raise ValueError(f"{name} is on {t.device}, the renderer on {expected}: move the tensors there")
        if t.dtype != torch.float32:
            raise ValueError(f"{name} must be float32, got {t.dtype}")
    if xi is None:
        xi = torch.zeros(6, dtype=torch.float32, device=expected)
    return RasterizeGaussians.apply(
        renderer, camera, T_WC, background, means, quats_xyzw, log_scales, opacity_logits, sh, xi
    )
