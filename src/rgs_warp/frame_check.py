"""The frames given to ``SLAM.process`` checked at the boundary, the first one included, before any
stage sees them (docs/decisions.md, "Frame validation"), and staged on the device once.

Two kinds of problem, two answers:

* The caller's mistakes, which every frame would repeat, raise ``ValueError`` and change nothing: a
  shape other than the camera's (transposed, another resolution, RGBA), a dtype that is not
  floating point (uint8 colour is not converted, since 8- and 16-bit colour, or millimetre and
  metre depth, cannot be told apart: the message says what to divide by), colour outside [0, 1],
  negative depth.
* The data's faults, as a sensor's dropouts, are masked and counted: a depth that is not finite
  becomes 0 (no depth, as everywhere); a colour pixel that is not finite takes the colour of the
  nearest finite pixel and loses its depth, so it seeds nothing and carries no depth term, and its
  flat fill gets almost no weight in tracking (Eq. 8's gradient weight); the mapper's colour loss,
  which has no per-pixel mask, sees the neighbour's colour.  A frame where more than
  ``MAX_NONFINITE_RGB`` of the colour is not finite, or (RGB-D) less than ``MIN_VALID_DEPTH`` of the
  pixels has depth, is unusable: ``SLAM.process`` refuses it as the first frame (no map can start
  from it) and marks a later one lost, with the reason, without tracking or mapping it.

The checked frame's images are device arrays, what every stage reads: ``wp.array`` frames in place,
NumPy frames copied into the checker's buffers (the SLAM's: the tracker's input buffers, which it then
reads without another copy).  ``wp.array`` frames are checked by a kernel on their device
(``kernels/frame_check.py``) and copied to the host only when something has to be masked or explained.
NumPy frames of a SLAM on a CUDA device are uploaded first and checked there the same way; on the CPU
device they are checked on the host, then copied (at 1200x680 the host's passes over the image took
2.3 ms of a frame on an H100 machine, the upload and kernel about 0.5 ms).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import warp as wp
from scipy.ndimage import distance_transform_edt

from rgs_warp.geometry import rigid_pose_problem
from rgs_warp.kernels import frame_check as fk
from rgs_warp.types import Camera

__all__ = ["CheckedFrame", "FrameChecker", "Uploads", "as_float_image"]

# Colour within [0, 1] up to this (float images that were resampled or colour-corrected may overshoot
# by rounding); values beyond are a scaling mistake, not noise.
RANGE_TOL = 1e-3
# A frame with more colour pixels than this fraction not finite is not used (the fill would invent
# that much of the image); below it the pixels are filled and counted.
MAX_NONFINITE_RGB = 0.01
# RGB-D: a frame with valid depth at fewer than this fraction of its pixels is not used (a covered or
# failed sensor; real indoor Kinect frames have depth at 60-95 % of their pixels).
MIN_VALID_DEPTH = 0.01


@dataclass
class CheckedFrame:
    """A frame after ``FrameChecker.check``: ``rgb`` and ``depth`` are what the stages get, device arrays
    at the camera's size (the input's ``wp.array``s, or the checker's buffers holding the NumPy input,
    faulty pixels masked; ``depth`` None in "mono"); ``nonfinite_rgb`` colour pixels were filled,
    ``nonfinite_depth`` depth values set to 0; ``unusable`` says why the frame cannot be tracked or
    mapped ("" when it can)."""

    rgb: wp.array
    depth: wp.array | None
    nonfinite_rgb: int = 0
    nonfinite_depth: int = 0
    unusable: str = ""


def as_float_image(image, shape: tuple[int, ...], name: str) -> np.ndarray:
    """``image`` (array-like) as a NumPy array of its own float dtype, if its shape is ``shape`` and its
    dtype floating point; else a ValueError that says how to fix it.  Values are not looked at."""
    try:
        a = np.asarray(image)
    except (TypeError, ValueError) as e:
        raise ValueError(f"{name}: not an array ({type(e).__name__}: {e})") from None
    kind = a.dtype.kind
    if kind in "ui":
        if name == "depth":
            fix = "pass float32 metres, e.g. depth.astype(np.float32) / 1000 for millimetres"
        else:
            bits = "16" if a.dtype.itemsize > 1 else "8"
            fix = f"pass float32 in [0, 1], e.g. rgb.astype(np.float32) / {65535 if bits == '16' else 255}"
        raise ValueError(f"{name}: dtype {a.dtype} is not converted ({fix})")
    if kind != "f":
        raise ValueError(f"{name}: dtype {a.dtype}: expected floating point (float32)")
    if a.shape != shape:
        raise ValueError(f"{name}: expected shape {shape} (the camera's), got {a.shape}{_shape_hint(a.shape, shape)}")
    return a


def _shape_hint(got: tuple, want: tuple) -> str:
    if len(got) == len(want) and got[:2] == want[:2][::-1] and got[2:] == want[2:]:
        return ": transposed? (rows are the image's height)"
    if len(want) == 3 and got == want[:2] + (4,):
        return ": drop the alpha channel (rgb[..., :3])"
    if len(want) == 3 and got == want[:2]:
        return ": a grey image? (np.repeat(grey[..., None], 3, axis=2))"
    if len(want) == 2 and got == want + (1,):
        return ": drop the last axis (depth[..., 0])"
    if len(got) == len(want) and got[2:] == want[2:]:
        return f": {got[1]}x{got[0]} images need a Camera of that size (or resize them to {want[1]}x{want[0]})"
    return ""


class Uploads:
    """NumPy images copied into device arrays: on a CUDA device through a page-locked host buffer of the
    destination's shape and dtype (made at its first use), on the CPU device straight into it."""

    def __init__(self, device):
        self.device = wp.get_device(device)
        self._host: dict[tuple, wp.array] = {}

    def copy(self, image: np.ndarray, dst: wp.array) -> wp.array:
        """``image`` (of ``dst``'s shape, channels last) copied into ``dst``; returns ``dst``."""
        if not self.device.is_cuda:  # a CPU array's NumPy view is its memory
            np.copyto(dst.numpy().reshape(image.shape), image)
            return dst
        key = (dst.shape, dst.dtype)
        if key not in self._host:
            self._host[key] = wp.empty(dst.shape, dtype=dst.dtype, device="cpu", pinned=True)
        host = self._host[key]
        np.copyto(host.numpy().reshape(image.shape), image)
        wp.copy(dst, host)
        return dst


