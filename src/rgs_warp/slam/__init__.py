"""The SLAM system (supplement §4.6): the stages chained frame by frame; ``python -m rgs_warp.slam``
(``__main__.py``) runs it on a dataset through ``rgs_warp.run``.

``SLAM(cfg, camera)`` is the library entry point: ``slam.track(rgb, depth)`` per frame returns the
camera-to-world pose.  Every frame is tracked against the map (``Tracker``); when the co-visibility
test accepts it as a keyframe (``KeyframeSelector``), dense matching -> triangulation -> seeding
(``DenseMatcher``, ``Triangulator``, ``Seeder``) -> windowed mapping (``Mapper``) -> merge / prune
(``Maintainer``) run before the next frame (same thread, deterministic).  With
``mapping.asynchronous`` they run in a worker thread instead (``slam/worker.py``) while tracking goes
on against the latest published version of the map; the initial window stays synchronous (with
``mapping.init_wait`` its first keyframe's mapping or seeds only).

``method=baseline`` (the dense initialization baseline of supplement Table 2) makes one dense start
at the first keyframe and grows the map by residual-driven densification inside the mapping
iterations (``Mapper`` with a ``Densifier``), without dense matching or merge / prune; later
keyframes only get measured-depth seeds where the map does not cover them yet (RGB-D), since
densification cannot reach regions no Gaussian sees.  Everything else is shared.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import warp as wp

from rgs_warp.bootstrap import MonoBootstrap, to_triangulated_points
from rgs_warp.config import Config, check_config, check_image_size, resolve_device
from rgs_warp.exposure import KeyframeExposure
from rgs_warp.frame_check import CheckedFrame, FrameChecker, checked_pose
from rgs_warp.keyframes import KeyframeArchive, KeyframeBuffer, KeyframeDecision, KeyframeHistory, KeyframeSelector
from rgs_warp.keypoint_odometry import KeypointOdometry, OdometryResult
from rgs_warp.maintenance import Maintainer
from rgs_warp.mapping import Mapper, MappingResult
from rgs_warp.matching import DenseMatcher
from rgs_warp.render import Renderer, RenderResult
from rgs_warp.seeding import Seeder
from rgs_warp.slam.storage import SlamSnapshot, load_slam, snapshot_slam
from rgs_warp.slam.worker import DeviceTurns, MappingWorker, MapPublisher
from rgs_warp.tracking import Tracker, TrackingResult
from rgs_warp.triangulation import Triangulator
from rgs_warp.types import Camera, Frame, GaussianMap

METHODS = ("rgs", "baseline")
# A lost frame is tracked again from the poses of this many keyframes nearest its last good pose.
RELOCALIZE_CANDIDATES = 3


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
        self.device = dev = wp.get_device(resolve_device(cfg.device) if device is None else device)
        self.frame_check = FrameChecker(camera, dev, self.mode)
        self.map = GaussianMap(4096, sh_degree=cfg.render.sh_degree, device=dev)
        self.renderer = Renderer(dev)
        # tracking's own renderer; asynchronous mapping also renders the published map with it
        self._tracking_renderer = Renderer(dev)
        self.tracker = Tracker(cfg.tracking, camera, dev, mode=self.mode, renderer=self._tracking_renderer)
        # monocular: started by the bootstrap (its two poses), then where each frame's tracking starts
        self.odometry = None
        if self.mode == "mono" and cfg.tracking.keypoint_odometry:
            self.odometry = KeypointOdometry(cfg.keypoints, camera)
        relocalize = cfg.tracking.relocalize
        self.relocalize = relocalize == "on" or (relocalize == "auto" and self.mode == "mono")
        tc = self.tracker.track_camera
        self.selector = KeyframeSelector(cfg.keyframes, tc, dev)
        self.keyframes = KeyframeBuffer(cfg.keyframes.buffer_size, camera.width, camera.height, dev)
        # mapping.history: the keyframes the buffer evicted, for mapping's views of older keyframes
        self.history = None
        if cfg.mapping.history > 0.0 and cfg.mapping.history_size > 0:
            self.history = KeyframeHistory(cfg.mapping.history_size, camera.width, camera.height, dev, cfg.seed)
        self.exposure = None  # tracking.exposure_from "map" or mono: the tracker's (g, b) colour the seeds
        if cfg.tracking.exposure_from == "keyframes" and self.mode == "rgbd":
            self.exposure = KeyframeExposure(camera, cfg.keyframes.buffer_size, dev)
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
        # monocular: a two-view bootstrap replaces the initial window (set to 0 once it built the map)
        self.bootstrap = None
        if self.mode == "mono" and cfg.bootstrap.enabled:
            self.bootstrap = MonoBootstrap(cfg.bootstrap, camera, dev, self.matcher.backbone, cfg.matching)
        self._boot_frames: list[tuple[np.ndarray, float]] = []  # (rgb, timestamp) while it waits
        self.bootstrap_fallback = ""  # why the bootstrap fell back to a plane, if it did (mono)
        self._init_window_end = cfg.mapping.init_window  # frames below are keyframes of the initial window
        self.T_first = np.eye(4) if T_first_WC is None else checked_pose(T_first_WC, "T_first_WC")
        self.poses: list[np.ndarray] = []  # camera-to-world of every processed frame
        self.timestamps: list[float] = []
        self.keyframe_indices: list[int] = []
        self.stats = {"tracking_s": 0.0, "mapping_s": 0.0, "seeding_s": 0.0, "maintenance_s": 0.0, "frames": 0}
        # PSNR against the cumulative mapping iterations: {"iteration", "frame", "phase" ("init" |
        # "keyframe"), "psnr_db" (mean over the mapping window, None for an empty map), "gaussians"}
        self.convergence: list[dict] = []
        # mapping.final_iters: host copies of every keyframe, and what the final refinement did
        self.archive = KeyframeArchive() if cfg.mapping.final_iters > 0 else None
        self.final_refinement: dict | None = None
        # mapping.asynchronous: the worker maps ``self.map``; tracking reads the versions ``publisher``
        # holds; ``keyframe_latency_s``: from a keyframe's tracking to the map with its seeds published
        self.worker = self.publisher = self.turns = None
        self.keyframe_latency_s: list[float] = []
        # tracked frames that wanted a frame fill, those that got none because mapping.fill_queue fills
        # already waited for the worker, and the most fills that waited at a frame's end (asynchronous)
        self.frame_fills = {"wanted": 0, "skipped": 0, "most_waiting": 0}
        if cfg.mapping.asynchronous:
            self.turns = DeviceTurns()
            self.publisher = MapPublisher(cfg.render.sh_degree, dev)
            self.worker = MappingWorker(self.turns)

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
        if self.worker is None:
            return self._process(rgb, depth, timestamp, T_init_WC, T_WC, self.map)
        self.worker.check()
        t0 = time.perf_counter()
        with self.turns.tracking():
            if self.publisher.version == 0 and len(self.map):  # a loaded or resumed map
                self.publisher.publish(self.map)
            with self.publisher.read() as published:
                result = self._process(rgb, depth, timestamp, T_init_WC, T_WC, published)
        # the initial window is mapped before the next frame, as in sync mode (mapping.init_wait: the first
        # keyframe's mapping, or its seeds, only)
        wait = self.cfg.mapping.init_wait
        waited = {"window": self._init_window_end, "first": 1, "seeds": 0}[wait]
        if wait == "seeds" and self.publisher.version == 0:
            self._wait_for_first_version()
        elif result.index < waited or self.publisher.version == 0:  # version 0: nothing to track against yet
            self.worker.drain()
        self.worker.wait_until_fewer("keyframe", self.cfg.mapping.async_queue + 1)
        result.seconds = time.perf_counter() - t0  # with the waits: the caller's latency
        return result

    def _process(self, rgb, depth, timestamp, T_init_WC, T_WC, tmap: GaussianMap) -> FrameResult:
        """``process`` with tracking against ``tmap`` (``self.map``, or its published version)."""
        t0 = time.perf_counter()
        i = len(self.poses)
        if self.bootstrap is not None and (T_init_WC is not None or T_WC is not None):
            raise ValueError("the monocular bootstrap finds its own poses: no T_init_WC / T_WC before it ends")
        frame = self.frame_check.check(rgb, depth)  # ValueError for the caller's mistakes
        if frame.unusable and i == 0:
            raise ValueError(f"frame 0 cannot start the map: {frame.unusable}")
        rgb, depth = frame.rgb, frame.depth
        if self.bootstrap is not None:
            return self._process_bootstrap(rgb, timestamp, t0, frame)
        if frame.unusable:
            return self._skip(i, frame, T_WC, timestamp, t0)
        tracking, given, odometry, odometry_motion = None, T_WC is not None, None, ""
        if self.odometry is not None and i > 0 and not given:  # every frame, for its tracks
            odometry, T_WC, odometry_motion = self._odometry_frame(rgb, T_init_WC)
        if i == 0:
            T = self.T_first.copy() if T_WC is None else np.array(T_WC, dtype=np.float64)
            self.tracker.reset(T)
            exposure, pose_ok = (1.0, 0.0), True
            decision = self._select_at(tmap, T)  # "first frame"
        elif T_WC is not None:
            T = np.array(T_WC, dtype=np.float64)
            self.tracker.load_frame(rgb, depth)  # the frame fill reads it
            self.tracker.reset(T, self.poses[-1])  # the motion model goes on from the given poses
            exposure, pose_ok = self.tracker.exposure(tmap, T), True
            decision = self.selector.should_add(self.tracker.alpha, T, depth=self.tracker.depth)
            if self.odometry is not None and given:  # its tracks go on through the frames whose pose is given
                self._odometry_pose(rgb, T)
        else:
            tr0 = time.perf_counter()
            before = self.tracker.state_dict()
            if odometry is not None and T_init_WC is None:  # tracking starts at the odometry's pose
                T_init_WC = odometry.T_WC
            tracking = self.tracker.track(rgb, depth, tmap, T_init_WC)
            if tracking.lost and self.relocalize and len(self.keyframes):
                tracking = self._relocalized(rgb, depth, tmap, tracking, before)
            self.stats["tracking_s"] += time.perf_counter() - tr0
            if tracking.diverged:  # neither the map nor the trajectory gets the estimate
                result = FrameResult(i, self.poses[-1].copy(), tracking, False, "not mapped: tracking diverged")
                return self._record(self._counted(result, frame, tracking.reason), timestamp, t0)
            T, exposure, pose_ok = tracking.T_WC, (tracking.gain, tracking.bias), not tracking.lost
            loss = None if tracking.lost else tracking.loss
            decision = self.selector.should_add(tracking.alpha, T, loss, depth=tracking.depth)
        is_kf, reason = decision.is_keyframe, decision.reason + (" (pose given)" if given and i else "")
        if 0 < i < self._init_window_end:
            is_kf, reason = True, f"initial window ({i + 1}/{self._init_window_end}{', pose given' if given else ''})"
        if tracking is not None and tracking.motion_inconsistent:  # a collapsed pose must not seed the map
            is_kf, reason = False, "not mapped: tracked motion inconsistent"
        if odometry_motion:
            is_kf, reason = False, "not mapped: the keypoint odometry's motion inconsistent"
        result = FrameResult(i, T, tracking, is_kf, reason, tracking_seconds=time.perf_counter() - t0)
        result.odometry = odometry
        lost_reason = tracking.reason if tracking is not None and tracking.lost else ""
        self._counted(result, frame, lost_reason or self._odometry_lost_reason(odometry, odometry_motion))
        if is_kf:
            self.selector.accept(T)
            self.keyframe_indices.append(i)
            rgb_k, depth_k = self._own(rgb), self._own(depth)
            # the initial window's jobs ("init") do not hold tracking back as later keyframes' may (async_queue)
            kind = "init" if i < self._init_window_end else "keyframe"
            self._run(kind, self._add_keyframe, i, T, rgb_k, depth_k, exposure, result, time.perf_counter())
            if self.worker is None:  # the next frame's tracking graphs, for the grown map: not in its latency
                self.tracker.prepare(self.map, T)
        else:
            # asynchronous: at most mapping.fill_queue frame fills wait for the worker (they seed most of
            # what this frame would)
            bound = self.cfg.mapping.fill_queue
            wants = pose_ok and self.seeder.wants_fill(decision.coverage)
            fill_waits = wants and self.worker is not None and 0 < bound <= self.worker.queued("fill")
            self.frame_fills["wanted"] += int(wants)
            self.frame_fills["skipped"] += int(fill_waits)
            if wants and not fill_waits:
                rgb_t, depth_t = self.tracker.frame
                # synchronous: the map as tracking's last render saw it (not rendered again)
                alpha = tracking.alpha if tracking is not None else self.tracker.alpha
                if self.worker is not None or alpha.shape != (self.camera.height, self.camera.width):
                    alpha = None
                fill_args = (i, self._own(rgb_t), self._own(depth_t), T, exposure, result, alpha)
                self._run("fill", self._fill_frame, *fill_args)
            # refinement between keyframes: one job waiting at most (it only uses the worker's idle time)
            if self.cfg.mapping.frame_iters > 0 and self.keyframe_indices:
                if self.worker is None or self.worker.queued("refine") == 0:
                    self._run("refine", self._refine_window, result)
        return self._record(result, timestamp, t0)

    def _relocalized(self, rgb, depth, tmap: GaussianMap, lost: TrackingResult, before: dict) -> TrackingResult:
        """``lost`` tracked again (``Tracker.relocalize``) from the last good pose and from the poses of
        the ``RELOCALIZE_CANDIDATES`` keyframes nearest it: the result that holds, its reason saying
        where it started, or ``lost``, its reason saying that relocalisation failed too."""
        kf = self.keyframes
        here = self.poses[-1]
        slots = sorted(kf.slots(), key=lambda s: float(np.linalg.norm(kf.poses[s][:3, 3] - here[:3, 3])))
        slots = slots[:RELOCALIZE_CANDIDATES]
        names = ["the last good pose"] + [f"keyframe {int(kf.frame_ids[s])}" for s in slots]
        candidates = [here.copy()] + [kf.poses[s].copy() for s in slots]
        found = self.tracker.relocalize(rgb, depth, tmap, candidates, before)
        if found is None:
            lost.reason += f"; relocalisation from {', '.join(names)} failed too"
            return lost
        result, k = found
        result.reason = f"relocalised from {names[k]} ({lost.reason}); " + result.reason
        return result

    def _run(self, kind: str, job, *args) -> None:
        """Run a mapping job now (synchronous) or queue it for the worker (its arguments then owned)."""
        if self.worker is None:
            job(*args)
        else:
            self.worker.submit(kind, lambda: job(*args))

    def _own(self, image):
        """``image`` itself (synchronous), or a copy that a queued job may hold while the caller and the
        tracker reuse their buffers (NumPy or ``wp.array``; None stays None)."""
        if self.worker is None or image is None:
            return image
        return wp.clone(image) if isinstance(image, wp.array) else np.array(image, dtype=np.float32, copy=True)

    def _fill_frame(self, i: int, rgb, depth, T: np.ndarray, exposure, result: FrameResult, alpha=None) -> None:
        t1 = time.perf_counter()
        if self.exposure is not None:  # tracking.exposure_from=keyframes: against the older keyframes
            exposure = self.exposure.estimate(self.keyframes, rgb, depth, T, exposure)
        result.seeded = self.seeder.fill_frame(self.map, i, rgb, depth, T, exposure, alpha)
        self.stats["seeding_s"] += time.perf_counter() - t1

    def _refine_window(self, result: FrameResult) -> None:
        """``mapping.frame_iters`` iterations over the current window, after a frame that is no keyframe
        (asynchronous: fewer if a keyframe comes meanwhile)."""
        t1 = time.perf_counter()
        window = self.keyframes.slots()[-self.cfg.mapping.window :]
        iters, held = self.cfg.mapping.frame_iters, self._held_exposures(window)
        result.mapping = self.mapper.optimize(
            self.keyframes,
            window,
            iters,
            fixed_exposure=held,
            pause=self._pause,
            history=self._older(window),
            stop=self._keyframe_waits,
        )
        self.stats["mapping_s"] += time.perf_counter() - t1
        self._publish()

    def _keyframe_waits(self, done: int) -> bool:
        """Whether a refinement between keyframes (``mapping.frame_iters``) ends after ``done`` iterations:
        with asynchronous mapping, as soon as a keyframe or a checkpoint waits for the worker (it uses
        idle time only)."""
        w = self.worker
        return w is not None and (w.queued("keyframe") + w.queued("init") > 0 or w.hurry.is_set())

    def _next_keyframe_waits(self, done: int) -> bool:
        """Whether a keyframe's window mapping ends after ``done`` iterations (``mapping.min_iters``):
        with asynchronous mapping, once it had that many and the next keyframe, or a checkpoint
        (``snapshot(hurry=True)``), waits for the worker."""
        n, w = self.cfg.mapping.min_iters, self.worker
        return w is not None and 0 < n <= done and (w.queued("keyframe") > 1 or w.hurry.is_set())

    def _wait_for_first_version(self) -> None:
        """``mapping.init_wait=seeds``: return once the worker has published the first keyframe's seeds (or
        has no initial job left, or failed: raised)."""
        while self.publisher.version == 0 and self.worker.queued("init") > 0:
            self.worker.check()
            time.sleep(0.001)
        self.worker.check()

    def _later_keyframe_waits(self, done: int) -> bool:
        """Whether an initial keyframe's mapping ends after ``done`` iterations (``mapping.min_iters``): once it
        had that many and as many later keyframes wait for the worker as may wait before tracking does
        (``mapping.async_queue``, at least one), or a checkpoint waits.  Only with ``mapping.init_wait`` first or
        seeds: otherwise tracking waits for the initial window's mappings and no later keyframe comes meanwhile."""
        n, w = self.cfg.mapping.min_iters, self.worker
        waiting = max(1, self.cfg.mapping.async_queue)
        return w is not None and 0 < n <= done and (w.queued("keyframe") >= waiting or w.hurry.is_set())

    def _publishing_pause(self, after: int):
        """A mapping job's ``pause`` that publishes the map once, after ``after`` iterations
        (``mapping.publish_after``), then pauses as ``_pause`` does."""
        done = 0

        def pause() -> None:
            nonlocal done
            done += 1
            if done == after:
                self._publish()
            self._pause()

        return pause

    def _pause(self) -> None:
        """A safe point of a mapping job: with asynchronous mapping, tracking may take the device (in the
        worker's thread only: the monocular bootstrap seeds in tracking's own turn)."""
        if self.turns is not None and self.worker.is_current():
            self.turns.pause()

    def _publish(self) -> None:
        if self.publisher is not None:
            self.publisher.publish(self.map)

    def _skip(self, i: int, frame: CheckedFrame, T_WC, timestamp: float | None, t0: float) -> FrameResult:
        """A frame whose input is unusable: neither tracked nor mapped; its pose is ``T_WC`` if given
        (the frame is then not lost), else the last good one, and the motion model goes on."""
        self.tracker.skip(T_WC)
        T = self.poses[-1].copy() if T_WC is None else np.array(T_WC, dtype=np.float64)
        result = FrameResult(i, T, None, False, f"not used: {frame.unusable}")
        return self._record(self._counted(result, frame, frame.unusable if T_WC is None else ""), timestamp, t0)

    @staticmethod
    def _counted(result: FrameResult, frame: CheckedFrame, lost_reason: str) -> FrameResult:
        """``result`` with the frame check's counts, and lost with ``lost_reason`` unless it is empty."""
        result.nonfinite_rgb, result.nonfinite_depth = frame.nonfinite_rgb, frame.nonfinite_depth
        result.lost, result.lost_reason = bool(lost_reason), lost_reason
        return result

    def _record(self, result: FrameResult, timestamp: float | None, t0: float) -> FrameResult:
        self.poses.append(result.T_WC)
        self.timestamps.append(float(result.index) if timestamp is None else float(timestamp))
        self.stats["frames"] += 1
        if self.worker is not None:
            result.fills_waiting = self.worker.queued("fill")
            self.frame_fills["most_waiting"] = max(self.frame_fills["most_waiting"], result.fills_waiting)
        result.seconds = time.perf_counter() - t0
        return result

    def _select_at(self, gmap: GaussianMap, T_WC: np.ndarray) -> KeyframeDecision:
        """The selector's decision on ``gmap`` seen from T_WC at the tracking resolution (an empty map:
        nothing visible)."""
        tc = self.tracker.track_camera
        if len(gmap) == 0:
            empty = wp.zeros((tc.height, tc.width), dtype=wp.float32, device=self.device)
            return self.selector.should_add(empty, T_WC, depth=empty)
        renderer = self.renderer if self.worker is None else self._tracking_renderer
        res = renderer.forward(gmap, tc, T_WC)
        return self.selector.should_add(res.alpha, T_WC, depth=res.depth)

    def _add_keyframe(self, i: int, T: np.ndarray, rgb, depth, exposure, result: FrameResult, t_tracked: float) -> None:
        """Keyframe ``i`` into the buffer, seeded, its window mapped and maintained (a mapping job)."""
        cfg, kf = self.cfg, self.keyframes
        if self.history is not None and len(kf) == kf.capacity:
            self.history.keep(kf, kf.slots()[0])  # the buffer evicts its oldest keyframe next
        slot = kf.add(i, T, rgb, depth, exposure)
        if self.exposure is not None:
            kf.exposure[slot] = self.exposure.estimate(kf, kf.rgb[slot], kf.depth[slot], T, exposure, exclude=slot)
        self._archive(slot)
        t0 = time.perf_counter()
        self.seeder.join_pending(self.map)
        # baseline: the one dense start is the first keyframe's; later the densifier grows the map
        first = int(kf.frame_ids[slot]) == self.keyframe_indices[0]
        result.seeded = self._seed(slot, matches=cfg.method == "rgs" or first)
        self.stats["seeding_s"] += time.perf_counter() - t0
        init = i < self._init_window_end
        early = -1 if init or self.publisher is None else cfg.mapping.publish_after
        if init and self.publisher is not None and self.publisher.version == 0 and cfg.mapping.init_wait == "seeds":
            early = 0  # the first keyframe's seeds, which tracking waits for
        if early == 0:
            self._publish()  # tracking sees the keyframe's surface before its window is mapped
        self._pause()
        t0 = time.perf_counter()
        window = kf.slots()[-(cfg.mapping.init_window if init else cfg.mapping.window) :]
        iters = cfg.mapping.init_iters // cfg.mapping.init_window if init else cfg.mapping.iters
        psnr_every = cfg.eval.convergence_every if init else 0
        held = self._held_exposures(window)
        result.mapping = self.mapper.optimize(
            kf,
            window,
            iters,
            psnr_every,
            held,
            pause=self._pause if early <= 0 else self._publishing_pause(early),
            history=self._older(window),
            stop=self._later_keyframe_waits if init else self._next_keyframe_waits,
        )
        self.stats["mapping_s"] += time.perf_counter() - t0
        if self.maintainer is not None:
            self._pause()
            t0 = time.perf_counter()
            result.pruned, result.merged = self.maintainer.maintain(self.map, kf.poses[slot])
            self.stats["maintenance_s"] += time.perf_counter() - t0
        else:
            result.pruned = result.mapping.pruned
        self.convergence += self.mapper.convergence(
            self.keyframes, window, result.mapping, i, "init" if init else "keyframe"
        )
        if self.publisher is not None:
            self._publish()
            self.keyframe_latency_s.append(time.perf_counter() - t_tracked)

    def _odometry_frame(self, rgb, T_init_WC: np.ndarray | None) -> tuple[OdometryResult, np.ndarray | None, str]:
        """The keypoint odometry on this frame: (its result, the frame's pose when it takes the odometry's or
        None when it is tracked, why the odometry's pose failed the motion check or "").

        The odometry predicts with its own motion model (its BA-refined poses) unless the caller gives a
        start, not with the tracker's: the photometric poses' prediction turned its PnP down at fast turns
        (office, 150 frames: 2.5-2.8 cm in the SLAM against 0.78 alone; experiments/results/mono.md, session
        29).  With tracking.odometry_pose a PnP pose is the frame's, except one that jumps or collapses against
        the motion model: the frame is then lost at the prediction, which the motion model goes on from (as
        tracking's motion check does), and the odometry is moved there (``KeypointOdometry.move_to``)."""
        odometry = self._odometry_pose(rgb, T_init_WC)
        takes = (
            self.cfg.tracking.odometry_pose
            and T_init_WC is None
            and odometry.T_WC is not None
            and not odometry.rotation_only
        )
        if not takes:
            return odometry, None, ""
        motion = self.tracker.motion_inconsistency(odometry.T_WC)
        if not motion:
            return odometry, odometry.T_WC, ""
        T_pred = self.tracker.predict()
        # the odometry goes on from the prediction: left where it was, each later frame jumped from the
        # prediction too (7-Scenes, H200, session 30: one jump lost frames 230-286)
        self.odometry.move_to(T_pred, self.poses[-1])
        return odometry, T_pred, motion

    def _odometry_lost_reason(self, odometry: OdometryResult | None, motion: str) -> str:
        """Why a frame that tracking did not lose counts as lost for the odometry (tracking.odometry_pose), or
        "": its pose failed the motion check, or the odometry gave the frame no PnP pose (lost, or a rotation
        only, its translation not measured: photometric tracking's pose stands, but tracking against the
        monocular map did not flag the office's failure at frames 200-250, H200, session 29, and a failure
        must not be silent)."""
        if motion:
            return f"keypoint odometry's pose: {motion}; the frame keeps the prediction"
        unposed = odometry is not None and (odometry.T_WC is None or odometry.rotation_only)
        if self.cfg.tracking.odometry_pose and unposed:
            return f"keypoint odometry: {odometry.reason}; the pose is photometric tracking's, from its rotation"
        return ""

    def _odometry_pose(self, rgb, T_pred_WC: np.ndarray | None) -> OdometryResult:
        """The keypoint odometry's pose of this frame (where tracking starts) from ``T_pred_WC``."""
        host = rgb.numpy() if isinstance(rgb, wp.array) else np.asarray(rgb, dtype=np.float32)
        return self.odometry.track(host, T_pred_WC)

    def _older(self, window: list[int]) -> list[tuple[KeyframeBuffer, int]]:
        """The keyframes older than ``window`` that mapping may render (``mapping.history``): the
        buffer's outside the window, then those the history kept."""
        if self.cfg.mapping.history <= 0.0:
            return []
        older = [(self.keyframes, s) for s in self.keyframes.slots() if s not in window]
        return older + (self.history.views() if self.history is not None else [])

    def _held_exposures(self, window: list[int]) -> list[int]:
        """The window's keyframes whose exposure mapping holds (``Mapper.optimize``'s ``fixed_exposure``):
        all but the newest, and always the first keyframe's (the identity: the gauge of the map's colour).
        A keyframe's exposure is refined while it is the newest, against the map and the held exposures
        of the older ones, then kept; so the map's colour stays in the first keyframe's gauge instead of
        drifting with exposures that all move."""
        kf = self.keyframes
        newest, first = kf.slots()[-1], self.keyframe_indices[0]
        return [s for s in window if s != newest or int(kf.frame_ids[s]) == first]

    def _seed(self, slot: int, matches: bool = True) -> int:
        """Dense initialization at keyframe ``slot``: (``matches``) matches with its neighbours,
        triangulated and seeded where the map does not explain the keyframe yet, then measured-depth
        seeds where it still does not cover it (``Seeder``).  Returns the number of seeds."""
        kf, added = self.keyframes, 0
        neighbours = self.matcher.select_neighbours(slot, kf) if matches and len(kf) >= 2 else []
        if neighbours:
            m = self.matcher.match(slot, kf, neighbours, use_depth=self.mode == "rgbd")
            self._pause()  # between stages: a frame waits for one of them at most (7-Scenes: about 8 ms each)
            points = self.triangulator.triangulate(m.P, m.ref_uv, m.match_uv, m.confidence)
            added += self.seeder.seed_matches(self.map, kf, slot, m, points)
            self._pause()
        return added + self.seeder.seed_depth(self.map, kf, slot)

    def _process_bootstrap(self, rgb, timestamp: float | None, t0: float, frame: CheckedFrame) -> FrameResult:
        """Monocular start (``bootstrap.py``): frame 0 waits for a frame k with enough parallax; then
        keyframes 0 and k are seeded from their triangulated matches and mapped together
        (``mapping.init_iters``), and the frames in between are tracked against that map.  After
        ``bootstrap.max_wait_frames`` frames without success the start falls back to frame 0 alone
        on a plane at ``matching.scene_depth_m`` (the frames since are then tracked against it).  A
        frame whose input is unusable waits with frame 0's pose and is never tracked."""
        cfg, i = self.cfg, len(self.poses)
        stamp = float(i) if timestamp is None else float(timestamp)
        T0 = self.T_first.copy()
        if frame.unusable:
            self._boot_frames.append((None, stamp))
            result = FrameResult(i, T0, None, False, f"monocular bootstrap: frame not used: {frame.unusable}")
            return self._record(self._counted(result, frame, frame.unusable), stamp, t0)
        # a copy: the frame waits beyond this call, and a wp.array's NumPy view on the CPU device is its
        # live memory (the caller's, or the frame check's buffer that the next frame reuses)
        rgb_host = np.array(rgb.numpy() if isinstance(rgb, wp.array) else rgb, dtype=np.float32, copy=True)
        self._boot_frames.append((rgb_host, stamp))
        result = FrameResult(i, T0, None, False, "monocular bootstrap: first frame, waiting for parallax")
        self._counted(result, frame, "")
        boot = None
        if i > 0:
            tb = time.perf_counter()
            boot = self.bootstrap.try_init(self._boot_frames[0][0], rgb_host)
            self.stats["seeding_s"] += time.perf_counter() - tb
            if boot is None and i < cfg.bootstrap.max_wait_frames:
                result.keyframe_reason = f"monocular bootstrap: {self.bootstrap.last_rejection}"
        if i == 0 or (boot is None and i < cfg.bootstrap.max_wait_frames):
            return self._record(result, self._boot_frames[-1][1], t0)  # provisional pose: frame 0's
        last_rejection = self.bootstrap.last_rejection
        frames, self._boot_frames, self.bootstrap = self._boot_frames, [], None
        self._init_window_end = 0
        tb = time.perf_counter()
        slot0 = self.keyframes.add(0, T0, frames[0][0], None)
        self._archive(slot0)
        self.keyframe_indices.append(0)
        if boot is not None:
            result.T_WC = T0 @ boot.T_0k
            slot_k = self.keyframes.add(i, result.T_WC, rgb_host, None)
            self._archive(slot_k)
            self.keyframe_indices.append(i)
            confidence = wp.array(boot.confidence, dtype=wp.float32, device=self.device)
            points = to_triangulated_points(boot, T0, self.device)
            result.seeded = self.seeder.seed_points(self.map, self.keyframes, [slot0, slot_k], points, confidence)
            window, retrack = [slot0, slot_k], range(1, i)
            result.keyframe = True
            result.keyframe_reason = f"monocular bootstrap with frame 0 ({len(boot.points)} points)"
        else:
            result.seeded = self._seed(slot0)  # the first keyframe's plane at matching.scene_depth_m
            window, retrack = [slot0], range(1, i + 1)
            result.keyframe_reason = f"monocular bootstrap gave up after {i} frames: plane at frame 0"
            self.bootstrap_fallback = (
                f"the monocular bootstrap found no frame with enough parallax against frame 0 in {i} frames "
                f"(bootstrap.max_wait_frames; the last: {last_rejection}); the map starts from a plane at "
                f"matching.scene_depth_m = {cfg.matching.scene_depth_m} m, on which tracking usually fails. A start "
                "that moves sideways, or a longer wait, gives the bootstrap its parallax"
            )
        self.stats["seeding_s"] += time.perf_counter() - tb
        tm = time.perf_counter()
        psnr_every = cfg.eval.convergence_every
        result.mapping = self.mapper.optimize(self.keyframes, window, cfg.mapping.init_iters, psnr_every, [slot0])
        self.stats["mapping_s"] += time.perf_counter() - tm
        self.convergence += self.mapper.convergence(self.keyframes, window, result.mapping, i, "init")
        starts = [None] * len(frames)  # where the frames that waited start tracking: the odometry's poses
        if self.odometry is not None:
            try:  # a plane at an assumed depth gives the odometry no second pose to start from
                if boot is None:
                    raise ValueError("the bootstrap fell back to a plane")
                starts = self.odometry.start([f[0] for f in frames], T0, result.T_WC)
            except ValueError as e:  # the run goes on, tracking from the constant-velocity prediction
                self.odometry = None
                result.keyframe_reason += f"; keypoint odometry not started: {e}"
        self.tracker.reset(T0)  # the frames that waited, tracked against the first map
        for j in retrack:
            if frames[j][0] is None:  # its input was unusable: the last good pose
                self.tracker.skip()
                self.poses[j] = self.poses[j - 1].copy()
                continue
            tr0 = time.perf_counter()
            tracking = self.tracker.track(frames[j][0], None, self.map, starts[j] if j < i else None)
            self.stats["tracking_s"] += time.perf_counter() - tr0
            T = self.poses[j - 1].copy() if tracking.diverged else tracking.T_WC
            if j < i:
                self.poses[j] = T
            else:
                result.tracking, result.T_WC = tracking, T
                self._counted(result, frame, tracking.reason if tracking.lost else "")
        if boot is not None:
            self.tracker.reset(result.T_WC, self.poses[i - 1] if i > 1 else T0)
        self._select_at(self.map, result.T_WC)
        self.selector.accept(result.T_WC)
        return self._record(result, frames[-1][1], t0)

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
        tracking's turn (from any thread)."""
        camera, background = camera or self.camera, self.cfg.render.background

        def whole(renderer: Renderer, gmap: GaussianMap) -> RenderResult:
            res = renderer.forward(gmap, camera, T_WC, background)
            return renderer.forward(gmap, camera, T_WC, background) if res.overflowed else res

        if self.worker is None:
            return whole(self.renderer, self.map)
        with self.turns.tracking():
            if self.publisher.version == 0 and len(self.map):
                self.publisher.publish(self.map)
            with self.publisher.read() as published:
                return whole(self._tracking_renderer, published)

    def wait_for_mapping(self, check: bool = True, hurry: bool = False) -> None:
        """Return when the mapping worker has done every job queued so far (at once without one);
        with ``check``, raises a job's exception; with ``hurry``, the keyframes' window mapping ends at
        ``mapping.min_iters`` (when set) instead of ``mapping.iters``, as when the next keyframe waits."""
        if self.worker is not None:
            self.worker.drain(check, hurry)

    def _archive(self, slot: int) -> None:
        if self.archive is not None:
            self.archive.add_from(self.keyframes, slot)

    def finish(self, refine: bool = True) -> None:
        """End of the sequence: the frame-fill seeds that wait for the next keyframe join the map
        (without mapping); then, with ``mapping.final_iters`` and ``refine``, the final refinement
        over every keyframe of the run (``Mapper.refine_all``; what it did: ``final_refinement``,
        its time counts as mapping).  ``run`` calls it after the last frame; ``track`` may go on
        after it."""
        self.wait_for_mapping()
        self.seeder.join_pending(self.map)
        if refine and self.archive is not None and len(self.archive) and len(self.map):
            t0 = time.perf_counter()
            self.archive.update_exposures(self.keyframes)
            cfg = self.cfg.mapping
            self.final_refinement = self.mapper.refine_all(self.archive, cfg.final_iters, cfg.window)
            self.final_refinement["seconds"] = time.perf_counter() - t0
            self.stats["mapping_s"] += self.final_refinement["seconds"]
        self._publish()  # asynchronous: renders after the run show the map as saved

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
