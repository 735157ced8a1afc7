"""Typed configuration: one dataclass per stage, filled from YAML files under ``configs/`` and from
Hydra-style command-line overrides (``group=option`` selects a YAML file of a group, ``a.b=value`` sets
a key).  One line per key says what it is and its unit; docs/config.md says more, with the evidence.
"""

from __future__ import annotations

import dataclasses
import difflib
import math
import os
import re
import types
import typing
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Literal

import yaml

from rgs_warp.io.atomic import write_text_atomic

CONFIG_DIR = Path(__file__).parent / "configs"
# Groups whose YAML fills one section; ``method`` and ``timing`` files set keys of several sections
GROUPS = {"dataset": "dataset", "method": None, "timing": None}
DEFAULTS = {"dataset": "synthetic/room0", "method": "rgs", "timing": "offline"}


class ConfigError(ValueError):
    """Invalid configuration or override; the message lists the valid choices."""


@dataclass(frozen=True)
class Bound:
    """The range a numeric key must lie in: ``lo`` / ``hi`` (None: unbounded), inclusive unless
    ``lo_open`` / ``hi_open``.  A tuple-valued key is checked element by element."""

    lo: float | None = None
    hi: float | None = None
    lo_open: bool = False
    hi_open: bool = False

    def holds(self, v: float) -> bool:
        lo_ok = self.lo is None or (v > self.lo if self.lo_open else v >= self.lo)
        hi_ok = self.hi is None or (v < self.hi if self.hi_open else v <= self.hi)
        return bool(lo_ok and hi_ok)

    def __str__(self) -> str:
        lo, hi = (f"{v:g}" if isinstance(v, float) else str(v) for v in (self.lo, self.hi))
        if self.hi is None:
            return f"{'>' if self.lo_open else '>='} {lo}"
        if self.lo is None:
            return f"{'<' if self.hi_open else '<='} {hi}"
        return f"in {'(' if self.lo_open else '['}{lo}, {hi}{')' if self.hi_open else ']'}"


POSITIVE = Bound(lo=0, lo_open=True)
NON_NEGATIVE = Bound(lo=0)
AT_LEAST_1 = Bound(lo=1)
FRACTION = Bound(0, 1)
# The ZNCC refinement's patch radius: a query's (2r+1)^2 patch is a fixed-size vector (kernels/math.py)
MAX_PATCH_RADIUS = 4
# Types that carry their key's range: ``check_config`` refuses a value out of it, naming the key, before
# anything runs (instead of a ZeroDivisionError, an SSIM error or a run at 35 m ATE).  Keys typed plainly
# are free (tracking.tau_grad, seeding.frame_fill_min_uncovered: <= 0 is off).  A Literal lists the choices.
Count = Annotated[int, AT_LEAST_1]
NonNegInt = Annotated[int, NON_NEGATIVE]
NonNegative = Annotated[float, NON_NEGATIVE]
Positive = Annotated[float, POSITIVE]
Fraction = Annotated[float, FRACTION]
OpenFraction = Annotated[float, Bound(0, 1, lo_open=True, hi_open=True)]
Beta = Annotated[float, Bound(0, 1, hi_open=True)]  # Adam's: 1 divides by zero in its bias correction
Seed = Annotated[int, Bound(0, 2**31 - 1)]  # NumPy's generators refuse negative seeds
PatchRadius = Annotated[int, Bound(0, MAX_PATCH_RADIUS)]
Switch = Literal["auto", "on", "off"]  # auto: as stated for the key


@dataclass
class DatasetConfig:
    type: Literal["replica", "tum", "7scenes", "synthetic", "realsense", "rosbag"] = "synthetic"  # the loader
    name: str = "room0"  # the sequence's name (synthetic: the scene generated)
    path: str = ""  # sequence folder or bag, relative to data_root unless absolute; realsense: empty = live camera
    stride: Count = 1  # every stride-th frame
    start: NonNegInt = 0  # index of the first frame
    max_frames: Annotated[int | None, AT_LEAST_1] = None  # at most this many frames; null: all
    downscale: Count = 1  # images divided by this on load (block means)
    depth_scale: NonNegative = 0.0  # raw depth units per metre (TUM, Replica, 7-Scenes PNGs); 0: the dataset's
    prefetch: NonNegInt = 6  # frames read ahead while the SLAM runs
    playback_fps: NonNegative = 0.0  # frames/s at which a recording is handed over, as a live camera would; 0: at once
    # 7-Scenes: colour and depth come from two cameras; colour_intrinsics: fx, fy, cx, cy
    register_depth: bool = True  # reproject depth into the colour camera and move the poses to it
    colour_intrinsics: Annotated[tuple[float, float, float, float], POSITIVE] = (526.0, 526.0, 322.0, 238.0)  # px
    depth_to_colour_m: tuple[float, float, float] = (-0.03, 0.0, 0.0)  # depth-camera point + this: colour's (m)
    colour_distortion: tuple[float, float, float, float, float] = (-0.04, 0.0, 0.0, 0.0, 0.0)  # OpenCV k1 k2 p1 p2 k3
    # TUM
    camera: str = "auto"  # fr1 | fr2 | fr3 | auto (from the folder name)
    max_dt: Positive = 0.08  # timestamp association tolerance (s; TUM and rosbag)
    require_pose: bool = True  # false: frames without ground truth are kept and the ATE is not scored
    undistort: bool = True  # undistort the images with the camera's model on load
    # realsense (its stream size: width and height below)
    fps: Count = 30  # live camera frame rate (Hz)
    serial: str = ""  # camera serial number; empty: the one connected
    # rosbag: the topics read; empty: the bag's only one of the kind (the error lists them otherwise)
    rgb_topic: str = ""  # sensor_msgs/Image or CompressedImage, colour
    depth_topic: str = ""  # 16UC1 (mm) or 32FC1 (m), registered to the colour camera
    camera_info_topic: str = ""  # sensor_msgs/CameraInfo; empty: the colour topic's camera_info
    pose_topic: str = ""  # ground truth: PoseStamped, Odometry or TF; empty: none
    pose_frame: str = ""  # TF only: the child frame whose transforms are the camera's poses
    stream: bool = False  # play the bag as a live robot's frames: paired as they arrive, no random access
    # synthetic
    width: Count = 240  # image width (px)
    height: Count = 136  # image height (px)
    n_frames: Count = 100  # frames generated
    depth_noise_m: NonNegative = 0.0  # standard deviation of the noise added to depth (m)
    exposure_drift: bool = False  # frames drift in gain and bias (truth in exposure.txt)
    motion_blur: bool = False  # frames blurred along the camera's motion
    seed: Seed = 0  # the scene's random seed