class FrameChecker:
    """Checks frames of ``camera``'s size for the SLAM on ``device`` (``mode`` "rgbd" reads depth) and
    stages them there; build once, call ``check`` per frame."""

    def __init__(
        self,
        camera: Camera,
        device,
        mode: str = "rgbd",
        upload: bool | None = None,
        buffers: tuple[wp.array, wp.array] | None = None,
    ):
        """``upload``: NumPy float32 frames are copied to the device first and checked there (module
        docstring); default: on CUDA devices.  ``buffers``: the (rgb, depth) device arrays of the camera's
        size that NumPy frames are copied into (the SLAM gives the tracker's, ``Tracker.frame_buffers``);
        default: the checker's own.  A checked frame's arrays are then these, valid until the next
        ``check``."""
        self.camera, self.device, self.mode = camera, wp.get_device(device), mode
        self.shape = (camera.height, camera.width)
        self.upload = self.device.is_cuda if upload is None else bool(upload)
        self._counts = wp.zeros(fk.N_COUNTS, dtype=wp.int32, device=self.device)
        self._no_depth = wp.zeros((1, 1), dtype=wp.float32, device=self.device)
        self._uploads = Uploads(self.device)
        self._buffers = {} if buffers is None else dict(zip(("rgb", "depth"), buffers, strict=True))

    def check(self, rgb, depth=None) -> CheckedFrame:
        """The frame checked and on the device (module docstring); ``depth`` is ignored unless the mode is
        "rgbd", where it is required.  Raises ValueError for the caller's mistakes."""
        if self.mode != "rgbd":
            depth = None
        elif depth is None:
            raise ValueError("mode 'rgbd' needs a depth image for every frame (or set mode=mono)")
        if isinstance(rgb, wp.array) or isinstance(depth, wp.array):
            frame = self._check_device(rgb, depth)
        else:
            frame = self._check_numpy(rgb, depth)
        frame.rgb, frame.depth = self._staged(frame.rgb, "rgb"), self._staged(frame.depth, "depth")
        return frame

    def _check_numpy(self, rgb, depth) -> CheckedFrame:
        if self.upload:
            rgb_h = as_float_image(rgb, self.shape + (3,), "rgb")
            depth_h = None if depth is None else as_float_image(depth, self.shape, "depth")
            if rgb_h.dtype == np.float32 and (depth_h is None or depth_h.dtype == np.float32):
                staged = [self._staged(image, name) for image, name in ((rgb_h, "rgb"), (depth_h, "depth"))]
                return self._check_device(*staged, host=(rgb_h, depth_h))
        return self._check_host(rgb, depth)

    def _staged(self, image: np.ndarray | wp.array | None, name: str) -> wp.array | None:
        """``image`` on the device: a device array as it is, a NumPy one copied into the buffer for ``name``."""
        if image is None or isinstance(image, wp.array):
            return image
        if name not in self._buffers:
            dtype = wp.vec3 if name == "rgb" else wp.float32
            self._buffers[name] = wp.empty(self.shape, dtype=dtype, device=self.device)
        return self._uploads.copy(image, self._buffers[name])

    def _check_device(self, rgb, depth, host: tuple | None = None) -> CheckedFrame:
        """``host``: the NumPy frame that ``rgb`` and ``depth`` were uploaded from (what is masked or
        explained when something is off, instead of a copy back).  A frame to mask comes back with the
        host check's NumPy images."""
        for image, name, dtype in ((rgb, "rgb", wp.vec3), (depth, "depth", wp.float32)):
            if image is None:
                continue
            if not isinstance(image, wp.array):
                raise ValueError(f"{name}: give rgb and depth both as wp.arrays or both as NumPy arrays")
            if image.shape != self.shape or image.dtype != dtype or image.device != self.device:
                raise ValueError(
                    f"{name}: expected a {self.shape} wp.array of {dtype.__name__} on {self.device} (the camera's "
                    f"size), got {image.shape} {image.dtype.__name__} on {image.device}"
                    + _shape_hint(image.shape, self.shape)
                )
        has_depth = depth is not None
        fk.frame_counts(rgb, depth if has_depth else self._no_depth, has_depth, RANGE_TOL, self._counts)
        counts = self._counts.numpy()
        if counts[[fk.C_RGB_NONFINITE, fk.C_RGB_OUT_OF_RANGE, fk.C_DEPTH_NONFINITE, fk.C_DEPTH_NEGATIVE]].any():
            if host is not None:
                return self._check_host(*host)  # to mask or explain
            return self._check_host(rgb.numpy(), depth.numpy() if has_depth else None)
        unusable = _depth_problem(int(counts[fk.C_DEPTH_VALID]), self.shape) if has_depth else ""
        return CheckedFrame(rgb, depth, unusable=unusable)

    def _check_host(self, rgb, depth) -> CheckedFrame:
        """The check on the host: the frame's images come back as float32 NumPy arrays (the input where
        nothing was masked)."""
        rgb = as_float_image(rgb, self.shape + (3,), "rgb")
        # min and max propagate NaN: finite bounds mean a finite image, the common case in two passes
        lo, hi = rgb.min(), rgb.max()
        finite_rgb = None if np.isfinite(lo) and np.isfinite(hi) else np.isfinite(rgb).all(axis=2)
        if finite_rgb is not None:
            lo, hi = _finite_bounds(rgb[finite_rgb])
        if lo < -RANGE_TOL or hi > 1.0 + RANGE_TOL:
            raise ValueError(f"rgb: values from {lo:g} to {hi:g}: expected [0, 1]{_range_hint(hi)}")
        out = CheckedFrame(np.asarray(rgb, dtype=np.float32), None)
        if depth is not None:
            depth = np.asarray(as_float_image(depth, self.shape, "depth"), dtype=np.float32)  # beyond float32: inf
            d_lo, d_hi = depth.min(), depth.max()
            finite_depth = None if np.isfinite(d_lo) and np.isfinite(d_hi) else np.isfinite(depth)
            if finite_depth is not None:
                d_lo, _ = _finite_bounds(depth[finite_depth])
            if d_lo < 0.0:
                n = int(np.count_nonzero(depth < 0.0)) - int(np.count_nonzero(depth == -np.inf))
                raise ValueError(
                    f"depth: {n} pixels are negative (down to {d_lo:g}): expected metres >= 0 with 0 = no depth "
                    f"(a depth of the wrong sign, e.g. OpenGL's -z?)"
                )
            if finite_depth is not None:
                out.nonfinite_depth = int(depth.size - np.count_nonzero(finite_depth))
                depth = np.where(finite_depth, depth, np.float32(0.0))
            out.depth = depth
        problems = []
        if finite_rgb is not None:
            bad = ~finite_rgb
            out.nonfinite_rgb = int(np.count_nonzero(bad))
            if out.nonfinite_rgb > MAX_NONFINITE_RGB * bad.size:
                share = out.nonfinite_rgb / bad.size
                problems.append(
                    f"{out.nonfinite_rgb} colour pixels ({share:.1%}) are not finite (> {MAX_NONFINITE_RGB:.0%})"
                )
            else:  # the nearest finite pixel's colour, and no depth
                rows, cols = distance_transform_edt(bad, return_distances=False, return_indices=True)
                out.rgb = out.rgb[rows, cols]
                if out.depth is not None:
                    out.depth = np.where(bad, np.float32(0.0), out.depth)
        if out.depth is not None:
            problems.append(_depth_problem(int(np.count_nonzero(out.depth > 0.0)), self.shape))
        out.unusable = "; ".join(p for p in problems if p)
        return out


