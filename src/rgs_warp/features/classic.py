"""``classic``: a training-free DAISY-like dense descriptor computed in Warp (no torch).

Design (Tola, Lepetit, Fua, "DAISY", PAMI 2010, adapted to a reduced-resolution grid):

1. Gradient orientation maps: for 8 directions theta_o = o * 45 deg, G_o = max(0, dI/d theta_o) of the
   grey image (central differences), i.e. the positive part of the directional derivative, a
   smooth orientation binning that needs no histogram interpolation.
2. Cells: G_o averaged over ``stride x stride`` pixel blocks; the feature grid is the cell grid, so
   feature pixel (i, j) covers image pixels stride*i .. stride*i + stride - 1 and its centre is at
   image coordinates stride*j + (stride - 1) / 2 (the convention of ``Camera.scaled``).
3. Pooling at two scales: box means of the cells over (2*POOL1+1)^2 and (2*POOL2+1)^2 cells.
4. Sampling pattern: the centre and a ring of 8 points at RING1 cells from the fine pooling, a
   ring of 8 points at RING2 cells from the coarse pooling (bilinear, borders clamped): 17
   histograms of 8 orientations, D = 136.  Upright (not rotated to a dominant orientation): SLAM
   cameras rarely roll much between keyframes and rotation invariance costs distinctiveness.
5. Normalisation: square root (the Hellinger kernel of RootSIFT: strong edges do not dominate),
   mean removed (so that unrelated patches score around 0 and Eq. 10's similarity uses the whole
   [-1, 1] range instead of crowding near 1 as non-negative histograms do), L2-normalised.  A
   descriptor of a textureless patch (norm below ``MIN_ENERGY``) is all zeros, similarity 0 to
   everything, so it never gets a confident match.

Affine brightness changes (Eq. 3's g, b) scale all G_o alike and cancel in the normalisation.
"""

from __future__ import annotations

import numpy as np
import warp as wp

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
    c = rgb[wp.clamp(y, 0, H - 1), wp.clamp(x, 0, W - 1)]
    return (c[0] + c[1] + c[2]) / 3.0


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
    H = pooled.shape[0]
    W = pooled.shape[1]
    yc = wp.clamp(y, 0.0, float(H - 1))
    xc = wp.clamp(x, 0.0, float(W - 1))
    y0 = wp.min(int(yc), H - 2)
    x0 = wp.min(int(xc), W - 2)
    fy = yc - float(y0)
    fx = xc - float(x0)
    top = (1.0 - fx) * pooled[y0, x0, o] + fx * pooled[y0, x0 + 1, o]
    bottom = (1.0 - fx) * pooled[y0 + 1, x0, o] + fx * pooled[y0 + 1, x0 + 1, o]
    return (1.0 - fy) * top + fy * bottom


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


class ClassicBackbone:
    """DAISY-like descriptors (module docstring) at 1/``stride`` resolution; D = 136."""

    name = "classic"
    dim = DIM

    def __init__(self, stride: int = 4, device=None):
        if stride < 1:
            raise ValueError(f"classic descriptor stride must be >= 1, got {stride}")
        self.stride = stride
        self.device = wp.get_device(device)
        self._shape: tuple[int, int] | None = None

    def grid_shape(self, height: int, width: int) -> tuple[int, int]:
        return height // self.stride, width // self.stride

    def _scratch(self, hf: int, wf: int) -> None:
        if self._shape == (hf, wf):
            return
        kw = {"dtype": wp.float32, "device": self.device}
        self._cells = wp.empty((hf, wf, 8), **kw)
        self._fine = wp.empty((hf, wf, 8), **kw)
        self._coarse = wp.empty((hf, wf, 8), **kw)
        self._shape = (hf, wf)

    def describe(self, rgb, out: wp.array | None = None) -> wp.array:
        """rgb: (H, W) ``wp.vec3`` array or (H, W, 3) float NumPy in [0, 1].  Returns (Hf, Wf, D)
        float32 descriptors on the device (written into ``out`` when given)."""
        if not isinstance(rgb, wp.array):
            rgb = wp.array(np.ascontiguousarray(rgb, dtype=np.float32), dtype=wp.vec3, device=self.device)
        hf, wf = self.grid_shape(*rgb.shape)
        if hf < 2 or wf < 2:
            raise ValueError(f"image {rgb.shape} too small for stride {self.stride}")
        self._scratch(hf, wf)
        if out is None:
            out = wp.empty((hf, wf, DIM), dtype=wp.float32, device=self.device)
        d = self.device
        wp.launch(orientation_cells, dim=(hf, wf), inputs=[rgb, self.stride], outputs=[self._cells], device=d)
        wp.launch(box_pool, dim=(hf, wf), inputs=[self._cells, POOL1], outputs=[self._fine], device=d)
        wp.launch(box_pool, dim=(hf, wf), inputs=[self._cells, POOL2], outputs=[self._coarse], device=d)
        wp.launch(daisy_descriptor, dim=(hf, wf), inputs=[self._fine, self._coarse], outputs=[out], device=d)
        return out
