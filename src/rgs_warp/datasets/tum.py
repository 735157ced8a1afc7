"""TUM RGB-D: ``rgb.txt``, ``depth.txt``, ``groundtruth.txt`` (``t tx ty tz qx qy qz qw``); colour,
depth and ground truth associated by nearest timestamp within a tolerance; depth = value / 5000."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from rgs_warp.datasets.base import (
    DatasetError,
    RGBDDataset,
    check_frame_size,
    check_pose,
    read_depth,
    read_rgb,
    undistort_frame,
    undistort_maps,
)
from rgs_warp.datasets.replica import read_cam_params
from rgs_warp.geometry import pose_from_tq
from rgs_warp.types import Camera, Frame

TUM_DEPTH_SCALE = 5000.0
# Calibrations published with the dataset (ROS default intrinsics for fr3, whose images are
# already undistorted); distortion is OpenCV's (k1, k2, p1, p2, k3).
TUM_CAMERAS = {
    "fr1": Camera(517.3, 516.5, 318.6, 255.3, 640, 480, (0.2624, -0.9531, -0.0054, 0.0026, 1.1633)),
    "fr2": Camera(520.9, 521.0, 325.1, 249.7, 640, 480, (0.2312, -0.7849, -0.0033, -0.0001, 0.9172)),
    "fr3": Camera(535.4, 539.2, 320.1, 247.6, 640, 480, ()),
}


def read_tum_list(path: Path, n_values: int) -> tuple[np.ndarray, list[list[str]]]:
    """Timestamps and remaining fields of a TUM list file (``#`` comments skipped)."""
    try:
        lines = path.read_text().splitlines()
    except FileNotFoundError:
        raise DatasetError(
            f"{path}: file not found (TUM layout: rgb.txt, depth.txt, groundtruth.txt; README, 'Your own data')"
        ) from None
    stamps, rows = [], []
    for lineno, line in enumerate(lines, 1):
        if not line.strip() or line.lstrip().startswith("#"):
            continue
        parts = line.split()
        if len(parts) != n_values + 1:
            raise DatasetError(f"{path}:{lineno}: expected {n_values + 1} fields, found {len(parts)}: {line[:80]!r}")
        try:
            t = float(parts[0])
        except ValueError:
            raise DatasetError(f"{path}:{lineno}: timestamp {parts[0]!r} is not a number") from None
        if not np.isfinite(t):
            raise DatasetError(f"{path}:{lineno}: timestamp is not finite")
        stamps.append(t)
        rows.append(parts[1:])
    return np.array(stamps), rows


def associate(t_query: np.ndarray, t_ref: np.ndarray, max_dt: float) -> np.ndarray:
    """Index into ``t_ref`` matched to each query timestamp, or -1.

    One-to-one, closest pairs first (as the benchmark's associate.py): a depth image is never
    given to two colour frames.
    """
    order = np.argsort(t_ref)
    ts = t_ref[order]
    lo = np.searchsorted(ts, t_query - max_dt, side="left")
    hi = np.searchsorted(ts, t_query + max_dt, side="right")
    pairs = [(abs(ts[j] - tq), q, order[j]) for q, tq in enumerate(t_query) for j in range(lo[q], hi[q])]
    pairs.sort()
    out = np.full(len(t_query), -1)
    used = set()
    for _, q, r in pairs:
        if out[q] < 0 and r not in used:
            out[q] = r
            used.add(r)
    return out


def camera_for_sequence(root: Path) -> Camera:
    m = re.search(r"freiburg([123])", root.name)
    if m is None:
        raise DatasetError(
            f"{root}: cannot tell the TUM camera (fr1/fr2/fr3) from the folder name; set dataset.camera "
            f"or put a cam_params.json ({{'camera': {{'w', 'h', 'fx', 'fy', 'cx', 'cy', 'scale'}}}}, scale = raw "
            f"depth units per metre) in the folder"
        )
    return TUM_CAMERAS[f"fr{m.group(1)}"]


class TUMDataset(RGBDDataset):
    layout = "<root>/rgb.txt, depth.txt, groundtruth.txt, rgb/<t>.png, depth/<t>.png"
    source = "https://cvg.cit.tum.de/data/datasets/rgbd-dataset/download (e.g. rgbd_dataset_freiburg1_desk)"

    def __init__(
        self,
        root,
        *,
        camera: str = "auto",
        max_dt: float = 0.08,
        undistort: bool = True,
        require_depth: bool = True,
        require_pose: bool = True,
        **selection,
    ):
        super().__init__(root, **selection)
        self.depth_scale = TUM_DEPTH_SCALE  # raw units per metre
        if camera == "auto" and (self.root / "cam_params.json").is_file():
            cam, self.depth_scale = read_cam_params(self.root / "cam_params.json", TUM_DEPTH_SCALE)
        elif camera == "auto":
            cam = camera_for_sequence(self.root)
        elif camera in TUM_CAMERAS:
            cam = TUM_CAMERAS[camera]
        else:
            raise DatasetError(f"unknown TUM camera {camera!r}; valid: auto, {', '.join(TUM_CAMERAS)}")
        self._undistort_maps = None
        if undistort and cam.distortion:
            # Keep the same K after undistortion, as the benchmark's tools do.
            self._undistort_maps = undistort_maps(cam, cam.distortion, f"{self.root} camera distortion")
            cam = cam.undistorted()
        self._native_camera = cam

        t_rgb, rgb_rows = read_tum_list(self.root / "rgb.txt", 1)
        if (self.root / "depth.txt").is_file():
            t_dep, dep_rows = read_tum_list(self.root / "depth.txt", 1)
        elif require_depth:
            raise DatasetError(
                f"{self.root / 'depth.txt'}: file not found: an RGB-D run reads depth images (colour only: mode=mono)"
            )
        else:  # monocular without depth images
            t_dep, dep_rows = np.zeros(0), []
        gt_path = self.root / "groundtruth.txt"
        if gt_path.is_file():
            t_gt, gt_rows = read_tum_list(gt_path, 7)
        elif require_pose:
            raise DatasetError(f"{gt_path}: file not found (set dataset.require_pose=false to run without it)")
        else:
            t_gt, gt_rows = np.zeros(0), []
        gt_poses = []
        for lineno, row in enumerate(gt_rows):
            try:
                v = np.array(row, dtype=np.float64)
            except ValueError:
                raise DatasetError(f"{gt_path}: pose {lineno + 1}: not numbers: {row}") from None
            if np.linalg.norm(v[3:]) < 1e-6:
                raise DatasetError(f"{gt_path}: pose {lineno + 1}: zero quaternion")
            gt_poses.append(check_pose(pose_from_tq(v[:3], v[3:]), f"{gt_path}: pose {lineno + 1}"))
        i_dep = associate(t_rgb, t_dep, max_dt)
        i_gt = associate(t_rgb, t_gt, max_dt)
        self._items = []
        no_depth = require_depth & (i_dep < 0)
        no_pose = require_pose & (i_gt < 0)
        for k in range(len(t_rgb)):
            if no_depth[k] or no_pose[k]:
                continue
            self._items.append(
                (
                    t_rgb[k],
                    self.root / rgb_rows[k][0],
                    self.root / dep_rows[i_dep[k]][0] if i_dep[k] >= 0 else None,
                    gt_poses[i_gt[k]] if i_gt[k] >= 0 else None,
                )
            )
        if not self._items and len(t_rgb):
            raise DatasetError(
                f"{self.root}: none of {len(t_rgb)} colour frames has depth and ground truth within "
                f"{max_dt} s (dataset.max_dt)"
            )
        if len(self._items) < len(t_rgb):
            why = [f"{int(no_depth.sum())} without a depth image"] if no_depth.any() else []
            why += [f"{int(no_pose.sum())} without a ground-truth pose"] if no_pose.any() else []
            listed = f"depth.txt lists {len(t_dep)} images"
            listed += f", groundtruth.txt {len(t_gt)} poses" if gt_rows else ""
            self.note(
                f"{len(t_rgb) - len(self._items)} of {len(t_rgb)} colour frames in rgb.txt dropped: "
                f"{' and '.join(why)} within dataset.max_dt = {max_dt} s ({listed})"
            )
        self._select()

    def _files(self, item) -> tuple[Path, ...]:
        return (item[1],) if item[2] is None else (item[1], item[2])

    def _load_full(self, item) -> Frame:
        t, rgb_path, depth_path, pose = item
        rgb = read_rgb(rgb_path)
        depth = read_depth(depth_path, self.depth_scale) if depth_path is not None else None
        size = (self._native_camera.height, self._native_camera.width)
        check_frame_size(size, str(rgb_path), colour=rgb)
        check_frame_size(size, str(depth_path), depth=depth)
        rgb, depth = undistort_frame(self._undistort_maps, rgb, depth, source=str(rgb_path))
        return Frame(rgb=rgb, depth=depth, pose_gt=None if pose is None else pose.copy(), timestamp=float(t), index=0)

    def _gt_pose(self, item):
        return None if item[3] is None else item[3].copy()
