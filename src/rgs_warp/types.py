"""Plain data shared by every stage: Camera, Frame (and GaussianMap, added with the renderer).

Conventions, stated once for the whole project:

* Camera frame is OpenCV's: x right, y down, z forward.
* Poses are camera-to-world ``T_WC`` (4x4, float64) at every interface.
* Pixel (u, v)'s centre is at image coordinates (u, v) (OpenCV's convention, the one the datasets'
  calibrations assume, e.g. Replica cx = 599.5 = (1200 - 1) / 2).  A point X_C projects to
  ``u = fx * x / z + cx``, ``v = fy * y / z + cy`` and the renderer samples pixel centres at integer
  (u, v), so rendering and depth back-projection agree.  (3DGS/gsplat sample at u + 0.5; we do not.)
* Images are float32 HxWx3 in [0, 1]; depth is float32 metres with 0 = invalid.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np


def grown_capacity(current: int, needed: int, minimum: int = 1) -> int:
    """Capacity after doubling ``current`` (at least ``minimum``) until ``needed`` rows fit: the
    growth rule of every preallocated buffer, so appends cost amortised O(1) and rarely reallocate."""
    capacity = max(current, minimum, 1)
    while capacity < needed:
        capacity *= 2
    return capacity


@dataclass(frozen=True)
class Camera:
    """Pinhole intrinsics (OpenCV convention) and image size; ``distortion`` is OpenCV's
    (k1, k2, p1, p2, k3) of the raw images, empty when the images are undistorted."""

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    distortion: tuple[float, ...] = field(default=())

    @property
    def K(self) -> np.ndarray:
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    def scaled(self, factor: int) -> Camera:
        """Intrinsics of the image downscaled by an integer ``factor`` (area averaging).

        New pixel u' averages old pixels s*u' .. s*u'+s-1, whose centre is s*u' + (s-1)/2, hence
        cx' = (cx - (s-1)/2) / s = (cx + 0.5) / s - 0.5.
        """
        if factor == 1:
            return self
        s = float(factor)
        return replace(
            self,
            fx=self.fx / s,
            fy=self.fy / s,
            cx=(self.cx + 0.5) / s - 0.5,
            cy=(self.cy + 0.5) / s - 0.5,
            width=self.width // factor,
            height=self.height // factor,
        )

    def undistorted(self) -> Camera:
        return replace(self, distortion=())


@dataclass
class Frame:
    """One RGB(-D) observation.

    rgb: HxWx3 float32 in [0, 1]; depth: HxW float32 metres (0 = invalid) or None (monocular);
    pose_gt: 4x4 float64 camera-to-world ground truth or None; timestamp in seconds; index is the
    position in the dataset (after start/stride).
    """

    rgb: np.ndarray
    depth: np.ndarray | None
    pose_gt: np.ndarray | None
    timestamp: float
    index: int

    @property
    def height(self) -> int:
        return self.rgb.shape[0]

    @property
    def width(self) -> int:
        return self.rgb.shape[1]


_GAUSSIAN_FIELDS = ("means", "rotations", "log_scales", "opacity_logits", "sh")


class GaussianMap:
    """The Gaussian map as struct-of-arrays ``wp.array`` fields (supplement §4.1).

    Fields hold ``capacity`` rows, of which the first ``len(map)`` are live; kernels launch over
    ``len(map)``.  ``means`` (vec3, world metres), ``rotations`` (``wp.quat``, x, y, z, w; normalised
    where used), ``log_scales`` (vec3, natural log of the axis standard deviations in metres),
    ``opacity_logits`` (float, opacity = sigmoid(logit)), ``sh`` (2D array of vec3, shape
    (capacity, (sh_degree + 1)^2): real SH coefficients per colour channel, 3DGS constants and
    band order; colour = max(SH(view direction) + 0.5, 0) as in 3DGS).

    Capacity doubles when an append needs more room; growing replaces the field arrays (holders
    of the old arrays must fetch them again), while ``remove`` compacts in place.
    """

    def __init__(self, capacity: int = 1024, sh_degree: int = 2, device=None, requires_grad: bool = False):
        import warp as wp

        if not 0 <= sh_degree <= 3:
            raise ValueError(f"sh_degree must be in 0..3, got {sh_degree}")
        self.device = wp.get_device(device)
        self.sh_degree = sh_degree
        self.requires_grad = requires_grad
        self.count = 0
        self._allocate(max(int(capacity), 1))

    @property
    def num_sh(self) -> int:
        return (self.sh_degree + 1) ** 2

    @property
    def capacity(self) -> int:
        return self.means.shape[0]

    def __len__(self) -> int:
        return self.count

    def _allocate(self, capacity: int) -> None:
        import warp as wp

        kw = {"device": self.device, "requires_grad": self.requires_grad}
        self.means = wp.zeros(capacity, dtype=wp.vec3, **kw)
        self.rotations = wp.zeros(capacity, dtype=wp.quat, **kw)
        self.log_scales = wp.zeros(capacity, dtype=wp.vec3, **kw)
        self.opacity_logits = wp.zeros(capacity, dtype=wp.float32, **kw)
        self.sh = wp.zeros((capacity, self.num_sh), dtype=wp.vec3, **kw)

    def reserve(self, capacity: int) -> None:
        """Grow to at least ``capacity`` rows (doubling), keeping the live rows."""
        import warp as wp

        if capacity <= self.capacity:
            return
        new_capacity = grown_capacity(self.capacity, capacity)
        old = {name: getattr(self, name) for name in _GAUSSIAN_FIELDS}
        self._allocate(new_capacity)
        if self.count:
            for name in _GAUSSIAN_FIELDS:
                wp.copy(getattr(self, name), old[name], count=self.count * (self.num_sh if name == "sh" else 1))

    def append(self, means, quats_xyzw, log_scales, opacity_logits, sh) -> None:
        """Append rows given as NumPy arrays or ``wp.array``s (same shapes as ``from_numpy``)."""
        import warp as wp

        n = int(means.shape[0])
        if sh.shape[1] != self.num_sh:
            raise ValueError(f"sh has {sh.shape[1]} coefficients per channel, map holds {self.num_sh}")
        self.reserve(self.count + n)
        dtypes = (wp.vec3, wp.quat, wp.vec3, wp.float32, wp.vec3)
        for name, dtype, value in zip(
            _GAUSSIAN_FIELDS, dtypes, (means, quats_xyzw, log_scales, opacity_logits, sh), strict=True
        ):
            if not isinstance(value, wp.array):
                value = wp.array(np.ascontiguousarray(value, dtype=np.float32), dtype=dtype, device=self.device)
            rows = self.num_sh if name == "sh" else 1
            wp.copy(getattr(self, name), value, dest_offset=self.count * rows, count=n * rows)
        self.count += n

    def remove(self, mask) -> None:
        """Remove the rows where ``mask`` (length ``len(self)``, bool NumPy or int32 ``wp.array``,
        nonzero = remove) is set, compacting the survivors in place in their original order."""
        import warp as wp

        from rgs_warp.kernels.map_ops import scatter_kept, scatter_kept_rows

        n = self.count
        if n == 0:
            return
        if not isinstance(mask, wp.array):
            mask = wp.array(np.asarray(mask).astype(np.int32), dtype=wp.int32, device=self.device)
        removed_before = wp.empty(n, dtype=wp.int32, device=self.device)
        wp.utils.array_scan(mask, removed_before, inclusive=False)
        removed = int(removed_before[n - 1 : n].numpy()[0] + mask[n - 1 : n].numpy()[0])
        for name in _GAUSSIAN_FIELDS:
            field_ = getattr(self, name)
            tmp = wp.empty_like(field_)
            if name == "sh":
                wp.launch(
                    scatter_kept_rows,
                    dim=(n, self.num_sh),
                    inputs=[field_, mask, removed_before, tmp],
                    device=self.device,
                )
            else:
                wp.launch(scatter_kept, dim=n, inputs=[field_, mask, removed_before, tmp], device=self.device)
            rows = self.num_sh if name == "sh" else 1
            wp.copy(field_, tmp, count=(n - removed) * rows)
        self.count = n - removed

    @classmethod
    def from_numpy(
        cls,
        means: np.ndarray,
        quats_xyzw: np.ndarray,
        log_scales: np.ndarray,
        opacity_logits: np.ndarray,
        sh: np.ndarray,
        device=None,
        requires_grad: bool = False,
        capacity: int | None = None,
    ) -> GaussianMap:
        """Map from arrays (N,3), (N,4), (N,3), (N,), (N, K, 3) with K = (degree + 1)^2."""
        num_sh = sh.shape[1]
        degree = round(num_sh**0.5) - 1
        if (degree + 1) ** 2 != num_sh or sh.ndim != 3 or sh.shape[2] != 3:
            raise ValueError(f"sh must be (N, (deg+1)^2, 3), got {sh.shape}")
        n = means.shape[0]
        gmap = cls(max(capacity or n, 1), degree, device, requires_grad)
        if n:
            gmap.append(means, quats_xyzw, log_scales, opacity_logits, sh)
        return gmap

    @classmethod
    def from_arrays(cls, means, rotations, log_scales, opacity_logits, sh) -> GaussianMap:
        """Zero-copy map over existing ``wp.array``s (e.g. ``wp.from_torch`` views), all rows live."""
        num_sh = sh.shape[1]
        gmap = cls.__new__(cls)
        gmap.device = means.device
        gmap.sh_degree = round(num_sh**0.5) - 1
        gmap.requires_grad = means.requires_grad
        gmap.count = means.shape[0]
        gmap.means, gmap.rotations, gmap.log_scales = means, rotations, log_scales
        gmap.opacity_logits, gmap.sh = opacity_logits, sh
        return gmap

    def to_numpy(self) -> dict[str, np.ndarray]:
        """Live rows as float32 NumPy arrays keyed by field name (rotations as x, y, z, w)."""
        n = self.count
        return {name: getattr(self, name).numpy()[:n] for name in _GAUSSIAN_FIELDS}
