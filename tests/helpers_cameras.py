"""Exact multi-view scenes for the keypoint odometry's and its bundle adjustment's tests: world-to-camera
poses along a path and points in front of them, with a pinhole K."""

from __future__ import annotations

import numpy as np

K = np.array([[300.0, 0.0, 160.0], [0.0, 300.0, 90.0], [0.0, 0.0, 1.0]])


def camera_T_CW(centre: np.ndarray, yaw_deg: float) -> np.ndarray:
    """World-to-camera of a camera at centre looking along +z turned by yaw about y."""
    a = np.radians(yaw_deg)
    R_WC = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])
    T = np.eye(4)
    T[:3, :3] = R_WC.T
    T[:3, 3] = -R_WC.T @ centre
    return T


def scene(rng: np.random.Generator, n_cameras: int = 6, n_points: int = 150) -> tuple[np.ndarray, np.ndarray]:
    """(n_cameras, 4, 4) world-to-camera poses 0.3 m and 3 deg apart, and (n_points, 3) points 1.5-5 m ahead."""
    cameras = np.stack([camera_T_CW(np.array([0.3 * j, 0.05 * j, 0.1 * (j % 2)]), 3.0 * j) for j in range(n_cameras)])
    points = rng.uniform([-2.0, -1.5, 1.5], [3.0, 1.5, 5.0], (n_points, 3))
    return cameras, points


def camera_centre(T_CW: np.ndarray) -> np.ndarray:
    return -T_CW[:3, :3].T @ T_CW[:3, 3]
