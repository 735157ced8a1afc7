"""TUM trajectory files: one pose a line, ``t tx ty tz qx qy qz qw``, '#' starts a comment.

Poses are camera-to-world 4x4 float64 (the project's convention), so ``evo`` reads what we write.
Numbers are written with 17 significant digits, enough for every float64 to read back bit-exact;
the rotation still passes through a quaternion, so it comes back to ~1e-16, not bit-exact.  Files are
written atomically (``rgs_warp.io.atomic``).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from rgs_warp.geometry import matrix_to_quat, pose_from_tq
from rgs_warp.io.atomic import write_text_atomic

# A rotation further than this from orthonormal is a caller's bug: its quaternion would silently
# describe a different rotation.
_ORTHONORMAL_TOL = 1e-6


class TrajectoryFormatError(ValueError):
    """A malformed trajectory file; the message names the file and the 1-based line."""


def read_tum_trajectory(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """Read a TUM trajectory file.

    Returns ``(timestamps_s (N,) float64, poses_c2w (N, 4, 4) float64)``. Blank lines and lines
    starting with '#' are skipped; values may be separated by whitespace or commas.
    Raises ``TrajectoryFormatError`` naming the file and line for a wrong number of values, a value
    that is not a finite number, or a zero quaternion.
    """
    path = Path(path)
    timestamps_s: list[float] = []
    poses_c2w: list[np.ndarray] = []
    with path.open("r", encoding="utf-8") as f:
        for lineno, line in enumerate(f, start=1):
            text = line.strip()
            if not text or text.startswith("#"):
                continue
            fields = text.replace(",", " ").split()
            where = f"{path}:{lineno}"
            if len(fields) != 8:
                raise TrajectoryFormatError(
                    f"{where}: expected 8 values 't tx ty tz qx qy qz qw', got {len(fields)}: {text!r}"
                )
            try:
                values = np.array([float(v) for v in fields])
            except ValueError as e:
                raise TrajectoryFormatError(f"{where}: not a number in {text!r}") from e
            if not np.all(np.isfinite(values)):
                raise TrajectoryFormatError(f"{where}: non-finite value in {text!r}")
            q_xyzw = values[4:8]
            if np.linalg.norm(q_xyzw) < 1e-12:
                raise TrajectoryFormatError(f"{where}: zero quaternion in {text!r}")
            timestamps_s.append(values[0])
            poses_c2w.append(pose_from_tq(values[1:4], q_xyzw))
    if not poses_c2w:
        return np.zeros(0), np.zeros((0, 4, 4))
    return np.array(timestamps_s), np.stack(poses_c2w)


def write_tum_trajectory(path: str | Path, timestamps_s: np.ndarray, poses_c2w: np.ndarray) -> None:
    """Write camera-to-world poses (N, 4, 4) with their timestamps (N,) as a TUM trajectory file."""
    timestamps_s = np.asarray(timestamps_s, dtype=np.float64).reshape(-1)
    poses_c2w = np.asarray(poses_c2w, dtype=np.float64)
    if poses_c2w.ndim != 3 or poses_c2w.shape[1:] != (4, 4):
        raise ValueError(f"poses_c2w must be (N, 4, 4), got {poses_c2w.shape}")
    if len(timestamps_s) != len(poses_c2w):
        raise ValueError(f"{len(timestamps_s)} timestamps for {len(poses_c2w)} poses")
    if not (np.all(np.isfinite(timestamps_s)) and np.all(np.isfinite(poses_c2w))):
        raise ValueError("timestamps and poses must be finite")
    rotations = poses_c2w[:, :3, :3]
    orthonormality_error = np.abs(rotations @ rotations.transpose(0, 2, 1) - np.eye(3)).max(axis=(1, 2))
    bad = np.flatnonzero((orthonormality_error > _ORTHONORMAL_TOL) | (np.linalg.det(rotations) < 0))
    if bad.size:
        raise ValueError(f"pose {bad[0]} has no proper rotation (orthonormality error or reflection)")
    lines = ["# timestamp tx ty tz qx qy qz qw (camera-to-world)"]
    for t_s, T in zip(timestamps_s, poses_c2w, strict=True):
        values = [t_s, *T[:3, 3], *matrix_to_quat(T[:3, :3])]
        lines.append(" ".join(f"{v:.17g}" for v in values))
    write_text_atomic(path, "\n".join(lines) + "\n")
