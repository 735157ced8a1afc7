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

from rgs_warp.kernels.features import DIM, POOL1, POOL2, box_pool, daisy_descriptor, orientation_cells


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