@dataclass
class RenderConfig:
    sh_degree: Annotated[int, Bound(0, 3)] = 1  # spherical-harmonics degree of the view-dependent colour (0-3)
    background: Annotated[tuple[float, float, float], FRACTION] = (0.0, 0.0, 0.0)  # RGB in [0, 1] behind the map


@dataclass
class TrackingConfig:
    iters: Count = 10  # Adam steps a frame after the direct alignment
    lr: Positive = 1e-3  # mean of the cosine schedule lr_k = lr (1 + cos(pi k / iters))
    adam_beta1: Beta = 0.7  # Adam's first-moment decay for the pose
    adam_beta2: Beta = 0.999  # Adam's second-moment decay
    adam_eps: Positive = 1e-8  # Adam's epsilon
    tau_alpha: Fraction = 0.5  # Eq. 7 opacity threshold
    tau_grad: float = 0.05  # Eq. 8 luminance-gradient threshold (intensity per px); <= 0: off
    depth_weight: NonNegative = 1.0  # RGB-D depth L1 (per metre) against the colour L1 (per channel)
    depth_slope_tau: NonNegative = 0.003  # depth term x 1 / (1 + |grad D| / (tau D)), |grad D| in m per px; 0: off
    brightness_min_alpha: Fraction = 0.98  # Eq. 3's gain from pixels the map covers at least this; 0: Eq. 7's weights
    brightness_max_residual: NonNegative = 0.1  # ... and within this mean |I - g I_hat| of the last step; 0: off
    colour_per_opacity: Switch = "auto"  # compare the frame with colour / opacity; auto: on in mono
    downscale: Count = 1  # tracking resolution = image / downscale
    tile_stride: NonNegInt = 0  # steps but the last render one 16x16 tile in this many; 0: auto (2 rgbd, 1 mono)
    direct_levels: NonNegInt = 3  # pyramid levels of the direct alignment before the Adam steps; 0: off
    direct_iters: Count = 4  # Gauss-Newton steps a pyramid level
    geometric: bool = True  # RGB-D: depth point to plane in the direct alignment; all terms weighted by their noise
    min_valid_ratio: NonNegative = 0.2  # lost below this fraction of pixels with opacity >= tau_alpha
    max_residual: Positive = 0.15  # lost above this weighted mean |I - g I_hat - b| per channel
    depth_edge_spread: NonNegative = 0.05  # downscaling: a block's depth is invalid above this relative spread
    motion_check: Switch = "auto"  # lose frames whose motion contradicts the prediction; auto: on in mono
    motion_min_ratio: Fraction = 0.2  # lost: step below this x the predicted step while the camera turns
    motion_min_step_m: NonNegative = 0.005  # ... once the predicted step is at least this (map units a frame)
    motion_min_rotation_deg: NonNegative = 0.2  # ... and the predicted turn at least this (deg a frame)
    motion_max_ratio: NonNegative = 4.0  # lost: off the prediction (or the recent steps) by this x their step ...
    motion_max_jump_m: Positive = 0.02  # ... plus this (m)
    motion_max_jump_deg: Positive = 3.0  # ... or turn plus this (deg)
    relocalize: Switch = "auto"  # track a lost frame again from the poses of nearby keyframes; auto: on in mono
    graph: Switch = "auto"  # a frame's Adam steps as one captured graph; auto: on on CUDA
    keypoint_odometry: bool = True  # mono: keypoint odometry (section keypoints) starts each frame's tracking
    odometry_pose: bool = True  # mono: a frame with a PnP pose from the odometry takes it, untracked


