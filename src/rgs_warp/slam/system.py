"""The SLAM system (supplement §4.6): the stages chained frame by frame; ``python -m rgs_warp.slam``
(``__main__.py``) runs it on a dataset through ``rgs_warp.app``.

``SLAM(cfg, camera)`` is the library entry point: ``slam.track(rgb, depth)`` per frame returns the
camera-to-world pose.  Every frame is checked and staged on the device (``FrameChecker``), then tracked
against the map (``Tracker``); when the co-visibility test accepts it as a keyframe
(``KeyframeSelector``), dense matching -> triangulation -> seeding (``DenseMatcher``, ``Triangulator``,
``Seeder``) -> windowed mapping (``Mapper``) -> merge / prune (``Maintainer``) follow as one mapping job;
a frame that is no keyframe may get a frame fill (measured-depth seeds) and a refinement of the window.
Mapping jobs run before the next frame (same thread, deterministic: ``InlineMapping``), or with
``mapping.asynchronous`` in a worker thread (``WorkerMapping``, ``slam/worker.py``) while tracking goes
on against the latest published version of the map; the initial window stays synchronous (with
``mapping.init_wait`` its first keyframe's mapping or seeds only).  In monocular mode a two-view start
replaces the initial window and a keypoint odometry helps each frame's tracking (``slam/mono_start.py``).

``method=baseline`` (the dense initialization baseline of supplement Table 2) makes one dense start
at the first keyframe and grows the map by residual-driven densification inside the mapping
iterations (``Mapper`` with a ``Densifier``), without dense matching or merge / prune; later
keyframes only get measured-depth seeds where the map does not cover them yet (RGB-D), since
densification cannot reach regions no Gaussian sees.  Everything else is shared.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import warp as wp

from rgs_warp.bootstrap import MonoBootstrap
from rgs_warp.config import Config, check_config, check_image_size, resolve_device
from rgs_warp.frame_check import CheckedFrame, FrameChecker, checked_pose
from rgs_warp.keyframes import (
    FrameViews,
    KeyframeBuffer,
    KeyframeDecision,
    KeyframeHistory,
    KeyframeSelector,
)
from rgs_warp.keypoint_odometry import KeypointOdometry, OdometryResult
from rgs_warp.maintenance import Maintainer
from rgs_warp.mapping import Mapper
from rgs_warp.mapping_budget import MappingBudget, iterations_per_frame
from rgs_warp.matching import DenseMatcher
from rgs_warp.render import Renderer, RenderResult
from rgs_warp.seeding import Seeder
from rgs_warp.slam.frame_result import FrameResult
from rgs_warp.slam.mono_start import MonoStart, odometry_lost_reason, odometry_pose
from rgs_warp.slam.storage import SlamSnapshot, load_slam, snapshot_slam
from rgs_warp.slam.worker import InlineMapping, WorkerMapping
from rgs_warp.tracking import Tracker, TrackingResult
from rgs_warp.triangulation import Triangulator
from rgs_warp.types import Camera, Frame, GaussianMap

METHODS = ("rgs", "baseline")
# A lost frame is tracked again from the poses of this many keyframes nearest its last good pose.
RELOCALIZE_CANDIDATES = 3


@dataclass
class _Pose:
    """A frame's pose as the tracking stage found it."""

    index: int
    given: bool  # the caller gave it (``T_WC``)
    T_WC: np.ndarray | None = None
    tracking: TrackingResult | None = None  # None: the first frame's pose, a given one, or the odometry's
    exposure: tuple[float, float] = (1.0, 0.0)  # (gain, bias) of Eq. 3
    odometry: OdometryResult | None = None  # monocular: the keypoint odometry's result
    odometry_motion: str = ""  # why the odometry's pose failed the motion check

    @property
    def ok(self) -> bool:
        return self.tracking is None or not self.tracking.lost

    @property
    def diverged(self) -> bool:
        return self.tracking is not None and self.tracking.diverged