def _finite_bounds(values: np.ndarray) -> tuple[float, float]:
    """(min, max) of finite values, (0, 0) when there are none."""
    return (float(values.min()), float(values.max())) if values.size else (0.0, 0.0)


def _range_hint(hi: float) -> str:
    if hi > 255.0 + RANGE_TOL:
        return " (16-bit values? divide by 65535)"
    if hi > 1.0 + RANGE_TOL:
        return " (8-bit values? divide by 255)"
    return " (clip with np.clip(rgb, 0, 1))"


def _depth_problem(valid: int, shape: tuple[int, int]) -> str:
    n = shape[0] * shape[1]
    if valid >= MIN_VALID_DEPTH * n:
        return ""
    return (
        f"depth at {valid} of {n} pixels (< {MIN_VALID_DEPTH:.0%}; 0 and non-finite values are no depth): nothing to "
        f"track or map with (check the depth scale, or use mode=mono)"
    )


def checked_pose(T, name: str) -> np.ndarray:
    """``T`` as a float64 4x4 if it is a finite rigid transform (rotation orthonormal to 1e-3, last row
    0 0 0 1, as the loaders' ``check_pose``), else a ValueError."""
    try:
        T = np.array(T, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"{name}: expected a 4x4 camera-to-world matrix of numbers") from None
    if T.shape != (4, 4):
        raise ValueError(f"{name}: expected a finite 4x4 camera-to-world matrix, got shape {T.shape}")
    if not np.all(np.isfinite(T)):
        rows, cols = np.nonzero(~np.isfinite(T))
        where = ", ".join(f"[{r}, {c}] = {T[r, c]}" for r, c in zip(rows[:3], cols[:3], strict=True))
        raise ValueError(f"{name}: expected a finite 4x4 camera-to-world matrix, got non-finite entries: {where}")
    problem = rigid_pose_problem(T)
    if problem:
        raise ValueError(f"{name}: {problem}")
    return T