@dataclass
class KeyframeConfig:
    iou_threshold: Fraction = 0.7  # Eq. 9 tau: a keyframe when the co-visibility IoU with the last is below this
    alpha_threshold: Fraction = 0.5  # visible: accumulated opacity above this
    min_translation_m: NonNegative = 0.05  # ... and the camera moved more than this (m) ...
    min_rotation_deg: NonNegative = 5.0  # ... or turned more than this (deg)
    buffer_size: Annotated[int, Bound(lo=2)] = 10  # keyframes kept on the device
    max_loss_ratio: NonNegative = 0.0  # also a keyframe when the tracking loss grows this x since the last; 0: off
    covisibility: Literal["pixels", "reprojected"] = "reprojected"  # the IoU of Eq. 9's masks or of the surface
    depth_tol: NonNegative = 0.05  # reprojected: relative depth agreement of a shared surface point


@dataclass
class MatchingConfig:
    backbone: str = "classic"  # descriptor: classic | xfeat | dinov2 | dinov3
    weights_path: str = ""  # local weights file for dinov2 / dinov3
    classic_stride: Count = 4  # classic descriptor grid = image / stride
    n_neighbours: Count = 3  # |N_r|: neighbour keyframes matched
    max_view_angle_deg: Positive = 45.0  # neighbours: optical axes closer than this (deg)
    target_parallax_deg: Positive = 5.0  # neighbours: preferred parallax at scene_depth_m (deg)
    scene_depth_m: Positive = 2.0  # typical scene depth (m): neighbours' parallax, mono's first plane
    min_depth_m: Positive = 0.1  # epipolar segment without depth: from this depth (m) ...
    max_depth_m: Positive = 10.0  # ... to this (m)
    depth_rel_tol: NonNegative = 0.05  # with depth d: segment d (1 -/+ tol)
    min_search_radius: NonNegative = 2.0  # segment extended to at least +/- this around its middle (feature px)
    band: NonNegInt = 1  # feature px either side of the epipolar line
    max_steps: Count = 512  # samples along a segment (longer ones are sampled coarser)
    refine_radius: NonNegative = 0.75  # ZNCC refinement within +/- ceil(this x stride) image px
    patch_radius_px: PatchRadius = 3  # ZNCC patch (2r+1)^2 (px)
    w_sim: NonNegative = 1.0  # Eq. 11 weight of the descriptor similarity
    w_fb: NonNegative = 1.0  # Eq. 11 weight of the forward-backward term
    w_epi: NonNegative = 1.0  # Eq. 11 weight of the epipolar term
    sigma_fb_px: Positive = 0.5  # rho_fb = exp(-e_fb^2 / (2 sigma_fb^2)), e_fb in image px
    sigma_epi_px: Positive = 0.5  # rho_epi = exp(-d_epi^2 / (2 sigma_epi^2)), d_epi in image px
    gamma0: float = 1.5  # Eq. 12: Eq. 11 score at confidence 0 ...
    gamma1: float = 2.5  # ... and at confidence 1
    thin_spacing: Positive = 2.0  # feature px between kept pixels after blue-noise thinning


@dataclass
class TriangulationConfig:
    min_parallax_deg: NonNegative = 1.0  # points need rays at least this far apart (deg)
    max_reproj_px: Positive = 2.0  # ... and reprojection errors within this (px)


@dataclass
class SeedingConfig:
    alpha_min: Fraction = 0.1  # Eq. 14 opacity of a seed at confidence 0 ...
    alpha_max: Fraction = 0.9  # ... and at confidence 1
    poisson_radius_px: Positive = 1.0  # seed spacing in pixel footprints (depth / focal) at the reference view
    tangential_scale: Positive = 0.8  # Eq. 13 tangential scale s_perp, in Poisson radii
    plane_radius_px: Positive = 8.0  # plane fit: triangulated neighbours within this many pixel footprints
    plane_min_neighbours: Annotated[int, Bound(lo=3)] = 6  # fewer: the normal is the viewing direction
    min_residual_px: NonNegative = 0.25  # Eq. 13 axial scale: floor of the per-point pixel noise (px)
    axial_min_ratio: Positive = 0.1  # axial scale clipped to at least this x s_perp ...
    axial_max_ratio: Positive = 1.0  # ... and at most this x s_perp
    covered_alpha: Fraction = 0.5  # seeds only where the map's opacity is below this ...
    covered_depth_tol: NonNegative = 0.05  # ... or its depth is off the seed's by more than this (relative)
    depth_consistency_tol: NonNegative = 0.05  # RGB-D: drop triangulated seeds off the measured depth by more; 0: off
    depth_fill: bool = True  # RGB-D: measured-depth seeds where the map still does not cover a keyframe
    depth_stride: Count = 2  # px between depth seeds
    depth_extrapolate_px: NonNegInt = 64  # RGB-D: depth seeds up to this far (px) into pixels without depth; 0: off
    detail_stride: NonNegInt = 1  # RGB-D: depth seeds at this finer stride (px) where the image has detail; 0: off
    detail_min_gradient: NonNegative = 0.03  # detail: grey-level gradient magnitude of at least this per px
    frame_fill_min_uncovered: float = 0.002  # RGB-D: seed a non-keyframe more uncovered than this fraction; < 0: off
    depth_max_rel_jump: NonNegative = 0.05  # no depth seeds on discontinuities (second difference / depth above this)


