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


def _is_finite(v) -> bool:
    """A real number that is finite (False for strings, None, NaN and infinities)."""
    try:
        return bool(np.isfinite(float(v)))
    except (TypeError, ValueError):
        return False


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

    def __post_init__(self) -> None:
        """Refuse intrinsics that would divide by zero or mirror the image (the loaders add the file)."""
        for name in ("width", "height"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int | np.integer) or v < 1:
                raise ValueError(f"{name} = {v}: the image size must be a positive integer number of pixels")
        for name in ("fx", "fy"):
            v = getattr(self, name)
            if not (_is_finite(v) and v > 0):
                raise ValueError(f"{name} = {v}: a focal length must be a positive finite number of pixels")
        for name, size in (("cx", self.width), ("cy", self.height)):
            v = getattr(self, name)
            if not (_is_finite(v) and -0.5 <= v <= size - 0.5):
                raise ValueError(
                    f"{name} = {v}: the principal point must lie inside the {self.width}x{self.height} image "
                    f"(-0.5 .. {size - 0.5}, pixel centres at integers)"
                )

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
        if self.width // factor < 1 or self.height // factor < 1:
            raise ValueError(f"downscaling the {self.width}x{self.height} image by {factor} leaves no pixel")
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


@dataclass
class _Column:
    """One per-Gaussian column of a GaussianMap: ``array`` has ``capacity`` rows of ``dtype`` with
    ``inner`` trailing dimensions (SH: the coefficients).  ``fill`` says what a row gets when the map
    grows over it: "zero", the value of another column (e.g. "means"), or None (the parameters, which
    whoever adds the rows writes).  ``scratch`` columns (per-iteration gradients, flags) only follow
    the capacity: no fill, and a compaction does not carry them."""

    array: object
    dtype: type
    inner: tuple[int, ...]
    fill: str | None
    scratch: bool = False
    requires_grad: bool = False


