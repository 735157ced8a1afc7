"""The keypoint odometry's windowed bundle adjustment on the host (NumPy / SciPy, float64): reprojection
residuals with their analytic sparse Jacobian, solved by SciPy's trust-region least squares with a Huber
loss, the rescaling of a solution to the start's baseline, and the world-to-camera pose helpers that the
odometry shares with it.
"""

from __future__ import annotations

import numpy as np
from scipy.optimize import least_squares
from scipy.sparse import csr_matrix

__all__ = [
    "Reprojection",
    "bundle_adjust",
    "centre",
    "centres",
    "cross_matrices",
    "project",
    "rescaled_to_baseline",
    "rigid",
    "rodrigues",
    "shifted",
]

MIN_DEPTH = 1e-6  # projection denominators are clamped here (a point behind the camera)


def rescaled_to_baseline(
    T_held: np.ndarray, T_start: np.ndarray, T_free: np.ndarray, j_start: int, X: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """The free cameras T_free (world-to-camera) and landmarks X scaled about the held camera's centre
    so that free camera j_start is as far from it as T_start was: a similarity that leaves every
    reprojection as it is (a BA with one camera held leaves the scale free)."""
    c0 = centre(T_held)
    before = np.linalg.norm(centre(T_start) - c0)
    after = np.linalg.norm(centre(T_free[j_start]) - c0)
    if after < 1e-12:
        return T_free, X
    s = before / after
    out = T_free.copy()
    for j, T in enumerate(T_free):
        c = c0 + s * (centre(T) - c0)
        out[j, :3, 3] = -T[:3, :3] @ c
    return out, c0 + s * (X - c0)


def rigid(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = np.ravel(t)
    return T


def centres(T_CW: np.ndarray) -> np.ndarray:
    """The camera centres of world-to-camera poses (n, 4, 4): (n, 3)."""
    return -np.einsum("nji,nj->ni", T_CW[:, :3, :3], T_CW[:, :3, 3])


def shifted(T_CW: np.ndarray, origin: np.ndarray) -> np.ndarray:
    """World-to-camera poses (n, 4, 4) for a world whose origin is moved to ``origin`` (X' = X - origin)."""
    out = T_CW.copy()
    out[:, :3, 3] += np.einsum("nij,j->ni", T_CW[:, :3, :3], origin)
    return out


def centre(T_CW: np.ndarray) -> np.ndarray:
    return -T_CW[:3, :3].T @ T_CW[:3, 3]


def cross_matrices(v: np.ndarray) -> np.ndarray:
    """(n, 3) vectors -> (n, 3, 3) cross-product matrices."""
    S = np.zeros((len(v), 3, 3))
    S[:, 0, 1], S[:, 0, 2] = -v[:, 2], v[:, 1]
    S[:, 1, 0], S[:, 1, 2] = v[:, 2], -v[:, 0]
    S[:, 2, 0], S[:, 2, 1] = -v[:, 1], v[:, 0]
    return S


def rodrigues(w: np.ndarray) -> np.ndarray:
    """(n, 3) rotation vectors -> (n, 3, 3) rotations."""
    theta = np.linalg.norm(w, axis=1)
    small = theta < 1e-12
    W = cross_matrices(w / np.where(small, 1.0, theta)[:, None])
    R = np.eye(3) + np.sin(theta)[:, None, None] * W + (1 - np.cos(theta))[:, None, None] * (W @ W)
    R[small] = np.eye(3)
    return R


def _left_jacobian(w: np.ndarray) -> np.ndarray:
    """(n, 3) rotation vectors -> (n, 3, 3) left Jacobians of SO(3): exp(w + d) = exp(J d) exp(w) to first
    order in d."""
    theta = np.linalg.norm(w, axis=1)
    small = theta < 1e-6
    th = np.where(small, 1.0, theta)
    a = np.where(small, 0.5, (1 - np.cos(th)) / th**2)  # series limits at 0: 1/2, 1/6
    b = np.where(small, 1.0 / 6.0, (th - np.sin(th)) / th**3)
    W = cross_matrices(w)
    return np.eye(3) + a[:, None, None] * W + b[:, None, None] * (W @ W)


def project(K: np.ndarray, T_CW: np.ndarray, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pixels and depths of world points X (n, 3) in the camera T_CW."""
    Xc = X @ T_CW[:3, :3].T + T_CW[:3, 3]
    z = Xc[:, 2]
    uv = Xc[:, :2] / np.where(np.abs(z) < 1e-12, 1e-12, z)[:, None]
    return uv * [K[0, 0], K[1, 1]] + [K[0, 2], K[1, 2]], z


class Reprojection:
    """The BA's residuals and their analytic sparse Jacobian.  Parameters: per free camera a rotation
    vector w and a translation step d (R = exp(w) R0, t = t0 + d), then every landmark's world point;
    residuals: per observation the pixel minus the projection of its landmark in its camera."""

    def __init__(self, T_CW, n_free, n_landmarks, cam, land, uv, K):
        self.R0, self.t0 = T_CW[:, :3, :3], T_CW[:, :3, 3]
        self.n_free, self.cam, self.land, self.uv = n_free, cam, land, uv
        self.f, self.c = np.array([K[0, 0], K[1, 1]]), np.array([K[0, 2], K[1, 2]])
        n_obs = len(cam)
        self.n_params = 6 * n_free + 3 * n_landmarks
        # the Jacobian's pattern: rows 2i, 2i+1 of observation i; the free camera's 6 columns (held
        # cameras have none), then its landmark's 3
        row = 2 * np.arange(n_obs)[:, None, None] + np.arange(2)[None, :, None]
        self.on_free = cam < n_free
        cam_cols = 6 * cam[self.on_free][:, None, None] + np.arange(6)[None, None, :]
        land_cols = 6 * n_free + 3 * land[:, None, None] + np.arange(3)[None, None, :]
        self.rows = np.concatenate(
            [
                np.broadcast_to(row[self.on_free], cam_cols.shape[:1] + (2, 6)).ravel(),
                np.broadcast_to(row, (n_obs, 2, 3)).ravel(),
            ]
        )
        self.cols = np.concatenate(
            [
                np.broadcast_to(cam_cols, cam_cols.shape[:1] + (2, 6)).ravel(),
                np.broadcast_to(land_cols, (n_obs, 2, 3)).ravel(),
            ]
        )

    def unpack(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        step = x[: 6 * self.n_free].reshape(-1, 6)
        R, t = self.R0.copy(), self.t0.copy()
        R[: self.n_free] = rodrigues(step[:, :3]) @ self.R0[: self.n_free]
        t[: self.n_free] += step[:, 3:]
        return R, t, x[6 * self.n_free :].reshape(-1, 3)

    def _camera_points(self, x):
        R, t, X = self.unpack(x)
        RX = np.einsum("nij,nj->ni", R[self.cam], X[self.land])
        return R, RX, RX + t[self.cam]

    def residuals(self, x: np.ndarray) -> np.ndarray:
        _, _, Y = self._camera_points(x)
        z = np.maximum(Y[:, 2], MIN_DEPTH)
        return (self.f * Y[:, :2] / z[:, None] + self.c - self.uv).ravel()

    def jacobian(self, x: np.ndarray) -> csr_matrix:
        R, RX, Y = self._camera_points(x)
        clamped = Y[:, 2] <= MIN_DEPTH
        z = np.where(clamped, MIN_DEPTH, Y[:, 2])
        # d pixel / d camera point; a clamped depth is a constant
        D = np.zeros((len(Y), 2, 3))
        D[:, 0, 0], D[:, 1, 1] = self.f[0] / z, self.f[1] / z
        D[:, :, 2] = np.where(clamped[:, None], 0.0, -self.f * Y[:, :2] / z[:, None] ** 2)
        # exp(w + d) R0 X = exp(J_l(w) d) R X: d (R X) / d w = -[R X]x J_l(w)
        J_l = _left_jacobian(x[: 6 * self.n_free].reshape(-1, 6)[:, :3])
        free = self.on_free
        d_w = -D[free] @ cross_matrices(RX[free]) @ J_l[self.cam[free]]
        d_camera = np.concatenate([d_w, D[free]], axis=2)
        d_point = D @ R[self.cam]
        data = np.concatenate([d_camera.ravel(), d_point.ravel()])
        return csr_matrix((data, (self.rows, self.cols)), shape=(2 * len(Y), self.n_params))


def bundle_adjust(
    T_CW: np.ndarray,
    n_free: int,
    X: np.ndarray,
    cam: np.ndarray,
    land: np.ndarray,
    uv: np.ndarray,
    K: np.ndarray,
    huber_px: float,
    max_evals: int,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Reprojection BA in float64 (trust-region reflective, Huber loss of huber_px): the first n_free of
    the cameras T_CW (m, 4, 4) move, the others are held; X (l, 3) the landmarks; observation i is
    landmark land[i] at pixel uv[i] in camera cam[i].  Returns the free cameras' T_CW, the landmarks and
    the residuals (n, 2) after it."""
    # solved about the free cameras' mean centre (the steps rotate each camera about the origin, and
    # translate it, so a world metres away couples rotation and translation), then moved back
    origin = centres(T_CW[:n_free]).mean(axis=0)
    problem = Reprojection(shifted(T_CW, origin), n_free, len(X), cam, land, uv, K)
    x0 = np.concatenate([np.zeros(6 * n_free), (X - origin).ravel()])
    fit = least_squares(
        problem.residuals,
        x0,
        jac=problem.jacobian,
        loss="huber",
        f_scale=huber_px,
        x_scale="jac",
        method="trf",
        max_nfev=max_evals,
        ftol=1e-6,
        xtol=1e-8,
    )
    R, t, X_out = problem.unpack(fit.x)
    T_free = shifted(np.stack([rigid(R[j], t[j]) for j in range(n_free)]), -origin)
    return T_free, X_out + origin, fit.fun.reshape(-1, 2)