@dataclass
class MappingConfig:
    rate_fps: NonNegative = 10.0  # frames/s the mapping budget is sized for (640x480, one H100); 0: the best map
    iters_per_frame: NonNegative = 0.0  # the budget in mapping iterations a frame; 0: from rate_fps
    keyframe_share: Fraction = 1.0  # of the budget until the next keyframe, what a new keyframe spends at once
    asynchronous: bool = False  # keyframe work in a worker thread beside tracking (timing=live)
    async_queue: NonNegInt = 1  # asynchronous: keyframes that may wait for the worker before tracking waits
    fill_queue: NonNegInt = 32  # asynchronous: frame fills that may wait for the worker (more: skipped); 0: no bound
    publish_after: Annotated[int, Bound(lo=-1)] = -1  # asynchronous: publish again after this many iterations; -1: off
    init_wait: Literal["window", "first", "seeds"] = "window"  # asynchronous: what of the first window tracking awaits
    min_iters: NonNegInt = 0  # asynchronous: a keyframe's mapping ends after this many once the next waits; 0: off
    final_share: NonNegative = 0.12  # after the last frame, this x the run's iterations over all keyframes; 0: off
    catch_up: bool = True  # asynchronous: after the last frame, mapping until the run had an offline run's iterations
    window: Count = 5  # keyframes in the sliding window
    views_per_iter: NonNegInt = 1  # window views rendered an iteration, a fresh random subset; 0: all
    graph: Switch = "auto"  # one-view mapping steps as captured graphs; auto: on on CUDA
    history: Fraction = 0.7  # probability that a view rendered is an older keyframe instead of a window view
    history_size: NonNegInt = 64  # older keyframes kept on the device for it (a uniform sample once more were evicted)
    frame_views: NonNegInt = 256  # frames between keyframes kept as views like older keyframes (a sample of the run)
    frame_view_every: Count = 3  # ... one kept every this many frames after a keyframe
    init_iters: Count = 1050  # mapping iterations of the initialization
    init_window: Count = 5  # frames of the initial window
    lr_color: NonNegative = 2e-3  # learning rate of the DC colour
    lr_color_rest_factor: NonNegative = 0.05  # the higher SH bands' rate as a fraction of lr_color
    lr_opacity: NonNegative = 2e-3  # learning rate of the opacity logit
    lr_position: NonNegative = 1e-3  # learning rate of the position (m)
    lr_rotation: NonNegative = 1e-3  # learning rate of the rotation quaternion
    lr_scale: NonNegative = 3e-3  # learning rate of the log scale
    lr_final_factor: NonNegative = 1.0  # cosine decay to this fraction of each rate within a mapping call; 1: none
    adam_beta1: Beta = 0.9  # Adam's first-moment decay
    adam_beta2: Beta = 0.999  # Adam's second-moment decay
    lambda_dssim: NonNegative = 0.2  # loss: L1 + lambda_dssim (1 - SSIM)
    grad_clip: Positive = 1.0  # global gradient-norm clipping
    depth_weight: NonNegative = 0.3  # RGB-D depth L1 (per metre) against the colour L1 (per channel)
    robust_scale: float = 0.25  # Cauchy scale of the per-pixel weights (mean |residual| per channel); <= 0: off
    reg_elongation: NonNegative = 1e-2  # weight of relu(log(s_max / s_mid) - log(max_anisotropy))^2
    max_anisotropy: Annotated[float, AT_LEAST_1] = 10.0  # largest / middle axis allowed without penalty
    reg_opacity: NonNegative = 1e-3  # weight of relu(|opacity logit| - max_abs_opacity_logit)^2
    max_abs_opacity_logit: Positive = 6.0  # opacity logit allowed without penalty
    reg_anchor: NonNegative = 1.0  # weight of |mu - mu_EMA|^2 (m^2)
    ema_eta: Fraction = 0.1  # Eq. 15 rate of the EMA position
    opacity_cull: Fraction = 0.05  # maintenance: prune below this opacity
    max_scale_m: Positive = 0.5  # prune: largest axis standard deviation above this (m)
    min_obs: NonNegInt = 3  # prune hidden Gaussians only once seen in this many renders ...
    min_visibility_ratio: Fraction = 0.1  # ... of which fewer than this fraction contributed to a pixel
    merge_footprint_px: NonNegative = 0.5  # merge: projected centres and radii closer than this (px); 0: no merging
    merge_color_diff: NonNegative = 0.05  # ... and colours closer than this (per channel)
    max_gaussians: NonNegInt = 0  # at most this many Gaussians (bounded memory); 0: no cap
    cap_headroom: Annotated[float, Bound(0, 1, lo_open=True)] = 0.9  # maintenance prunes down to this x the cap


@dataclass
class DensifyConfig:
    """Residual-driven densification of ``method=baseline`` (3DGS's adaptive density control)."""

    grad_threshold: Positive = 2e-4  # mean screen-space (NDC) gradient norm that densifies
    start: NonNegInt = 500  # densify at cumulative mapping iterations start < it < stop ...
    stop: NonNegInt = 15000  # ...
    interval: Count = 100  # ... that are multiples of this
    opacity_reset_interval: NonNegInt = 3000  # iterations between opacity resets; 0: never
    opacity_reset_value: OpenFraction = 0.1  # opacity after a reset (twice mapping.opacity_cull)
    percent_dense: Positive = 0.01  # clone if the largest scale <= this x scene_extent_m, else split
    prune_scale_fraction: Positive = 0.1  # after the first reset, prune largest scale > this x scene_extent_m
    scene_extent_m: Positive = 6.0  # the unit of the two fractions above (m)


