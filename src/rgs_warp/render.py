"""Differentiable Gaussian rasterizer: colour, expected depth and accumulated opacity, with gradients
for every Gaussian parameter and the analytic camera-pose gradient (supplement §4.1-4.2).

Pipeline (one kernel per stage, all in ``rgs_warp.kernels``): EWA projection + SH colour + tile
count per Gaussian -> inclusive scan -> (tile << 32 | depth) keys per tile touched -> radix sort ->
tile ranges -> front-to-back compositing per 16x16 tile.  The backward runs the hand-written
compositing adjoint, then a per-Gaussian projection adjoint that also reduces the pose twist
gradient block by block.

The only host synchronisation is reading the number of tile intersections after the scan, to size
the sort; intersection buffers are preallocated and grown when that count exceeds them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import warp as wp

from rgs_warp.geometry import invert_pose
from rgs_warp.kernels.projection import (
    FRUSTUM_MARGIN,
    PROJECT_BLOCK,
    TILE_SIZE,
    CameraParams,
    emit_intersections,
    invert_rigid,
    project_gaussians,
    project_gaussians_backward,
    tile_ranges_from_keys,
    vec10,
)
from rgs_warp.kernels.rasterize import (
    rasterize_pixels,
    rasterize_pixels_backward,
    rasterize_tiles,
    rasterize_tiles_backward,
)
from rgs_warp.types import Camera, GaussianMap

__all__ = ["GaussianGrads", "RenderResult", "Renderer", "render"]


@dataclass
class RenderResult:
    """Images (``wp.array`` on the renderer's device, owned by the renderer and overwritten by its
    next ``forward``) and the intermediates later stages reuse.

    color: (H, W) vec3 = sum_i w_i c_i + T_final * background; depth: (H, W) float, expected depth
    sum_i w_i z_i in metres (not normalised by alpha); alpha: (H, W) accumulated opacity
    1 - T_final; n_contrib: (H, W) int32, entries of the pixel's tile list up to its last
    contributor; radii: (capacity,) vec2i pixel half-extents, (0, 0) for culled Gaussians;
    xy_opacity_depth: (capacity,) vec4 (u, v, opacity, z) of each projected Gaussian; tile_ranges:
    (tiles, 2) int32 [start, end) into the depth-sorted ``sorted_ids``.
    """

    color: wp.array
    depth: wp.array
    alpha: wp.array
    n_contrib: wp.array
    radii: wp.array
    xy_opacity_depth: wp.array
    tile_ranges: wp.array
    sorted_ids: wp.array
    num_gaussians: int
    num_intersections: int


@dataclass
class GaussianGrads:
    """Gradients shaped like the GaussianMap fields (capacity rows, the first ``count`` valid)."""

    means: wp.array
    rotations: wp.array
    log_scales: wp.array
    opacity_logits: wp.array
    sh: wp.array

    @classmethod
    def of_map_grads(cls, gmap: GaussianMap) -> GaussianGrads:
        """The ``.grad`` arrays of a map created with ``requires_grad=True``."""
        return cls(gmap.means.grad, gmap.rotations.grad, gmap.log_scales.grad, gmap.opacity_logits.grad, gmap.sh.grad)

    def to_numpy(self, count: int) -> dict[str, np.ndarray]:
        names = ("means", "rotations", "log_scales", "opacity_logits", "sh")
        return {name: getattr(self, name).numpy()[:count] for name in names}


def _grow(capacity: int, needed: int) -> int:
    while capacity < needed:
        capacity *= 2
    return capacity


class Renderer:
    """Owns every buffer of the rasterizer; ``forward`` then ``backward`` per iteration.

    ``tiled=True`` composites with one 256-thread block per 16x16 tile and shared-memory batches
    (the fast path); ``tiled=False`` uses one thread per pixel reading global memory (a simple
    second implementation).  ``near`` is the near-plane depth in metres below which Gaussians are
    culled.
    """

    def __init__(self, device=None, tiled: bool = True, near: float = 0.01):
        self.device = wp.get_device(device)
        self.tiled = tiled
        self.near = near
        self._gaussian_capacity = 0
        self._isect_capacity = 0
        self._image_shape = None
        self._view = wp.zeros(1, dtype=wp.mat44, device=self.device)
        self._view_host = wp.zeros(1, dtype=wp.mat44, device="cpu", pinned=self.device.is_cuda)
        self._count_host = wp.zeros(1, dtype=wp.int32, device="cpu", pinned=self.device.is_cuda)
        self.pose_grad = wp.zeros(6, dtype=wp.float32, device=self.device)
        self._last = None

    # ---- buffers -----------------------------------------------------------------------------
    def _ensure_gaussians(self, capacity: int, num_sh: int) -> None:
        if capacity <= self._gaussian_capacity and self.grads.sh.shape[1] == num_sh:
            return
        n = max(capacity, 1)
        kw = {"device": self.device}
        self._xyod = wp.zeros(n, dtype=wp.vec4, **kw)
        self._depth = wp.zeros(n, dtype=wp.float32, **kw)
        self._depth_bits = self._depth.view(wp.int32)
        self._conic = wp.zeros(n, dtype=wp.vec3, **kw)
        self._color = wp.zeros(n, dtype=wp.vec3, **kw)
        self._radii = wp.zeros(n, dtype=wp.vec2i, **kw)
        self._touched = wp.zeros(n, dtype=wp.int32, **kw)
        self._offsets = wp.zeros(n, dtype=wp.int32, **kw)
        self._grad2d = wp.zeros(n, dtype=vec10, **kw)
        self.grads = GaussianGrads(
            wp.zeros(n, dtype=wp.vec3, **kw),
            wp.zeros(n, dtype=wp.quat, **kw),
            wp.zeros(n, dtype=wp.vec3, **kw),
            wp.zeros(n, dtype=wp.float32, **kw),
            wp.zeros((n, num_sh), dtype=wp.vec3, **kw),
        )
        self._gaussian_capacity = n

    def _ensure_intersections(self, count: int) -> None:
        if count <= self._isect_capacity:
            return
        n = _grow(max(self._isect_capacity, 1024), count)
        # radix_sort_pairs uses the second half as scratch
        self._keys = wp.zeros(2 * n, dtype=wp.int64, device=self.device)
        self._ids = wp.zeros(2 * n, dtype=wp.int32, device=self.device)
        self._isect_capacity = n

    def _ensure_image(self, camera: Camera) -> None:
        shape = (camera.height, camera.width)
        if shape == self._image_shape:
            return
        kw = {"device": self.device}
        # the images carry .grad so that losses recorded on a wp.Tape can deposit dL/dimage there
        self._out_color = wp.zeros(shape, dtype=wp.vec3, requires_grad=True, **kw)
        self._out_depth = wp.zeros(shape, dtype=wp.float32, requires_grad=True, **kw)
        self._out_alpha = wp.zeros(shape, dtype=wp.float32, requires_grad=True, **kw)
        self._final_t = wp.zeros(shape, dtype=wp.float32, **kw)
        self._n_contrib = wp.zeros(shape, dtype=wp.int32, **kw)
        tiles = ((camera.width + TILE_SIZE - 1) // TILE_SIZE) * ((camera.height + TILE_SIZE - 1) // TILE_SIZE)
        self._ranges = wp.zeros((tiles, 2), dtype=wp.int32, **kw)
        self._zero_depth = wp.zeros(shape, dtype=wp.float32, **kw)
        self._zero_alpha = wp.zeros(shape, dtype=wp.float32, **kw)
        self._image_shape = shape

    def _camera_params(self, camera: Camera) -> CameraParams:
        p = CameraParams()
        p.fx, p.fy, p.cx, p.cy = camera.fx, camera.fy, camera.cx, camera.cy
        p.width, p.height = camera.width, camera.height
        p.tiles_x = (camera.width + TILE_SIZE - 1) // TILE_SIZE
        p.tiles_y = (camera.height + TILE_SIZE - 1) // TILE_SIZE
        p.near = self.near
        # image edges (pixel centres -0.5 .. W-0.5) widened by FRUSTUM_MARGIN of the image size
        mx = FRUSTUM_MARGIN * camera.width
        my = FRUSTUM_MARGIN * camera.height
        p.tan_x_min = (-0.5 - mx - camera.cx) / camera.fx
        p.tan_x_max = (camera.width - 0.5 + mx - camera.cx) / camera.fx
        p.tan_y_min = (-0.5 - my - camera.cy) / camera.fy
        p.tan_y_max = (camera.height - 0.5 + my - camera.cy) / camera.fy
        return p

    # ---- forward -----------------------------------------------------------------------------
    def forward(
        self,
        gmap: GaussianMap,
        camera: Camera,
        T_WC,
        background=(0.0, 0.0, 0.0),
        tape: wp.Tape | None = None,
    ) -> RenderResult:
        """Render ``gmap`` seen from camera-to-world pose ``T_WC`` (4x4 NumPy, or a 1-element
        ``wp.array`` of ``wp.mat44`` on the device, e.g. a pose the tracker updates on the GPU).

        With ``tape``, the backward is registered on it: ``tape.backward()`` after losses that read
        the returned images then accumulates into ``gmap``'s ``.grad`` arrays (when the map was made
        with ``requires_grad=True``) and into ``self.pose_grad`` (the twist gradient, zeroed here).
        """
        dev = self.device
        n = len(gmap)
        self._ensure_gaussians(gmap.capacity, gmap.num_sh)
        self._ensure_image(camera)
        cam = self._camera_params(camera)
        if isinstance(T_WC, wp.array):
            wp.launch(invert_rigid, dim=1, inputs=[T_WC], outputs=[self._view], device=dev, record_tape=False)
        else:
            self._view_host.numpy()[0] = invert_pose(np.asarray(T_WC, dtype=np.float64))
            wp.copy(self._view, self._view_host)

        num_isect = 0
        if n > 0:
            wp.launch(
                project_gaussians,
                dim=n,
                inputs=[gmap.means, gmap.rotations, gmap.log_scales, gmap.opacity_logits, gmap.sh, gmap.num_sh]
                + [self._view, cam],
                outputs=[self._xyod, self._depth, self._conic, self._color, self._radii, self._touched],
                device=dev,
                record_tape=False,
            )
            wp.utils.array_scan(self._touched[:n], self._offsets[:n], inclusive=True)
            wp.copy(self._count_host, self._offsets, src_offset=n - 1, count=1)
            wp.synchronize_device(dev)
            num_isect = int(self._count_host.numpy()[0])
        self._ranges.zero_()
        if num_isect > 0:
            self._ensure_intersections(num_isect)
            wp.launch(
                emit_intersections,
                dim=n,
                inputs=[self._xyod, self._depth_bits, self._radii, self._touched, self._offsets, cam],
                outputs=[self._keys, self._ids],
                device=dev,
                record_tape=False,
            )
            tile_bits = max(1, math.ceil(math.log2(self._ranges.shape[0] + 1)))
            wp.utils.radix_sort_pairs(self._keys, self._ids, num_isect, end_bit=32 + tile_bits)
            wp.launch(
                tile_ranges_from_keys,
                dim=num_isect,
                inputs=[self._keys, num_isect],
                outputs=[self._ranges],
                device=dev,
                record_tape=False,
            )
        else:
            self._ensure_intersections(1)

        bg = wp.vec3(*[float(c) for c in background])
        self._launch_raster(cam, bg, backward=False)
        self._last = (gmap, n, cam, bg, num_isect)
        result = RenderResult(
            self._out_color,
            self._out_depth,
            self._out_alpha,
            self._n_contrib,
            self._radii,
            self._xyod,
            self._ranges,
            self._ids,
            n,
            num_isect,
        )
        if tape is not None:
            for image in (self._out_color, self._out_depth, self._out_alpha):
                image.grad.zero_()
            self.pose_grad.zero_()
            arrays = [self._out_color, self._out_depth, self._out_alpha]
            if gmap.requires_grad:
                arrays += [gmap.means, gmap.rotations, gmap.log_scales, gmap.opacity_logits, gmap.sh]
            tape.record_func(backward=self._tape_backward, arrays=arrays)
        return result

    def _launch_raster(self, cam: CameraParams, bg, backward: bool, grads=None) -> None:
        common = [self._ranges, self._ids, self._xyod, self._conic, self._color, bg, cam.width, cam.height]
        common.append(cam.tiles_x)
        shape = self._image_shape
        if backward:
            kernel = rasterize_tiles_backward if self.tiled else rasterize_pixels_backward
            inputs = common + [self._final_t, self._n_contrib, *grads]
            outputs = [self._grad2d]
        else:
            kernel = rasterize_tiles if self.tiled else rasterize_pixels
            inputs = common
            outputs = [self._out_color, self._out_depth, self._out_alpha, self._final_t, self._n_contrib]
        if self.tiled:
            wp.launch_tiled(
                kernel,
                dim=[self._ranges.shape[0]],
                inputs=inputs,
                outputs=outputs,
                block_dim=TILE_SIZE * TILE_SIZE,
                device=self.device,
                record_tape=False,
            )
        else:
            wp.launch(kernel, dim=shape, inputs=inputs, outputs=outputs, device=self.device, record_tape=False)

    # ---- backward ----------------------------------------------------------------------------
    def backward(
        self,
        dL_dcolor: wp.array,
        dL_ddepth: wp.array | None = None,
        dL_dalpha: wp.array | None = None,
        pose_only: bool = False,
        grads_out: GaussianGrads | None = None,
        accumulate: bool = False,
    ) -> tuple[GaussianGrads | None, wp.array]:
        """Gradients of a loss given its gradients w.r.t. the last ``forward``'s images
        (dL_dcolor (H, W) vec3, dL_ddepth and dL_dalpha (H, W) float; None = zero).

        Returns (per-Gaussian gradients or None when ``pose_only``, twist gradient (6,) float32 for
        xi = (rho, phi) with T_CW <- Exp(xi) T_CW).  Per-Gaussian gradients go to ``grads_out``
        (default: the renderer's own ``self.grads``), overwritten, or added when ``accumulate``;
        the twist gradient is ``self.pose_grad``, likewise overwritten or added to.
        ``pose_only`` skips writing per-Gaussian parameter gradients (the tracker's path).
        """
        if self._last is None:
            raise RuntimeError("backward() needs a forward() first")
        gmap, n, cam, bg, num_isect = self._last
        if not accumulate:
            self.pose_grad.zero_()
        grads = None if pose_only else (grads_out or self.grads)
        if n == 0:
            return grads, self.pose_grad
        image_grads = [
            dL_dcolor,
            self._zero_depth if dL_ddepth is None else dL_ddepth,
            self._zero_alpha if dL_dalpha is None else dL_dalpha,
        ]
        self._grad2d.zero_()
        if num_isect > 0:
            self._launch_raster(cam, bg, backward=True, grads=image_grads)
        g = grads or self.grads
        wp.launch_tiled(
            project_gaussians_backward,
            dim=[(n + PROJECT_BLOCK - 1) // PROJECT_BLOCK],
            inputs=[gmap.means, gmap.rotations, gmap.log_scales, gmap.opacity_logits, gmap.sh, gmap.num_sh, n]
            + [self._view, cam, self._radii, self._conic, self._grad2d, int(pose_only), int(accumulate)],
            outputs=[g.means, g.rotations, g.log_scales, g.opacity_logits, g.sh, self.pose_grad],
            block_dim=PROJECT_BLOCK,
            device=self.device,
            record_tape=False,
        )
        return grads, self.pose_grad

    def _tape_backward(self) -> None:
        gmap = self._last[0]
        grads_out = GaussianGrads.of_map_grads(gmap) if gmap.requires_grad else None
        self.backward(
            self._out_color.grad,
            self._out_depth.grad,
            self._out_alpha.grad,
            pose_only=grads_out is None,
            grads_out=grads_out,
            accumulate=True,
        )


def render(
    gmap: GaussianMap,
    camera: Camera,
    T_WC,
    background=(0.0, 0.0, 0.0),
    renderer: Renderer | None = None,
    tiled: bool = True,
) -> RenderResult:
    """One-shot rendering (a fresh ``Renderer`` unless one is given; reuse one in loops)."""
    renderer = renderer or Renderer(gmap.device, tiled=tiled)
    return renderer.forward(gmap, camera, T_WC, background)
