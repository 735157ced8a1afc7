"""Replica in the NICE-SLAM layout: ``results/frame%06d.jpg``, ``results/depth%06d.png`` (metres =
value / 6553.5), ``traj.txt`` (one row-major 4x4 camera-to-world per line)."""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np

from rgs_warp.datasets.base import DatasetError, RGBDDataset, check_pose, checked_distortion, read_depth, read_rgb
from rgs_warp.types import Camera, Frame

# NICE-SLAM's Replica rendering: 1200x680, fx = fy = 600, principal point at the image centre.
REPLICA_CAMERA = Camera(fx=600.0, fy=600.0, cx=599.5, cy=339.5, width=1200, height=680)
REPLICA_DEPTH_SCALE = 6553.5
REPLICA_FPS = 30.0  # rendered sequences have no timestamps; index / fps stands in for them


def read_matrix_lines(path: Path, n_rows: int | None = None) -> np.ndarray:
    """(N, 4, 4) poses from a file of row-major flattened 4x4 matrices, one per line."""
    try:
        lines = path.read_text().splitlines()
    except FileNotFoundError:
        raise DatasetError(f"{path}: trajectory file not found") from None
    poses = []
    for lineno, line in enumerate(lines, 1):
        if not line.strip() or line.lstrip().startswith("#"):
            continue
        try:
            vals = np.array([float(v) for v in line.split()])
        except ValueError:
            raise DatasetError(f"{path}:{lineno}: not a list of numbers: {line.strip()[:80]!r}") from None
        if vals.size != 16:
            raise DatasetError(f"{path}:{lineno}: expected 16 numbers (a 4x4 matrix), found {vals.size}")
        poses.append(check_pose(vals.reshape(4, 4), f"{path}:{lineno}"))
        if n_rows is not None and len(poses) == n_rows:
            break
    return np.array(poses).reshape(-1, 4, 4)


def read_cam_params(path: Path, default_scale: float = REPLICA_DEPTH_SCALE) -> tuple[Camera, float]:
    """Camera and depth scale from a NICE-SLAM style ``{"camera": {"w", "h", "fx", "fy", "cx", "cy", "scale"}}``,
    with the lens's OpenCV coefficients where it gives ``"distortion": [k1, k2, p1, p2, k3]``."""
    try:
        c = json.loads(path.read_text())["camera"]
        values = {k: float(c[k]) for k in ("fx", "fy", "cx", "cy")}
        values.update(width=int(c["w"]), height=int(c["h"]))
        scale = float(c.get("scale", default_scale))
        distortion = tuple(float(v) for v in c.get("distortion", ()))
    except (ValueError, KeyError, TypeError, OverflowError) as e:
        raise DatasetError(f"{path}: malformed camera parameters ({type(e).__name__}: {e})") from None
    values.update(distortion=checked_distortion(distortion, f"{path}: distortion ="))
    try:
        cam = Camera(**values)
    except ValueError as e:
        raise DatasetError(f"{path}: {e}") from None
    if not (np.isfinite(scale) and scale > 0):
        raise DatasetError(f"{path}: scale = {scale!r}: the depth scale (raw units per metre) must be positive")
    return cam, scale


class ReplicaDataset(RGBDDataset):
    layout = "<root>/results/frame000000.jpg, <root>/results/depth000000.png, <root>/traj.txt"
    source = (
        "the NICE-SLAM Replica renders (download script 'bash scripts/download_replica.sh' in the "
        "NICE-SLAM repository, cvg/nice-slam); see data_tools/README.md"
    )

    def __init__(self, root, **selection):
        super().__init__(root, **selection)
        results = self.root / "results"
        if not results.is_dir():
            raise DatasetError(f"{self.root}: no 'results' folder (expected layout: {self.layout})")
        frames = sorted(results.glob("frame*.jpg"))
        pattern = re.compile(r"frame(\d{6})\.jpg$")
        ids = []
        for f in frames:
            m = pattern.search(f.name)
            if m is None:
                raise DatasetError(f"{f}: unexpected file name (expected frame%06d.jpg)")
            ids.append(int(m.group(1)))
        if ids != list(range(len(ids))):
            missing = sorted(set(range(max(ids, default=-1) + 1)) - set(ids))[:5]
            raise DatasetError(f"{results}: frame numbers are not consecutive from 0 (missing e.g. {missing})")
        self._camera_and_scale()
        self._poses = read_matrix_lines(self.root / "traj.txt", n_rows=len(frames))
        if len(self._poses) < len(frames):
            raise DatasetError(f"{self.root / 'traj.txt'}: {len(self._poses)} poses for {len(frames)} images")
        self._items = list(range(len(frames)))
        self._select()

    def _camera_and_scale(self) -> None:
        self._native_camera, self.depth_scale = REPLICA_CAMERA, REPLICA_DEPTH_SCALE
        self.cam_params_path = None
        for cand in (self.root / "cam_params.json", self.root.parent / "cam_params.json"):
            if cand.is_file():
                self._native_camera, self.depth_scale = read_cam_params(cand, REPLICA_DEPTH_SCALE)
                if self._native_camera.distortion:
                    raise DatasetError(
                        f"{cand}: gives a lens distortion, but the Replica layout holds pinhole renders: a camera "
                        f"with a lens goes through the TUM layout, whose loader undoes it"
                    )
                self.cam_params_path = cand
                return

    def _files(self, j: int) -> tuple[Path, ...]:
        return (self.root / "results" / f"depth{j:06d}.png",)

    def _load_full(self, j: int) -> Frame:
        res = self.root / "results"
        return Frame(
            rgb=read_rgb(res / f"frame{j:06d}.jpg"),
            depth=read_depth(res / f"depth{j:06d}.png", self.depth_scale),
            pose_gt=self._poses[j].copy(),
            timestamp=j / REPLICA_FPS,
            index=j,
        )

    def _gt_pose(self, j: int) -> np.ndarray:
        return self._poses[j].copy()
