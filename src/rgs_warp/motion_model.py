"""The tracker's constant-velocity motion model and its motion check (supplement §4.2).

``MotionModel`` keeps the last two tracked camera-to-world poses and predicts the next by repeating the
last relative motion; with the motion check on (``tracking.motion_check``) it also keeps the last tracked
steps, and ``motion_inconsistency`` says why a tracked pose breaks the model: a jump from the prediction,
a speed-up against the recent steps, or a translation that collapsed while the camera still turns.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from rgs_warp.config import TrackingConfig
from rgs_warp.geometry import invert_pose, rotation_angle_deg

__all__ = ["MotionModel", "motion_inconsistency", "nearest_rigid", "pose_error"]


# Motion check: the camera "still turns" when its tracked rotation since the last frame is at least
# this fraction of the constant-velocity prediction's (a camera that stops turns far less; the office's
# collapsed runs kept turning at 0.65-1.0 of the truth's rate, slam.md runs 32-35)
STILL_TURNING = 0.5
# how ``motion_inconsistency``'s reason for a pose that ran away from the prediction begins
JUMPED = "motion check: the pose jumped"
SPED_UP = "motion check: the camera sped up to"
# the tracked steps (length, turn) the motion check's speed bound takes its median of; it waits for
# MOTION_HISTORY_MIN of them (after a start, a reset or a relocalisation)
MOTION_HISTORY = 10
MOTION_HISTORY_MIN = 3


class MotionModel:
    """The last two tracked camera-to-world poses (oldest first) for the constant-velocity prediction and,
    with ``check`` (the motion check on), the last ``MOTION_HISTORY`` tracked steps (metres, degrees) whose
    median the check's speed bound takes."""

    def __init__(self, cfg: TrackingConfig, check: bool):
        self.cfg = cfg
        self.check = check
        self._poses: list[np.ndarray] = []
        self._steps: list[tuple[float, float]] = []  # the last tracked steps (metres, degrees), oldest first

    def reset(self, T_WC: np.ndarray | None = None, T_prev_WC: np.ndarray | None = None) -> None:
        """Forget the poses; with ``T_WC``, make it the latest, with ``T_prev_WC`` also the one before."""
        poses = [T_prev_WC, T_WC] if T_prev_WC is not None and T_WC is not None else [T_WC]
        self._poses = [np.array(T, dtype=np.float64) for T in poses if T is not None]
        self._steps = []

    def state_dict(self) -> dict[str, np.ndarray]:
        return {
            "motion_poses": np.array(self._poses, dtype=np.float64).reshape(-1, 4, 4),
            "motion_steps": np.array(self._steps, dtype=np.float64).reshape(-1, 2),
        }

    def load_state_dict(self, state: dict[str, np.ndarray]) -> None:
        self._poses = [np.array(T, dtype=np.float64) for T in state["motion_poses"]]
        # states saved before the steps were kept: the check waits for new ones
        self._steps = [(float(m), float(d)) for m, d in state.get("motion_steps", np.zeros((0, 2)))]

    def predict(self) -> np.ndarray | None:
        """Constant-velocity prediction T_k = T_{k-1} T_{k-2}^-1 T_{k-1} (the last relative motion
        repeated in the camera frame); the last pose when only one is known; None before any."""
        if not self._poses:
            return None
        if len(self._poses) == 1:
            return self._poses[-1].copy()
        prev, last = self._poses[-2], self._poses[-1]
        return nearest_rigid(last @ invert_pose(prev) @ last)

    def inconsistency(self, T_WC: np.ndarray) -> str:
        """Why ``T_WC`` fails the motion check against the last two poses (``motion_inconsistency``), or ""
        (also with the check off or fewer poses)."""
        if not self.check or len(self._poses) < 2:
            return ""
        return motion_inconsistency(*self._poses, T_WC, self.cfg, self._steps)

    def push(self, T_WC: np.ndarray, tracked: bool) -> None:
        """``T_WC`` becomes the latest pose; ``tracked`` (not a lost or skipped frame's stand-in): its step
        joins those the check's speed bound takes its median of."""
        if self.check and tracked and self._poses:
            self._steps = [*self._steps, _step_size(self._poses[-1], T_WC)][-MOTION_HISTORY:]
        self._poses = (self._poses + [T_WC])[-2:]