@dataclass
class BootstrapConfig:
    """Monocular two-view bootstrap (``rgs_warp.bootstrap``; mode=mono)."""

    enabled: bool = True  # false: the first keyframe is a plane at matching.scene_depth_m
    coarse_step: NonNegInt = 4  # feature px between the coarse pass's queries; 0: no coarse pass
    search_radius: Count = 12  # window half-width around the query's moved cell (feature px)
    ratio_exclusion: NonNegInt = 2  # the second best is sought outside this of the best (feature px)
    min_similarity: float = 0.5  # Eq. 10 similarity of the best match at least this
    max_ratio: Positive = 0.9  # Lowe's ratio of descriptor distances, best / second best, at most this
    max_fb_px: NonNegative = 1.0  # forward-backward error at most this (image px)
    refine_radius_px: NonNegInt = 3  # ZNCC refinement within +/- this (image px); 0: parabola only
    patch_radius_px: PatchRadius = 3  # ZNCC patch (2r+1)^2 (px)
    ransac_iters: Count = 1000  # USAC's upper bound on iterations
    ransac_confidence: OpenFraction = 0.999999999  # USAC stops when a better pose is this unlikely to be missed
    ransac_threshold_px: Positive = 1.0  # Sampson error of an inlier (image px)
    min_inliers: Annotated[int, Bound(lo=5)] = 100  # fewer inliers: the pose is not trusted
    min_inlier_ratio: Fraction = 0.8  # inliers / selected matches below this: not trusted
    min_cheirality_ratio: Fraction = 0.98  # inliers in front of both cameras below this fraction: not trusted
    min_parallax_deg: NonNegative = 2.0  # median inlier parallax below this: wait for a later frame (deg)
    max_reproj_px: Positive = 1.0  # points kept with RMS reprojection error within this (px) ...
    min_point_parallax_deg: NonNegative = 0.5  # ... and parallax of at least this (deg)
    max_wait_frames: Count = 60  # frames tried against frame 0 before the plane is taken


@dataclass
class KeypointsConfig:
    """Monocular keypoint odometry (``rgs_warp.keypoint_odometry``; mode=mono).  Pixel values are for
    640 px of image width and scale with the width (not below half)."""

    max_features: Count = 600  # Shi-Tomasi corners kept
    min_distance_px: Positive = 12.0  # least distance between corners (px)
    redetect_fraction: Fraction = 0.8  # new corners every frame once fewer than this fraction are tracked
    fb_px: Positive = 0.5  # KLT forward-backward limit (px)
    pnp_px: Positive = 2.0  # PnP RANSAC inlier limit (px)
    min_inliers: Annotated[int, Bound(lo=6)] = 15  # fewest PnP inliers for a pose (else rotation-only)
    residual_px: NonNegative = 1.5  # a track reprojecting further than this after the pose is dropped (px); 0: pnp_px
    max_dev_deg: Positive = 5.0  # a PnP pose turned more than this from the prediction is refused (deg) ...
    max_dev_step: NonNegative = 4.0  # ... or with its centre off by more than this x the predicted step ...
    max_dev_depth: NonNegative = 0.01  # ... plus this x the median scene depth
    rotation_min_tracks: Annotated[int, Bound(lo=3)] = 20  # fewer tracks for a rotation-only pose: the frame is lost
    min_parallax_deg: NonNegative = 1.5  # a track in 2+ keyframes is triangulated once its rays span this (deg) ...
    max_reproj_px: Positive = 2.0  # ... and kept when every reprojection is within this (px)
    kf_tracked_fraction: Fraction = 0.7  # keyframe: fewer than this fraction of the last one's tracks remain,
    kf_landmark_fraction: Fraction = 0.6  # ... fewer than this fraction of its usable landmarks,
    kf_min_landmarks: NonNegInt = 100  # ... fewer than this many landmarks,
    kf_parallax_deg: Positive = 2.0  # ... median parallax to it above this (deg), or a rotation-only pose
    kf_min_gap: Count = 1  # frames between keyframes at least
    ba_window: NonNegInt = 8  # local bundle adjustment over the last this many keyframes; 0: none
    ba_held_max: Annotated[int, Bound(lo=2)] = 12  # older keyframes held in it (gauge and scale), at most
    ba_huber_px: Positive = 1.0  # Huber loss scale of the reprojection errors (px)
    ba_iters: Count = 30  # cost evaluations, at most


@dataclass
class EvalConfig:
    every: Count = 5  # photometric metrics on every n-th frame, keyframes excluded
    convergence_every: NonNegInt = 50  # window PSNR every this many initial mapping iterations; 0: after keyframes only
    lpips_alexnet_path: str = ""  # torchvision's AlexNet weights for LPIPS; empty: LPIPS n/a
    lpips_linear_path: str = ""  # LPIPS v0.1 linear layers (alex.pth); empty: the lpips package's


@dataclass
class ExportConfig:
    mesh: bool = False  # mesh.ply in the run folder: TSDF fusion of the map rendered at every keyframe
    voxel_m: Positive = 0.01  # TSDF voxel size (m)