class SLAM:
    """RGS-SLAM on one camera.  ``track`` frames in order; read ``map``, ``keyframes``,
    ``trajectory()``, ``convergence``; ``render(T_WC)``; ``save(dir)`` / ``SLAM.load(dir)``.

    ``T_first_WC``: pose of the first frame (default identity: the trajectory is then relative to
    it; pass the ground-truth first pose to compare maps in the ground truth's frame).
    """

    def __init__(self, cfg: Config, camera: Camera, device=None, T_first_WC: np.ndarray | None = None):
        if cfg.method not in METHODS:
            raise ValueError(f"unknown method {cfg.method!r}: SLAM implements {', '.join(METHODS)}")
        check_config(cfg)  # a Config changed in code after load_config (which checks it) too
        check_image_size(camera.width, camera.height, cfg)
        self.cfg, self.camera, self.mode = cfg, camera, cfg.mode
        self.device = dev = wp.get_device(resolve_device(cfg.device if device is None else device))
        self.map = GaussianMap(4096, sh_degree=cfg.render.sh_degree, device=dev)
        self.renderer = Renderer(dev)
        # tracking's own renderer; asynchronous mapping also renders the published map with it
        tracking_renderer = Renderer(dev)
        self.tracker = Tracker(cfg.tracking, camera, dev, mode=self.mode, renderer=tracking_renderer)
        # frames are staged once, into the tracker's input buffers, which every stage then reads
        self.frame_check = FrameChecker(camera, dev, self.mode, buffers=self.tracker.frame_buffers)
        relocalize = cfg.tracking.relocalize
        self.relocalize = relocalize == "on" or (relocalize == "auto" and self.mode == "mono")
        self.selector = KeyframeSelector(cfg.keyframes, self.tracker.track_camera, dev)
        self.keyframes = KeyframeBuffer(cfg.keyframes.buffer_size, camera.width, camera.height, dev)
        # mapping.history: the keyframes the buffer evicted, for mapping's views of older keyframes
        self.history = None
        if cfg.mapping.history > 0.0 and cfg.mapping.history_size > 0:
            self.history = KeyframeHistory(cfg.mapping.history_size, camera.width, camera.height, dev, cfg.seed)
        # mapping.frame_views: frames between keyframes kept as views beside the older keyframes
        self.frame_views = None
        views, every = cfg.mapping.frame_views, cfg.mapping.frame_view_every
        if cfg.mapping.history > 0.0 and views > 0:
            self.frame_views = FrameViews(views, every, camera.width, camera.height, dev, cfg.seed)
        self.matcher = DenseMatcher(cfg.matching, camera, dev)
        self.triangulator = Triangulator(cfg.triangulation, dev)
        self.seeder = Seeder(
            cfg.seeding,
            camera,
            dev,
            mode=self.mode,
            match_spacing_px=cfg.matching.thin_spacing * self.matcher.stride,
            scene_depth_m=cfg.matching.scene_depth_m,
            sh_degree=cfg.render.sh_degree,
            renderer=self.renderer,
            max_gaussians=cfg.mapping.max_gaussians,
        )
        baseline = cfg.method == "baseline"
        self.mapper = Mapper(
            cfg.mapping, camera, self.map, dev, self.mode, self.renderer, cfg.seed, cfg.densify if baseline else None
        )
        self.maintainer = None if baseline else Maintainer(cfg.mapping, camera, dev)
        # the mapping iterations each frame may spend (mapping.rate_fps by the renderer's cost model, or given)
        m = cfg.mapping
        per_frame = m.iters_per_frame or iterations_per_frame(m.rate_fps, m.final_share)
        self.budget = MappingBudget(per_frame, m.keyframe_share)
        # mapping iterations run: the initial window's, keyframes' window mappings, refinements between
        # keyframes, the final refinement after the last frame (mapping.final_share)
        self.mapping_iterations = {"init": 0, "keyframe": 0, "refine": 0, "final": 0}
        # monocular: a two-view start replaces the initial window (None once it built the map), and starts
        # the keypoint odometry, which then gives each frame its pose or where its tracking starts
        self.mono_start = self.odometry = None
        if self.mode == "mono" and cfg.bootstrap.enabled:
            self.mono_start = MonoStart(cfg, camera, dev, self.matcher.backbone)
            if cfg.tracking.keypoint_odometry:
                self.odometry = KeypointOdometry(cfg.keypoints, camera)
        self.bootstrap_fallback = ""  # why the monocular start fell back to a plane, if it did
        self._init_window_end = cfg.mapping.init_window  # frames below are keyframes of the initial window
        self.T_first = np.eye(4) if T_first_WC is None else checked_pose(T_first_WC, "T_first_WC")
        self.poses: list[np.ndarray] = []  # camera-to-world of every processed frame
        self.timestamps: list[float] = []
        self.keyframe_indices: list[int] = []
        # mapping_s: keyframes' window mappings, refine_s: between keyframes, final_s: the final refinement
        stats = ("tracking_s", "mapping_s", "refine_s", "final_s", "seeding_s", "maintenance_s")
        self.stats = {**dict.fromkeys(stats, 0.0), "frames": 0}
        # PSNR against the cumulative mapping iterations: {"iteration", "frame", "phase" ("init" |
        # "keyframe" | "final"), "psnr_db" (mean over the mapping window, after the final refinement over
        # every keyframe; None for an empty map), "gaussians"}
        self.convergence: list[dict] = []
        # what the final refinement (mapping.final_share) did
        self.final_refinement: dict | None = None
        # asynchronous: from a keyframe's tracking to the map with its seeds published
        self.keyframe_latency_s: list[float] = []
        # tracked frames that wanted a frame fill, those that got none because mapping.fill_queue fills
        # already waited for the worker, and the most fills that waited at a frame's end (asynchronous)
        self.frame_fills = {"wanted": 0, "skipped": 0, "most_waiting": 0}
        # where mapping jobs run: at once (renders in tracking's turn then use the mapping renderer), or in
        # the worker, tracking reading published versions of the map with its own renderer
        if cfg.mapping.asynchronous:
            self.mapping_jobs = WorkerMapping(self.map, tracking_renderer, cfg.mapping, cfg.render.sh_degree, dev)
        else:
            self.mapping_jobs = InlineMapping(self.map, self.renderer)

    @property
    def bootstrap(self) -> MonoBootstrap | None:
        """The monocular bootstrap while it waits for a frame with enough parallax (None otherwise)."""
        return None if self.mono_start is None else self.mono_start.bootstrap

    # ---- per frame -----------------------------------------------------------------------------
    def track(self, rgb, depth=None, timestamp=None, T_init_WC=None, T_WC=None) -> np.ndarray:
        """Track one frame and return its camera-to-world pose (``process`` says more)."""
        return self.process(rgb, depth, timestamp, T_init_WC=T_init_WC, T_WC=T_WC).T_WC

    def process(
        self,
        rgb,
        depth=None,
        timestamp: float | None = None,
        T_init_WC: np.ndarray | None = None,
        T_WC: np.ndarray | None = None,
    ) -> FrameResult:
        """One frame (``rgb`` HxWx3 float32 in [0, 1], ``depth`` HxW metres or None in mono mode; NumPy
        arrays or ``wp.array``s on the SLAM's device, or a ``Frame``) through the stages.

        ``T_init_WC``: where tracking starts (e.g. from wheel odometry or an IMU); default the
        constant-velocity prediction.  ``T_WC``: the frame's pose is known (motion capture, another
        odometry): tracking is skipped and the frame goes to keyframe selection and mapping at that
        pose.  Both are 4x4 camera-to-world, in the SLAM's world frame.  The first frame is not
        tracked: its pose is ``T_WC`` if given, else ``T_first_WC``.

        Every frame is checked first (``rgs_warp.frame_check``): a shape other than the camera's, a
        dtype that is not floating point, colour outside [0, 1] or negative depth raise ValueError
        and change nothing; pixels that are not finite are masked and counted (``nonfinite_rgb``,
        ``nonfinite_depth``); a frame with too few usable pixels is refused as the first frame and
        lost (``lost_reason``) later, at the last good pose, as is one whose tracking diverged.  A frame
        whose tracked motion fails the motion check (``tracking.motion_check``: the translation collapsed)
        is lost at the tracker's estimate and neither a keyframe nor seeded, and the motion model goes on
        from its prediction."""
        if isinstance(rgb, Frame):
            rgb, depth, timestamp = rgb.rgb, rgb.depth, rgb.timestamp
        if T_init_WC is not None and T_WC is not None:
            raise ValueError("give T_init_WC (where tracking starts) or T_WC (the known pose), not both")
        T_init_WC = None if T_init_WC is None else checked_pose(T_init_WC, "T_init_WC")
        T_WC = None if T_WC is None else checked_pose(T_WC, "T_WC")
        t0 = time.perf_counter()
        with self.mapping_jobs.tracking_map(check=True) as tmap:  # asynchronous: the latest published version
            result = self._record(self._stages(rgb, depth, T_init_WC, T_WC, tmap), timestamp)
        self.mapping_jobs.after_frame(result.index, self._init_window_end)  # asynchronous: the waits
        result.seconds = time.perf_counter() - t0  # with the waits: the caller's latency
        return result

    def _stages(self, rgb, depth, T_init_WC, T_WC, tmap: GaussianMap) -> FrameResult:
        """One frame through the stages, tracking against ``tmap``: checked; then the monocular start while
        it waits; else tracked (or at a pose given or the odometry's), selected, and added as a keyframe
        (seeded, its window mapped and maintained) or filled and refined."""
        t0 = time.perf_counter()
        frame = self._check(rgb, depth, T_init_WC, T_WC)
        if self.mono_start is not None:
            return self.mono_start.process(self, frame)
        if frame.unusable:
            return self._skip(frame, T_WC)
        pose = self._pose(frame, T_init_WC, T_WC, tmap)
        if pose.diverged:  # neither the map nor the trajectory gets the estimate
            T_last, reason = self.poses[-1].copy(), "not mapped: tracking diverged"
            return FrameResult(pose.index, T_last, pose.tracking, False, reason).checked(frame, pose.tracking.reason)
        decision = self._select(pose, tmap)
        result = self._result(frame, pose, decision, t0)
        if result.keyframe:
            self._take_keyframe(frame, pose, result)
        else:
            self._fill_and_refine(frame, pose, decision, result)
        return result

    def _check(self, rgb, depth, T_init_WC, T_WC) -> CheckedFrame:
        """The frame checked and staged on the device; ValueError for the caller's mistakes."""
        if self.mono_start is not None and (T_init_WC is not None or T_WC is not None):
            raise ValueError("the monocular bootstrap finds its own poses: no T_init_WC / T_WC before it ends")
        frame = self.frame_check.check(rgb, depth)
        if frame.unusable and not self.poses:
            raise ValueError(f"frame 0 cannot start the map: {frame.unusable}")
        return frame

    def _skip(self, frame: CheckedFrame, T_WC) -> FrameResult:
        """A frame whose input is unusable: neither tracked nor mapped; its pose is ``T_WC`` if given
        (the frame is then not lost), else the last good one, and the motion model goes on."""
        self.tracker.skip(T_WC)
        T = self.poses[-1].copy() if T_WC is None else np.array(T_WC, dtype=np.float64)
        result = FrameResult(len(self.poses), T, None, False, f"not used: {frame.unusable}")
        return result.checked(frame, frame.unusable if T_WC is None else "")

    def _pose(self, frame: CheckedFrame, T_init_WC, T_WC, tmap: GaussianMap) -> _Pose:
        """The frame's pose: the first frame's is ``T_first_WC`` (or the given one); a given pose, or the
        keypoint odometry's (monocular, ``tracking.odometry_pose``), is taken with the frame's exposure
        against ``tmap``; else the frame is tracked (from the odometry's pose where it has one)."""
        pose = _Pose(len(self.poses), T_WC is not None)
        if self.odometry is not None and pose.index > 0 and not pose.given:  # every frame, for its tracks
            odometry = odometry_pose(self.odometry, self.tracker, self.cfg.tracking, frame.rgb, T_init_WC, self.poses)
            pose.odometry, T_WC, pose.odometry_motion = odometry
        if pose.index == 0:
            pose.T_WC = self.T_first.copy() if T_WC is None else np.array(T_WC, dtype=np.float64)
            self.tracker.reset(pose.T_WC)
        elif T_WC is not None:
            pose.T_WC = np.array(T_WC, dtype=np.float64)
            self.tracker.load_frame(frame.rgb, frame.depth)
            self.tracker.reset(pose.T_WC, self.poses[-1])  # the motion model goes on from the given poses
            pose.exposure = self.tracker.exposure(tmap, pose.T_WC)
            if self.odometry is not None and pose.given:  # its tracks go on through the frames whose pose is given
                self.odometry.track(frame.rgb.numpy(), pose.T_WC)
        else:
            if pose.odometry is not None and T_init_WC is None:  # tracking starts at the odometry's pose
                T_init_WC = pose.odometry.T_WC
            pose.tracking = self._track(frame, tmap, T_init_WC)
            pose.T_WC, pose.exposure = pose.tracking.T_WC, (pose.tracking.gain, pose.tracking.bias)
        return pose

    def _track(self, frame: CheckedFrame, tmap: GaussianMap, T_init_WC: np.ndarray | None) -> TrackingResult:
        """The frame tracked against ``tmap``; a lost frame relocalised (``tracking.relocalize``)."""
        t0 = time.perf_counter()
        before = self.tracker.state_dict()
        tracking = self.tracker.track(frame.rgb, frame.depth, tmap, T_init_WC)
        if tracking.lost and self.relocalize and len(self.keyframes):
            tracking = self._relocalized(frame, tmap, tracking, before)
        self.stats["tracking_s"] += time.perf_counter() - t0
        return tracking

    def _relocalized(self, frame: CheckedFrame, tmap: GaussianMap, lost: TrackingResult, before: dict):
        """``lost`` tracked again (``Tracker.relocalize``) from the last good pose and from the poses of
        the ``RELOCALIZE_CANDIDATES`` keyframes nearest it: the result that holds, its reason saying
        where it started, or ``lost``, its reason saying that relocalisation failed too."""
        kf = self.keyframes
        here = self.poses[-1]
        slots = sorted(kf.slots(), key=lambda s: float(np.linalg.norm(kf.poses[s][:3, 3] - here[:3, 3])))
        slots = slots[:RELOCALIZE_CANDIDATES]
        names = ["the last good pose"] + [f"keyframe {int(kf.frame_ids[s])}" for s in slots]
        candidates = [here.copy()] + [kf.poses[s].copy() for s in slots]
        found = self.tracker.relocalize(frame.rgb, frame.depth, tmap, candidates, before)
        if found is None:
            lost.reason += f"; relocalisation from {', '.join(names)} failed too"
            return lost
        result, k = found
        result.reason = f"relocalised from {names[k]} ({lost.reason}); " + result.reason
        return result

    def _select(self, pose: _Pose, tmap: GaussianMap) -> KeyframeDecision:
        """The keyframe selector's decision on the frame at its pose, from tracking's last render (the
        first frame: a render of ``tmap``)."""
        if pose.index == 0:
            return self._select_at(tmap, pose.T_WC)  # "first frame"
        tracking = pose.tracking
        if tracking is None:
            return self.selector.should_add(self.tracker.alpha, pose.T_WC, depth=self.tracker.depth)
        loss = None if tracking.lost else tracking.loss
        return self.selector.should_add(tracking.alpha, pose.T_WC, loss, depth=tracking.depth)

    def _select_at(self, gmap: GaussianMap, T_WC: np.ndarray) -> KeyframeDecision:
        """The selector's decision on ``gmap`` seen from T_WC at the tracking resolution (an empty map:
        nothing visible)."""
        tc = self.tracker.track_camera
        if len(gmap) == 0:
            empty = wp.zeros((tc.height, tc.width), dtype=wp.float32, device=self.device)
            return self.selector.should_add(empty, T_WC, depth=empty)
        res = self.mapping_jobs.renderer.forward(gmap, tc, T_WC)
        return self.selector.should_add(res.alpha, T_WC, depth=res.depth)

    def _result(self, frame: CheckedFrame, pose: _Pose, decision: KeyframeDecision, t0: float) -> FrameResult:
        """The frame's result: a keyframe as the selector decided, or as one of the initial window, unless
        its pose is not to be mapped (its motion inconsistent); lost as tracking or the odometry says."""
        i, given, tracking = pose.index, pose.given, pose.tracking
        is_kf, reason = decision.is_keyframe, decision.reason + (" (pose given)" if given and i else "")
        if 0 < i < self._init_window_end:
            is_kf, reason = True, f"initial window ({i + 1}/{self._init_window_end}{', pose given' if given else ''})"
        if tracking is not None and tracking.motion_inconsistent:  # a collapsed pose must not seed the map
            is_kf, reason = False, "not mapped: tracked motion inconsistent"
        if pose.odometry_motion:
            is_kf, reason = False, "not mapped: the keypoint odometry's motion inconsistent"
        result = FrameResult(i, pose.T_WC, tracking, is_kf, reason, tracking_seconds=time.perf_counter() - t0)
        result.odometry = pose.odometry
        lost_reason = tracking.reason if tracking is not None and tracking.lost else ""
        odometry_reason = odometry_lost_reason(self.cfg.tracking, pose.odometry, pose.odometry_motion)
        return result.checked(frame, lost_reason or odometry_reason)

    def _take_keyframe(self, frame: CheckedFrame, pose: _Pose, result: FrameResult) -> None:
        """The frame becomes the selector's reference and a keyframe; its mapping job runs or is queued."""
        i, jobs = result.index, self.mapping_jobs
        self.selector.accept(result.T_WC)
        self.keyframe_indices.append(i)
        # the initial window's jobs ("init") do not hold tracking back as later keyframes' may (async_queue)
        kind = "init" if i < self._init_window_end else "keyframe"
        if kind == "init":
            iters = self.cfg.mapping.init_iters // self.cfg.mapping.init_window
            self.budget.start(i)
        else:
            self.budget.frame()
            iters = self.budget.keyframe(i)
        rgb, depth = jobs.own(frame.rgb), jobs.own(frame.depth)
        args = (i, result.T_WC, rgb, depth, pose.exposure, result, iters, time.perf_counter())
        jobs.run(kind, self._add_keyframe, *args)
        jobs.prepare_tracking(self.tracker, result.T_WC)

    def _fill_and_refine(self, frame: CheckedFrame, pose: _Pose, decision: KeyframeDecision, result: FrameResult):
        """A frame that is no keyframe: measured-depth seeds where the map does not cover it (a frame fill,
        ``seeding.frame_fill_min_uncovered``), then the budget's iterations over the window (``mapping.rate_fps``)."""
        cfg, jobs = self.cfg.mapping, self.mapping_jobs
        # asynchronous: at most mapping.fill_queue frame fills wait for the worker (they seed most of what
        # this frame would)
        wants = pose.ok and self.seeder.wants_fill(decision.coverage)
        waits = wants and 0 < cfg.fill_queue <= jobs.queued("fill")
        self.frame_fills["wanted"] += int(wants)
        self.frame_fills["skipped"] += int(waits)
        if wants and not waits:
            alpha = pose.tracking.alpha if pose.tracking is not None else self.tracker.alpha
            # synchronous: the map as tracking's last render saw it (not rendered again)
            alpha = jobs.working_alpha(alpha) if alpha.shape == (self.camera.height, self.camera.width) else None
            rgb, depth = jobs.own(frame.rgb), jobs.own(frame.depth)
            jobs.run("fill", self._fill_frame, result.index, rgb, depth, result.T_WC, pose.exposure, result, alpha)
        views, last = self.frame_views, self.keyframe_indices[-1] if self.keyframe_indices else None
        if views is not None and pose.ok and last is not None and views.wants(result.index, last):
            rgb, depth = jobs.own(frame.rgb), jobs.own(frame.depth)
            jobs.run("view", views.keep, result.index, result.T_WC, rgb, depth, pose.exposure)
        # refinement between keyframes with what the budget holds: one job waiting at most (asynchronous: the
        # worker refines whenever it would idle, ended when a keyframe waits)
        if self.keyframe_indices and result.index >= self._init_window_end:
            self.budget.frame()
            if jobs.queued("refine") == 0:
                iters = jobs.refine_iters(self.budget.refine(), self.budget.per_frame)
                if iters:
                    jobs.run("refine", self._refine_window, result, iters)

    def _record(self, result: FrameResult, timestamp: float | None) -> FrameResult:
        self.poses.append(result.T_WC)
        self.timestamps.append(float(result.index) if timestamp is None else float(timestamp))
        self.stats["frames"] += 1
        result.fills_waiting = self.mapping_jobs.queued("fill")
        self.frame_fills["most_waiting"] = max(self.frame_fills["most_waiting"], result.fills_waiting)
        return result

    # ---- mapping jobs (InlineMapping runs them at once, WorkerMapping in its thread) --------------------------
    def _add_keyframe(
        self, i: int, T: np.ndarray, rgb, depth, exposure, result: FrameResult, iters: int, t_tracked: float
    ) -> None:
        """Keyframe ``i`` into the buffer, seeded, its window mapped (``iters`` iterations) and maintained."""
        cfg, kf, jobs = self.cfg, self.keyframes, self.mapping_jobs
        if self.history is not None and len(kf) == kf.capacity:
            self.history.keep(kf, kf.slots()[0])  # the buffer evicts its oldest keyframe next
        slot = kf.add(i, T, rgb, depth, exposure)
        t0 = time.perf_counter()
        self.seeder.join_pending(self.map)
        # baseline: the one dense start is the first keyframe's; later the densifier grows the map
        first = int(kf.frame_ids[slot]) == self.keyframe_indices[0]
        result.seeded = self._seed(slot, matches=cfg.method == "rgs" or first)
        self.stats["seeding_s"] += time.perf_counter() - t0
        init = i < self._init_window_end
        pause, stop = jobs.begin_window(init)
        t0 = time.perf_counter()
        window = kf.slots()[-(cfg.mapping.init_window if init else cfg.mapping.window) :]
        psnr_every = cfg.eval.convergence_every if init else 0
        result.mapping = self.mapper.optimize(
            kf, window, iters, psnr_every, pause=pause, history=self._older(window), stop=stop
        )
        self.stats["mapping_s"] += time.perf_counter() - t0
        self.mapping_iterations["init" if init else "keyframe"] += result.mapping.iters
        if self.maintainer is not None:
            jobs.pause()
            t0 = time.perf_counter()
            result.pruned, result.merged = self.maintainer.maintain(self.map, kf.poses[slot])
            self.stats["maintenance_s"] += time.perf_counter() - t0
        else:
            result.pruned = result.mapping.pruned
        self.convergence += self.mapper.convergence(kf, window, result.mapping, i, "init" if init else "keyframe")
        if jobs.publish():  # asynchronous: tracking sees the keyframe's map from now on
            self.keyframe_latency_s.append(time.perf_counter() - t_tracked)

    def _seed(self, slot: int, matches: bool = True) -> int:
        """Dense initialization at keyframe ``slot``: (``matches``) matches with its neighbours,
        triangulated and seeded where the map does not explain the keyframe yet, then measured-depth
        seeds where it still does not cover it (``Seeder``).  Returns the number of seeds."""
        kf, added = self.keyframes, 0
        neighbours = self.matcher.select_neighbours(slot, kf) if matches and len(kf) >= 2 else []
        if neighbours:
            m = self.matcher.match(slot, kf, neighbours, use_depth=self.mode == "rgbd")
            self.mapping_jobs.pause()  # between stages: a frame waits for one stage at most (7-Scenes: 8 ms each)
            points = self.triangulator.triangulate(m.P, m.ref_uv, m.match_uv, m.confidence)
            added += self.seeder.seed_matches(self.map, kf, slot, m, points)
            self.mapping_jobs.pause()
        return added + self.seeder.seed_depth(self.map, kf, slot)

    def _fill_frame(self, i: int, rgb, depth, T: np.ndarray, exposure, result: FrameResult, alpha=None) -> None:
        t0 = time.perf_counter()
        result.seeded = self.seeder.fill_frame(self.map, i, rgb, depth, T, exposure, alpha)
        self.stats["seeding_s"] += time.perf_counter() - t0

    def _refine_window(self, result: FrameResult, iters: int) -> None:
        """``iters`` iterations over the current window and the older keyframes, after a frame that is no
        keyframe (asynchronous: fewer if a keyframe comes meanwhile)."""
        t0 = time.perf_counter()
        jobs = self.mapping_jobs
        window = self.keyframes.slots()[-self.cfg.mapping.window :]
        result.mapping = self.mapper.optimize(
            self.keyframes,
            window,
            iters,
            pause=jobs.pause,
            history=self._older(window),
            stop=jobs.refine_stop,
        )
        self.stats["refine_s"] += time.perf_counter() - t0
        self.mapping_iterations["refine"] += result.mapping.iters
        if self.maintainer is None:  # baseline: the densification's culling
            result.pruned = result.mapping.pruned
        jobs.publish()

    def _older(self, window: list[int]) -> list[tuple[KeyframeBuffer, int]]:
        """The views besides ``window`` that mapping may render (``mapping.history``; ``optimize`` renders
        none with 0): the buffer's keyframes outside the window, those the history kept, and the frames
        between keyframes kept as views."""
        older = [(self.keyframes, s) for s in self.keyframes.slots() if s not in window]
        older += self.history.views() if self.history is not None else []
        return older + (self.frame_views.views() if self.frame_views is not None else [])

    # ---- outputs -------------------------------------------------------------------------------
    def trajectory(self) -> tuple[np.ndarray, np.ndarray]:
        """(timestamps (N,), camera-to-world poses (N, 4, 4)) of the processed frames."""
        poses = np.array(self.poses) if self.poses else np.zeros((0, 4, 4))
        return np.array(self.timestamps), poses

    def render(self, T_WC: np.ndarray, camera: Camera | None = None) -> RenderResult:
        """Render the map from a camera-to-world pose (default camera: the SLAM's); the result's
        images are the renderer's buffers, valid until the next render.  A view that needs more tile
        intersections than the renderer's buffers hold (sized by its previous render) is rendered
        again, whole.  With asynchronous mapping: the latest published version, rendered in
        tracking's turn (from any thread), its colour, depth and opacity copied to the host in that turn
        (``wp.array``s on the CPU, the caller's own): a copy made after it, on the device's one stream,
        could land in a graph the worker is capturing."""
        camera, background = camera or self.camera, self.cfg.render.background
        renderer = self.mapping_jobs.renderer
        with self.mapping_jobs.tracking_map() as gmap:
            res = renderer.forward(gmap, camera, T_WC, background)
            if res.overflowed:
                res = renderer.forward(gmap, camera, T_WC, background)
            if self.cfg.mapping.asynchronous:
                res = replace(res, **{k: wp.clone(getattr(res, k), device="cpu") for k in ("color", "depth", "alpha")})
            return res

    def wait_for_mapping(self, check: bool = True, hurry: bool = False) -> None:
        """Return when the mapping worker has done every job queued so far (at once without one);
        with ``check``, raises a job's exception; with ``hurry``, the keyframes' window mapping ends at
        ``mapping.min_iters`` (when set) instead of its budget, as when the next keyframe waits."""
        self.mapping_jobs.drain(check, hurry)

    def finish(self, refine: bool = True, stop: Callable[[int], bool] | None = None) -> None:
        """End of the sequence: the frame-fill seeds that wait for the next keyframe join the map
        (without mapping); then, with ``mapping.final_share`` and ``refine``, the final refinement
        (``final_iters()`` iterations) over the keyframes on the device (the buffer's and the history's:
        every keyframe while the history has room) and the frames kept as views (``Mapper.refine_all``;
        what it did: ``final_refinement``, its time ``stats["final_s"]``).  ``stop``: called with the
        iterations done after each; True ends the refinement there (``run``: Ctrl-C).  ``run`` calls it
        after the last frame; ``track`` may go on after it."""
        self.wait_for_mapping()
        self.seeder.join_pending(self.map)
        cfg = self.cfg.mapping
        iters = self.final_iters()
        if refine and iters > 0 and len(self.keyframes) and len(self.map):
            t0 = time.perf_counter()
            slots = self.keyframes.slots()
            # an iteration renders as a keyframe's mapping does (mapping.views_per_iter of a window), each view
            # drawn from the buffer's keyframes, the history's and the frames kept as views alike
            window = slots[-cfg.window :]
            history = self.history.views() if self.history is not None else []
            scored = [(self.keyframes, s) for s in slots] + history
            self.final_refinement = self.mapper.refine_all(
                self.keyframes, window, self._older(window), iters, scored, stop
            )
            self.mapping_iterations["final"] += self.final_refinement["iters"]
            self.stats["final_s"] += time.perf_counter() - t0
            after = self.final_refinement["keyframe_psnr_after_db"]
            self.convergence.append(
                {
                    "iteration": self.mapper.total_iters,
                    "frame": len(self.poses) - 1,
                    "phase": "final",
                    "psnr_db": float(after) if np.isfinite(after) else None,
                    "gaussians": len(self.map),
                }
            )
        self.mapping_jobs.publish()  # asynchronous: renders after the run show the map as saved

    def final_iters(self) -> int:
        """The final refinement's iterations: ``mapping.final_share`` x the run's; live
        (``mapping.asynchronous`` with ``mapping.catch_up``) at least what makes the run's count an
        offline run's (its budget for the frames so far, and its final share)."""
        cfg, done = self.cfg.mapping, self.mapper.total_iters
        iters = round(cfg.final_share * done)
        if cfg.asynchronous and cfg.catch_up:
            offline = cfg.init_iters + self.budget.given()
            iters = max(iters, round((1.0 + cfg.final_share) * offline) - done)
        return iters

    def save(self, directory: str | Path, state: bool = False) -> Path:
        """Write ``trajectory.txt``, ``keyframes.npz``, ``map.ply``, ``config.yaml`` (each atomically;
        ``SaveError`` names a file that failed and what was saved) and with ``state`` the checkpoint's
        ``state.npz``: ``slam.storage.snapshot_slam`` says what each holds.  Waits for the mapping
        worker first (a worker that failed does not stop the save: what was tracked is kept)."""
        return self.snapshot(state).write(directory)

    def snapshot(self, state: bool = False, hurry: bool = False) -> SlamSnapshot:
        """What ``save(directory, state)`` writes, copied into host memory now (after waiting for the
        mapping worker, ``wait_for_mapping(hurry=hurry)``): its ``write(directory)`` does not read the
        SLAM, so it can run in another thread while this SLAM goes on (a run's checkpoints, which
        hurry, and final save)."""
        self.wait_for_mapping(check=False, hurry=hurry)
        return snapshot_slam(self, state)

    @classmethod
    def load(cls, directory: str | Path, device=None) -> SLAM:
        """A SLAM restored from ``save``: map, trajectory, keyframe buffer and the count of mapping
        iterations; tracking continues from the last pose.  The optimiser state starts afresh, unless
        the folder has the ``state.npz`` of ``save(..., state=True)``: then the SLAM goes on exactly as
        the saved one would have.  A missing, truncated or inconsistent file raises ``LoadError`` (or
        the reader's own ``PlyFormatError``, ``TrajectoryFormatError``, ``ConfigError``), naming the
        file and what is wrong."""
        return load_slam(cls, directory, device)