def motion_inconsistency(
    T_prev_WC: np.ndarray,
    T_last_WC: np.ndarray,
    T_WC: np.ndarray,
    cfg: TrackingConfig,
    steps: Sequence[tuple[float, float]] = (),
) -> str:
    """Why the tracked pose ``T_WC`` breaks the constant-velocity motion of the two poses before it
    (camera-to-world), or "" where it does not or the motion is too small to tell.

    The prediction repeats the last step ``T_prev^-1 T_last`` from ``T_last``; the tracked step is
    ``T_last^-1 T_WC``.  Inconsistent:

    * a jump: ``T_WC`` lies more than ``cfg.motion_max_ratio`` x the predicted step plus
      ``cfg.motion_max_jump_m`` from the prediction, or turned more than ``cfg.motion_max_ratio`` x the
      predicted turn plus ``cfg.motion_max_jump_deg`` away from it (monocular tracking running away
      where the map lacks the surface in view);
    * a speed-up: with ``steps`` (the last tracked steps' lengths and turns, at least
      ``MOTION_HISTORY_MIN``), the tracked step is longer than ``cfg.motion_max_ratio`` x their median
      plus ``cfg.motion_max_jump_m``, or turns more than ``cfg.motion_max_ratio`` x their median plus
      ``cfg.motion_max_jump_deg`` (a run-away at a steady speed matches its own prediction);
    * a collapse: the tracked step's translation is below ``cfg.motion_min_ratio`` x the predicted
      step's while the camera still turns (its rotation at least ``STILL_TURNING`` x the predicted one's):
      the image moves on but the pose hardly travels, how monocular tracking collapses (scale is
      defined only by the map there).  A camera that stops stops turning too, and passes.  Only steps
      of at least ``cfg.motion_min_step_m`` and ``cfg.motion_min_rotation_deg`` are judged."""
    predicted_m, predicted_deg = _step_size(T_prev_WC, T_last_WC)
    step_m, step_deg = _step_size(T_last_WC, T_WC)
    jump = pose_error(T_WC, T_last_WC @ invert_pose(T_prev_WC) @ T_last_WC)
    if why := _beyond(jump, (predicted_m, predicted_deg), cfg):
        return f"{JUMPED} {why[0]} from the constant-velocity prediction ({why[1]} the predicted step of {why[2]})"
    if len(steps) >= MOTION_HISTORY_MIN:
        usual = tuple(float(v) for v in np.median(np.asarray(steps, dtype=np.float64), axis=0))
        if why := _beyond((step_m, step_deg), usual, cfg):
            return f"{SPED_UP} {why[0]} ({why[1]} the median of the last {len(steps)} steps, {why[2]})"
    if predicted_m < cfg.motion_min_step_m or predicted_deg < cfg.motion_min_rotation_deg:
        return ""
    ratio = step_m / predicted_m
    if ratio >= cfg.motion_min_ratio or step_deg < STILL_TURNING * predicted_deg:
        return ""
    return (
        f"motion check: the translation collapsed to {ratio:.2f} x the constant-velocity prediction "
        f"({1e3 * step_m:.1f} of {1e3 * predicted_m:.1f} mm; < {cfg.motion_min_ratio:g}) while the camera "
        f"still turns ({step_deg:.2f} deg against {predicted_deg:.2f} deg predicted)"
    )


def _step_size(T_from_WC: np.ndarray, T_to_WC: np.ndarray) -> tuple[float, float]:
    """(metres, degrees) of the step between two camera-to-world poses."""
    step = invert_pose(T_from_WC) @ T_to_WC
    return float(np.linalg.norm(step[:3, 3])), rotation_angle_deg(step[:3, :3])


def _beyond(moved: tuple[float, float], reference: tuple[float, float], cfg: TrackingConfig) -> tuple[str, ...]:
    """The motion check's run-away bound: where ``moved`` (metres, degrees) exceeds
    ``cfg.motion_max_ratio`` x ``reference`` plus (``motion_max_jump_m``, ``motion_max_jump_deg``) in either,
    the reason's parts (what moved, the bound and its factor, the reference); () within it."""
    ratio, floor_m, floor_deg = cfg.motion_max_ratio, cfg.motion_max_jump_m, cfg.motion_max_jump_deg
    bound_m, bound_deg = ratio * reference[0] + floor_m, ratio * reference[1] + floor_deg
    if moved[0] <= bound_m and moved[1] <= bound_deg:
        return ()
    return (
        f"{1e3 * moved[0]:.1f} mm and {moved[1]:.2f} deg",
        f"at most {1e3 * bound_m:.1f} mm and {bound_deg:.2f} deg: {ratio:g} x",
        f"{1e3 * reference[0]:.1f} mm and {reference[1]:.2f} deg, plus {1e3 * floor_m:g} mm and {floor_deg:g} deg",
    )


def nearest_rigid(T: np.ndarray) -> np.ndarray:
    """``T`` with its rotation projected onto SO(3) (nearest in Frobenius norm).  Rounding leaves
    ~1e-16 of non-orthogonality per step, and the constant-velocity extrapolation T R_prev^T T
    amplifies it about 2.4x a frame (measured: 5e-7 after 24 frames, diverging by 40); projecting
    every pose handed out keeps it at rounding level."""
    U, _, Vt = np.linalg.svd(T[:3, :3])
    out = T.copy()
    out[:3, :3] = U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt
    return out


def pose_error(T_est_WC: np.ndarray, T_ref_WC: np.ndarray) -> tuple[float, float]:
    """(translation error in metres, rotation error in degrees) between two camera-to-world poses."""
    rel = invert_pose(T_ref_WC) @ T_est_WC
    return float(np.linalg.norm(T_est_WC[:3, 3] - T_ref_WC[:3, 3])), rotation_angle_deg(rel[:3, :3])