@dataclass
class Config:
    device: str = "auto"  # auto: cuda:0 when Warp sees a GPU, else cpu
    mode: Literal["rgbd", "mono"] = "rgbd"  # with depth or colour only
    method: Literal["rgs", "baseline"] = "rgs"  # dense seeding at every keyframe, or densification (method group)
    seed: Seed = 0  # random seed of the run
    data_root: str = ""  # root of the dataset paths; empty: $RGS_DATA, else the current directory
    output_dir: str = "runs"  # folder of the run folders
    run_name: str = ""  # run folder name; empty: <dataset>-<date>-<time> (-2, -3, ... if taken)
    overwrite: bool = False  # true: an existing run folder of run_name is cleared and reused
    checkpoint_every: NonNegInt = 10  # a checkpoint every this many keyframes (resume=RUN_DIR); 0: off
    viewer: bool = False  # serve the web viewer during the run (the `viewer` extra)
    viewer_port: Annotated[int, Bound(0, 65535)] = 8080  # the viewer's port; 0: a free one
    viewer_host: str = "127.0.0.1"  # the viewer's interface; 0.0.0.0: every interface, no access control
    cpu_sized: bool = True  # the command line on the CPU: a synthetic scene without size keys at CPU_SIZED's sizes
    dataset: DatasetConfig = field(default_factory=DatasetConfig)
    render: RenderConfig = field(default_factory=RenderConfig)
    tracking: TrackingConfig = field(default_factory=TrackingConfig)
    keyframes: KeyframeConfig = field(default_factory=KeyframeConfig)
    matching: MatchingConfig = field(default_factory=MatchingConfig)
    triangulation: TriangulationConfig = field(default_factory=TriangulationConfig)
    seeding: SeedingConfig = field(default_factory=SeedingConfig)
    mapping: MappingConfig = field(default_factory=MappingConfig)
    densify: DensifyConfig = field(default_factory=DensifyConfig)
    bootstrap: BootstrapConfig = field(default_factory=BootstrapConfig)
    keypoints: KeypointsConfig = field(default_factory=KeypointsConfig)
    eval: EvalConfig = field(default_factory=EvalConfig)
    export: ExportConfig = field(default_factory=ExportConfig)

    def resolved_data_root(self) -> Path:
        return Path(self.data_root or os.environ.get("RGS_DATA", "") or ".").expanduser()

    def dataset_path(self) -> Path:
        p = Path(self.dataset.path).expanduser()
        return p if p.is_absolute() else self.resolved_data_root() / p

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)


def leaves(obj, prefix: str = "") -> Iterator[tuple[str, typing.Any]]:
    """(dotted key, value) of every key of a config (or one of its sections), in definition order."""
    for f in dataclasses.fields(obj):
        value = getattr(obj, f.name)
        if dataclasses.is_dataclass(value):
            yield from leaves(value, prefix + f.name + ".")
        else:
            yield prefix + f.name, value


def _hints(cls, prefix: str = "") -> Iterator[tuple[str, typing.Any]]:
    for name, hint in typing.get_type_hints(cls, include_extras=True).items():
        if dataclasses.is_dataclass(hint):
            yield from _hints(hint, prefix + name + ".")
        else:
            yield prefix + name, hint


# The values of every key typed with a Literal, and the range of every key typed with one (above)
CHOICES = {key: typing.get_args(hint) for key, hint in _hints(Config) if typing.get_origin(hint) is Literal}
CONSTRAINTS = {key: hint.__metadata__[0] for key, hint in _hints(Config) if typing.get_origin(hint) is Annotated}
# Pairs of keys whose first must not exceed the second, and why (appended to the message)
ORDERED_KEYS = (
    ("matching.min_depth_m", "matching.max_depth_m", ": they bound the epipolar search"),
    ("seeding.alpha_min", "seeding.alpha_max", ": Eq. 14's opacity range"),
    ("seeding.axial_min_ratio", "seeding.axial_max_ratio", ": the clip of Eq. 13's axial scale"),
    ("seeding.detail_stride", "seeding.depth_stride", ": detail seeds are the finer ones"),
    ("mapping.init_window", "mapping.init_iters", ": each initial frame gets init_iters // init_window iterations"),
)
# The smallest images the pipeline runs on: mapping's SSIM has an 11x11 window (at 20x11 the office's map
# stayed empty, 22x12 ran); tracking needs neighbours for its image gradients (Eq. 8)
MIN_IMAGE_PX = 16
MIN_TRACKING_PX = 4
# Keys that apply to asynchronous mapping only, and the value that leaves them off
ASYNC_ONLY = (("mapping.min_iters", 0), ("mapping.publish_after", -1), ("mapping.init_wait", "window"))


def _config_value(cfg: Config, key: str):
    node = cfg
    for part in key.split("."):
        node = getattr(node, part)
    return node


