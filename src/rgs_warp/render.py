"""Differentiable Gaussian rasterizer: colour, expected depth and accumulated opacity, with gradients
for every Gaussian parameter and the analytic camera-pose gradient (supplement §4.1-4.2).

Pipeline (one kernel per stage, all in ``rgs_warp.kernels``): EWA projection + SH colour + tile
count per Gaussian -> inclusive scan -> 32-bit (tile, quantized depth) keys per tile touched -> radix sort ->
tile ranges -> front-to-back compositing per 16x16 tile.  The backward runs the hand-written
compositing adjoint, then a per-Gaussian projection adjoint that also reduces the pose twist
gradient block by block.

Intersection buffers have a capacity: the last known count times a margin.  The count of each render
stays on the device (copied asynchronously to pinned host memory) and is read lazily, at the next
forward, when the previous render has long finished; a render whose count exceeds the capacity drops
the excess intersections, says so in ``RenderResult.overflowed`` and the next forward grows the
buffers.  The forward reads the count synchronously only when it has none to go by: the first render,
and whenever the number of Gaussians or the image size changed.  So in a tracking loop nothing waits
for the GPU, and ``forward`` + ``backward`` can be captured in a CUDA graph (``wp.ScopedCapture``)
once a render has sized the buffers; after replays, ``intersections_overflowed()`` tells whether the
graph must be re-captured.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import warp as wp

from rgs_warp.geometry import invert_pose
from rgs_warp.kernels.math import FRUSTUM_MARGIN, TILE_SIZE, CameraParams, camera_params, vec10, vec32
from rgs_warp.kernels.projection import (
    PROJECT_BLOCK,
    emit_intersections,
    intersection_key_layout,
    invert_rigid,
    pad_intersection_keys,
    project_gaussians,
    project_gaussians_backward,
    skip_tiles,
    tile_ranges_from_keys,
)
from rgs_warp.kernels.rasterize import (
    rasterize_pixels,
    rasterize_pixels_backward,
    rasterize_tiles,
    rasterize_tiles_backward,
    rasterize_tiles_pose_backward,
)
from rgs_warp.types import Camera, GaussianMap, grown_capacity

# Intersections reserved before a render is captured in a graph (tracking's steps, mapping's), x the
# count its view last needed: a replayed forward cannot grow its buffers
GRAPH_HEADROOM = 1.3

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
    (tiles, 2) int32 [start, end) into the depth-sorted ``sorted_ids``; intersection_capacity: the
    length of the intersection buffers this render used.

    ``num_intersections`` and ``overflowed`` read the count from the device: they wait for the
    render's projection stage, and like the images they describe the renderer's latest forward.
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
    intersection_capacity: int
    _renderer: Renderer = field(repr=False)

    @property
    def num_intersections(self) -> int:
        """Tile intersections the render needed (more than ``intersection_capacity`` if it overflowed)."""
        return self._renderer._read_count()

    @property
    def overflowed(self) -> bool:
        """True when intersections were dropped for lack of capacity (the next forward grows it)."""
        return self.num_intersections > self.intersection_capacity


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


class Renderer:
    """Owns every buffer of the rasterizer; ``forward`` then ``backward`` per iteration.

    ``tiled=True`` composites with one 256-thread block per 16x16 tile and shared-memory batches
    (the fast path); ``tiled=False`` uses one thread per pixel reading global memory (a simple
    second implementation).  ``near`` is the near-plane depth in metres below which Gaussians are
    culled.  ``isect_margin``: intersection capacity as a multiple of the last known count (the sort
    processes the whole capacity, so a large margin costs sort time; a small one risks overflow when
    the view changes quickly between two renders).
    """

    def __init__(self, device=None, tiled: bool = True, near: float = 0.01, isect_margin: float = 1.15):
        self.device = wp.get_device(device)
        self.tiled = tiled
        self.near = near
        self.isect_margin = isect_margin
        self._gaussian_capacity = 0
        self._isect_alloc = 0
        self._isect_capacity = 0
        self._image_shape = None
        self._view = wp.zeros(1, dtype=wp.mat44, device=self.device)
        self._view_host = wp.zeros(1, dtype=wp.mat44, device="cpu", pinned=self.device.is_cuda)
        self._isect_count = wp.zeros(1, dtype=wp.int32, device=self.device)
        self._count_host = wp.zeros(1, dtype=wp.int32, device="cpu", pinned=self.device.is_cuda)
        self._count_event = None
        self._count_key = None  # (number of Gaussians, camera) of the render whose count _count_host holds
        self._last_capacity = None  # the intersection capacity of that render (None: captured)
        self._count_view = None  # the ``view`` key of that render
        self._view_counts: dict = {}  # intersections each ``view`` key's latest counted render needed
        # eager forwards found at the next forward to have dropped intersections (no extra wait: the
        # count is read then anyway); a render of another map size or camera is not checked
        self.overflowed_renders = 0
        self.pose_grad = wp.zeros(6, dtype=wp.float32, device=self.device)
        self._no_step = wp.zeros(1, dtype=wp.int32, device=self.device)  # forward's tile_step when not given
        self._last = None
        # counts the reallocations of the buffers a render reads and writes: a captured graph holds
        # their addresses, so one captured before a reallocation must not be replayed after it
        self.buffers_version = 0

    # ---- buffers -----------------------------------------------------------------------------
    def _ensure_gaussians(self, capacity: int, num_sh: int) -> None:
        if capacity <= self._gaussian_capacity and self.grads.sh.shape[1] == num_sh:
            return
        n = max(capacity, 1)
        kw = {"device": self.device}
        self.buffers_version += 1
        self._xyod = wp.zeros(n, dtype=wp.vec4, **kw)
        self._depth = wp.zeros(n, dtype=wp.float32, **kw)
        self._depth_bits = self._depth.view(wp.int32)
        self._conic = wp.zeros(n, dtype=wp.vec3, **kw)
        self._color = wp.zeros(n, dtype=wp.vec3, **kw)
        self._radii = wp.zeros(n, dtype=wp.vec2i, **kw)
        self._touched = wp.zeros(n, dtype=wp.int32, **kw)
        self._offsets = wp.zeros(n, dtype=wp.int32, **kw)
        self._grad2d = wp.zeros(n, dtype=vec10, **kw)
        self._grad2d_floats = self._grad2d.view(wp.float32)  # (n, 10): the tiled backward adds per component
        self._pose_jac = wp.zeros(1, dtype=vec32, **kw)  # grown by the first render that needs it
        self.grads = GaussianGrads(
            wp.zeros(n, dtype=wp.vec3, **kw),
            wp.zeros(n, dtype=wp.quat, **kw),
            wp.zeros(n, dtype=wp.vec3, **kw),
            wp.zeros(n, dtype=wp.float32, **kw),
            wp.zeros((n, num_sh), dtype=wp.vec3, **kw),
        )
        self._gaussian_capacity = n

    def reserve_intersections(self, count: int) -> None:
        """Make room for ``count`` tile intersections (e.g. before capturing a graph that will render
        more than the last render needed)."""
        count = max(int(count), 1)
        if count > self._isect_alloc:
            n = grown_capacity(self._isect_alloc, count, minimum=1024)
            # radix_sort_pairs uses the second half as scratch
            self._keys = wp.zeros(2 * n, dtype=wp.uint32, device=self.device)
            self._ids = wp.zeros(2 * n, dtype=wp.int32, device=self.device)
            self._isect_alloc = n
            self.buffers_version += 1
        self._isect_capacity = max(self._isect_capacity, count)

    def _size_intersections(self, needed: int) -> None:
        """Capacity = needed x margin; shrunk (without reallocating) when far above, since the sort
        works on the whole capacity."""
        target = math.ceil(needed * self.isect_margin) + 1
        if target > self._isect_capacity or target * self.isect_margin < self._isect_capacity:
            self._isect_capacity = 0
            self.reserve_intersections(target)

    def _read_count(self) -> int:
        """The intersection count of the latest forward (waits for its projection stage)."""
        if self._count_event is not None:
            wp.synchronize_event(self._count_event)
        else:
            wp.synchronize_device(self.device)
        return int(self._count_host.numpy()[0])

    @property
    def intersection_capacity(self) -> int:
        """Tile intersections the next forward has room for (``reserve_intersections``)."""
        return self._isect_capacity

    def intersection_count(self) -> int:
        """Tile intersections the latest forward (eager or replayed from a graph) needed; waits for it."""
        return self._read_count()

    def settle(self) -> None:
        """What a forward does with the previous (eager) render's count, done now (``_settle``): before a
        capture, whose forwards cannot wait (a view rendered just before a capture was otherwise never
        counted, and its next eager render was sized by another view's count)."""
        if not self.device.is_capturing:
            self._settle()

    def _settle(self) -> int | None:
        """The previous eager render's intersection count (waiting for it), after its bookkeeping: counted
        if it overflowed its capacity, kept as its view's count; None before any render."""
        if self._count_key is None:
            return None
        count = self._read_count()
        if self._last_capacity is not None and count > self._last_capacity:
            self.overflowed_renders += 1
        if self._count_view is not None:
            self._view_counts[self._count_view] = count
        self._last_capacity, self._count_view = None, None
        return count

    def view_intersections(self, view) -> int:
        """Tile intersections the latest eager render of ``view`` (``forward``'s key) needed, 0 if none
        was seen (``settle`` first: waits for the latest render)."""
        self.settle()
        return self._view_counts.get(view, 0)

    @property
    def intersection_count_array(self) -> wp.array:
        """(1,) int32 on the device: the tile intersections the latest forward needed (a captured
        forward writes it at each replay)."""
        return self._isect_count

    def intersections_overflowed(self) -> bool:
        """Whether the latest forward (eager or replayed from a graph) dropped intersections."""
        return self._read_count() > self._isect_capacity

    def _ensure_image(self, camera: Camera) -> None:
        shape = (camera.height, camera.width)
        if shape == self._image_shape:
            return
        kw = {"device": self.device}
        self.buffers_version += 1
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

    # ---- forward -----------------------------------------------------------------------------
    def forward(
        self,
        gmap: GaussianMap,
        camera: Camera,
        T_WC,
        background=(0.0, 0.0, 0.0),
        tape: wp.Tape | None = None,
        pose_jacobians: bool = False,
        view=None,
        tile_stride: int = 1,
        tile_phase: int = 0,
        tile_step: wp.array | None = None,
        fit: bool = False,
    ) -> RenderResult:
        """Render ``gmap`` seen from camera-to-world pose ``T_WC`` (4x4 NumPy, or a 1-element
        ``wp.array`` of ``wp.mat44`` on the device, e.g. a pose the tracker updates on the GPU).

        With ``tape``, the backward is registered on it: ``tape.backward()`` after losses that read
        the returned images then accumulates into ``gmap``'s ``.grad`` arrays (when the map was made
        with ``requires_grad=True``) and into ``self.pose_grad`` (the twist gradient, zeroed here).

        ``pose_jacobians``: also store the per-Gaussian pose Jacobians that ``backward(pose_only=True)``
        folds the screen-space gradients through (without them that backward first re-runs the
        projection to get them: the tracker asks for them in every forward).

        ``view``: a key of the viewpoint (mapping: the keyframe's frame id) for a caller that
        alternates between views of different density: the capacity is then also what this view's
        previous render needed (x margin), not only the previous render's, which a denser view would
        overflow (dropping intersections: a wrong image and gradient).

        ``tile_stride`` > 1: only one 16x16 tile in ``tile_stride`` is rasterized (a checkerboard for 2,
        shifted by ``tile_phase`` plus ``tile_step[0]`` if given, a device counter:
        ``kernels.projection.skip_tiles``); the others render as nothing (colour = background, depth 0,
        opacity 0), and the backward does no work there.  The tracker's cheaper steps.

        ``fit``: size the intersection buffers by this render's own count (it waits for the projection)
        rather than by the previous render's, for a view unlike the one before it (after a view that saw
        little of the map, the previous count would drop intersections); ignored inside a capture.
        """
        dev = self.device
        n = len(gmap)
        self._ensure_gaussians(gmap.capacity, gmap.num_sh)
        self._ensure_image(camera)
        cam = camera_params(camera, self.near, FRUSTUM_MARGIN)
        if isinstance(T_WC, wp.array):
            wp.launch(invert_rigid, dim=1, inputs=[T_WC], outputs=[self._view], device=dev, record_tape=False)
        else:
            if self._count_event is not None:
                # the previous render's upload from this pinned buffer must have happened
                wp.synchronize_event(self._count_event)
            self._view_host.numpy()[0] = invert_pose(np.asarray(T_WC, dtype=np.float64))
            wp.copy(self._view, self._view_host)

        capturing = dev.is_capturing  # a CUDA graph, or Warp's CPU graph
        # Capacity from the previous render's count (finished long ago in a loop: no stall), unless
        # there is none to go by; inside a graph capture the capacity is whatever was reserved.
        exact = False
        if not capturing:
            if self._count_key == (n, camera):
                previous = self._settle()
                if fit:
                    exact = n > 0
                else:
                    self._size_intersections(previous)
            else:
                exact = n > 0
        if n > 0:
            self._project(gmap, n, cam, pose_jacobians)
            wp.utils.array_scan(self._touched[:n], self._offsets[:n], inclusive=True)
            wp.copy(self._isect_count, self._offsets, src_offset=n - 1, count=1)
        else:
            self._isect_count.zero_()
        wp.copy(self._count_host, self._isect_count)
        if capturing:
            self._count_event = None  # after a replay only a device synchronisation orders the copy
        else:
            self._count_event = wp.record_event() if dev.is_cuda else None
            self._count_key = (n, camera)
        self._count_view = None if capturing else view
        if exact:
            self._size_intersections(self._read_count())
        seen = self._view_counts.get(view, 0) if view is not None else 0
        self.reserve_intersections(max(1, math.ceil(seen * self.isect_margin)))
        capacity = self._isect_capacity
        self._last_capacity = None if capturing else capacity

        self._ranges.zero_()
        if n > 0:
            num_tiles = self._ranges.shape[0]
            depth_key_bits, depth_shift = intersection_key_layout(num_tiles)
            # the keys count depth from the near plane's float bits (from 0.1 mm for a plane at 0)
            near_bits = int(np.float32(max(self.near, 1e-4)).view(np.int32))
            wp.launch(
                emit_intersections,
                dim=n,
                inputs=[
                    self._xyod,
                    self._depth_bits,
                    self._conic,
                    self._radii,
                    self._touched,
                    self._offsets,
                    cam,
                    capacity,
                    depth_key_bits,
                    depth_shift,
                    near_bits,
                ],
                outputs=[self._keys, self._ids],
                device=dev,
                record_tape=False,
            )
            wp.launch(
                pad_intersection_keys,
                dim=capacity,
                inputs=[self._isect_count, num_tiles, depth_key_bits],
                outputs=[self._keys],
                device=dev,
                record_tape=False,
            )
            wp.utils.radix_sort_pairs(self._keys, self._ids, capacity)
            wp.launch(
                tile_ranges_from_keys,
                dim=capacity,
                inputs=[self._keys, self._isect_count, capacity, depth_key_bits],
                outputs=[self._ranges],
                device=dev,
                record_tape=False,
            )
            if tile_stride > 1:
                wp.launch(
                    skip_tiles,
                    dim=num_tiles,
                    inputs=[
                        cam.tiles_x,
                        int(tile_stride),
                        int(tile_phase),
                        self._no_step if tile_step is None else tile_step,
                    ],
                    outputs=[self._ranges],
                    device=dev,
                    record_tape=False,
                )

        bg = wp.vec3(*[float(c) for c in background])
        self._launch_raster(cam, bg, backward=False)
        self._last = (gmap, n, cam, bg, bool(pose_jacobians))
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
            capacity,
            self,
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

    def _project(self, gmap: GaussianMap, n: int, cam: CameraParams, pose_jacobians: bool) -> None:
        # 128 bytes per Gaussian, so only renderers that run the pose-only backward hold them
        if pose_jacobians and self._pose_jac.shape[0] < self._gaussian_capacity:
            self._pose_jac = wp.zeros(self._gaussian_capacity, dtype=vec32, device=self.device)
            self.buffers_version += 1
        wp.launch(
            project_gaussians,
            dim=n,
            inputs=[gmap.means, gmap.rotations, gmap.log_scales, gmap.opacity_logits, gmap.sh, gmap.num_sh]
            + [self._view, cam, int(pose_jacobians)],
            outputs=[self._xyod, self._depth, self._conic, self._color, self._radii, self._touched, self._pose_jac],
            device=self.device,
            record_tape=False,
        )

    def _launch_raster(self, cam: CameraParams, bg, backward: bool, grads=None, pose_only: bool = False) -> None:
        common = [self._ranges, self._ids, self._xyod, self._conic, self._color, bg, cam.width, cam.height]
        common.append(cam.tiles_x)
        shape = self._image_shape
        if backward and self.tiled and pose_only:
            kernel = rasterize_tiles_pose_backward
            inputs = common + [self._final_t, self._n_contrib, *grads, self._pose_jac, cam.fx, cam.fy]
            outputs = [self.pose_grad]
        elif backward and self.tiled:
            kernel = rasterize_tiles_backward
            inputs = common + [self._final_t, self._n_contrib, *grads]
            outputs = [self._grad2d_floats]
        elif backward:
            kernel = rasterize_pixels_backward
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
        with_pose: bool = True,
    ) -> tuple[GaussianGrads | None, wp.array | None]:
        """Gradients of a loss given its gradients w.r.t. the last ``forward``'s images
        (dL_dcolor (H, W) vec3, dL_ddepth and dL_dalpha (H, W) float; None = zero).

        Returns (per-Gaussian gradients or None when ``pose_only``, twist gradient (6,) float32 for
        xi = (rho, phi) with T_CW <- Exp(xi) T_CW).  Per-Gaussian gradients go to ``grads_out``
        (default: the renderer's own ``self.grads``), overwritten, or added when ``accumulate``;
        the twist gradient is ``self.pose_grad``, likewise overwritten or added to.
        ``pose_only`` skips writing per-Gaussian parameter gradients (the tracker's path);
        ``with_pose=False`` skips the twist gradient (the mapper's path: ``self.pose_grad`` is left as
        it is and None returned for it).
        """
        if self._last is None:
            raise RuntimeError("backward() needs a forward() first")
        gmap, n, cam, bg, have_pose_jac = self._last
        with_pose = with_pose or pose_only
        pose_grad = self.pose_grad if with_pose else None
        if with_pose and not accumulate:
            self.pose_grad.zero_()
        grads = None if pose_only else (grads_out or self.grads)
        if n == 0:
            return grads, pose_grad
        image_grads = [
            dL_dcolor,
            self._zero_depth if dL_ddepth is None else dL_ddepth,
            self._zero_alpha if dL_dalpha is None else dL_dalpha,
        ]
        if pose_only and self.tiled:
            if not have_pose_jac:
                self._project(gmap, n, cam, pose_jacobians=True)
                self._last = (gmap, n, cam, bg, True)
            self._launch_raster(cam, bg, backward=True, grads=image_grads, pose_only=True)
            return grads, self.pose_grad
        self._grad2d.zero_()
        self._launch_raster(cam, bg, backward=True, grads=image_grads)
        g = grads or self.grads
        wp.launch_tiled(
            project_gaussians_backward,
            dim=[(n + PROJECT_BLOCK - 1) // PROJECT_BLOCK],
            inputs=[gmap.means, gmap.rotations, gmap.log_scales, gmap.opacity_logits, gmap.sh, gmap.num_sh, n]
            + [self._view, cam, self._radii, self._conic, self._grad2d]
            + [int(pose_only), int(with_pose), int(accumulate)],
            outputs=[g.means, g.rotations, g.log_scales, g.opacity_logits, g.sh, self.pose_grad],
            block_dim=PROJECT_BLOCK,
            device=self.device,
            record_tape=False,
        )
        return grads, pose_grad

    # ---- read-only views of the latest render, for the stages that follow it --------------------
    @property
    def grad2d(self) -> wp.array:
        """(capacity,) ``vec10`` screen-space gradients of the latest full (not pose-only) ``backward``,
        layout of ``kernels.projection.vec10``: [0], [1] = dL/du, dL/dv of the projected mean in pixels."""
        return self._grad2d

    @property
    def radii(self) -> wp.array:
        """(capacity,) ``vec2i`` pixel half-extents of the latest forward, (0, 0) for culled Gaussians."""
        return self._radii

    @property
    def image_shape(self) -> tuple[int, int] | None:
        """(height, width) of the latest forward's images (None before the first)."""
        return self._image_shape

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
