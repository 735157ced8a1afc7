"""The SLAM system (supplement §4.6) and its command line, ``python -m rgs_warp.slam``.

``SLAM(cfg, camera)`` is also the library entry point: ``slam.track(rgb, depth)`` per frame returns
the camera-to-world pose; every frame is tracked against the map, and when the co-visibility test
accepts it as a keyframe, dense matching -> triangulation -> seeding -> windowed mapping -> merge /
prune run before the next frame (same thread, deterministic).

``method=baseline`` (the dense initialization baseline of supplement Table 2) makes one dense start
at the first keyframe and grows the map by residual-driven densification inside the mapping
iterations (``Mapper`` with a ``Densifier``), without dense matching or merge / prune; later
keyframes only get measured-depth seeds where the map does not cover them yet (RGB-D), since
densification cannot reach regions no Gaussian sees (a run without them is lost once the camera
leaves the first view).  Everything else is shared.
"""

from __future__ import annotations

import json
import signal
import sys
import time
from dataclasses import dataclass, replace
from datetime import datetime
from pathlib import Path

import numpy as np
import warp as wp
from tqdm import tqdm

from rgs_warp import maintenance
from rgs_warp.bootstrap import MonoBootstrap, to_triangulated_points
from rgs_warp.config import Config, ConfigError, help_text, load_config, parse_yaml, save_config
from rgs_warp.datasets import DatasetError, open_dataset
from rgs_warp.geometry import invert_pose
from rgs_warp.io.ply import load_ply, save_ply
from rgs_warp.io.trajectory import read_tum_trajectory, write_tum_trajectory
from rgs_warp.kernels import mapping as km
from rgs_warp.keyframes import KeyframeBuffer, KeyframeSelector
from rgs_warp.mapping import Mapper, MappingResult
from rgs_warp.matching import DenseMatcher
from rgs_warp.render import Renderer, RenderResult
from rgs_warp.seeding import Seeder
from rgs_warp.tracking import Tracker, TrackingResult
from rgs_warp.triangulation import TriangulatedPoints, Triangulator
from rgs_warp.types import Camera, Frame, GaussianMap

METHODS = ("rgs", "baseline")

USAGE = """usage: python -m rgs_warp.slam [group=option ...] [key=value ...]

examples:
  python -m rgs_warp.slam                                  # generated synthetic room (CPU-sized)
  python -m rgs_warp.slam method=baseline                  # the same with the dense initialization baseline
  python -m rgs_warp.slam dataset=replica/office0 data_root=/data tracking.iters=40
  python -m rgs_warp.slam dataset=7scenes/redkitchen dataset.path=../shared/data/7scenes-redkitchen
"""


@dataclass
class FrameResult:
    """What ``SLAM.track`` did with one frame."""

    index: int
    T_WC: np.ndarray
    tracking: TrackingResult | None  # None for the first frame (its pose is given)
    keyframe: bool
    keyframe_reason: str
    seeded: int = 0  # Gaussians added by seeding (a keyframe's, or a frame fill's: seeding.frame_fill_min_uncovered)
    pruned: int = 0  # rgs: by the maintenance after mapping; baseline: by the densification's culling
    merged: int = 0
    # monocular keyframe: the map's depth over its triangulated points' where the map covers them
    # (median; 1 = the new surface has the map's scale); None where too few points overlap
    seed_depth_ratio: float | None = None
    mapping: MappingResult | None = None
    seconds: float = 0.0
    tracking_seconds: float = 0.0


