"""The monocular front end around tracking: the two-view start (``MonoStart``, ``bootstrap.py``), which
replaces the initial window, and the keypoint odometry's part in each later frame (``odometry_pose``,
``odometry_lost_reason``).  Part of the SLAM itself: the start adds the first keyframes, maps them and
tracks the frames that waited, through the SLAM's stages."""

from __future__ import annotations

import time

import numpy as np
import warp as wp

from rgs_warp.bootstrap import BootstrapResult, MonoBootstrap, to_triangulated_points
from rgs_warp.config import Config, TrackingConfig
from rgs_warp.frame_check import CheckedFrame
from rgs_warp.keypoint_odometry import KeypointOdometry, OdometryResult
from rgs_warp.slam.frame_result import FrameResult
from rgs_warp.tracking import Tracker
from rgs_warp.types import Camera


class MonoStart:
    """Monocular start: frame 0 waits for a frame k with enough parallax; then keyframes 0 and k are
    seeded from their triangulated matches and mapped together (``mapping.init_iters``), the keypoint
    odometry starts from their poses, and the frames in between are tracked against that map.  After
    ``bootstrap.max_wait_frames`` frames without success the start falls back to frame 0 alone on a
    plane at ``matching.scene_depth_m`` (the frames since are then tracked against it).  A frame whose
    input is unusable waits with frame 0's pose and is never tracked.  The SLAM drops it once the map
    is built."""

    def __init__(self, cfg: Config, camera: Camera, device, backbone):
        self.cfg = cfg
        self.bootstrap = MonoBootstrap(cfg.bootstrap, camera, device, backbone, cfg.matching)
        # the frames that wait: host copies (a frame check's arrays are reused by the next frame), None
        # where the input was unusable
        self.frames: list[np.ndarray | None] = []

    def process(self, slam, frame: CheckedFrame) -> FrameResult:
        """One frame while the start waits: its provisional pose is frame 0's, until a frame gives the
        bootstrap its pair or the wait ends (``start``)."""
        cfg, i = self.cfg, len(slam.poses)
        T0 = slam.T_first.copy()
        if frame.unusable:
            self.frames.append(None)
            result = FrameResult(i, T0, None, False, f"monocular bootstrap: frame not used: {frame.unusable}")
            return result.checked(frame, frame.unusable)
        rgb = np.array(frame.rgb.numpy(), dtype=np.float32, copy=True)
        self.frames.append(rgb)
        result = FrameResult(i, T0, None, False, "monocular bootstrap: first frame, waiting for parallax")
        result.checked(frame, "")
        if i == 0:
            return result
        tb = time.perf_counter()
        boot = self.bootstrap.try_init(self.frames[0], rgb)
        slam.stats["seeding_s"] += time.perf_counter() - tb
        if boot is None and i < cfg.bootstrap.max_wait_frames:
            result.keyframe_reason = f"monocular bootstrap: {self.bootstrap.last_rejection}"
            return result
        return self._start(slam, frame, boot, result)

    def _start(self, slam, frame: CheckedFrame, boot: BootstrapResult | None, result: FrameResult) -> FrameResult:
        """The map from the bootstrap's pair (``boot``), or from frame 0 on a plane where it is None; then the
        frames that waited are tracked against it."""
        cfg, i, kf = self.cfg, result.index, slam.keyframes
        frames, T0 = self.frames, slam.T_first.copy()
        slam.mono_start, slam._init_window_end = None, 0  # the start replaces the initial window
        tb = time.perf_counter()
        slot0 = kf.add(0, T0, frames[0], None)
        slam.keyframe_indices.append(0)
        if boot is not None:
            result.T_WC = T0 @ boot.T_0k
            slot_k = kf.add(i, result.T_WC, frames[i], None)
            slam.keyframe_indices.append(i)
            confidence = wp.array(boot.confidence, dtype=wp.float32, device=slam.device)
            points = to_triangulated_points(boot, T0, slam.device)
            result.seeded = slam.seeder.seed_points(slam.map, kf, [slot0, slot_k], points, confidence)
            window, retrack = [slot0, slot_k], range(1, i)
            result.keyframe = True
            result.keyframe_reason = f"monocular bootstrap with frame 0 ({len(boot.points)} points)"
        else:
            result.seeded = slam._seed(slot0)  # the first keyframe's plane at matching.scene_depth_m
            window, retrack = [slot0], range(1, i + 1)
            result.keyframe_reason = f"monocular bootstrap gave up after {i} frames: plane at frame 0"
            slam.bootstrap_fallback = (
                f"the monocular bootstrap found no frame with enough parallax against frame 0 in {i} frames "
                f"(bootstrap.max_wait_frames; the last: {self.bootstrap.last_rejection}); the map starts from a "
                f"plane at matching.scene_depth_m = {cfg.matching.scene_depth_m} m, on which tracking usually "
                "fails. A start that moves sideways, or a longer wait, gives the bootstrap its parallax"
            )
        slam.stats["seeding_s"] += time.perf_counter() - tb
        tm = time.perf_counter()
        psnr_every = cfg.eval.convergence_every
        result.mapping = slam.mapper.optimize(kf, window, cfg.mapping.init_iters, psnr_every)
        slam.stats["mapping_s"] += time.perf_counter() - tm
        slam.mapping_iterations["init"] += result.mapping.iters
        slam.convergence += slam.mapper.convergence(kf, window, result.mapping, i, "init")
        starts = self._start_odometry(slam, boot, result)
        self._retrack(slam, frame, result, retrack, starts)
        if boot is not None:
            slam.tracker.reset(result.T_WC, slam.poses[i - 1] if i > 1 else T0)
        slam._select_at(slam.map, result.T_WC)
        slam.selector.accept(result.T_WC)
        return result

    def _start_odometry(self, slam, boot: BootstrapResult | None, result: FrameResult) -> list[np.ndarray | None]:
        """The keypoint odometry started from the bootstrap's two poses: where each frame that waited starts
        tracking (None: from the constant-velocity prediction, as every frame where it did not start)."""
        starts = [None] * len(self.frames)
        if slam.odometry is None:
            return starts
        try:  # a plane at an assumed depth gives the odometry no second pose to start from
            if boot is None:
                raise ValueError("the bootstrap fell back to a plane")
            return slam.odometry.start(self.frames, slam.T_first.copy(), result.T_WC)
        except ValueError as e:  # the run goes on, tracking from the constant-velocity prediction
            slam.odometry = None
            result.keyframe_reason += f"; keypoint odometry not started: {e}"
            return starts

    def _retrack(self, slam, frame: CheckedFrame, result: FrameResult, frames: range, starts: list) -> None:
        """The waiting ``frames`` tracked against the first map, from ``starts``; those before the result's
        frame get their poses in the trajectory, the result's frame (after a fallback) its tracking."""
        i = result.index
        slam.tracker.reset(slam.T_first.copy())
        for j in frames:
            if self.frames[j] is None:  # its input was unusable: the last good pose
                slam.tracker.skip()
                slam.poses[j] = slam.poses[j - 1].copy()
                continue
            tr0 = time.perf_counter()
            tracking = slam.tracker.track(self.frames[j], None, slam.map, starts[j] if j < i else None)
            slam.stats["tracking_s"] += time.perf_counter() - tr0
            T = slam.poses[j - 1].copy() if tracking.diverged else tracking.T_WC
            if j < i:
                slam.poses[j] = T
            else:
                result.tracking, result.T_WC = tracking, T
                result.checked(frame, tracking.reason if tracking.lost else "")


