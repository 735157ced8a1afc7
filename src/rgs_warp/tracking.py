"""Camera tracking against a fixed Gaussian map (supplement §4.2, §4.6).

Per frame: start from a constant-velocity prediction (or a given pose), align the frame to one render
of the map there by Gauss-Newton on an image pyramid (``direct_levels``, direct_align.py), then
``iters`` Adam steps on the twist xi = (rho, phi) with ``T_CW <- Exp(xi) T_CW``.  Each step renders the
map, solves the brightness gain g of Eq. 3 in closed form (b = 0), evaluates the weighted L1 loss of
Eq. 5-8 (plus, for RGB-D, a depth L1 term) and takes the twist gradient from the renderer's pose-only
backward.  With ``tracking.geometric`` (RGB-D) the direct alignment aligns the measured depth point to plane
and estimates each term's noise, and the steps follow the gradient with each term in units of that noise.
The map is only read.  Adam works on the twist taken about a pivot on the optical axis at the mean
rendered depth (kernels/tracking.py, ``adam_pose_step``): the same left update, better conditioned.

Everything an iteration needs lives on the device (pose in float64, Adam moments, schedule from the
iteration index), and nothing is read back inside the loop: the per-iteration sums go to a history
array read once at the end, so the loop can be captured in a CUDA graph (with the renderer's
intersection capacity reserved beforehand, ``Renderer.reserve_intersections``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import warp as wp

from rgs_warp.config import TrackingConfig
from rgs_warp.direct_align import DirectAlignment
from rgs_warp.frame_check import Uploads, as_float_image
from rgs_warp.geometry import invert_pose
from rgs_warp.kernels import tracking as tk
from rgs_warp.kernels.math import REDUCE_BLOCK, reduce_blocks
from rgs_warp.motion_model import JUMPED, SPED_UP, MotionModel, nearest_rigid, pose_error
from rgs_warp.render import GRAPH_HEADROOM, Renderer
from rgs_warp.types import Camera, GaussianMap

__all__ = ["Tracker", "TrackingResult", "settled_iters"]


@dataclass
class TrackingResult:
    """Outcome of one ``Tracker.track``.

    T_WC: 4x4 float64 camera-to-world pose; loss: Eq. 5 (+ depth term) per pixel at the last
    iteration; valid_ratio: fraction of pixels whose rendered opacity reaches tau_alpha; gain, bias:
    Eq. 3 at the last iteration (bias 0: the gain model); converged: over the last quarter of the steps the twist
    gradient kept flipping sign (Adam's |m_hat| / sqrt(v_hat) below ``CONVERGED_CONSISTENCY``) and
    the frame is not lost; lost: the map does not
    explain the frame (too little coverage, too large a residual), the estimate diverged, or its motion
    is inconsistent with the motion model's (``motion_inconsistent``); reason: why;
    diverged: the estimate was not finite, or moved implausibly far from the start pose
    (``MAX_CORRECTION_M``, ``MAX_CORRECTION_DEG``): it is discarded and ``T_WC`` is the start pose;
    iters: Adam steps taken; residual: weighted mean |I - g I_hat - b| per channel; loss_history:
    loss per iteration; alpha, depth: the accumulated opacity and expected depth (not normalised) of the
    last render (tracking resolution), for the keyframe selector, valid until the tracker's renderer
    renders again; motion_inconsistent: lost by
    the motion check (``tracking.motion_check``, ``motion_model.motion_inconsistency``): the translation collapsed
    while the rotation went on as predicted, or the pose jumped away from the prediction (then ``T_WC``
    is the prediction), so the pose is not to be mapped; settled_iters: the steps
    after which the pose stayed put (``settled_iters``), what an early stop could save.
    """

    T_WC: np.ndarray
    loss: float
    valid_ratio: float
    gain: float
    bias: float
    converged: bool
    lost: bool
    reason: str
    iters: int
    residual: float
    loss_history: np.ndarray
    alpha: wp.array
    depth: wp.array
    diverged: bool = False
    motion_inconsistent: bool = False
    settled_iters: int = 0
    # how the frame's steps ran (``Tracker._steps``): "replayed" from captured graphs, "captured" (a new map
    # version: a sizing step, the captures, then the replay), "eager" (no graphs), "overflowed" (a replay
    # that overflowed, run again eagerly); "" where no steps ran
    steps: str = ""


# Converged: over the last quarter of the steps Adam's |m_hat| / sqrt(v_hat) (1 = the gradient keeps its
# sign, the pose is still travelling; ~0.25 = it flips around the minimum) averages below this.
CONVERGED_CONSISTENCY = 0.4
# Diverged: tracking corrects the start pose (the motion model's prediction) by millimetres to
# centimetres (experiments/results/tracking.md); a correction of a metre or 45 deg within one frame's
# Adam steps is an optimisation that ran away (e.g. a far too high tracking.lr), not camera motion.
MAX_CORRECTION_M = 1.0
MAX_CORRECTION_DEG = 45.0
SWITCHES = ("auto", "on", "off")  # tracking.motion_check, tracking.graph, tracking.colour_per_opacity
# Captured graphs of the frame's steps kept at once: asynchronous mapping publishes the map into three
# buffers in turn, each its own graph (different addresses)
GRAPHS_KEPT = 3


class Tracker:
    """Frame-to-map pose tracker; build once, call ``track`` frame by frame.

    ``camera`` describes the input frames; tracking runs at ``camera.scaled(cfg.downscale)``.
    ``mode`` is "rgbd" (colour + depth terms) or "mono" (colour only).  ``renderer`` may be shared
    with other stages (it is only used between ``track``'s entry and return).

    The tracker remembers the last two tracked poses for its constant-velocity prediction;
    ``reset`` clears or seeds them.
    """

    def __init__(
        self,
        cfg: TrackingConfig,
        camera: Camera,
        device=None,
        mode: str = "rgbd",
        renderer: Renderer | None = None,
    ):
        if mode not in ("rgbd", "mono"):
            raise ValueError(f"mode must be 'rgbd' or 'mono', got {mode!r}")
        for key in ("motion_check", "graph", "colour_per_opacity"):
            if getattr(cfg, key) not in SWITCHES:
                raise ValueError(f"tracking.{key} must be one of {', '.join(SWITCHES)}, got {getattr(cfg, key)!r}")
        if cfg.iters < 1 or cfg.downscale < 1:
            raise ValueError(f"need tracking.iters >= 1 and tracking.downscale >= 1, got {cfg.iters}, {cfg.downscale}")
        self.cfg = cfg
        self.mode = mode
        self.motion_check = cfg.motion_check == "on" or (cfg.motion_check == "auto" and mode == "mono")
        self.colour_per_opacity = cfg.colour_per_opacity == "on" or (
            cfg.colour_per_opacity == "auto" and mode == "mono"
        )
        if cfg.tile_stride < 0:
            raise ValueError(f"tracking.tile_stride must be >= 0 (0 = auto), got {cfg.tile_stride}")
        # auto: a checkerboard of tiles in RGB-D (measured: the same ATE, 17-23 % faster), every tile in
        # mono, whose steps only the image constrains (a CPU test at 96x54 drifts 2.8 mm against 2 mm)
        self.tile_stride = cfg.tile_stride or (2 if mode == "rgbd" else 1)
        self.device = wp.get_device(device)
        self.camera = camera
        self.track_camera = camera.scaled(cfg.downscale)
        self.renderer = renderer or Renderer(self.device)

        dev = self.device
        full = (camera.height, camera.width)
        shape = (self.track_camera.height, self.track_camera.width)
        pinned = dev.is_cuda
        self._uploads = Uploads(dev)  # NumPy frames given to ``track`` / ``load_frame``
        if cfg.downscale > 1:
            self._rgb_full = wp.zeros(full, dtype=wp.vec3, device=dev)
            self._depth_full = wp.zeros(full, dtype=wp.float32, device=dev)
        self._rgb = wp.zeros(shape, dtype=wp.vec3, device=dev)
        self._depth = wp.zeros(shape, dtype=wp.float32, device=dev)
        self._w_grad = wp.zeros(shape, dtype=wp.float32, device=dev)
        self._d_color = wp.zeros(shape, dtype=wp.vec3, device=dev)
        self._d_depth = wp.zeros(shape, dtype=wp.float32, device=dev)
        self._d_alpha = wp.zeros(shape, dtype=wp.float32, device=dev)
        self._blocks = [reduce_blocks(shape[0] * shape[1])]  # per-pixel reductions
        self._history = wp.zeros((cfg.iters, tk.H_COLUMNS), dtype=wp.float64, device=dev)
        self._history_host = wp.zeros((cfg.iters, tk.H_COLUMNS), dtype=wp.float64, device="cpu", pinned=pinned)
        self._adam_m = wp.zeros(6, dtype=wp.float32, device=dev)
        self._adam_v = wp.zeros(6, dtype=wp.float32, device=dev)
        self._T_CW = wp.zeros(1, dtype=wp.mat44d, device=dev)
        self._pose_history = wp.zeros(cfg.iters, dtype=wp.mat44d, device=dev)
        self._pose_history_host = wp.zeros(cfg.iters, dtype=wp.mat44d, device="cpu", pinned=pinned)
        self._T_WC = wp.zeros(1, dtype=wp.mat44, device=dev)
        self._T_CW_host = wp.zeros(1, dtype=wp.mat44d, device="cpu", pinned=pinned)
        self._T_WC_host = wp.zeros(1, dtype=wp.mat44, device="cpu", pinned=pinned)
        # the pose the Adam steps start from (the start pose, or the direct alignment's)
        self._T_CW_start = wp.zeros(1, dtype=wp.mat44d, device=dev)
        self._T_WC_start = wp.zeros(1, dtype=wp.mat44, device=dev)
        self._direct = DirectAlignment(cfg, self.track_camera, (self._rgb, self._depth), dev)
        self._motion = MotionModel(cfg, self.motion_check)
        self._last_render = None
        self._frame: tuple | None = None
        # the frame's steps as captured graphs (``_steps``): by what they were captured against
        self.use_graph = cfg.graph == "on" or (cfg.graph == "auto" and self.device.is_cuda)
        self._graphs: dict[tuple, tuple] = {}
        # the step counter a captured step reads its row from (tk.advance_step); eager steps read 0
        self._step = wp.zeros(1, dtype=wp.int32, device=dev)
        self._no_step = wp.zeros(1, dtype=wp.int32, device=dev)
        self.graph_counts = {"eager": 0, "captured": 0, "replayed": 0, "overflowed": 0}

    # ---- motion model ------------------------------------------------------------------------
    def reset(self, T_WC: np.ndarray | None = None, T_prev_WC: np.ndarray | None = None) -> None:
        """Forget the tracked poses; with ``T_WC``, make it the latest (e.g. the first frame's pose),
        with ``T_prev_WC`` also the one before (the motion model resumes, e.g. after loading)."""
        self._motion.reset(T_WC, T_prev_WC)

    def state_dict(self) -> dict[str, np.ndarray]:
        """The motion model's poses (the last two tracked, or a lost frame's start pose in its place),
        which ``reset`` alone cannot tell; ``load_state_dict`` restores them."""
        return self._motion.state_dict()

    def load_state_dict(self, state: dict[str, np.ndarray]) -> None:
        self._motion.load_state_dict(state)

    @property
    def alpha(self) -> wp.array:
        """Accumulated opacity of the last render of the last ``track`` (tracking resolution), for
        the keyframe selector; valid until the renderer renders again."""
        if self._last_render is None:
            raise RuntimeError("no frame tracked yet")
        return self._last_render.alpha

    @property
    def depth(self) -> wp.array:
        """Expected depth (not normalised by ``alpha``) of the same render."""
        if self._last_render is None:
            raise RuntimeError("no frame tracked yet")
        return self._last_render.depth

    @property
    def frame_buffers(self) -> tuple[wp.array, wp.array]:
        """The (rgb, depth) device arrays at the camera's resolution that ``load_frame`` copies a NumPy frame
        into: a frame given as these arrays is read in place (the SLAM's frame check stages frames there)."""
        if self.cfg.downscale == 1:
            return self._rgb, self._depth
        return self._rgb_full, self._depth_full

    def skip(self, T_WC: np.ndarray | None = None) -> None:
        """A frame that is not tracked (its input unusable): the motion model goes on as after a lost
        frame, with the prediction as its latest pose, or ``T_WC`` when that is known."""
        T = self.predict() if T_WC is None else np.array(T_WC, dtype=np.float64)
        if T is not None:
            self._motion.push(T, tracked=False)

    def motion_inconsistency(self, T_WC: np.ndarray) -> str:
        """Why ``T_WC`` (a pose from elsewhere, e.g. the monocular keypoint odometry's) would fail this
        tracker's motion check against its last two poses, or "" (also with the check off or fewer poses)."""
        return self._motion.inconsistency(T_WC)

    def predict(self) -> np.ndarray | None:
        """Constant-velocity prediction T_k = T_{k-1} T_{k-2}^-1 T_{k-1} (the last relative motion
        repeated in the camera frame); the last pose when only one is known; None before any."""
        return self._motion.predict()

    # ---- tracking ----------------------------------------------------------------------------
    def track(self, rgb, depth, gmap: GaussianMap, T_init_WC: np.ndarray | None = None) -> TrackingResult:
        """Track one frame against ``gmap``.

        ``rgb``: HxWx3 float32 NumPy or (H, W) ``wp.array`` of vec3 on the tracker's device, at the
        camera's resolution; ``depth``: HxW float32 metres (0 = invalid), NumPy or ``wp.array``, or
        None (required in "rgbd" mode, ignored in "mono").  ``T_init_WC``: start pose; default the
        constant-velocity prediction.  The tracked pose becomes the motion model's latest, unless the
        frame is lost, in which case the start pose takes its place.
        """
        use_depth = self.mode == "rgbd"
        if use_depth and depth is None:
            raise ValueError("rgbd tracking needs a depth image (or build the Tracker with mode='mono')")
        T_init = self.predict() if T_init_WC is None else np.asarray(T_init_WC, dtype=np.float64)
        if T_init is None:
            raise ValueError("no start pose: pass T_init_WC for the first frame (or call reset(T_WC))")
        self.load_frame(rgb, depth)
        self._begin(T_init)
        steps = self._steps(gmap, use_depth, T_init)
        result = self._finish(T_init)
        result.steps = steps
        return result

    def relocalize(
        self, rgb, depth, gmap: GaussianMap, candidates: list[np.ndarray], state_before: dict
    ) -> tuple[TrackingResult, int] | None:
        """Track the frame again from each camera-to-world pose of ``candidates`` (e.g. keyframes'), the
        motion model as in ``state_before`` (``state_dict`` before the lost try) for each; the best try
        that is not lost (lowest loss) and its candidate's index, the motion model restarted at its pose
        and ``alpha`` that of its render; None, the motion model as the lost try left it, if none holds."""
        after = self.state_dict()
        best = None
        for k, T in enumerate(candidates):
            self.load_state_dict(state_before)
            result = self.track(rgb, depth, gmap, T_init_WC=T)
            if not result.lost and (best is None or result.loss < best[0].loss):
                best = (result, k)
        if best is None:
            self.load_state_dict(after)
            return None
        result, k = best
        self.reset(result.T_WC)  # the velocity before the loss is not this pose's
        if k != len(candidates) - 1:  # alpha is the last render's: render the chosen pose again
            self.exposure(gmap, result.T_WC)
            result.alpha, result.depth = self._last_render.alpha, self._last_render.depth
        return result, k

    def load_frame(self, rgb, depth) -> None:
        """Stage a frame on the device without tracking it (for ``exposure`` or ``prepare``); ``track``
        does this itself.  ``depth`` is ignored in "mono"."""
        if self.mode != "rgbd":
            depth = None
        cfg = self.cfg
        dev = self.device
        full = (self.camera.height, self.camera.width)
        rgb_dst = self._rgb if cfg.downscale == 1 else self._rgb_full
        depth_dst = self._depth if cfg.downscale == 1 else self._depth_full
        rgb = self._stage(rgb, rgb_dst, full, wp.vec3, "rgb")
        if depth is not None:
            depth = self._stage(depth, depth_dst, full, wp.float32, "depth")
        self._frame = (rgb, depth)
        if cfg.downscale > 1:
            has_depth = depth is not None
            wp.launch(
                tk.downsample_rgbd,
                dim=self._rgb.shape,
                inputs=[rgb, depth if has_depth else self._depth_full, cfg.downscale, int(has_depth)]
                + [cfg.depth_edge_spread],
                outputs=[self._rgb, self._depth],
                device=dev,
            )
        else:
            for src, dst in ((rgb, self._rgb), (depth, self._depth)):
                if src is not None and src is not dst:
                    wp.copy(dst, src)
        wp.launch(
            tk.gradient_weight,
            dim=self._rgb.shape,
            inputs=[self._rgb, cfg.tau_grad],
            outputs=[self._w_grad],
            device=dev,
        )
        self._direct.downsample_frame(depth is not None)

    def exposure(self, gmap: GaussianMap, T_WC: np.ndarray) -> tuple[float, float]:
        """Eq. 3 brightness (gain, bias 0) of the frame last loaded (``load_frame``) against the map
        rendered at ``T_WC``, in closed form, without moving the pose; ``alpha`` is then that render's."""
        if self._frame is None:
            raise RuntimeError("no frame loaded")
        self._T_WC_host.numpy()[0] = np.asarray(T_WC, dtype=np.float32)
        wp.copy(self._T_WC, self._T_WC_host)
        self._history.zero_()
        # sized by its own needs, not the previous render's: after a view that saw little of the map (a
        # lost try, a jump to a given pose) those would drop intersections
        self._render_and_brightness(gmap, 0, fit=True)
        wp.copy(self._history_host, self._history)
        wp.synchronize_device(self.device)
        row = self._history_host.numpy()[0]
        return float(row[tk.H_GAIN]), float(row[tk.H_BIAS])

    def _stage(self, image, dst: wp.array, shape: tuple[int, int], dtype, name: str) -> wp.array:
        """The frame image as a device array at the camera's resolution: a device array is checked and
        used in place, a NumPy array is copied into ``dst``."""
        if isinstance(image, wp.array):
            if image.shape != shape or image.dtype != dtype or image.device != self.device:
                raise ValueError(
                    f"{name}: expected a {shape} wp.array of {dtype.__name__} on {self.device}, "
                    f"got {image.shape} {image.dtype.__name__} on {image.device}"
                )
            return image
        expected = shape + ((3,) if dtype is wp.vec3 else ())
        return self._uploads.copy(as_float_image(image, expected, name), dst)

    def _begin(self, T_init_WC: np.ndarray) -> None:
        T_CW = invert_pose(T_init_WC)
        self._T_CW_host.numpy()[0] = T_CW
        self._T_WC_host.numpy()[0] = T_init_WC.astype(np.float32)
        wp.copy(self._T_CW_start, self._T_CW_host)
        wp.copy(self._T_WC_start, self._T_WC_host)
        self._restart()

    def _restart(self) -> None:
        """Pose, Adam moments and history as before the frame's first Adam step."""
        wp.copy(self._T_CW, self._T_CW_start)
        wp.copy(self._T_WC, self._T_WC_start)
        self._adam_m.zero_()
        self._adam_v.zero_()
        self._history.zero_()

    def _align(self, gmap: GaussianMap, use_depth: bool) -> None:
        """The direct alignment (``tracking.direct_levels``, ``DirectAlignment``) from the start pose: the Adam
        steps start where it ends."""
        self._direct.align(self.renderer, gmap, use_depth, self._T_CW, self._T_WC)
        wp.copy(self._T_CW_start, self._T_CW)
        wp.copy(self._T_WC_start, self._T_WC)

    def _steps(self, gmap: GaussianMap, use_depth: bool, T_init_WC: np.ndarray) -> str:
        """The frame's direct alignment (``_align``, with ``tracking.direct_levels``) and ``iters`` Adam
        steps, launched one by one, or replayed from captured graphs: the alignment's, one
        of a step on part of the tiles, replayed ``iters - 1`` times, and one of the last step, each
        reading its step from a device counter (``tk.advance_step``), so a capture records about 15
        launches, not ``iters`` x 15 (a capture of every step made the frame after each new map size the
        slowest of a run: 35 against 13 ms at 640x360 on an H100).

        A graph holds the addresses of the map's and the renderer's arrays and the map's size, so it
        is kept by those (``_graph_key``).  At a new key one step runs eagerly on every tile (its render
        sizes the renderer's buffers for this map and view), the pose is put back, ``GRAPH_HEADROOM`` (render.py) x
        the intersections that render needed are reserved, and the alignment and the two steps are
        captured and replayed:
        the frame after a keyframe costs one eager step and two captures more than a replayed frame
        (6.6 ms at 1200x680 on an H100), not ``iters`` eager steps (which had made it the run's tracking
        p99: experiments/results/perf.md).  A replay whose renders needed more intersections than the
        graph has room for is discarded with its graph, and the frame's steps run again eagerly from
        the start pose.  Returns how the steps ran (``TrackingResult.steps``)."""
        if not self.use_graph or len(gmap) == 0:
            self._eager_steps(gmap, use_depth)
            return "eager"
        key = self._graph_key(gmap, use_depth)
        entry = self._graphs.get(key)
        kind = "replayed"
        if entry is None:
            key, entry = self._capture(gmap, use_depth)
            kind = "captured"
        align, (*steps, last), capacity = entry
        self._step.zero_()
        if align is not None:
            wp.capture_launch(align)
        for _ in range(self.cfg.iters - 1):
            wp.capture_launch(steps[0])
        wp.capture_launch(last)
        self.graph_counts["replayed"] += 1
        if self.renderer.intersection_count() > capacity:
            self.graph_counts["overflowed"] += 1
            self._graphs.pop(key, None)
            self._begin(T_init_WC)
            self._eager_steps(gmap, use_depth)
            return "overflowed"
        return kind

    def _capture(self, gmap: GaussianMap, use_depth: bool) -> tuple[tuple, tuple]:
        """Size the renderer with one eager step from the start pose (put back after it), then capture
        the alignment and the two steps for ``gmap``: their key and entry, kept in ``_graphs``."""
        renderer = self.renderer
        self._iteration(gmap, 0, use_depth, tile_stride=1)  # sizes the buffers (may reallocate them)
        self._restart()
        renderer.reserve_intersections(math.ceil(GRAPH_HEADROOM * renderer.intersection_count()))
        key = self._graph_key(gmap, use_depth)
        align = None
        if self._direct.levels:
            with wp.ScopedCapture(device=self.device) as capture:
                self._align(gmap, use_depth)
            align = capture.graph
        # one step on part of the tiles and the last step on all, each reading its row from the
        # device counter: two captures of about 15 launches, not one of iters x 15
        graphs = []
        for stride in ((self.tile_stride,) if self.cfg.iters > 1 else ()) + (1,):
            with wp.ScopedCapture(device=self.device) as capture:
                self._iteration(gmap, 0, use_depth, tile_stride=stride, step=self._step)
            graphs.append(capture.graph)
        entry = (align, graphs, renderer.intersection_capacity)
        while len(self._graphs) >= GRAPHS_KEPT:
            self._graphs.pop(next(iter(self._graphs)))
        self._graphs[key] = entry
        self.graph_counts["captured"] += 1
        return key, entry

    def prepare(self, gmap: GaussianMap, T_WC: np.ndarray) -> None:
        """Capture the steps' graphs for ``gmap`` now, sized by its render at ``T_WC`` against the frame
        last loaded, where the next ``track`` would capture them (a new map size or new arrays: after a
        keyframe) inside its latency.  Nothing without graphs, a frame or a map, or where they exist.
        The motion model and the next ``track`` are unchanged by it."""
        if not self.use_graph or self._frame is None or len(gmap) == 0:
            return
        use_depth = self.mode == "rgbd"
        if self._graph_key(gmap, use_depth) in self._graphs:
            return
        self._begin(np.asarray(T_WC, dtype=np.float64))
        self._capture(gmap, use_depth)

    def _eager_steps(self, gmap: GaussianMap, use_depth: bool) -> None:
        if self._direct.levels and len(gmap) > 0:
            self._align(gmap, use_depth)
        for k in range(self.cfg.iters):
            self._iteration(gmap, k, use_depth)
        self.graph_counts["eager"] += 1

    def _graph_key(self, gmap: GaussianMap, use_depth: bool) -> tuple:
        """What a captured graph of the steps depends on besides the arrays' contents: the map's size,
        the addresses of its arrays and of the renderer's (``Renderer.buffers_version``)."""
        arrays = (gmap.means, gmap.rotations, gmap.log_scales, gmap.opacity_logits, gmap.sh)
        return (len(gmap), tuple(a.ptr for a in arrays), self.renderer.buffers_version, use_depth)

    def _render_and_brightness(
        self, gmap: GaussianMap, k: int, tile_stride: int = 1, step: wp.array | None = None, fit: bool = False
    ):
        """Render the map at the current pose (one tile in ``tile_stride``, shifting with the step) and
        solve Eq. 3's (g, b) into history row ``k`` + ``step[0]`` (``step``: the device step counter of a
        captured step, ``tk.advance_step``; None: a counter at 0); ``fit``: ``Renderer.forward``'s."""
        cfg, dev = self.cfg, self.device
        step = self._no_step if step is None else step
        res = self.renderer.forward(
            gmap,
            self.track_camera,
            self._T_WC,
            pose_jacobians=True,
            tile_stride=tile_stride,
            tile_phase=k,
            tile_step=step,
            fit=fit,
        )
        self._last_render = res
        wp.launch_tiled(
            tk.brightness_sums,
            dim=self._blocks,
            inputs=[
                self._rgb,
                res.color,
                res.depth,
                res.alpha,
                cfg.tau_alpha,
                cfg.brightness_min_alpha,
                cfg.brightness_max_residual,
                k,
                step,
            ],
            outputs=[self._history],
            block_dim=REDUCE_BLOCK,
            device=dev,
        )
        wp.launch(tk.solve_brightness, dim=1, inputs=[k, step], outputs=[self._history], device=dev)
        return res

    def _iteration(
        self, gmap: GaussianMap, k: int, use_depth: bool, tile_stride: int | None = None, step: wp.array | None = None
    ) -> None:
        """Step ``k`` (+ ``step[0]``, the device counter of a captured step, which it then advances).
        ``tile_stride``: default, every step but the last on a part of the tiles; the last renders all:
        its coverage, loss and exposure are the frame's."""
        cfg = self.cfg
        dev = self.device
        if tile_stride is None:
            tile_stride = self.tile_stride if k < cfg.iters - 1 else 1
        counter = self._no_step if step is None else step
        res = self._render_and_brightness(gmap, k, tile_stride, counter)
        wp.launch_tiled(
            tk.tracking_loss,
            dim=self._blocks,
            inputs=[self._rgb, self._depth, self._w_grad, res.color, res.depth, res.alpha]
            + [cfg.tau_alpha, int(use_depth), cfg.depth_weight, cfg.depth_slope_tau, int(self.colour_per_opacity)]
            + [int(use_depth and cfg.geometric), self._direct.scales, k, counter],
            outputs=[self._d_color, self._d_depth, self._d_alpha, self._history],
            block_dim=REDUCE_BLOCK,
            device=dev,
        )
        _, pose_grad = self.renderer.backward(self._d_color, self._d_depth, self._d_alpha, pose_only=True)
        wp.launch(
            tk.adam_pose_step,
            dim=1,
            inputs=[pose_grad, k, cfg.iters, cfg.lr, cfg.adam_beta1, cfg.adam_beta2, cfg.adam_eps, counter]
            + [self._history],
            outputs=[self._adam_m, self._adam_v, self._T_CW, self._T_WC, self._pose_history],
            device=dev,
        )
        if step is not None:
            wp.launch(tk.advance_step, dim=1, inputs=[step], device=dev)

    def step_history(self) -> tuple[np.ndarray, np.ndarray]:
        """The last ``track``'s steps read back from the device (``track`` does so once, at its end): the
        per-step sums (``kernels.tracking.H_*`` columns) and the world-to-camera pose after each step.
        ``exposure`` overwrites the sums."""
        wp.copy(self._history_host, self._history)
        wp.copy(self._pose_history_host, self._pose_history)
        wp.synchronize_device(self.device)
        return self._history_host.numpy().copy(), np.array(self._pose_history_host.numpy(), dtype=np.float64)

    def _finish(self, T_init_WC: np.ndarray) -> TrackingResult:
        cfg = self.cfg
        hist, poses_CW = self.step_history()
        T_WC = (
            nearest_rigid(invert_pose(poses_CW[-1])) if np.all(np.isfinite(poses_CW[-1])) else invert_pose(poses_CW[-1])
        )
        last = hist[-1]
        n_pixels = self._rgb.shape[0] * self._rgb.shape[1]
        valid_ratio = float(last[tk.H_VALID] / n_pixels)
        residual = float(last[tk.H_PHOTO] / (3.0 * last[tk.H_WEIGHT])) if last[tk.H_WEIGHT] > 0 else float("inf")
        tail = max(1, cfg.iters // 4)
        consistency = float(hist[-tail:, tk.H_CONSISTENCY].mean())
        before = invert_pose(poses_CW[-1 - tail]) if cfg.iters > tail else T_init_WC
        moved_m, moved_deg = pose_error(T_WC, before)
        lost, converged, diverged, motion_inconsistent = True, False, False, False
        correction_m, correction_deg = pose_error(T_WC, T_init_WC)
        if not (np.all(np.isfinite(T_WC)) and np.isfinite(last[tk.H_LOSS])):
            diverged, reason = True, "diverged: non-finite pose or loss; the estimate is discarded"
        elif not (correction_m <= MAX_CORRECTION_M and correction_deg <= MAX_CORRECTION_DEG):
            diverged = True
            reason = (
                f"diverged: the pose moved {correction_m:.3g} m, {correction_deg:.3g} deg from its start (more than "
                f"{MAX_CORRECTION_M:g} m or {MAX_CORRECTION_DEG:g} deg); the estimate is discarded"
            )
        elif valid_ratio < cfg.min_valid_ratio:
            reason = f"map covers {valid_ratio:.1%} of the view (< {cfg.min_valid_ratio:.0%})"
        elif residual > cfg.max_residual:
            reason = f"photometric residual {residual:.3f} > {cfg.max_residual}"
        elif why := self._motion.inconsistency(T_WC):
            reason, motion_inconsistent = why, True
            if why.startswith((JUMPED, SPED_UP)):  # the prediction is the better guess than a pose that ran away
                T_WC = np.array(T_init_WC, dtype=np.float64)
                reason += "; the frame keeps the prediction"
        else:
            lost = False
            converged = consistency < CONVERGED_CONSISTENCY
            reason = "converged" if converged else "still descending"
            reason += (
                f": gradient consistency {consistency:.2f} over the last {tail} steps, "
                f"which moved the pose {1e3 * moved_m:.2f} mm, {moved_deg:.3f} deg"
            )
        if diverged:
            T_WC = np.array(T_init_WC, dtype=np.float64)
        self._motion.push(T_init_WC.copy() if lost else T_WC, tracked=not lost)
        return TrackingResult(
            T_WC=T_WC,
            loss=float(last[tk.H_LOSS]),
            valid_ratio=valid_ratio,
            gain=float(last[tk.H_GAIN]),
            bias=float(last[tk.H_BIAS]),
            converged=converged,
            lost=lost,
            reason=reason,
            iters=cfg.iters,
            residual=residual,
            loss_history=hist[:, tk.H_LOSS].copy(),
            alpha=self._last_render.alpha,
            depth=self._last_render.depth,
            diverged=diverged,
            motion_inconsistent=motion_inconsistent,
            settled_iters=settled_iters(poses_CW),
        )


# A step within these of the final pose has settled: 1/40 of the office's ATE (0.4 cm), far below what
# an image of it shows; ``settled_iters`` counts the steps before the pose stays there.
SETTLED_M = 1e-4
SETTLED_DEG = 0.01


def settled_iters(poses_CW: np.ndarray) -> int:
    """The number of Adam steps after which the pose (world-to-camera after each step, ``poses_CW``)
    stays within ``SETTLED_M`` and ``SETTLED_DEG`` of its last value: what an early stop could have
    saved (every step is taken; the per-frame log records it).  All steps where the last is not
    finite."""
    final = poses_CW[-1]
    if not np.all(np.isfinite(final)):
        return len(poses_CW)
    T_final = invert_pose(final)
    for k in range(len(poses_CW) - 1, -1, -1):
        if not np.all(np.isfinite(poses_CW[k])):
            return k + 1
        moved_m, moved_deg = pose_error(invert_pose(poses_CW[k]), T_final)
        if moved_m > SETTLED_M or moved_deg > SETTLED_DEG:
            return k + 1
    return 0