class SLAM:
    """RGS-SLAM on one camera.  ``track`` frames in order; read ``map``, ``keyframes``,
    ``trajectory()``, ``convergence``; ``render(T_WC)``; ``save(dir)`` / ``SLAM.load(dir)``.

    ``T_first_WC``: pose of the first frame (default identity: the trajectory is then relative to
    it; pass the ground-truth first pose to compare maps in the ground truth's frame).
    """

    def __init__(self, cfg: Config, camera: Camera, device=None, T_first_WC: np.ndarray | None = None):
        self.cfg = cfg
        self.camera = camera
        self.device = wp.get_device(resolve_device(cfg.device) if device is None else device)
        self.mode = cfg.mode
        if cfg.method not in METHODS:
            raise ValueError(f"unknown method {cfg.method!r}: SLAM implements {', '.join(METHODS)}")
        dev = self.device
        self.map = GaussianMap(4096, sh_degree=cfg.render.sh_degree, device=dev)
        self.tracker = Tracker(cfg.tracking, camera, dev, mode=self.mode, renderer=Renderer(dev))
        tc = self.tracker.track_camera
        self.selector = KeyframeSelector(cfg.keyframes, tc.width, tc.height, dev)
        if cfg.keyframes.buffer_size < 2:
            n_kf = cfg.keyframes.buffer_size
            raise ValueError(f"keyframes.buffer_size must be >= 2 (triangulation needs pairs), got {n_kf}")
        if cfg.mapping.extra_keyframes < 0:
            raise ValueError(f"mapping.extra_keyframes must be >= 0, got {cfg.mapping.extra_keyframes}")
        self.keyframes = KeyframeBuffer(cfg.keyframes.buffer_size, camera.width, camera.height, dev)
        # frame fill (seeding.frame_fill_min_uncovered): a tracked frame's images, and the seeds taken
        # from frames since the last keyframe, which join the map when the next keyframe is processed
        self._fill_frame: KeyframeBuffer | None = None
        self._pending = GaussianMap(1024, sh_degree=cfg.render.sh_degree, device=dev)
        self.matcher = DenseMatcher(cfg.matching, camera, dev)
        self.triangulator = Triangulator(cfg.triangulation, dev)
        # Poisson radius and tangential scale in units of the sample spacing of each seed source
        spacing = cfg.matching.thin_spacing * self.matcher.stride
        self.seeder = Seeder(
            replace(cfg.seeding, poisson_radius_px=cfg.seeding.poisson_radius_px * spacing), camera, dev
        )
        depth_spacing = cfg.seeding.depth_stride
        self.depth_seeder = Seeder(
            replace(cfg.seeding, poisson_radius_px=cfg.seeding.poisson_radius_px * depth_spacing), camera, dev
        )
        self.renderer = Renderer(dev)
        self._merge_scratch = maintenance.MergeScratch(dev)
        self.mapper = Mapper(
            cfg.mapping,
            camera,
            self.map,
            dev,
            mode=self.mode,
            renderer=self.renderer,
            seed=cfg.seed,
            densify=cfg.densify if cfg.method == "baseline" else None,
        )
        self.T_first = np.eye(4) if T_first_WC is None else np.asarray(T_first_WC, dtype=np.float64)
        self.poses: list[np.ndarray] = []  # camera-to-world of every tracked frame
        self.timestamps: list[float] = []
        self.keyframe_indices: list[int] = []
        self._given_poses: set[int] = set()  # frames whose pose the caller gave (process(T_WC=...))
        self._rng = np.random.default_rng([cfg.seed, 1])  # mapping.extra_keyframes
        self.first_slot: int | None = None
        self._slot_of_frame: dict[int, int] = {}
        hg, wg = camera.height // depth_spacing, camera.width // depth_spacing
        n_depth = hg * wg
        kw = {"device": dev}
        self._depth_grid = (hg, wg)
        self._depth_pts = TriangulatedPoints(
            wp.zeros(n_depth, dtype=wp.vec3d, **kw),
            wp.zeros(n_depth, dtype=wp.float64, **kw),
            wp.zeros(n_depth, dtype=wp.float64, **kw),
            wp.zeros(n_depth, dtype=wp.int32, **kw),
            wp.zeros(n_depth, dtype=wp.int32, **kw),
        )
        self._depth_conf = wp.zeros(n_depth, dtype=wp.float32, **kw)
        self._mono_depth = wp.full((camera.height, camera.width), cfg.matching.scene_depth_m, dtype=wp.float32, **kw)
        self._zero_alpha = wp.zeros((camera.height, camera.width), dtype=wp.float32, **kw)
        self.stats = {"tracking_s": 0.0, "mapping_s": 0.0, "seeding_s": 0.0, "maintenance_s": 0.0, "frames": 0}
        # frames below this index are forced keyframes of the initialization window; a monocular
        # two-view bootstrap replaces that window (set to 0 when it has built the first map)
        self._init_window_end = cfg.mapping.init_window
        self._bootstrap = (
            MonoBootstrap(cfg.bootstrap, camera, dev, backbone=self.matcher.backbone, matching=cfg.matching)
            if self.mode == "mono" and cfg.bootstrap.enabled
            else None
        )
        self._boot_frames: list[tuple[np.ndarray, float]] = []  # (rgb, timestamp) while it waits
        # PSNR against the cumulative mapping iterations: {"iteration", "frame", "phase" ("init" |
        # "keyframe"), "psnr_db" (mean over the mapping window, None for an empty map), "gaussians"}
        self.convergence: list[dict] = []

    # ---- per frame -----------------------------------------------------------------------------
    def track(
        self,
        rgb,
        depth=None,
        timestamp: float | None = None,
        T_init_WC: np.ndarray | None = None,
        T_WC: np.ndarray | None = None,
    ) -> np.ndarray:
        """Track one frame (``rgb`` HxWx3 float32 in [0, 1], ``depth`` HxW metres or None in mono
        mode; NumPy arrays or ``wp.array``s on the SLAM's device) and return its camera-to-world pose.

        ``T_init_WC``: where tracking starts (e.g. from wheel odometry or an IMU); default the
        constant-velocity prediction.  ``T_WC``: the frame's pose is known (motion capture, another
        odometry): tracking is skipped and the frame goes to keyframe selection and mapping at that
        pose (mapping with known poses).  Both are 4x4 camera-to-world, in the SLAM's world frame.  The
        first frame is not tracked: its pose is ``T_WC`` if given, else ``T_first_WC``."""
        return self.process(rgb, depth, timestamp, T_init_WC=T_init_WC, T_WC=T_WC).T_WC

    def process(
        self,
        rgb,
        depth=None,
        timestamp: float | None = None,
        T_init_WC: np.ndarray | None = None,
        T_WC: np.ndarray | None = None,
    ) -> FrameResult:
        """``track`` with the diagnostics of what happened to the frame (``tracking`` is None when
        the pose was given)."""
        if isinstance(rgb, Frame):
            rgb, depth, timestamp = rgb.rgb, rgb.depth, rgb.timestamp
        if T_init_WC is not None and T_WC is not None:
            raise ValueError("give T_init_WC (where tracking starts) or T_WC (the known pose), not both")
        for name, T_given in (("T_init_WC", T_init_WC), ("T_WC", T_WC)):
            if T_given is not None and (np.shape(T_given) != (4, 4) or not np.all(np.isfinite(T_given))):
                raise ValueError(f"{name}: expected a finite 4x4 camera-to-world matrix, got {np.shape(T_given)}")
        t0 = time.perf_counter()
        i = len(self.poses)
        use_depth = self.mode == "rgbd"
        if use_depth and depth is None:
            raise ValueError("mode 'rgbd' needs a depth image for every frame (or set mode=mono)")
        if not use_depth:
            depth = None
        if self._bootstrap is not None:
            if T_init_WC is not None or T_WC is not None:
                raise ValueError("the monocular bootstrap finds its own poses: no T_init_WC / T_WC before it ends")
            return self._process_bootstrap(rgb, timestamp, t0)
        init_phase = i < self._init_window_end
        tracking = None
        if i == 0:
            T = self.T_first.copy() if T_WC is None else np.array(T_WC, dtype=np.float64)
            if T_WC is not None:
                self._given_poses.add(i)
            self.tracker.reset(T)
            is_kf, reason = True, "first frame"
            exposure, pose_ok = (1.0, 0.0), True
            self.selector.should_add(self._alpha_at(T), T)
        elif T_WC is not None:
            T = np.array(T_WC, dtype=np.float64)
            self.tracker.load_frame(rgb, depth)  # the frame fill reads it
            self.tracker.reset(T, self.poses[-1])  # the motion model goes on from the given poses
            exposure, pose_ok = self.tracker.exposure(self.map, T), True
            self._given_poses.add(i)  # mapping keeps them
            decision = self.selector.should_add(self.tracker.alpha, T)
            is_kf, reason = decision.is_keyframe, f"{decision.reason} (pose given)"
            if init_phase:
                is_kf, reason = True, f"initial window ({i + 1}/{self._init_window_end}, pose given)"
        else:
            tr0 = time.perf_counter()
            tracking = self.tracker.track(rgb, depth, self.map, T_init_WC)
            self.stats["tracking_s"] += time.perf_counter() - tr0
            T = tracking.T_WC
            exposure, pose_ok = (tracking.gain, tracking.bias), not tracking.lost
            decision = self.selector.should_add(self.tracker.alpha, T, None if tracking.lost else tracking.loss)
            is_kf, reason = decision.is_keyframe, decision.reason
            if init_phase:
                is_kf, reason = True, f"initial window ({i + 1}/{self._init_window_end})"
        result = FrameResult(i, T, tracking, is_kf, reason, tracking_seconds=time.perf_counter() - t0)
        fill = self.cfg.seeding.frame_fill_min_uncovered
        if not is_kf and use_depth and fill >= 0.0 and pose_ok and 1.0 - decision.coverage > fill:
            t1 = time.perf_counter()
            result.seeded = self._fill_frame_gaps(T, exposure)
            self.stats["seeding_s"] += time.perf_counter() - t1
        if is_kf:
            self.selector.accept(T)
            self._add_keyframe(i, T, rgb, depth, exposure, result)
            T = self.keyframes.poses[self._slot_of_frame[i]].copy()
            self.tracker.set_last_pose(T)
            result.T_WC = T
        self.poses.append(T)
        self.timestamps.append(float(i) if timestamp is None else float(timestamp))
        self.stats["frames"] += 1
        result.seconds = time.perf_counter() - t0
        return result

    def _alpha_at(self, T_WC: np.ndarray) -> wp.array:
        """The map's accumulated opacity seen from T_WC at the tracking resolution (zeros if empty)."""
        tc = self.tracker.track_camera
        if len(self.map) == 0:
            return wp.zeros((tc.height, tc.width), dtype=wp.float32, device=self.device)
        return self.renderer.forward(self.map, tc, T_WC).alpha

    def _store_keyframe(self, i: int, T: np.ndarray, rgb, depth, exposure) -> int:
        """Frame i into the keyframe buffer (the oldest leaves when full); returns its slot."""
        kf = self.keyframes
        evicted = kf.frame_ids[kf.slots()[0]] if len(kf) == kf.capacity else None
        if evicted is not None:
            self._slot_of_frame.pop(int(evicted), None)
        slot = kf.add(i, T, rgb, depth, exposure)
        self._slot_of_frame[i] = slot
        if self.first_slot is None:
            self.first_slot = slot
        elif self.first_slot == slot:
            self.first_slot = -1  # the first keyframe left the buffer: nothing is fixed any more
        self.keyframe_indices.append(i)
        return slot

    def _process_bootstrap(self, rgb, timestamp: float | None, t0: float) -> FrameResult:
        """Monocular start (``bootstrap.py``): frame 0 waits for a frame k with enough parallax; then
        keyframes 0 and k are seeded from their triangulated matches and mapped together
        (``mapping.init_iters``), and the frames in between are tracked against that map.  After
        ``bootstrap.max_wait_frames`` frames without success the start falls back to frame 0 alone
        on a plane at ``matching.scene_depth_m`` (the frames since are then tracked against it)."""
        cfg, dev = self.cfg, self.device
        i = len(self.poses)
        rgb_host = rgb.numpy() if isinstance(rgb, wp.array) else np.asarray(rgb, dtype=np.float32)
        self._boot_frames.append((rgb_host, float(i) if timestamp is None else float(timestamp)))
        T0 = self.T_first.copy()
        result = FrameResult(i, T0, None, False, "monocular bootstrap: first frame, waiting for parallax")
        boot = None
        if i > 0:
            tb = time.perf_counter()
            boot = self._bootstrap.try_init(self._boot_frames[0][0], rgb_host)
            self.stats["seeding_s"] += time.perf_counter() - tb
            if boot is None and i < cfg.bootstrap.max_wait_frames:
                result.keyframe_reason = f"monocular bootstrap: {self._bootstrap.last_rejection}"
        if i == 0 or (boot is None and i < cfg.bootstrap.max_wait_frames):
            self.poses.append(T0)  # provisional: replaced once the first map exists
            self.timestamps.append(self._boot_frames[-1][1])
            self.stats["frames"] += 1
            result.seconds = time.perf_counter() - t0
            return result
        frames, self._boot_frames, self._bootstrap = self._boot_frames, [], None
        self._init_window_end = 0
        tb = time.perf_counter()
        slot0 = self._store_keyframe(0, T0, frames[0][0], None, (1.0, 0.0))
        if boot is not None:
            T_k = T0 @ boot.T_0k
            slot_k = self._store_keyframe(i, T_k, rgb_host, None, (1.0, 0.0))
            points = to_triangulated_points(boot, T0, dev)
            confidence = wp.array(boot.confidence, dtype=wp.float32, device=dev)
            result.seeded = self.seeder.seed(points, confidence, self.keyframes, [slot0, slot_k], self.map)
            window, retrack = [slot0, slot_k], range(1, i)
            result.keyframe, result.keyframe_reason = (
                True,
                f"monocular bootstrap with frame 0 ({len(boot.points)} points)",
            )
        else:
            result.seeded, _ = self._seed(slot0)  # the first keyframe's plane at matching.scene_depth_m
            window, retrack = [slot0], range(1, i + 1)
            result.keyframe_reason = f"monocular bootstrap gave up after {i} frames: plane at frame 0"
        self.stats["seeding_s"] += time.perf_counter() - tb
        tm = time.perf_counter()
        result.mapping = self.mapper.optimize(
            self.keyframes, window, cfg.mapping.init_iters, fixed=[slot0], psnr_every=cfg.eval.convergence_every
        )
        self.stats["mapping_s"] += time.perf_counter() - tm
        self._log_convergence(i, "init", window, result.mapping)
        # the frames that waited, tracked against the first map
        self.tracker.reset(T0)
        for j in retrack:
            tr0 = time.perf_counter()
            tracking = self.tracker.track(frames[j][0], None, self.map)
            self.stats["tracking_s"] += time.perf_counter() - tr0
            if j < i:
                self.poses[j] = tracking.T_WC
            else:
                result.tracking, result.T_WC = tracking, tracking.T_WC
        if boot is not None:
            result.T_WC = self.keyframes.poses[slot_k].copy()
            self.tracker.reset(result.T_WC, self.poses[i - 1] if i > 1 else T0)
        self.poses[0] = self.keyframes.poses[slot0].copy()
        self.selector.should_add(self._alpha_at(result.T_WC), result.T_WC)
        self.selector.accept(result.T_WC)
        self.poses.append(result.T_WC)
        self.timestamps.append(frames[-1][1])
        self.stats["frames"] += 1
        result.seconds = time.perf_counter() - t0
        return result

    def _add_keyframe(self, i: int, T: np.ndarray, rgb, depth, exposure, result: FrameResult) -> None:
        cfg = self.cfg
        kf = self.keyframes
        slot = self._store_keyframe(i, T, rgb, depth, exposure)
        # baseline: the one dense start is the first keyframe's; later the densifier grows the map
        # and new regions get depth seeds only (no matching)
        t0 = time.perf_counter()
        self._join_pending()
        result.seeded, result.seed_depth_ratio = self._seed(
            slot, matches=cfg.method == "rgs" or len(self.keyframe_indices) == 1
        )
        self.stats["seeding_s"] += time.perf_counter() - t0
        t0 = time.perf_counter()
        init = i < self._init_window_end
        window = kf.slots()[-(cfg.mapping.init_window if init else cfg.mapping.window) :]
        older = kf.slots()[: -len(window)]
        if not init and cfg.mapping.extra_keyframes > 0 and older:
            picked = self._rng.choice(len(older), min(cfg.mapping.extra_keyframes, len(older)), replace=False)
            window = [older[j] for j in sorted(picked)] + window
        iters = cfg.mapping.init_iters // cfg.mapping.init_window if init else cfg.mapping.iters
        fixed = [self.first_slot] if self.first_slot is not None and self.first_slot >= 0 else []
        fixed += [s for s in window if int(kf.frame_ids[s]) in self._given_poses]
        psnr_every = cfg.eval.convergence_every if init else 0
        result.mapping = self.mapper.optimize(kf, window, iters, fixed=fixed, psnr_every=psnr_every)
        self.stats["mapping_s"] += time.perf_counter() - t0
        if cfg.method == "rgs":
            t0 = time.perf_counter()
            result.pruned, result.merged = self._maintain(slot)
            self.stats["maintenance_s"] += time.perf_counter() - t0
        else:
            result.pruned = result.mapping.pruned
        self._log_convergence(i, "init" if init else "keyframe", window, result.mapping)

    def _log_convergence(self, i: int, phase: str, window: list[int], mapping: MappingResult) -> None:
        """The samples taken during keyframe i's mapping, then the window's PSNR after it (and after
        the maintenance), which replaces a sample at the same iteration; nothing without mapping."""
        if mapping.iters == 0:
            return
        points = list(mapping.psnr_curve)
        if points and points[-1][0] == self.mapper.total_iters:
            points.pop()
        points.append((self.mapper.total_iters, self.mapper.window_psnr(self.keyframes, window), len(self.map)))
        for it, psnr_db, n in points:
            psnr_db = float(psnr_db) if np.isfinite(psnr_db) else None
            self.convergence.append({"iteration": it, "frame": i, "phase": phase, "psnr_db": psnr_db, "gaussians": n})

    # ---- seeding -------------------------------------------------------------------------------
    def _seed(self, slot: int, matches: bool = True) -> tuple[int, float | None]:
        """Dense initialization at keyframe ``slot``: (``matches``) matches with its neighbours,
        triangulated, seeded where the map does not explain the keyframe yet; then (RGB-D,
        ``seeding.depth_fill``, or the very first keyframe) measured-depth seeds where the map still
        does not cover it.  Returns the number of seeds and (monocular) the map's depth over the
        triangulated points' (``FrameResult.seed_depth_ratio``)."""
        cfg, kf, dev = self.cfg, self.keyframes, self.device
        added, ratio = 0, None
        T = kf.poses[slot]
        T_CW = wp.mat44d(invert_pose(T))
        neighbours = self.matcher.select_neighbours(slot, kf) if matches and len(kf) >= 2 else []
        if neighbours:
            m = self.matcher.match(slot, kf, neighbours, use_depth=self.mode == "rgbd")
            pts = self.triangulator.triangulate(m.P, m.ref_uv, m.match_uv, m.confidence)
            if self.mode == "rgbd" and cfg.seeding.depth_consistency_tol > 0.0:
                wp.launch(
                    km.reject_depth_inconsistent_points,
                    dim=pts.X.shape[0],
                    inputs=[m.ref_uv, kf.depth[slot], pts.X, T_CW, cfg.seeding.depth_consistency_tol],
                    outputs=[pts.valid],
                    device=dev,
                )
            if len(self.map):
                res = self.renderer.forward(self.map, self.camera, T)
                if self.mode == "mono":
                    ratio = self._seed_depth_ratio(pts, m.ref_uv, res, T_CW)
                wp.launch(
                    km.mask_covered_points,
                    dim=pts.X.shape[0],
                    inputs=[m.ref_uv, res.alpha, res.depth, pts.X, T_CW]
                    + [cfg.seeding.covered_alpha, cfg.seeding.covered_depth_tol],
                    outputs=[pts.valid],
                    device=dev,
                )
            added += self.seeder.seed(pts, m.aggregated, kf, [slot, *neighbours], self.map)
        first = len(self.map) == 0
        if first or (self.mode == "rgbd" and cfg.seeding.depth_fill):
            alpha = self._zero_alpha if first else self.renderer.forward(self.map, self.camera, T).alpha
            added += self._depth_seed(kf, slot, alpha, None if self.mode == "rgbd" else self._mono_depth)
        return added, ratio

    def _seed_depth_ratio(self, pts, ref_uv: wp.array, res, T_CW: wp.mat44d) -> float | None:
        """Monocular: the median of the map's depth over the triangulated points' where the map covers
        them (``res``: the map rendered at the keyframe, world-to-camera ``T_CW``); None with fewer than
        ``seeding.depth_ratio_min_points`` such points."""
        n = pts.X.shape[0]
        ratio = wp.empty(n, dtype=wp.float32, device=self.device)
        wp.launch(
            km.map_depth_ratio,
            dim=n,
            inputs=[ref_uv, res.alpha, res.depth, pts.X, pts.valid, T_CW, self.cfg.seeding.covered_alpha],
            outputs=[ratio],
            device=self.device,
        )
        r = ratio.numpy()
        r = r[r > 0.0]
        return float(np.median(r)) if len(r) >= self.cfg.seeding.depth_ratio_min_points else None

    def _fill_frame_gaps(self, T: np.ndarray, exposure) -> int:
        """Measured-depth seeds from the frame just tracked (not a keyframe) where neither the map
        nor the seeds pending since the last keyframe cover it (``seeding.frame_fill_min_uncovered``):
        surface that shows up between keyframes, which no keyframe may see again.  The seeds take the
        frame's colour (exposure-corrected) and wait in ``_pending``: tracking does not change the map
        (§4.6), so the co-visibility test of the next frames sees the same map; they join it at the
        next keyframe, before its seeding, and its mapping refines those it sees."""
        dev = self.device
        if self._fill_frame is None:
            self._fill_frame = KeyframeBuffer(1, self.camera.width, self.camera.height, dev)
            self._fill_alpha = wp.empty((self.camera.height, self.camera.width), dtype=wp.float32, device=dev)
        rgb, depth = self.tracker.frame
        self._fill_frame.add(len(self.poses), T, rgb, depth, exposure)
        alpha = self.renderer.forward(self.map, self.camera, T).alpha
        if len(self._pending):
            wp.copy(self._fill_alpha, alpha)  # the renderer's buffers are reused by the next render
            alpha = self._fill_alpha
            pending = self.renderer.forward(self._pending, self.camera, T).alpha
            wp.launch(km.union_alpha, dim=alpha.shape, inputs=[alpha, pending], outputs=[alpha], device=dev)
        return self._depth_seed(self._fill_frame, 0, alpha, target=self._pending)

    def _join_pending(self) -> None:
        """The frame-fill seeds since the last keyframe join the map."""
        p, n = self._pending, len(self._pending)
        if n:
            self.map.append(p.means[:n], p.rotations[:n], p.log_scales[:n], p.opacity_logits[:n], p.sh[:n])
            p.count = 0

    def _depth_seed(
        self,
        frames: KeyframeBuffer,
        slot: int,
        alpha: wp.array,
        depth: wp.array | None = None,
        target: GaussianMap | None = None,
    ) -> int:
        """Seeds from the measured depth of ``frames`` slot ``slot`` (``depth`` in its place, e.g. the
        monocular first keyframe's nominal plane) where ``alpha`` is below ``seeding.covered_alpha``,
        appended to ``target`` (default the map)."""
        cfg = self.cfg.seeding
        T = frames.poses[slot]
        p = self._depth_pts
        wp.launch(
            km.depth_points,
            dim=self._depth_grid,
            inputs=[frames.depth[slot] if depth is None else depth]
            + [self.camera.fx, self.camera.fy, self.camera.cx, self.camera.cy, wp.mat44d(T), cfg.depth_stride]
            + [cfg.depth_max_rel_jump, cfg.min_residual_px, 90.0, alpha, cfg.covered_alpha],
            outputs=[p.X, p.residual_px, p.parallax_deg, p.support, p.valid],
            device=self.device,
        )
        self._depth_conf.fill_(1.0 if self.mode == "rgbd" else 0.0)
        return self.depth_seeder.seed(p, self._depth_conf, frames, [slot], self.map if target is None else target)

    # ---- maintenance ---------------------------------------------------------------------------
    def _maintain(self, slot: int) -> tuple[int, int]:
        """Prune, then merge near-duplicates seen from keyframe ``slot`` among the survivors (§4.5);
        returns (pruned, merged).  The masks combine on the device; one read of the two counts."""
        cfg = self.cfg.mapping
        if len(self.map) == 0:
            return 0, 0
        self.mapper.sync()
        prune, prune_stats = maintenance.prune_mask(
            self.map,
            self.mapper.obs_count,
            self.mapper.vis_count,
            opacity_min=cfg.opacity_cull,
            max_scale_m=cfg.max_scale_m,
            min_obs=cfg.min_obs,
            min_visibility_ratio=cfg.min_visibility_ratio,
        )
        remove, n_merged = maintenance.merge_duplicates(
            self.map,
            self.camera,
            self.keyframes.poses[slot],
            max_footprint_px=cfg.merge_footprint_px,
            max_color_diff=cfg.merge_color_diff,
            exclude=prune,
            scratch=self._merge_scratch,
        )
        pruned = maintenance.PruneStats.read(prune_stats).total
        merged = int(n_merged.numpy()[0])
        if pruned + merged:
            self.mapper.remove(remove)
        return pruned, merged

    # ---- outputs -------------------------------------------------------------------------------
    def trajectory(self) -> tuple[np.ndarray, np.ndarray]:
        """(timestamps (N,), camera-to-world poses (N, 4, 4)) of the tracked frames; keyframes carry
        their mapping-refined poses."""
        poses = np.array(self.poses) if self.poses else np.zeros((0, 4, 4))
        kf = self.keyframes
        for slot in kf.slots():
            i = int(kf.frame_ids[slot])
            if 0 <= i < len(poses):
                poses[i] = kf.poses[slot]
        return np.array(self.timestamps), poses

    def render(self, T_WC: np.ndarray, camera: Camera | None = None) -> RenderResult:
        """Render the map from a camera-to-world pose (default camera: the SLAM's); the result's
        images are the renderer's buffers, valid until the next render."""
        return self.renderer.forward(self.map, camera or self.camera, T_WC, self.cfg.render.background)

    def finish(self) -> None:
        """End of the sequence: the frame-fill seeds that wait for the next keyframe join the map
        (without mapping).  ``run`` calls it after the last frame; ``track`` may go on after it."""
        self._join_pending()

    def save(self, directory: str | Path) -> Path:
        """Write ``map.ply``, ``trajectory.txt`` (TUM), ``keyframes.npz`` and ``config.yaml``.  The
        frame-fill seeds still waiting for a keyframe are not in ``map.ply`` unless ``finish`` ran."""
        directory = Path(directory)
        directory.mkdir(parents=True, exist_ok=True)
        save_ply(directory / "map.ply", self.map)
        stamps, poses = self.trajectory()
        write_tum_trajectory(directory / "trajectory.txt", stamps, poses)
        kf = self.keyframes
        slots = kf.slots()
        np.savez_compressed(
            directory / "keyframes.npz",
            frame_ids=kf.frame_ids[slots],
            poses=kf.poses[slots],
            exposure=kf.exposure[slots],
            rgb=np.stack([kf.rgb[s].numpy() for s in slots]) if slots else np.zeros((0,)),
            depth=np.stack([kf.depth[s].numpy() for s in slots]) if slots else np.zeros((0,)),
            keyframe_indices=np.array(self.keyframe_indices),
            mapping_iters=self.mapper.total_iters,  # the densification schedule's clock
            camera=np.array([self.camera.fx, self.camera.fy, self.camera.cx, self.camera.cy]),
            size=np.array([self.camera.width, self.camera.height]),
            first_pose=self.T_first,
            given_poses=np.array(sorted(self._given_poses), dtype=np.int64),  # mapping keeps these
        )
        save_config(self.cfg, directory / "config.yaml")
        return directory

    @classmethod
    def load(cls, directory: str | Path, device=None) -> SLAM:
        """A SLAM restored from ``save``: map, trajectory, keyframe buffer and the count of mapping
        iterations; tracking continues from the last pose (the optimiser state starts afresh)."""
        directory = Path(directory)
        for name in ("map.ply", "trajectory.txt", "keyframes.npz", "config.yaml"):
            if not (directory / name).is_file():
                raise FileNotFoundError(f"{directory / name}: missing (not a folder written by SLAM.save)")
        cfg = _load_saved_config(directory)
        data = np.load(directory / "keyframes.npz")
        fx, fy, cx, cy = (float(v) for v in data["camera"])
        w, h = (int(v) for v in data["size"])
        slam = cls(cfg, Camera(fx, fy, cx, cy, w, h), device=device, T_first_WC=data["first_pose"])
        loaded = load_ply(directory / "map.ply", device=slam.device)
        n = len(loaded)
        slam.map.append(
            loaded.means[:n], loaded.rotations[:n], loaded.log_scales[:n], loaded.opacity_logits[:n], loaded.sh[:n]
        )
        stamps, poses = read_tum_trajectory(directory / "trajectory.txt")
        slam.poses = [p for p in poses]
        slam.timestamps = [float(t) for t in stamps]
        slam.keyframe_indices = [int(v) for v in data["keyframe_indices"]]
        for k, frame_id in enumerate(int(v) for v in data["frame_ids"]):
            depth = data["depth"][k] if cfg.mode == "rgbd" else None
            slot = slam.keyframes.add(frame_id, data["poses"][k], data["rgb"][k], depth, data["exposure"][k])
            slam._slot_of_frame[frame_id] = slot
        slam.first_slot = -1  # the gauge is the loaded map's
        if "given_poses" in data:
            slam._given_poses = {int(v) for v in data["given_poses"]}
        if "mapping_iters" in data:  # folders saved before it was recorded start the count afresh
            slam.mapper.total_iters = int(data["mapping_iters"])
        if slam.poses:
            slam.tracker.reset(slam.poses[-1], slam.poses[-2] if len(slam.poses) > 1 else None)
        if len(slam.keyframes):
            T_kf = slam.keyframes.poses[slam.keyframes.slots()[-1]]
            slam.selector.should_add(slam._alpha_at(T_kf), T_kf)
            slam.selector.accept(T_kf)
        slam.mapper.sync()
        return slam


