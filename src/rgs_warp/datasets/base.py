"""Common machinery of the dataset loaders: lazy frame loading with background prefetch, image
readers that fail with a clear message, integer downscaling, selection by start/stride/max_frames."""

from __future__ import annotations

import math
import warnings
from collections import deque
from collections.abc import Iterable, Iterator
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import cv2
import numpy as np

from rgs_warp.geometry import rigid_pose_problem
from rgs_warp.types import Camera, Frame


class DatasetError(RuntimeError):
    """A dataset that is missing or malformed; the message names the file and the problem."""


class DatasetWarning(UserWarning):
    """A dataset that loads but not as a whole (e.g. frames dropped); also in the dataset's repr."""


# Threads that read frames ahead of the SLAM (``RGBDDataset.__iter__``).  One 1200x680 Replica frame took
# 23 ms to read on a 2-core CPU; with a consumer at 15 ms a frame and a busy second thread it waited
# 2.9-4.6 ms a frame with one thread (2 ahead), 0.7-0.8 with two (4 ahead), 1.0-1.3 with three (6 ahead)
# (docs/decisions.md, "Prefetch"; three for the GPU machines' 16 cores, not measured there).  A live
# office run on the H100 waited 3.1 s of 12.0 s for frames with one thread.
LOAD_THREADS = 3


def read_rgb(path: Path) -> np.ndarray:
    """HxWx3 float32 RGB in [0, 1] from a JPEG/PNG file (8 or 16 bit)."""
    data = _read_bytes(path)
    if path.suffix.lower() in (".jpg", ".jpeg") and not data.rstrip(b"\x00").endswith(b"\xff\xd9"):
        # OpenCV decodes a truncated JPEG silently (grey bottom rows), so check the end marker.
        raise DatasetError(f"{path}: truncated JPEG (no end-of-image marker)")
    img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise DatasetError(f"{path}: not a readable image (corrupt or truncated)")
    if img.ndim == 2:
        img = np.repeat(img[:, :, None], 3, axis=2)
    if img.shape[2] == 4:
        img = img[:, :, :3]
    scale = 65535.0 if img.dtype == np.uint16 else 255.0
    return np.ascontiguousarray(img[:, :, ::-1], dtype=np.float32) / np.float32(scale)


