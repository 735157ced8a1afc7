"""Smooth hand-held camera paths through look-at waypoints.

Positions and orientations share one interpolant: a cubic Hermite spline per segment, for orientations
written in the tangent space of the segment's first key (``R(t) = R_i Exp(r(t))``, so with zero end
tangents it is an eased slerp).  Key tangents are the harmonic-mean blend of the neighbouring segment
velocities (zero where the motion reverses), which keeps a rapid swing next to a slow pan from
overshooting.  A small multi-sine shake on top gives the camera a hand-held feel.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from rgs_warp.geometry import matrix_to_quat, so3_exp


@dataclass(frozen=True)
class Waypoint:
    time_s: float
    eye: tuple[float, float, float]
    target: tuple[float, float, float]
    roll_deg: float = 0.0


def look_at(eye, target, roll_deg: float = 0.0, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """Camera-to-world pose (OpenCV axes: x right, y down, z forward) at ``eye`` looking at ``target``."""
    eye = np.asarray(eye, float)
    z = np.asarray(target, float) - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, np.asarray(up, float))
    if np.linalg.norm(x) < 1e-6:
        raise ValueError("look-at direction parallel to the up vector")
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    T = np.eye(4)
    T[:3, :3] = np.stack([x, y, z], 1) @ so3_exp(np.array([0.0, 0.0, np.radians(roll_deg)]))
    T[:3, 3] = eye
    return T


def so3_log(R: np.ndarray) -> np.ndarray:
    q = matrix_to_quat(R)
    s = np.linalg.norm(q[:3])
    if s < 1e-12:
        return np.zeros(3)
    return q[:3] / s * 2.0 * np.arctan2(s, q[3])


def _key_tangents(deltas: list[np.ndarray], durations: np.ndarray) -> list[np.ndarray]:
    vel = [d / h for d, h in zip(deltas, durations, strict=True)]
    tangents = [np.zeros(3)]
    for a, b in zip(vel[:-1], vel[1:], strict=True):
        na, nb = np.linalg.norm(a), np.linalg.norm(b)
        if na < 1e-12 or nb < 1e-12:
            tangents.append(np.zeros(3))
            continue
        direction = 0.5 * (a / na + b / nb)
        tangents.append(direction * (2.0 * na * nb / (na + nb)))
    tangents.append(np.zeros(3))
    return tangents


def _hermite(s: float, p0, p1, m0, m1, h: float):
    s2, s3 = s * s, s * s * s
    return (2 * s3 - 3 * s2 + 1) * p0 + (s3 - 2 * s2 + s) * h * m0 + (-2 * s3 + 3 * s2) * p1 + (s3 - s2) * h * m1


class Trajectory:
    """Continuous camera-to-world pose ``pose(t)`` for ``t`` in [0, duration] seconds."""

    def __init__(self, waypoints: list[Waypoint], seed: int = 0, shake_m: float = 0.002, shake_deg: float = 0.2):
        self.waypoints = waypoints
        self.times = np.array([w.time_s for w in waypoints], float)
        if np.any(np.diff(self.times) <= 0) or self.times[0] != 0.0:
            raise ValueError("waypoint times must start at 0 and increase")
        keys = [look_at(w.eye, w.target, w.roll_deg) for w in waypoints]
        self._R = [k[:3, :3] for k in keys]
        self._p = [k[:3, 3] for k in keys]
        h = np.diff(self.times)
        self._dp = [b - a for a, b in zip(self._p[:-1], self._p[1:], strict=True)]
        self._dr = [so3_log(a.T @ b) for a, b in zip(self._R[:-1], self._R[1:], strict=True)]
        self._mp = _key_tangents(self._dp, h)
        self._mr = _key_tangents(self._dr, h)
        rng = np.random.default_rng(seed)
        self._shake_freq = rng.uniform(0.4, 2.5, (2, 3, 3))
        self._shake_phase = rng.uniform(0, 2 * np.pi, (2, 3, 3))
        self._shake_amp = np.array([shake_m, np.radians(shake_deg)]) / np.sqrt(3.0)

    @property
    def duration(self) -> float:
        return float(self.times[-1])

    def smooth_pose(self, t: float) -> np.ndarray:
        t = float(np.clip(t, 0.0, self.duration))
        i = int(np.clip(np.searchsorted(self.times, t, side="right") - 1, 0, len(self.times) - 2))
        h = self.times[i + 1] - self.times[i]
        s = (t - self.times[i]) / h
        p = _hermite(s, self._p[i], self._p[i + 1], self._mp[i], self._mp[i + 1], h)
        r = _hermite(s, np.zeros(3), self._dr[i], self._mr[i], self._mr[i + 1], h)
        T = np.eye(4)
        T[:3, :3] = self._R[i] @ so3_exp(r)
        T[:3, 3] = p
        return T

    def pose(self, t: float) -> np.ndarray:
        T = self.smooth_pose(t)
        wave = np.sin(2 * np.pi * self._shake_freq * t + self._shake_phase).sum(-1) * self._shake_amp[:, None]
        shake = np.eye(4)
        shake[:3, :3] = so3_exp(wave[1])
        shake[:3, 3] = wave[0]
        return T @ shake

    def poses(self, times) -> np.ndarray:
        return np.stack([self.pose(t) for t in np.atleast_1d(times)])