def _load_saved_config(directory: Path) -> Config:
    from rgs_warp.config import config_from_dict

    return config_from_dict(parse_yaml((directory / "config.yaml").read_text(encoding="utf-8")))


def resolve_device(name: str) -> str:
    import warp as wp

    if name != "auto":
        return name
    return "cuda:0" if wp.is_cuda_available() else "cpu"


def make_run_dir(cfg: Config) -> Path:
    name = cfg.run_name or f"{cfg.dataset.type}-{cfg.dataset.name}-{datetime.now():%Y%m%d-%H%M%S}"
    run_dir = Path(cfg.output_dir) / name
    run_dir.mkdir(parents=True, exist_ok=True)
    return run_dir


def dataset_summary(ds) -> dict:
    c = ds.camera
    return {
        "dataset": repr(ds),
        "frames": len(ds),
        "resolution": [c.width, c.height],
        "intrinsics": {"fx": c.fx, "fy": c.fy, "cx": c.cx, "cy": c.cy},
    }


def ground_truth_mesh(cfg: Config, ds) -> Path | None:
    """The sequence's ground-truth mesh when there is one: the synthetic scenes' ``mesh.ply``, or
    Replica's ``<scene>_mesh.ply`` next to the scene folder (the NICE-SLAM layout)."""
    path = getattr(ds, "mesh_path", None)
    if path is not None and Path(path).is_file():
        return Path(path)
    if cfg.dataset.type == "replica":
        folder = cfg.dataset_path()
        candidate = folder.parent / f"{folder.name}_mesh.ply"
        if candidate.is_file():
            return candidate
    return None