def read_depth(path: Path, scale: float) -> np.ndarray:
    """HxW float32 depth in metres (raw / scale; 0 stays 0 = invalid) from a 16-bit PNG."""
    img = cv2.imdecode(np.frombuffer(_read_bytes(path), np.uint8), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise DatasetError(f"{path}: not a readable depth image (corrupt or truncated)")
    if img.dtype != np.uint16 or img.ndim != 2:
        raise DatasetError(
            f"{path}: expected a single-channel 16-bit depth PNG, got dtype {img.dtype} with shape {img.shape}"
        )
    return img.astype(np.float32) / np.float32(scale)


# a first frame's median depth outside this (m) is in other units than the depth scale says
PLAUSIBLE_DEPTH_M = (0.1, 20.0)
KNOWN_DEPTH_SCALES = (1000.0, 5000.0, 6553.5)  # raw units per metre: millimetres, TUM, Replica


def check_depth_scale(ds) -> None:
    """A ``DatasetError`` naming ``dataset.depth_scale`` and a value that fits when the first frame's
    depth (``ds.depth_scale`` raw units per metre), at the median of its valid pixels, lies outside
    ``PLAUSIBLE_DEPTH_M``: read in the wrong unit, every frame would be lost."""
    depth = ds[0].depth
    valid = depth[depth > 0] if depth is not None else ()
    if len(valid) == 0:  # no depth: the frame check says so
        return
    median_m, (lo, hi) = float(np.median(valid)), PLAUSIBLE_DEPTH_M
    if lo <= median_m <= hi:
        return
    raw = median_m * ds.depth_scale
    fits = [s for s in KNOWN_DEPTH_SCALES if lo <= raw / s <= hi]
    fit = min(fits, key=lambda s: abs(math.log(raw / s / 2.0))) if fits else float(f"{raw / 2.0:.3g}")
    raise DatasetError(
        f"{ds.root}: the first frame's depth is {median_m:.3g} m at its median ({raw:.4g} raw / depth scale "
        f"{ds.depth_scale:g}), outside {lo:g}-{hi:g} m: its depth images are in other units; "
        f"dataset.depth_scale={fit:g} (raw units per metre) reads them as {raw / fit:.2g} m"
    )


def _read_bytes(path: Path) -> bytes:
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        raise DatasetError(f"{path}: file not found") from None
    except OSError as e:
        raise DatasetError(f"{path}: cannot read ({e.strerror})") from None
    if not data:
        raise DatasetError(f"{path}: empty file")
    return data


def check_pose(T: np.ndarray, where: str) -> np.ndarray:
    """Validate a camera-to-world pose: finite, rigid (orthonormal rotation to 1e-3, last row
    0 0 0 1); returns it with the rotation replaced by the nearest rotation matrix (SVD) unless it
    is one to 1e-9 already, since
    text files round it (7-Scenes' KinectFusion poses are orthonormal only to ~2e-4, and a pose
    written back, e.g. as a TUM trajectory, must be a rotation to 1e-6)."""
    problem = rigid_pose_problem(T)
    if problem:
        raise DatasetError(f"{where}: pose: {problem}")
    R = T[:3, :3]
    if np.abs(R @ R.T - np.eye(3)).max() <= 1e-9:
        return T  # already a rotation to float precision: returned as read
    U, _, Vt = np.linalg.svd(R)
    out = np.array(T, dtype=np.float64)
    out[:3, :3] = U @ Vt
    out[3] = (0.0, 0.0, 0.0, 1.0)
    return out


def reproject_depth(
    depth: np.ndarray, source: Camera, target: Camera, offset_m: np.ndarray, rotation: np.ndarray | None = None
) -> np.ndarray:
    """Depth image of pinhole camera ``source`` (metres, 0 invalid) seen from pinhole camera ``target``,
    whose coordinates are ``rotation`` (3x3, default the identity) times the source's plus ``offset_m``:
    every valid pixel's surface point lands on the target pixel nearest its projection, and where
    several land the nearest surface wins.  Target pixels no point lands on are 0 (occluded, outside
    the source's view, or between samples).  7-Scenes registers its depth to the colour camera with
    it, the RealSense source a recording's depth."""
    h, w = depth.shape
    z = depth.astype(np.float32).ravel()
    ray_x = (np.arange(w, dtype=np.float32) - source.cx) / source.fx  # per column / row, broadcast below
    ray_y = (np.arange(h, dtype=np.float32) - source.cy) / source.fy
    x = (ray_x[None, :] * depth).ravel().astype(np.float32)
    y = (ray_y[:, None] * depth).ravel().astype(np.float32)
    if rotation is not None:
        R = np.asarray(rotation, dtype=np.float32)
        x, y, z = (
            R[0, 0] * x + R[0, 1] * y + R[0, 2] * z,
            R[1, 0] * x + R[1, 1] * y + R[1, 2] * z,
            R[2, 0] * x + R[2, 1] * y + R[2, 2] * z,
        )
    valid = depth.ravel() > 0.0
    x, y = x + np.float32(offset_m[0]), y + np.float32(offset_m[1])
    zt = z + np.float32(offset_m[2])
    keep = valid & (zt > 1e-6)
    x, y, zt = x[keep], y[keep], zt[keep]
    ut = np.rint(target.fx * x / zt + target.cx).astype(np.int32)
    vt = np.rint(target.fy * y / zt + target.cy).astype(np.int32)
    inside = (ut >= 0) & (ut < target.width) & (vt >= 0) & (vt < target.height)
    out = np.full(target.height * target.width, np.inf, dtype=np.float32)
    np.minimum.at(out, vt[inside] * target.width + ut[inside], zt[inside])  # the nearest surface wins
    out[np.isinf(out)] = 0.0
    return out.reshape(target.height, target.width)


def checked_distortion(distortion, what: str) -> tuple[float, ...]:
    """``distortion`` as OpenCV's lens coefficients (k1, k2, p1, p2[, k3[, ...]]), () for none or all 0;
    DatasetError naming ``what`` (the coefficients' source) for a count OpenCV does not take or a value
    that is not finite."""
    d = tuple(float(v) for v in np.asarray(distortion, dtype=np.float64).ravel())
    if d and (len(d) not in (4, 5, 8, 12, 14) or not np.all(np.isfinite(d))):
        raise DatasetError(
            f"{what} {list(distortion)}: expected OpenCV's 4, 5, 8, 12 or 14 finite coefficients (k1, k2, p1, p2, ...)"
        )
    return d if any(d) else ()


def check_frame_size(shape: tuple[int, int], source: str, **images: np.ndarray | None) -> None:
    """A ``DatasetError`` naming ``source`` when one of ``images`` (by name) is not ``shape`` (rows, columns): the
    calibration's size, which a remap or a reprojection would otherwise force on it."""
    h, w = shape
    for name, image in images.items():
        if image is not None and image.shape[:2] != (h, w):
            raise DatasetError(
                f"{source}: {name} image is {image.shape[1]}x{image.shape[0]}, the calibration says {w}x{h}"
            )


def undistort_maps(camera: Camera, distortion, what: str) -> tuple[np.ndarray, np.ndarray] | None:
    """OpenCV's remap maps that undistort an image of ``camera`` with ``distortion`` (``checked_distortion``)
    onto the same pinhole intrinsics; None when there is nothing to undo."""
    d = checked_distortion(distortion, what)
    if not d:
        return None
    size = (camera.width, camera.height)
    return cv2.initUndistortRectifyMap(camera.K, np.array(d), None, camera.K, size, cv2.CV_32FC1)


def undistort_frame(
    maps, rgb: np.ndarray, depth: np.ndarray | None, source: str
) -> tuple[np.ndarray, np.ndarray | None]:
    """``rgb`` (linear) and ``depth`` (nearest: no depth between two surfaces; 0 outside) remapped by
    ``undistort_maps``' ``maps``; as they are when ``maps`` is None.  An image of another size than the
    maps' (which the remap would silently resample to their size) is a ``DatasetError`` naming ``source``."""
    if maps is None:
        return rgb, depth
    check_frame_size(maps[0].shape[:2], source, colour=rgb, depth=depth)
    rgb = cv2.remap(rgb, *maps, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
    if depth is not None:
        depth = cv2.remap(depth, *maps, cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT)
    return rgb, depth


def downscale_rgb(rgb: np.ndarray, factor: int) -> np.ndarray:
    h, w = rgb.shape[0] // factor, rgb.shape[1] // factor
    return np.ascontiguousarray(
        rgb[: h * factor, : w * factor].reshape(h, factor, w, factor, 3).mean(axis=(1, 3), dtype=np.float32)
    )


def downscale_depth(depth: np.ndarray, factor: int, max_rel_spread: float = 0.05) -> np.ndarray:
    """Block mean of the valid depths; a block that straddles a depth edge (spread above
    ``max_rel_spread`` of its mean) becomes invalid rather than a flying point between surfaces."""
    h, w = depth.shape[0] // factor, depth.shape[1] // factor
    blocks = depth[: h * factor, : w * factor].reshape(h, factor, w, factor).transpose(0, 2, 1, 3)
    blocks = blocks.reshape(h, w, factor * factor)
    valid = blocks > 0
    count = valid.sum(axis=2)
    mean = np.where(count > 0, blocks.sum(axis=2) / np.maximum(count, 1), 0.0)
    hi = np.where(valid, blocks, -np.inf).max(axis=2)
    lo = np.where(valid, blocks, np.inf).min(axis=2)
    ok = (count > 0) & (hi - lo <= max_rel_spread * mean)
    return np.where(ok, mean, 0.0).astype(np.float32)


class RGBDDataset:
    """Base of the loaders.  Subclasses fill ``self._items`` (one entry per frame of the full
    sequence, in order) and implement ``_load_full(item) -> Frame`` at native resolution; this class
    applies start/stride/max_frames, downscaling, and prefetching iteration.  Subclasses take their
    own options keyword-only and pass the selection (``stride``, ``start``, ``max_frames``,
    ``downscale``, ``prefetch``) through as ``**selection``.

    ``ds[i]`` loads frame i of the selection; ``iter(ds)`` yields all of them while up to
    ``LOAD_THREADS`` background threads read the next ``prefetch`` frames (OpenCV decodes without
    holding the GIL, so they decode in parallel).
    """

    layout = ""  # human description of the expected folder layout, for error messages
    source = ""  # where the dataset can be obtained

    def __init__(
        self,
        root,
        stride: int = 1,
        start: int = 0,
        max_frames: int | None = None,
        downscale: int = 1,
        prefetch: int = 6,
    ):
        self.root = Path(root).expanduser()
        if stride < 1 or start < 0 or downscale < 1 or prefetch < 0:
            raise ValueError(
                f"need stride >= 1, start >= 0, downscale >= 1, prefetch >= 0; got "
                f"stride={stride}, start={start}, downscale={downscale}, prefetch={prefetch}"
            )
        if max_frames is not None and max_frames < 1:
            raise ValueError(f"max_frames must be >= 1 or None, got {max_frames}")
        if not self.root.is_dir():
            raise DatasetError(
                f"{type(self).__name__}: dataset folder {self.root} does not exist.\n"
                f"  expected layout: {self.layout}\n  obtain it from: {self.source}"
            )
        if next(self.root.iterdir(), None) is None:  # before a loader reads it as a wrong layout or camera
            raise DatasetError(
                f"{type(self).__name__}: dataset folder {self.root} is empty.\n"
                f"  expected layout: {self.layout}\n  obtain it from: {self.source}"
            )
        self.stride, self.start, self.max_frames = stride, start, max_frames
        self.downscale, self.prefetch = downscale, prefetch
        self._items: list = []
        self._native_camera: Camera | None = None
        self.notes: list[str] = []  # what the loader left out and why (``note``); shown in the repr

    def note(self, message: str) -> None:
        """Record and warn (``DatasetWarning``) that part of the sequence is left out, and why."""
        self.notes.append(message)
        warnings.warn(f"{self.root}: {message}", DatasetWarning, stacklevel=3)

    def _select(self) -> None:
        """Called by subclasses once ``_items`` and ``_native_camera`` are set."""
        n_all = len(self._items)
        if n_all == 0:
            raise DatasetError(f"{self.root}: no frames found (expected layout: {self.layout})")
        self._indices = list(range(self.start, n_all, self.stride))
        if self.max_frames is not None:
            self._indices = self._indices[: self.max_frames]
        if not self._indices:
            raise DatasetError(f"{self.root}: start={self.start} is past the last of {n_all} frames")
        # at open, not at the frame that needs it minutes into a run
        missing = [p for j in self._indices for p in self._files(self._items[j]) if not p.is_file()]
        if missing:
            shown = ", ".join(str(p) for p in missing[:3]) + (", ..." if len(missing) > 3 else "")
            files = f"{len(missing)} files of the selected frames are" if len(missing) > 1 else "a file of a frame is"
            raise DatasetError(f"{self.root}: {files} missing: {shown} (an incomplete download or copy?)")

    def _files(self, item) -> tuple[Path, ...]:
        """The files frame ``item`` reads that listing the folder did not already find (checked at open)."""
        return ()

    @property
    def native_camera(self) -> Camera:
        """The files' camera, before ``downscale``."""
        return self._native_camera

    @property
    def camera(self) -> Camera:
        return self._native_camera.scaled(self.downscale)

    def __len__(self) -> int:
        return len(self._indices)

    def __getitem__(self, i: int) -> Frame:
        if not -len(self) <= i < len(self):
            raise IndexError(f"frame {i} out of range for {len(self)} frames")
        i %= len(self)
        frame = self._load_full(self._items[self._indices[i]])
        if frame.depth is not None and frame.depth.shape != frame.rgb.shape[:2]:
            (dh, dw), (h, w) = frame.depth.shape, frame.rgb.shape[:2]
            raise DatasetError(f"{self.root}: frame {self._indices[i]}: depth is {dw}x{dh} but colour is {w}x{h}")
        cam = self._native_camera
        if frame.rgb.shape[:2] != (cam.height, cam.width):
            raise DatasetError(
                f"{self.root}: frame {self._indices[i]}: image is {frame.rgb.shape[1]}x{frame.rgb.shape[0]}, "
                f"calibration says {cam.width}x{cam.height}"
            )
        frame.index = i
        if self.downscale > 1:
            frame.rgb = downscale_rgb(frame.rgb, self.downscale)
            if frame.depth is not None:
                frame.depth = downscale_depth(frame.depth, self.downscale)
        return frame

    def __iter__(self) -> Iterator[Frame]:
        return self.frames(range(len(self)))

    def frames(self, indices: Iterable[int]) -> Iterator[Frame]:
        """``self[i]`` for each of ``indices`` in order, the next ``prefetch`` read ahead by background
        threads (the evaluation's scored frames and keyframes, a resumed run's rest)."""
        indices = [int(i) for i in indices]
        if self.prefetch == 0:
            for i in indices:
                yield self[i]
            return
        with ThreadPoolExecutor(
            max_workers=min(self.prefetch, LOAD_THREADS), thread_name_prefix="rgs-prefetch"
        ) as pool:
            pending: deque = deque()
            nxt = 0
            while nxt < len(indices) and len(pending) <= self.prefetch:
                pending.append(pool.submit(self.__getitem__, indices[nxt]))
                nxt += 1
            while pending:
                frame = pending.popleft().result()
                if nxt < len(indices):
                    pending.append(pool.submit(self.__getitem__, indices[nxt]))
                    nxt += 1
                yield frame

    def gt_poses(self) -> np.ndarray | None:
        """(N, 4, 4) ground-truth camera-to-world poses of the selected frames, or None."""
        poses = [self._gt_pose(self._items[j]) for j in self._indices]
        return None if any(p is None for p in poses) else np.stack(poses)

    def _gt_pose(self, item) -> np.ndarray | None:
        raise NotImplementedError

    def _load_full(self, item) -> Frame:
        raise NotImplementedError

    def __repr__(self) -> str:
        c = self.camera
        notes = "".join(f"; {n}" for n in self.notes)
        return (
            f"{type(self).__name__}({str(self.root)!r}, {len(self)} frames, {c.width}x{c.height}, "
            f"fx={c.fx:g} fy={c.fy:g} cx={c.cx:g} cy={c.cy:g}{notes})"
        )
