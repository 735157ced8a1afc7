"""Keypoint pose prior for monocular tracking (issue 22): where tracking starts a frame.

Monocular photometric tracking from the constant-velocity prediction explains a turn onto surface the
map lacks by rotation: the tracked translation collapses while the rotation stays right (issue 22,
the synthetic office).  Sparse keypoints pin the translation that the photometric loss leaves loose:

* at each keyframe, ORB keypoints of its image are lifted to 3-D with the map's rendered depth at the
  keyframe's pose (where the map covers the pixel): landmarks, in world coordinates, of the last
  ``keypoint_keyframes`` keyframes;
* at each frame, its keypoints are matched to the landmarks (Hamming distance, Lowe's ratio test),
  and a PnP pose with RANSAC (OpenCV, from the prediction) is where tracking starts, when enough
  matches agree with it (``keypoint_min_inliers``); otherwise tracking starts from the prediction.

The landmarks take the map's scale (the monocular bootstrap's), so the prior keeps it too.  Host
work (OpenCV) on the frame already on the host.  ``tracking.keypoint_prior`` is off by default: not
yet run on the GPU, and on small images (160x90) the PnP pose is off by centimetres (keypoints
without sub-pixel precision), as a start for tracking no better than a good prediction.
"""

from __future__ import annotations

import threading
from collections import deque
from dataclasses import dataclass

import cv2
import numpy as np

from rgs_warp.geometry import invert_pose
from rgs_warp.types import Camera

__all__ = ["PosePrior", "PriorResult"]

RATIO = 0.8  # Lowe's ratio test on the two nearest descriptors
REPROJECTION_PX = 3.0  # RANSAC inlier threshold (pixels)
MIN_INLIER_SHARE = 0.3  # of the ratio-test matches
MIN_ALPHA = 0.5  # a keypoint is lifted where the map's rendered opacity reaches this


@dataclass
class PriorResult:
    """A frame's prior: ``T_WC`` (4x4 camera-to-world) or None (too few agreeing matches), the
    ratio-test ``matches`` and RANSAC ``inliers``, and ``reason`` when there is no pose."""

    T_WC: np.ndarray | None
    matches: int
    inliers: int
    reason: str = ""


class PosePrior:
    """Landmarks of the last ``keyframes`` keyframes and PnP poses against them (module docstring).
    ``add_keyframe`` may run on the mapping worker while ``pose`` runs on the tracking thread."""

    def __init__(self, camera: Camera, features: int = 1000, keyframes: int = 3, min_inliers: int = 30):
        if features < 10 or keyframes < 1 or min_inliers < 6:
            raise ValueError(
                f"need keypoint_features >= 10, keypoint_keyframes >= 1 and keypoint_min_inliers >= 6; got "
                f"{features}, {keyframes}, {min_inliers}"
            )
        self.camera, self.min_inliers = camera, min_inliers
        self._K = camera.K.astype(np.float64)
        # ORB's 31-pixel patches leave small images (the CPU tests' 160x90) almost no room: 15 there
        patch = 31 if min(camera.width, camera.height) >= 360 else 15
        self._orb = cv2.ORB_create(nfeatures=features, edgeThreshold=patch, patchSize=patch, fastThreshold=10)
        self._matcher = cv2.BFMatcher(cv2.NORM_HAMMING)
        self._landmarks: deque = deque(maxlen=keyframes)  # (descriptors (N, 32) uint8, points (N, 3) world)
        self._lock = threading.Lock()

    def __len__(self) -> int:
        """Landmarks held."""
        with self._lock:
            return sum(len(points) for _, points in self._landmarks)

    def keypoints(self, rgb: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """ORB keypoints of an HxWx3 image in [0, 1]: pixel coordinates (N, 2) and descriptors (N, 32)."""
        grey = cv2.cvtColor(np.clip(np.asarray(rgb) * 255.0 + 0.5, 0, 255).astype(np.uint8), cv2.COLOR_RGB2GRAY)
        found, desc = self._orb.detectAndCompute(grey, None)
        if desc is None or not found:
            return np.zeros((0, 2)), np.zeros((0, 32), np.uint8)
        return np.array([k.pt for k in found], dtype=np.float64), desc

    def add_keyframe(self, rgb: np.ndarray, depth: np.ndarray, alpha: np.ndarray, T_WC: np.ndarray) -> int:
        """Landmarks of a keyframe: ``rgb`` HxWx3, the map's rendered ``depth`` (expected depth, not
        normalised by opacity) and ``alpha`` at its pose ``T_WC``.  Returns how many were lifted."""
        uv, desc = self.keypoints(rgb)
        if len(uv) == 0:
            return 0
        h, w = alpha.shape
        col = np.clip(np.rint(uv[:, 0]).astype(int), 0, w - 1)
        row = np.clip(np.rint(uv[:, 1]).astype(int), 0, h - 1)
        a = alpha[row, col]
        keep = a >= MIN_ALPHA
        z = depth[row, col][keep] / a[keep]
        keep_z = np.isfinite(z) & (z > 0)
        uv, desc, z = uv[keep][keep_z], desc[keep][keep_z], z[keep_z]
        cam = self.camera
        X_C = np.stack([(uv[:, 0] - cam.cx) / cam.fx * z, (uv[:, 1] - cam.cy) / cam.fy * z, z], axis=1)
        X_W = X_C @ T_WC[:3, :3].T + T_WC[:3, 3]
        with self._lock:
            self._landmarks.append((desc, X_W))
        return len(X_W)

    def pose(self, rgb: np.ndarray, T_pred_WC: np.ndarray) -> PriorResult:
        """The PnP pose of a frame (HxWx3 in [0, 1]) against the landmarks, RANSAC started from the
        prediction ``T_pred_WC``."""
        with self._lock:
            sets = list(self._landmarks)
        if not sets:
            return PriorResult(None, 0, 0, "no landmarks yet")
        desc_l = np.concatenate([d for d, _ in sets])
        X_W = np.concatenate([p for _, p in sets])
        uv, desc = self.keypoints(rgb)
        if len(uv) < self.min_inliers or len(desc_l) < 2:
            return PriorResult(None, 0, 0, f"{len(uv)} keypoints")
        pairs = self._matcher.knnMatch(desc, desc_l, k=2)
        good = [p[0] for p in pairs if len(p) == 2 and p[0].distance < RATIO * p[1].distance]
        if len(good) < self.min_inliers:
            return PriorResult(None, len(good), 0, f"{len(good)} matches (< {self.min_inliers})")
        obj = X_W[[m.trainIdx for m in good]]
        img = uv[[m.queryIdx for m in good]]
        T_CW = invert_pose(T_pred_WC)
        rvec0, _ = cv2.Rodrigues(T_CW[:3, :3])
        ok, rvec, tvec, inliers = cv2.solvePnPRansac(
            obj,
            img,
            self._K,
            None,
            rvec=rvec0.copy(),
            tvec=T_CW[:3, 3].reshape(3, 1).copy(),
            useExtrinsicGuess=True,
            iterationsCount=100,
            reprojectionError=REPROJECTION_PX,
            confidence=0.999,
            flags=cv2.SOLVEPNP_ITERATIVE,
        )
        n_in = 0 if inliers is None else len(inliers)
        if not ok or n_in < max(self.min_inliers, MIN_INLIER_SHARE * len(good)):
            return PriorResult(None, len(good), n_in, f"{n_in} of {len(good)} matches agree")
        R, _ = cv2.Rodrigues(rvec)
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = R, tvec.ravel()
        return PriorResult(invert_pose(T), len(good), n_in)