def peak_memory_mib(device) -> float | None:
    device = wp.get_device(device)
    if not device.is_cuda or not wp.is_mempool_enabled(device):
        return None
    return wp.get_mempool_used_mem_high(device) / 2**20


def run(cfg: Config, run_dir: Path | None = None, progress: bool = True) -> tuple[Path, dict]:
    """Run SLAM on the configured sequence and evaluate it; returns (run folder, metrics).

    The folder gets: ``config.yaml``, ``dataset.json``, ``trajectory.txt`` (TUM, readable by evo),
    ``map.ply`` (3DGS layout), ``keyframes.npz``, ``metrics.json`` + ``metrics.md``,
    ``trajectory_topview.png``, ``renders/*.png`` (render | ground truth side by side),
    ``log.jsonl`` (one line per frame) and ``convergence.json`` + ``convergence.png`` (``SLAM.convergence``:
    window PSNR against the cumulative mapping iterations).  If the run stops early (error, Ctrl-C),
    what was tracked so far is still saved, and the error is re-raised.
    """
    device = resolve_device(cfg.device)
    ds = open_dataset(cfg, device=device)
    run_dir = run_dir or make_run_dir(cfg)
    run_dir.mkdir(parents=True, exist_ok=True)
    save_config(cfg, run_dir / "config.yaml")
    (run_dir / "dataset.json").write_text(json.dumps(dataset_summary(ds), indent=2))
    first = ds[0]
    slam = SLAM(cfg, ds.camera, device=device, T_first_WC=first.pose_gt)
    gt_poses, frame_losses, lost = [], [], []  # lost: (frame, reason) of each frame whose tracking was lost
    t_start = time.perf_counter()
    bar = tqdm(total=len(ds), desc=f"{cfg.dataset.type}/{cfg.dataset.name}", unit="frame", disable=not progress)
    log = (run_dir / "log.jsonl").open("w", encoding="utf-8", buffering=1)  # a line per frame, readable while it runs
    try:
        for frame in ds:
            result = slam.process(frame.rgb, frame.depth if cfg.mode == "rgbd" else None, frame.timestamp)
            gt_poses.append(frame.pose_gt)
            entry = {
                "frame": result.index,
                "keyframe": result.keyframe,
                "reason": result.keyframe_reason,
                "seconds": round(result.seconds, 4),
                "gaussians": len(slam.map),
            }
            if result.tracking is not None:
                entry.update(loss=result.tracking.loss, lost=result.tracking.lost, gain=result.tracking.gain)
                frame_losses.append(result.tracking.loss)
                if result.tracking.lost:
                    entry["lost_reason"] = result.tracking.reason
                    lost.append((result.index, result.tracking.reason))
            if result.keyframe:
                entry.update(seeded=result.seeded, pruned=result.pruned, merged=result.merged)
                if result.seed_depth_ratio is not None:
                    entry["seed_depth_ratio"] = round(result.seed_depth_ratio, 4)
                if result.mapping is not None and result.mapping.iters:
                    entry["mapping_l1"] = result.mapping.final_l1
                if cfg.method == "baseline" and result.mapping is not None:
                    entry.update(cloned=result.mapping.cloned, split=result.mapping.split)
            elif result.seeded:  # frame fill: seeds waiting for the next keyframe
                entry["seeded"] = result.seeded
            log.write(json.dumps(entry) + "\n")
            elapsed = time.perf_counter() - t_start
            bar.set_postfix(
                fps=f"{(result.index + 1) / elapsed:.2f}",
                kf=len(slam.keyframe_indices),
                gaussians=len(slam.map),
                loss=f"{frame_losses[-1]:.4f}" if frame_losses else "-",
                lost=len(lost),
            )
            bar.update(1)
    finally:
        bar.close()
        log.close()
        slam.finish()
        slam.save(run_dir)
        write_convergence(run_dir, slam.convergence, title=f"{cfg.dataset.type}/{cfg.dataset.name} ({cfg.method})")
    wall = time.perf_counter() - t_start
    metrics = evaluate_run(cfg, ds, slam, gt_poses, run_dir, wall, tracking_section(len(frame_losses), lost))
    return run_dir, metrics


