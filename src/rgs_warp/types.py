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