def check_config(cfg: Config) -> Config:
    """``cfg`` if its values are usable (``CONSTRAINTS``, every float finite, and the relations
    between keys), else a ConfigError naming the key, its value and the range."""
    for key, value in leaves(cfg):
        items = value if isinstance(value, tuple) else (value,)
        numbers = [v for v in items if isinstance(v, int | float) and not isinstance(v, bool)]
        if any(isinstance(v, float) and not math.isfinite(v) for v in numbers):
            raise ConfigError(f"{key}: {value!r} is not a finite number")
        bound = CONSTRAINTS.get(key)
        if bound is not None and not all(bound.holds(v) for v in numbers):
            raise ConfigError(f"{key}: {value!r} is out of range: it must be {bound}")
    for small, large, why in ORDERED_KEYS:
        a, b = _config_value(cfg, small), _config_value(cfg, large)
        if a > b:
            raise ConfigError(f"{small} ({a!r}) must not exceed {large} ({b!r}){why}")
    for key, off in ASYNC_ONLY:
        value = _config_value(cfg, key)
        if value != off and not cfg.mapping.asynchronous:
            shown = f"={value}" if isinstance(value, str) else f" ({value})"
            raise ConfigError(
                f"{key}{shown} applies to asynchronous mapping only: set mapping.asynchronous=true with it, "
                f"or leave it at {off}"
            )
    if cfg.dataset.type == "synthetic":
        check_image_size(cfg.dataset.width, cfg.dataset.height, cfg, native=True)
    return cfg


def check_image_size(width: int, height: int, cfg: Config, native: bool = False) -> None:
    """ConfigError unless images of ``width`` x ``height`` (the camera's; ``native``: before
    ``dataset.downscale``) stay at least ``MIN_IMAGE_PX`` after the downscaling and ``MIN_TRACKING_PX``
    at the tracking resolution."""
    factor = cfg.dataset.downscale if native else 1
    w, h = width // factor, height // factor
    key, got = ("dataset.downscale", f"{width}x{height} images to {w}x{h}") if native else ("the camera", f"{w}x{h}")
    if min(w, h) < MIN_IMAGE_PX:
        what = f"{key} = {factor} shrinks the {got}" if native else f"{key} is {got}"
        raise ConfigError(f"{what}: the pipeline needs at least {MIN_IMAGE_PX} px a side (mapping's 11x11 SSIM)")
    t = cfg.tracking.downscale
    if min(w // t, h // t) < MIN_TRACKING_PX:
        raise ConfigError(
            f"tracking.downscale = {t} shrinks the {w}x{h} images to {w // t}x{h // t} for tracking: it needs at "
            f"least {MIN_TRACKING_PX} px a side"
        )


def group_options(group: str) -> list[str]:
    """Names of the YAML files of a group, e.g. ``['replica/office0', 'synthetic/room0', ...]``."""
    base = CONFIG_DIR / group
    return sorted(str(p.relative_to(base).with_suffix("")) for p in base.rglob("*.yaml"))


def _suggest(word: str, options, prefix: str = "") -> str:
    close = difflib.get_close_matches(word, list(options), n=1, cutoff=0.5)
    return f" Did you mean {prefix + close[0]!r}?" if close else ""


def _coerce(value, tp, key: str):
    origin = typing.get_origin(tp)
    args = typing.get_args(tp)
    if origin in (typing.Union, types.UnionType):
        if value is None and type(None) in args:
            return None
        inner = [a for a in args if a is not type(None)]
        return _coerce(value, inner[0], key)
    if origin is Literal:
        return _coerce(value, str, key)
    if origin is tuple:
        if not isinstance(value, list | tuple):
            raise ConfigError(f"{key}: expected a list like [0, 0, 0], got {value!r}")
        if len(value) != len(args):
            raise ConfigError(f"{key}: expected {len(args)} values, got {len(value)}")
        return tuple(_coerce(v, a, key) for v, a in zip(value, args, strict=True))
    if tp in (int, float) and isinstance(value, str):
        # YAML 1.1 reads "1e-3" as a string; accept what Python reads as a number.
        try:
            value = int(value) if tp is int else float(value)
        except ValueError:
            pass
    if tp is bool:
        if isinstance(value, bool):
            return value
        raise ConfigError(f"{key}: expected true or false, got {value!r}")
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"{key}: expected an integer, got {value!r}")
        return value
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise ConfigError(f"{key}: expected a number, got {value!r}")
        return float(value)
    if tp is str:
        return "" if value is None else str(value)
    raise ConfigError(f"{key}: unsupported type {tp}")


def _set_tree(obj, tree: dict, prefix: str = "") -> None:
    """Set the values of a nested dict on a dataclass tree, checking keys and types."""
    if not isinstance(tree, dict):
        raise ConfigError(f"{prefix.rstrip('.') or 'config'}: expected a mapping of keys, got {tree!r}")
    types = typing.get_type_hints(type(obj))
    for k, v in tree.items():
        key = prefix + str(k)
        if k not in types:
            valid = sorted(types)
            raise ConfigError(
                f"unknown key {key!r}.{_suggest(str(k), valid, prefix)} Valid keys under "
                f"{prefix.rstrip('.') or 'the top level'}: {', '.join(valid)}"
            )
        current = getattr(obj, k)
        if dataclasses.is_dataclass(current):
            _set_tree(current, v, key + ".")
        else:
            value = _coerce(v, types[k], key)
            if key in CHOICES and value not in CHOICES[key]:
                raise ConfigError(
                    f"{key}: {value!r} is not one of {', '.join(CHOICES[key])}.{_suggest(value, CHOICES[key])}"
                )
            setattr(obj, k, value)


class _YamlLoader(yaml.SafeLoader):
    """YAML with only true / false as booleans (YAML 1.2): PyYAML's YAML 1.1 also reads on / off /
    yes / no as booleans, which turned ``tracking.graph=off`` into False."""