def tracking_section(tracked: int, lost: list[tuple[int, str]]) -> dict:
    """The report's ``tracking`` section: how many of the ``tracked`` frames were lost (``lost``: frame
    index and the tracker's reason of each) and the first of them."""
    section: dict = {"tracked_frames": tracked, "lost_frames": len(lost)}
    if lost:
        section["first_lost_frame"], section["first_lost_reason"] = lost[0]
    else:
        section["first_lost_frame"] = section["first_lost_reason"] = None
        section["first_lost_frame_na_reason"] = section["first_lost_reason_na_reason"] = "never lost"
    return section


def write_convergence(run_dir: Path, points: list[dict], title: str) -> None:
    """``convergence.json`` (the points of ``SLAM.convergence``) and ``convergence.png``: the window's
    PSNR against the cumulative mapping iterations (initialization samples joined by a line, one
    marker per keyframe's mapping after it) with the number of Gaussians on a second axis."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    (run_dir / "convergence.json").write_text(json.dumps(points, indent=1) + "\n", encoding="utf-8")
    fig, ax = plt.subplots(figsize=(7.0, 4.0), dpi=150)
    count_ax = ax.twinx()
    for phase, style in (("init", "-o"), ("keyframe", "s")):
        shown = [p for p in points if p["phase"] == phase and p["psnr_db"] is not None]
        label = "initialization window" if phase == "init" else "window after a keyframe's mapping"
        ax.plot([p["iteration"] for p in shown], [p["psnr_db"] for p in shown], style, markersize=3, label=label)
    count_ax.plot([p["iteration"] for p in points], [p["gaussians"] for p in points], color="gray", linewidth=0.8)
    count_ax.set_ylabel("Gaussians", color="gray")
    ax.set_xlabel("mapping iterations (cumulative)")
    ax.set_ylabel("mean window PSNR (dB)")
    ax.set_title(title)
    ax.grid(True, linewidth=0.3)
    ax.legend(loc="lower right", fontsize=8)
    fig.tight_layout()
    fig.savefig(run_dir / "convergence.png")
    plt.close(fig)


def evaluate_run(
    cfg: Config, ds, slam: SLAM, gt_poses: list, run_dir: Path, wall_s: float, tracking: dict | None = None
) -> dict:
    """Metrics of a finished run (supplement §3) written with ``write_report``; ``tracking``: the
    section of ``tracking_section``."""
    from rgs_warp.eval import (
        LPIPS,
        ate_keyframes_and_all,
        eval_frame_indices,
        photometric_metrics,
        plot_trajectory_topview,
        write_report,
    )

    _, est = slam.trajectory()
    n = len(est)
    metrics: dict = {
        "dataset": f"{cfg.dataset.type}/{cfg.dataset.name}",
        "method": cfg.method,
        "mode": cfg.mode,
        "device": str(slam.device),
        "frames": n,
        "keyframes": len(slam.keyframe_indices),
        "gaussians": len(slam.map),
        "fps": n / wall_s if wall_s > 0 else None,
        "tracking_fps": (n - 1) / slam.stats["tracking_s"] if slam.stats["tracking_s"] > 0 else None,
        "wall_s": wall_s,
    }
    mem = peak_memory_mib(slam.device)
    metrics["peak_memory_mib"] = mem
    if mem is None:
        metrics["peak_memory_mib_na_reason"] = "measured on CUDA devices only (Warp's memory pool)"
    if metrics["tracking_fps"] is None:
        metrics["tracking_fps_na_reason"] = "a single frame"
    metrics["time_s"] = {k: v for k, v in slam.stats.items() if k.endswith("_s")}
    if tracking is not None:
        metrics["tracking"] = tracking
    has_gt = all(p is not None for p in gt_poses) and n >= 3
    if has_gt:
        gt = np.array(gt_poses)
        align = "sim3" if cfg.mode == "mono" else "se3"
        metrics["ate"] = ate_keyframes_and_all(est, gt, np.array(slam.keyframe_indices), align=align)
        for section in metrics["ate"].values():
            section.pop("align_T", None)
        plot_trajectory_topview(est, gt, run_dir / "trajectory_topview.png", title=metrics["dataset"], align=align)
    else:
        metrics["ate"] = None
        metrics["ate_na_reason"] = "no ground-truth poses" if n >= 3 else "fewer than 3 frames"
        if n >= 2:
            plot_trajectory_topview(est, None, run_dir / "trajectory_topview.png", title=metrics["dataset"])
    # photometric metrics: every eval.every-th frame, keyframes excluded (§3), rendered at the estimate
    idx = eval_frame_indices(n, slam.keyframe_indices, cfg.eval.every)
    renders, refs, depths, ref_depths = [], [], [], []
    for i in idx:
        frame = ds[int(i)]
        res = slam.render(est[i])
        renders.append(np.clip(res.color.numpy(), 0.0, 1.0))
        refs.append(frame.rgb)
        if frame.depth is not None and cfg.mode == "rgbd":  # monocular depth has the map's own scale
            alpha = res.alpha.numpy()
            depths.append(np.where(alpha > 0.5, res.depth.numpy() / np.maximum(alpha, 1e-6), 0.0))
            ref_depths.append(frame.depth)
    if renders:
        lpips = LPIPS(cfg.eval.lpips_alexnet_path or None, cfg.eval.lpips_linear_path or None)
        metrics["photometric"] = photometric_metrics(
            renders, refs, lpips, depths if depths else None, ref_depths if ref_depths else None
        )
        save_side_by_side(run_dir / "renders", [int(i) for i in idx], renders, refs)
    else:
        metrics["photometric"] = None
        metrics["photometric_na_reason"] = "no non-keyframe frame to score"
    metrics.update(mesh_section(cfg, ds, slam, est))
    write_report(run_dir, metrics, title=f"rgs_warp {metrics['dataset']} ({cfg.method}, {cfg.mode})")
    return metrics


def mesh_section(cfg: Config, ds, slam: SLAM, est: np.ndarray) -> dict:
    """Acc / Comp / Comp.Ratio of the TSDF fusion of rendered depth along the keyframe trajectory."""
    mesh_path = ground_truth_mesh(cfg, ds)
    if mesh_path is None:
        return {"mesh": None, "mesh_na_reason": "no ground-truth mesh for this sequence"}
    if cfg.mode != "rgbd":
        return {"mesh": None, "mesh_na_reason": "monocular run (scale-free map)"}
    try:
        import open3d as o3d

        from rgs_warp.eval import mesh_metrics, tsdf_fuse
    except ImportError as e:
        return {"mesh": None, "mesh_na_reason": f"open3d not importable ({e})"}
    depths, poses = [], []
    for i in slam.keyframe_indices:
        res = slam.render(est[i])
        alpha = res.alpha.numpy()
        depths.append(np.where(alpha > 0.5, res.depth.numpy() / np.maximum(alpha, 1e-6), 0.0).astype(np.float32))
        poses.append(est[i])
    rec = tsdf_fuse(depths, poses, slam.camera)
    gt = o3d.io.read_triangle_mesh(str(mesh_path))
    return {"mesh": mesh_metrics(rec, gt)}


def save_side_by_side(folder: Path, indices: list[int], renders: list, refs: list, count: int = 4) -> None:
    """A few render | ground-truth pairs as PNG (as the seed's Figure 1), evenly over the run."""
    import cv2

    folder.mkdir(parents=True, exist_ok=True)
    picks = np.unique(np.linspace(0, len(indices) - 1, min(count, len(indices))).round().astype(int))
    for k in picks:
        pair = np.concatenate([renders[k], refs[k]], axis=1)
        image = (np.clip(pair, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
        cv2.imwrite(str(folder / f"frame{indices[k]:05d}_render_vs_gt.png"), image[..., ::-1])


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if any(a in ("-h", "--help") for a in argv):
        print(USAGE)
        print(help_text())
        return 0
    try:
        cfg = load_config(argv)
    except ConfigError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    try:
        run_dir, metrics = run(cfg)
    except DatasetError as e:
        print(f"error: {e}", file=sys.stderr)
        return 1
    except ValueError as e:
        print(f"error: {e}", file=sys.stderr)
        return 1
    ate = (metrics.get("ate") or {}).get("all_frames", {})
    photo = metrics.get("photometric") or {}
    print(f"run dir   {run_dir}")
    print(
        f"frames {metrics['frames']}, keyframes {metrics['keyframes']}, Gaussians {metrics['gaussians']}, "
        f"{metrics['fps']:.2f} frames/s"
    )
    if ate:
        print(f"ATE RMSE  {ate['rmse_cm']:.2f} cm (all frames)")
    if photo:
        print(f"PSNR      {photo['psnr_db']:.2f} dB, SSIM {photo['ssim']:.3f}")
    print(f"report    {run_dir / 'metrics.md'}")
    tracking = metrics.get("tracking") or {}
    if tracking.get("lost_frames"):
        print(
            f"warning: tracking was lost in {tracking['lost_frames']} of {tracking['tracked_frames']} tracked frames, "
            f"first at frame {tracking['first_lost_frame']} ({tracking['first_lost_reason']}); poses from there on "
            f"are unreliable (each frame's entry in {run_dir / 'log.jsonl'} says why)",
            file=sys.stderr,
        )
    return 0


if __name__ == "__main__":
    # a job scheduler stops a run with SIGTERM: leave through the run's `finally`, which saves what was
    # tracked (as Ctrl-C does), with the shell's exit status for it
    signal.signal(signal.SIGTERM, lambda signum, frame: sys.exit(128 + signum))
    sys.exit(main())
