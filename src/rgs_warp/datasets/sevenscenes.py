"""Microsoft 7-Scenes: ``frame-XXXXXX.color.jpg``, ``.depth.png`` (uint16 mm, 0 and 65535 invalid),
``.pose.txt`` (4x4 camera-to-world, from KinectFusion), optional ``camera-intrinsics.txt``.

The dataset's page gives one calibration (585, 585, 320, 240), the depth camera's, which KinectFusion
used: the poses are the depth camera's.  The colour images come from the Kinect's other camera, with
a wider field of view and an offset.  By default the loader therefore registers each depth image to
the colour camera (reprojects it, nearest surface wins) and moves the ground-truth poses to the
colour camera, so that frames are what the RGB-D pipeline assumes: colour and depth on one pinhole
camera.  The colour calibration is ours, measured on the shared redkitchen frames by aligning depth
discontinuities with colour edges (``experiments/results/slam.md``, section "7-Scenes
calibration"); DSAC's public code uses the same colour focal
length (525 px).  The colour lens (a slight barrel, ``colour_distortion``, measured there too) is
undone on load, onto the same intrinsics."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from rgs_warp.config import DatasetConfig
from rgs_warp.datasets.base import (
    DatasetError,
    RGBDDataset,
    check_frame_size,
    check_pose,
    read_depth,
    read_rgb,
    reproject_depth,
    undistort_frame,
    undistort_maps,
)
from rgs_warp.types import Camera, Frame

# The dataset's stated calibration (Kinect v1, 640x480): the depth camera's.
SEVENSCENES_DEPTH_SCALE = 1000.0  # millimetres
SEVENSCENES_CAMERA = Camera(fx=585.0, fy=585.0, cx=320.0, cy=240.0, width=640, height=480)
# The colour camera (fx, fy, cx, cy) and the depth-to-colour offset (a depth-camera point plus this is
# the colour-camera point, metres), measured (experiments/results/slam.md, 7-Scenes calibration); the
# numbers live in the config's defaults
SEVENSCENES_COLOUR_INTRINSICS = DatasetConfig.colour_intrinsics
SEVENSCENES_DEPTH_TO_COLOUR_M = DatasetConfig.depth_to_colour_m
SEVENSCENES_COLOUR_DISTORTION = DatasetConfig.colour_distortion
KINECT_FPS = 30.0


class SevenScenesDataset(RGBDDataset):
    layout = "<root>/frame-000000.color.jpg, frame-000000.depth.png, frame-000000.pose.txt (one sequence folder)"
    source = "https://www.microsoft.com/en-us/research/project/rgb-d-dataset-7-scenes/ (seq-XX folders)"

    def __init__(
        self,
        root,
        *,
        register_depth: bool = True,
        colour_intrinsics: tuple[float, float, float, float] = SEVENSCENES_COLOUR_INTRINSICS,
        depth_to_colour_m: tuple[float, float, float] = SEVENSCENES_DEPTH_TO_COLOUR_M,
        colour_distortion: tuple[float, ...] = SEVENSCENES_COLOUR_DISTORTION,
        **selection,
    ):
        """``register_depth=False`` gives the files as they are: colour and depth both on the depth
        camera's calibration (what earlier runs and most papers used), poses unchanged."""
        super().__init__(root, **selection)
        self.depth_scale = SEVENSCENES_DEPTH_SCALE  # raw units per metre
        pattern = re.compile(r"frame-(\d{6})\.color\.(jpg|png)$")
        colour = {}
        for f in self.root.iterdir():
            m = pattern.match(f.name)
            if m:
                colour[int(m.group(1))] = f
        if not colour:
            seqs = sorted(p.name for p in self.root.glob("seq-*") if p.is_dir())
            hint = f" It has sequence folders {seqs}: point the path at one of them." if seqs else ""
            raise DatasetError(f"{self.root}: no frame-XXXXXX.color.jpg files (expected layout: {self.layout}).{hint}")
        self._depth_camera = self._read_intrinsics()
        self._native_camera = self._depth_camera
        self._offset = None
        self._undistort_maps = None
        if register_depth:
            if len(colour_intrinsics) != 4 or len(depth_to_colour_m) != 3:
                raise ValueError(
                    f"colour_intrinsics needs (fx, fy, cx, cy) and depth_to_colour_m (x, y, z); got "
                    f"{colour_intrinsics} and {depth_to_colour_m}"
                )
            fx, fy, cx, cy = (float(v) for v in colour_intrinsics)
            try:
                self._native_camera = Camera(fx=fx, fy=fy, cx=cx, cy=cy, width=640, height=480)
            except ValueError as e:
                raise DatasetError(f"dataset.colour_intrinsics {tuple(colour_intrinsics)}: {e}") from None
            self._offset = np.asarray(depth_to_colour_m, dtype=np.float64)
            self._undistort_maps = undistort_maps(self._native_camera, colour_distortion, "dataset.colour_distortion")
        self._items = [(colour[k], self._read_pose(colour[k])) for k in sorted(colour)]
        self._select()

    def _read_intrinsics(self) -> Camera:
        path = self.root / "camera-intrinsics.txt"
        if not path.is_file():
            return SEVENSCENES_CAMERA
        try:
            K = np.loadtxt(path)
        except ValueError as e:
            raise DatasetError(f"{path}: malformed intrinsics ({e})") from None
        if K.shape != (3, 3) or not np.all(np.isfinite(K)):
            raise DatasetError(f"{path}: expected a finite 3x3 matrix, got shape {K.shape}")
        try:
            return Camera(fx=K[0, 0], fy=K[1, 1], cx=K[0, 2], cy=K[1, 2], width=640, height=480)
        except ValueError as e:
            raise DatasetError(f"{path}: {e}") from None

    @staticmethod
    def _sibling(colour_path, suffix: str):
        return colour_path.with_name(colour_path.name.split(".")[0] + suffix)

    def _read_pose(self, colour_path) -> np.ndarray:
        path = self._sibling(colour_path, ".pose.txt")
        try:
            vals = np.array(path.read_text().split(), dtype=np.float64)
        except FileNotFoundError:
            raise DatasetError(f"{path}: pose file missing for {colour_path.name}") from None
        except ValueError:
            raise DatasetError(f"{path}: not a 4x4 matrix of numbers") from None
        if vals.size != 16:
            raise DatasetError(f"{path}: expected 16 numbers (a 4x4 matrix), found {vals.size}")
        return check_pose(vals.reshape(4, 4), str(path))

    def _files(self, item) -> tuple[Path, ...]:
        return (self._sibling(item[0], ".depth.png"),)

    def _load_full(self, item) -> Frame:
        colour_path, pose = item
        depth_path = self._sibling(colour_path, ".depth.png")
        depth = read_depth(depth_path, self.depth_scale)
        depth[depth >= 65.535] = 0.0  # 65535 marks missing depth in 7-Scenes
        if self._offset is not None:
            dc = self._depth_camera
            check_frame_size((dc.height, dc.width), str(depth_path), depth=depth)
            depth = reproject_depth(depth, dc, self._native_camera, self._offset)
        idx = int(colour_path.name[6:12])
        # the colour only: depth is registered onto the pinhole camera above
        rgb, _ = undistort_frame(self._undistort_maps, read_rgb(colour_path), None, str(colour_path))
        return Frame(rgb=rgb, depth=depth, pose_gt=self._gt_pose(item), timestamp=idx / KINECT_FPS, index=idx)

    def _gt_pose(self, item) -> np.ndarray:
        """The file's (depth-camera) pose, moved to the colour camera when depth is registered."""
        if self._offset is None:
            return item[1].copy()
        colour_in_depth = np.eye(4)
        colour_in_depth[:3, 3] = -self._offset  # the colour camera's centre in depth-camera coordinates
        return item[1] @ colour_in_depth