_YamlLoader.yaml_implicit_resolvers = {
    first: [(tag, rx) for tag, rx in resolvers if tag != "tag:yaml.org,2002:bool"]
    for first, resolvers in yaml.SafeLoader.yaml_implicit_resolvers.items()
}
_YamlLoader.add_implicit_resolver(
    "tag:yaml.org,2002:bool", re.compile(r"^(?:true|True|TRUE|false|False|FALSE)$"), list("tTfF")
)


def parse_yaml(text: str):
    """YAML as the configs read it (booleans only true / false)."""
    return yaml.load(text, Loader=_YamlLoader)


def _load_yaml(path: Path) -> dict:
    try:
        data = parse_yaml(path.read_text()) or {}
    except yaml.YAMLError as e:
        raise ConfigError(f"{path}: invalid YAML: {e}") from None
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: expected a mapping at the top level")
    return data


def _apply_group(cfg: Config, group: str, option: str) -> None:
    options = group_options(group)
    if option not in options:
        raise ConfigError(f"unknown {group} {option!r}.{_suggest(option, options)} Valid: {', '.join(options)}")
    data = _load_yaml(CONFIG_DIR / group / f"{option}.yaml")
    # a section's file may set keys of others (a dataset's sensor wants other tracking settings):
    # ``settings: {tracking: {tau_grad: 0.0}}``, applied after the section; command-line keys still win
    settings = data.pop("settings", None)
    section = GROUPS[group]
    if section is None:
        _set_tree(cfg, data)
    else:
        fresh = type(getattr(cfg, section))()  # a group option replaces the whole section
        setattr(cfg, section, fresh)
        _set_tree(fresh, data, section + ".")
    if settings is not None:
        _set_tree(cfg, settings)


def load_config(overrides: list[str] | tuple[str, ...] = ()) -> Config:
    """Defaults, then group selections (``dataset=replica/office0``), then ``key=value`` overrides,
    each value parsed as YAML (``tracking.iters=40``, ``render.background=[1,1,1]``)."""
    selections = dict(DEFAULTS)
    keys: list[tuple[str, object]] = []
    for item in overrides:
        if "=" not in item:
            raise ConfigError(f"override {item!r} is not of the form key=value (see --help)")
        k, raw = item.split("=", 1)
        k = k.strip()
        if k in GROUPS:
            selections[k] = raw.strip()
            continue
        try:
            value = parse_yaml(raw) if raw.strip() else ""
        except yaml.YAMLError:
            value = raw
        keys.append((k, value))
    cfg = Config()
    for group, option in selections.items():
        _apply_group(cfg, group, option)
    for k, value in keys:
        tree: dict = {}
        node = tree
        parts = k.split(".")
        for p in parts[:-1]:
            node = node.setdefault(p, {})
        node[parts[-1]] = value
        _set_tree(cfg, tree)
    return check_config(cfg)


def config_from_dict(data: dict) -> Config:
    """A Config from a nested dict (e.g. a saved ``config.yaml``), keys and types checked."""
    cfg = Config()
    _set_tree(cfg, data)
    return check_config(cfg)


def load_saved_config(path: str | Path) -> Config:
    """The config of a run folder (``config.yaml`` as ``save_config`` wrote it); every error names the
    file.  A file cut short (a copy interrupted) lacks its last sections: that is an error too."""
    path = Path(path)
    try:
        data = parse_yaml(path.read_text(encoding="utf-8"))
    except (yaml.YAMLError, UnicodeDecodeError) as e:
        raise ConfigError(f"{path}: not readable YAML (truncated or damaged?): {e}") from None
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: expected a mapping of keys, got {type(data).__name__} (truncated or damaged?)")
    sections = [f.name for f in dataclasses.fields(Config) if dataclasses.is_dataclass(getattr(Config(), f.name))]
    missing = [name for name in sections if name not in data]
    if missing:
        # a copy cut short lacks the last sections; one lacking an earlier section is of another version
        cut = all(name not in data for name in sections[sections.index(missing[0]) :])
        why = "truncated?" if cut else "written by another version of rgs_warp?"
        raise ConfigError(f"{path}: sections {', '.join(missing)} missing ({why})")
    try:
        return config_from_dict(data)
    except ConfigError as e:
        raise ConfigError(f"{path}: {e}") from None


def save_config(cfg: Config, path: Path) -> None:
    def plain(x):
        if isinstance(x, dict):
            return {k: plain(v) for k, v in x.items()}
        if isinstance(x, tuple):
            return [plain(v) for v in x]
        return x

    write_text_atomic(path, yaml.safe_dump(plain(cfg.to_dict()), sort_keys=False))


def resolve_device(name):
    """``device=auto``: ``cuda:0`` when Warp sees a GPU, else ``cpu``; a device Warp has, as given (a
    ``wp`` device too); any other name a ``ConfigError`` that lists the devices there are."""
    import warp as wp

    auto = "cuda:0" if wp.is_cuda_available() else "cpu"
    if name == "auto":
        return auto
    devices = [d.alias for d in wp.get_devices()]
    if not isinstance(name, str) or name in devices or (name == "cuda" and wp.is_cuda_available()):
        return name
    gpu = "" if wp.is_cuda_available() else " (Warp sees no CUDA GPU here)"
    raise ConfigError(
        f"device={name}: no such device{gpu}; the devices are {', '.join(devices)}, and device=auto picks {auto}"
    )
