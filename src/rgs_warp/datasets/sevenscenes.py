"""Microsoft 7-Scenes: ``frame-XXXXXX.color.jpg``, ``.depth.png`` (uint16 mm, 0 and 65535 invalid),
``.pose.txt`` (4x4 camera-to-world, from KinectFusion), optional ``camera-intrinsics.txt``."""

from __future__ import annotations

import re

import numpy as np

from rgs_warp.datasets.base import DatasetError, RGBDDataset, check_pose, read_depth, read_rgb
from rgs_warp.types import Camera, Frame

# The dataset's stated calibration (Kinect v1, 640x480); colour and depth are not exactly registered.
SEVENSCENES_CAMERA = Camera(fx=585.0, fy=585.0, cx=320.0, cy=240.0, width=640, height=480)
KINECT_FPS = 30.0


class SevenScenesDataset(RGBDDataset):
    layout = "<root>/frame-000000.color.jpg, frame-000000.depth.png, frame-000000.pose.txt (one sequence folder)"
    source = "https://www.microsoft.com/en-us/research/project/rgb-d-dataset-7-scenes/ (seq-XX folders)"

    def __init__(
        self,
        root,
        stride: int = 1,
        start: int = 0,
        max_frames: int | None = None,
        downscale: int = 1,
        prefetch: int = 2,
    ):
        super().__init__(root, stride, start, max_frames, downscale, prefetch)
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
        self._native_camera = self._read_intrinsics()
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
        return Camera(fx=K[0, 0], fy=K[1, 1], cx=K[0, 2], cy=K[1, 2], width=640, height=480)

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

    def _load_full(self, item) -> Frame:
        colour_path, pose = item
        depth = read_depth(self._sibling(colour_path, ".depth.png"), 1000.0)
        depth[depth >= 65.535] = 0.0  # 65535 marks missing depth in 7-Scenes
        idx = int(colour_path.name[6:12])
        return Frame(rgb=read_rgb(colour_path), depth=depth, pose_gt=pose.copy(), timestamp=idx / KINECT_FPS, index=idx)

    def _gt_pose(self, item) -> np.ndarray:
        return item[1].copy()
