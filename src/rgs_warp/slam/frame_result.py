"""What ``SLAM.process`` did with one frame (``FrameResult``)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from rgs_warp.frame_check import CheckedFrame
from rgs_warp.keypoint_odometry import OdometryResult
from rgs_warp.mapping import MappingResult
from rgs_warp.tracking import TrackingResult


@dataclass
class FrameResult:
    """What ``SLAM.process`` did with one frame."""

    index: int
    T_WC: np.ndarray
    tracking: TrackingResult | None  # None for the first frame and for given poses
    keyframe: bool
    keyframe_reason: str
    seeded: int = 0  # Gaussians added by seeding (a keyframe's, or a frame fill's: seeding.frame_fill_min_uncovered)
    pruned: int = 0  # rgs: by the maintenance after mapping; baseline: by the densification's culling
    merged: int = 0
    mapping: MappingResult | None = None
    seconds: float = 0.0
    tracking_seconds: float = 0.0
    # lost: the frame gave no pose, its input unusable or its tracking lost (lost_reason says which);
    # T_WC is then the last good pose where the input was unusable or tracking diverged, else the
    # tracker's estimate
    lost: bool = False
    lost_reason: str = ""
    # pixels the frame check masked (rgs_warp.frame_check): colour pixels that were not finite
    # (filled from the nearest finite pixel, without depth) and depth values that were not (set to 0)
    nonfinite_rgb: int = 0
    nonfinite_depth: int = 0
    # monocular, tracking.keypoint_odometry: the odometry's result for the frame (where tracking started, or
    # the frame's pose with tracking.odometry_pose), None when it is off, in the bootstrap, in frames whose
    # pose the caller gave, and in RGB-D
    odometry: OdometryResult | None = None
    # asynchronous: frame fills waiting for (or running in) the mapping worker as the frame ends
    fills_waiting: int = 0

    def checked(self, frame: CheckedFrame, lost_reason: str) -> FrameResult:
        """This result with the frame check's counts, and lost with ``lost_reason`` unless it is empty."""
        self.nonfinite_rgb, self.nonfinite_depth = frame.nonfinite_rgb, frame.nonfinite_depth
        self.lost, self.lost_reason = bool(lost_reason), lost_reason
        return self