def odometry_pose(
    odometry: KeypointOdometry,
    tracker: Tracker,
    cfg: TrackingConfig,
    rgb: wp.array,
    T_init_WC: np.ndarray | None,
    poses: list[np.ndarray],
) -> tuple[OdometryResult, np.ndarray | None, str]:
    """The keypoint odometry on a frame after the start (``poses``: the trajectory before it): (its result,
    the frame's pose when it takes the odometry's or None when it is tracked, why the odometry's pose failed
    the motion check or "").

    The odometry predicts with its own motion model (its BA-refined poses) unless the caller gives a
    start, not with the tracker's: the photometric poses' prediction turned its PnP down at fast turns
    (office, 150 frames: 2.5-2.8 cm in the SLAM against 0.78 alone; experiments/results/mono.md).  With
    tracking.odometry_pose a PnP pose is the frame's, except one that jumps or collapses against the
    motion model: the frame is then lost at the prediction, which the motion model goes on from (as
    tracking's motion check does), and the odometry is moved there (``KeypointOdometry.move_to``)."""
    odometry_result = odometry.track(rgb.numpy(), T_init_WC)
    takes = (
        cfg.odometry_pose
        and T_init_WC is None
        and odometry_result.T_WC is not None
        and not odometry_result.rotation_only
    )
    if not takes:
        return odometry_result, None, ""
    motion = tracker.motion_inconsistency(odometry_result.T_WC)
    if not motion:
        return odometry_result, odometry_result.T_WC, ""
    T_pred = tracker.predict()
    # the odometry goes on from the prediction: left where it was, each later frame jumped from the
    # prediction too (7-Scenes: one jump lost frames 230-286)
    odometry.move_to(T_pred, poses[-1])
    return odometry_result, T_pred, motion


def odometry_lost_reason(cfg: TrackingConfig, odometry: OdometryResult | None, motion: str) -> str:
    """Why a frame that tracking did not lose counts as lost for the odometry (tracking.odometry_pose), or
    "": its pose failed the motion check, or the odometry gave the frame no PnP pose (lost, or a rotation
    only, its translation not measured: photometric tracking's pose stands, but tracking against the
    monocular map did not flag the office's failure at frames 200-250, and a failure must not be
    silent)."""
    if motion:
        return f"keypoint odometry's pose: {motion}; the frame keeps the prediction"
    unposed = odometry is not None and (odometry.T_WC is None or odometry.rotation_only)
    if cfg.odometry_pose and unposed:
        return f"keypoint odometry: {odometry.reason}; the pose is photometric tracking's, from its rotation"
    return ""
