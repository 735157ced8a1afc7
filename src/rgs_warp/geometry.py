"""Host-side (NumPy, float64) rigid-body helpers: quaternions, SE(3) exponential, pose algebra.

Quaternions are (x, y, z, w), Warp's and TUM's order.  The twist xi = (rho, phi) has translation
first, rotation second, and updates act on the left of the camera-from-world pose:
``T_CW <- Exp(xi) @ T_CW`` (supplement §4.2).
"""

from __future__ import annotations

import numpy as np


def quat_to_matrix(q_xyzw: np.ndarray) -> np.ndarray:
    """Rotation matrix (..., 3, 3) of unit quaternions (..., 4) in x, y, z, w order (normalised here)."""
    q = np.asarray(q_xyzw, dtype=np.float64)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    x, y, z, w = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    R = np.empty(q.shape[:-1] + (3, 3))
    R[..., 0, 0] = 1 - 2 * (y * y + z * z)
    R[..., 0, 1] = 2 * (x * y - z * w)
    R[..., 0, 2] = 2 * (x * z + y * w)
    R[..., 1, 0] = 2 * (x * y + z * w)
    R[..., 1, 1] = 1 - 2 * (x * x + z * z)
    R[..., 1, 2] = 2 * (y * z - x * w)
    R[..., 2, 0] = 2 * (x * z - y * w)
    R[..., 2, 1] = 2 * (y * z + x * w)
    R[..., 2, 2] = 1 - 2 * (x * x + y * y)
    return R


def matrix_to_quat(R: np.ndarray) -> np.ndarray:
    """Unit quaternion (x, y, z, w), w >= 0, of a rotation matrix (3, 3) (Shepperd's method)."""
    R = np.asarray(R, dtype=np.float64)
    tr = np.trace(R)
    if tr > 0:
        s = 2.0 * np.sqrt(tr + 1.0)
        q = np.array([(R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s, 0.25 * s])
    elif R[0, 0] > R[1, 1] and R[0, 0] > R[2, 2]:
        s = 2.0 * np.sqrt(1.0 + R[0, 0] - R[1, 1] - R[2, 2])
        q = np.array([0.25 * s, (R[0, 1] + R[1, 0]) / s, (R[0, 2] + R[2, 0]) / s, (R[2, 1] - R[1, 2]) / s])
    elif R[1, 1] > R[2, 2]:
        s = 2.0 * np.sqrt(1.0 + R[1, 1] - R[0, 0] - R[2, 2])
        q = np.array([(R[0, 1] + R[1, 0]) / s, 0.25 * s, (R[1, 2] + R[2, 1]) / s, (R[0, 2] - R[2, 0]) / s])
    else:
        s = 2.0 * np.sqrt(1.0 + R[2, 2] - R[0, 0] - R[1, 1])
        q = np.array([(R[0, 2] + R[2, 0]) / s, (R[1, 2] + R[2, 1]) / s, 0.25 * s, (R[1, 0] - R[0, 1]) / s])
    q /= np.linalg.norm(q)
    return q if q[3] >= 0 else -q


def pose_from_tq(t: np.ndarray, q_xyzw: np.ndarray) -> np.ndarray:
    """4x4 pose from a translation and an (x, y, z, w) quaternion (TUM's line order)."""
    T = np.eye(4)
    T[:3, :3] = quat_to_matrix(q_xyzw)
    T[:3, 3] = t
    return T


def skew(v: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def so3_exp(phi: np.ndarray) -> np.ndarray:
    theta = float(np.linalg.norm(phi))
    K = skew(phi)
    if theta < 1e-8:
        return np.eye(3) + K + 0.5 * K @ K
    return np.eye(3) + np.sin(theta) / theta * K + (1 - np.cos(theta)) / theta**2 * K @ K


def se3_exp(xi: np.ndarray) -> np.ndarray:
    """4x4 matrix exponential of the twist xi = (rho, phi) (translation first)."""
    rho, phi = np.asarray(xi[:3], float), np.asarray(xi[3:], float)
    theta = float(np.linalg.norm(phi))
    K = skew(phi)
    if theta < 1e-8:
        V = np.eye(3) + 0.5 * K + K @ K / 6.0
    else:
        V = np.eye(3) + (1 - np.cos(theta)) / theta**2 * K + (theta - np.sin(theta)) / theta**3 * K @ K
    T = np.eye(4)
    T[:3, :3] = so3_exp(phi)
    T[:3, 3] = V @ rho
    return T


def invert_pose(T: np.ndarray) -> np.ndarray:
    """Inverse of a rigid 4x4 transform."""
    Ti = np.eye(4)
    R = T[:3, :3]
    Ti[:3, :3] = R.T
    Ti[:3, 3] = -R.T @ T[:3, 3]
    return Ti


def rotation_angle_deg(R: np.ndarray) -> float:
    """Angle of a rotation matrix in degrees."""
    c = np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0)
    return float(np.degrees(np.arccos(c)))


def rigid_pose_problem(T: np.ndarray) -> str | None:
    """What keeps the 4x4 ``T`` from being a finite rigid transform (rotation orthonormal to 1e-3, last
    row 0 0 0 1), or None; the loaders' ``check_pose`` and the library's ``checked_pose`` both ask."""
    if not np.all(np.isfinite(T)):
        return "non-finite values"
    R = T[:3, :3]
    if np.abs(R @ R.T - np.eye(3)).max() > 1e-3 or abs(np.linalg.det(R) - 1.0) > 1e-3:
        return f"the rotation is not orthonormal (det {np.linalg.det(R):.4f})"
    if np.abs(T[3] - [0.0, 0.0, 0.0, 1.0]).max() > 1e-6:
        return f"last row is {T[3].tolist()}, expected [0, 0, 0, 1]"
    return None


def pose_to_transform(T: np.ndarray):
    """A 4x4 rigid pose as a ``wp.transform`` (translation, quaternion x, y, z, w; float32), e.g. a
    camera-to-world pose from ``SLAM.track`` for Warp code that takes transforms (warp.sim, a planner)."""
    import warp as wp

    T = np.asarray(T, dtype=np.float64)
    problem = rigid_pose_problem(T)
    if problem:
        raise ValueError(f"not a rigid pose: {problem}")
    q = matrix_to_quat(T[:3, :3])
    return wp.transform(wp.vec3(*T[:3, 3]), wp.quat(*q))


def transform_to_pose(t) -> np.ndarray:
    """The 4x4 float64 pose of a ``wp.transform`` (``pose_to_transform``'s inverse, to float32)."""
    import warp as wp

    p, q = wp.transform_get_translation(t), wp.transform_get_rotation(t)
    return pose_from_tq(np.array([p[0], p[1], p[2]]), np.array([q[0], q[1], q[2], q[3]]))