class GaussianMap:
    """The Gaussian map as struct-of-arrays ``wp.array`` columns (supplement §4.1).

    Parameters (``PARAMETERS``): ``means`` (vec3, world metres), ``rotations`` (``wp.quat``, x, y, z, w;
    normalised where used), ``log_scales`` (vec3, natural log of the axis standard deviations in
    metres), ``opacity_logits`` (float, opacity = sigmoid(logit)), ``sh`` (2D array of vec3, shape
    (capacity, (sh_degree + 1)^2): real SH coefficients per colour channel, 3DGS constants and band
    order; colour = max(SH(view direction) + 0.5, 0) as in 3DGS).

    Every other per-Gaussian state lives here too, as a registered column (``add_column``): the
    optimiser's moments, the mapper's statistics, the densifier's sums.  All columns hold
    ``capacity`` rows, of which the first ``len(map)`` are live, kernels launch over ``len(map)``,
    and they change together in one place:

    * growth (``reserve``) doubles the capacity of every column, keeping the live rows; it replaces
      the arrays, so holders fetch them again (``column(name)``, or the parameter attributes);
    * new rows (``count`` set higher, ``append``) get each column's fill (zero, or a copy of another
      column), whoever wrote their parameters (a Seeder, the densifier);
    * ``remove(mask)`` compacts every non-scratch column in place, in one pass.
    """

    PARAMETERS = ("means", "rotations", "log_scales", "opacity_logits", "sh")

    def __init__(self, capacity: int = 1024, sh_degree: int = 2, device=None, requires_grad: bool = False):
        import warp as wp

        if not 0 <= sh_degree <= 3:
            raise ValueError(f"sh_degree must be in 0..3, got {sh_degree}")
        self.device = wp.get_device(device)
        self.sh_degree = sh_degree
        self.requires_grad = requires_grad
        self._count = 0
        self._capacity = max(int(capacity), 1)
        self._columns: dict[str, _Column] = {}
        for name, dtype, inner in self.parameter_layout():
            self.add_column(name, dtype, inner, fill=None, requires_grad=requires_grad)

    def parameter_layout(self):
        import warp as wp

        return (
            ("means", wp.vec3, ()),
            ("rotations", wp.quat, ()),
            ("log_scales", wp.vec3, ()),
            ("opacity_logits", wp.float32, ()),
            ("sh", wp.vec3, (self.num_sh,)),
        )

    @property
    def num_sh(self) -> int:
        return (self.sh_degree + 1) ** 2

    @property
    def capacity(self) -> int:
        return self._capacity

    def __len__(self) -> int:
        return self._count

    # ---- columns -----------------------------------------------------------------------------
    means = property(lambda self: self._columns["means"].array)
    rotations = property(lambda self: self._columns["rotations"].array)
    log_scales = property(lambda self: self._columns["log_scales"].array)
    opacity_logits = property(lambda self: self._columns["opacity_logits"].array)
    sh = property(lambda self: self._columns["sh"].array)

    def add_column(
        self,
        name: str,
        dtype,
        inner: tuple[int, ...] = (),
        fill: str | None = "zero",
        scratch: bool = False,
        requires_grad: bool = False,
    ):
        """Register a per-Gaussian column (see the class and ``_Column``) and return its array;
        registering a name again with the same layout returns the existing column (a stage rebuilt on
        the same map)."""
        import warp as wp

        inner = tuple(inner)
        if scratch:
            fill = None
        elif fill not in (None, "zero") and fill not in self._columns:
            raise ValueError(f"column {name!r}: fill {fill!r} is neither 'zero', None nor a column of the map")
        if name in self._columns:
            c = self._columns[name]
            if (c.dtype, c.inner, c.fill, c.scratch) != (dtype, inner, fill, scratch):
                raise ValueError(f"column {name!r} exists with another layout ({c.dtype}, {c.inner}, {c.fill!r})")
            return c.array
        array = wp.zeros((self._capacity, *inner), dtype=dtype, device=self.device, requires_grad=requires_grad)
        self._columns[name] = _Column(array, dtype, inner, fill, scratch, requires_grad)
        if self._count and fill is not None:
            self._fill(name, 0, self._count)
        return array

    def column(self, name: str):
        """The array of a registered column (replaced when the map grows: fetch it again)."""
        try:
            return self._columns[name].array
        except KeyError:
            raise KeyError(f"no column {name!r} in the map; columns: {', '.join(self._columns)}") from None

    def has_column(self, name: str) -> bool:
        return name in self._columns

    def column_names(self, scratch: bool = False) -> list[str]:
        """Names of the registered columns, parameters first; scratch columns only with ``scratch``."""
        return [name for name, c in self._columns.items() if scratch or not c.scratch]

    # ---- rows --------------------------------------------------------------------------------
    @property
    def count(self) -> int:
        return self._count

    @count.setter
    def count(self, n: int) -> None:
        """Set the number of live rows (e.g. after a kernel wrote new rows' parameters); rows that
        become live get every column's fill."""
        n = int(n)
        if not 0 <= n <= self._capacity:
            raise ValueError(f"count {n} outside 0..{self._capacity} (reserve first)")
        old, self._count = self._count, n
        if n > old:
            for name, c in self._columns.items():
                if c.fill is not None:
                    self._fill(name, old, n)

    def _fill(self, name: str, start: int, stop: int) -> None:
        import warp as wp

        c = self._columns[name]
        if c.fill == "zero":
            c.array[start:stop].zero_()
        else:
            rows = int(np.prod(c.inner, dtype=np.int64))
            wp.copy(c.array, self._columns[c.fill].array, start * rows, start * rows, (stop - start) * rows)

    def reserve(self, capacity: int) -> None:
        """Grow every column to at least ``capacity`` rows (doubling), keeping the live rows."""
        import warp as wp

        if capacity <= self._capacity:
            return
        self._capacity = grown_capacity(self._capacity, capacity)
        for c in self._columns.values():
            old = c.array
            c.array = wp.zeros(
                (self._capacity, *c.inner), dtype=c.dtype, device=self.device, requires_grad=c.requires_grad
            )
            if self._count:
                wp.copy(c.array, old, count=self._count * int(np.prod(c.inner, dtype=np.int64)))

    def append(self, means, quats_xyzw, log_scales, opacity_logits, sh) -> None:
        """Append rows given as NumPy arrays or ``wp.array``s (same shapes as ``from_numpy``)."""
        import warp as wp

        n = int(means.shape[0])
        if sh.shape[1] != self.num_sh:
            raise ValueError(f"sh has {sh.shape[1]} coefficients per channel, map holds {self.num_sh}")
        self.reserve(self._count + n)
        values = (means, quats_xyzw, log_scales, opacity_logits, sh)
        for (name, dtype, _), value in zip(self.parameter_layout(), values, strict=True):
            if not isinstance(value, wp.array):
                value = wp.array(np.ascontiguousarray(value, dtype=np.float32), dtype=dtype, device=self.device)
            rows = self.num_sh if name == "sh" else 1
            wp.copy(self.column(name), value, dest_offset=self._count * rows, count=n * rows)
        self.count = self._count + n

    def assign_parameters(self, src: GaussianMap) -> None:
        """Make this map's live rows a copy of ``src``'s parameter columns (device copies, ordered on
        the stream; other columns are left as they are): a published version of a working map."""
        import warp as wp

        if src.num_sh != self.num_sh:
            raise ValueError(f"src holds {src.num_sh} SH coefficients per channel, this map {self.num_sh}")
        n = len(src)
        self.reserve(n)
        self._count = n  # no fill: the copy writes every live row
        for name, _, _ in self.parameter_layout():
            rows = self.num_sh if name == "sh" else 1
            if n:
                wp.copy(self.column(name), src.column(name), count=n * rows)

    def remove(self, mask) -> None:
        """Remove the rows where ``mask`` (length ``len(self)``, bool NumPy or int32 ``wp.array``,
        nonzero = remove) is set: every column but scratch is compacted in place, in one pass, the
        survivors keeping their order."""
        import warp as wp

        from rgs_warp.kernels.map_ops import compact_rows

        n = self._count
        if not isinstance(mask, wp.array):
            mask = wp.array(np.asarray(mask).astype(np.int32), dtype=wp.int32, device=self.device)
        if mask.shape[0] != n:
            raise ValueError(f"removal mask has {mask.shape[0]} entries for {n} Gaussians")
        if n == 0:
            return
        removed_before = wp.empty(n, dtype=wp.int32, device=self.device)
        wp.utils.array_scan(mask, removed_before, inclusive=False)
        removed = int(removed_before[n - 1 : n].numpy()[0] + mask[n - 1 : n].numpy()[0])
        if removed == 0:
            return
        for c in self._columns.values():
            if c.scratch:
                continue
            width = int(np.prod(c.inner, dtype=np.int64))
            rows = c.array.reshape((self._capacity, width))
            tmp = wp.empty((n - removed, width), dtype=c.dtype, device=self.device)
            wp.launch(
                compact_rows, dim=(n, width), inputs=[rows, mask, removed_before], outputs=[tmp], device=self.device
            )
            wp.copy(c.array, tmp, count=(n - removed) * width)
        self._count = n - removed

    # ---- conversion --------------------------------------------------------------------------
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
        gmap._count = gmap._capacity = means.shape[0]
        arrays = (means, rotations, log_scales, opacity_logits, sh)
        gmap._columns = {
            name: _Column(array, dtype, inner, None, requires_grad=gmap.requires_grad)
            for (name, dtype, inner), array in zip(gmap.parameter_layout(), arrays, strict=True)
        }
        return gmap

    def to_numpy(self) -> dict[str, np.ndarray]:
        """Live parameter rows as float32 NumPy arrays keyed by name (rotations as x, y, z, w), each a
        host copy of its own (``live_rows``)."""
        return {name: self.live_rows(name) for name in self.PARAMETERS}

    def live_rows(self, name: str) -> np.ndarray:
        """Column ``name``'s live rows as a NumPy array of its own: from a GPU only the live rows are
        copied (not the capacity), and on the CPU device the copy is no view of the map's memory."""
        rows = self.column(name)[: self._count].numpy()
        return rows.copy() if self.device.is_cpu else rows
