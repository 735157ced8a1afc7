"""Photometric losses of the mapper (supplement Table 1: L1 + lambda_dssim (1 - SSIM)) as Warp
kernels with hand-written gradients, on preallocated buffers."""

from __future__ import annotations

import numpy as np
import warp as wp

from rgs_warp.kernels import ssim as k

SSIM_SIGMA = 1.5


def gaussian_window(radius: int = k.SSIM_RADIUS, sigma: float = SSIM_SIGMA) -> np.ndarray:
    t = np.arange(-radius, radius + 1, dtype=np.float64)
    w = np.exp(-(t**2) / (2.0 * sigma**2))
    return (w / w.sum()).astype(np.float32)


class DSSIMLoss:
    """``weight * (1 - SSIM(x, y))`` for HxW vec3 images and its gradient w.r.t. ``x``.

    SSIM is the standard one (11x11 Gaussian window, sigma 1.5, K1 0.01, K2 0.03) averaged over
    the valid region and the channels, the same definition as ``rgs_warp.eval.ssim``.
    """

    def __init__(self, height: int, width: int, device):
        n = 2 * k.SSIM_RADIUS
        if height <= n or width <= n:
            raise ValueError(f"SSIM needs images larger than {n + 1}x{n + 1}, got {width}x{height}")
        self.height, self.width, self.device = height, width, wp.get_device(device)
        self._window = wp.array(gaussian_window(), dtype=wp.float32, device=self.device)
        hw, vw = (height, width - n), (height - n, width - n)
        self._h = [wp.zeros(hw, dtype=wp.vec3, device=self.device) for _ in range(5)]
        self._ssim = wp.zeros(vw, dtype=wp.vec3, device=self.device)
        self._partials = [wp.zeros(vw, dtype=wp.vec3, device=self.device) for _ in range(3)]
        self._adj_v = self._h[:3]  # the horizontal moments are dead once the map is computed
        self._sum = wp.zeros(1, dtype=wp.vec3, device=self.device)
        self._n_valid = vw[0] * vw[1]

    def accumulate_grad(self, x: wp.array2d, y: wp.array2d, weight: float, grad_x_out: wp.array2d) -> None:
        """Adds ``weight * d(1 - SSIM)/dx`` to ``grad_x_out``; the SSIM map stays for ``value()``."""
        if x.shape != (self.height, self.width) or y.shape != x.shape or grad_x_out.shape != x.shape:
            raise ValueError(f"images must be {self.height}x{self.width}")
        n = 2 * k.SSIM_RADIUS
        dev = self.device
        wp.launch(
            k.ssim_moments_h,
            dim=(self.height, self.width - n),
            inputs=[x, y, self._window],
            outputs=self._h,
            device=dev,
        )
        dloss_dssim = -float(weight) / (3.0 * self._n_valid)
        wp.launch(
            k.ssim_map_v,
            dim=(self.height - n, self.width - n),
            inputs=[*self._h, self._window, dloss_dssim],
            outputs=[self._ssim, *self._partials],
            device=dev,
        )
        wp.launch(
            k.ssim_adjoint_v,
            dim=(self.height, self.width - n),
            inputs=[*self._partials, self._window],
            outputs=self._adj_v,
            device=dev,
        )
        wp.launch(
            k.ssim_adjoint_h,
            dim=(self.height, self.width),
            inputs=[*self._adj_v, x, y, self._window],
            outputs=[grad_x_out],
            device=dev,
        )

    def ssim(self) -> float:
        """Mean SSIM of the last ``accumulate_grad`` call (reads back to the host)."""
        wp.utils.array_sum(self._ssim.flatten(), out=self._sum)
        return float(self._sum.numpy()[0].sum()) / (3.0 * self._n_valid)
