"""Typed configuration: one dataclass per stage, filled from YAML files under ``configs/`` and from
Hydra-style command-line overrides (``group=option`` selects a YAML file of a group,
``a.b=value`` sets a key).

Numbers without a comment are the supplement's Table 1 / §4 values; the others say where they were
measured (``experiments/results/``) or decided (``docs/decisions.md``).
"""

from __future__ import annotations

import dataclasses
import difflib
import math
import os
import re
import typing
from dataclasses import dataclass, field
from pathlib import Path

import yaml

from rgs_warp.io.atomic import write_text_atomic

CONFIG_DIR = Path(__file__).parent / "configs"
# Groups whose YAML fills one section of the config; ``method`` files are merged at the top level
# because a method sets values in several stages at once.
GROUPS = {"dataset": "dataset", "method": None, "timing": None}
DEFAULTS = {"dataset": "synthetic/room0", "method": "rgs", "timing": "offline"}


class ConfigError(ValueError):
    """Invalid configuration or override; the message lists the valid choices."""


@dataclass
class DatasetConfig:
    type: str = "synthetic"  # replica | tum | 7scenes | synthetic | realsense
    name: str = "room0"
    # relative to data_root unless absolute; unused for synthetic; realsense: a recording, empty = live camera
    path: str = ""
    stride: int = 1
    start: int = 0
    max_frames: int | None = None
    downscale: int = 1
    prefetch: int = 6  # frames read ahead while the SLAM runs, by up to 3 threads (datasets/base.py)
    # frames/s at which a run plays a recorded sequence, as a live camera would deliver it: frame i is
    # handed to the SLAM no earlier than i / playback_fps seconds after frame 0 (never dropped: a frame
    # the SLAM takes late is taken at once, and its lag is logged; no checkpoints, as for a live
    # stream); 0: as fast as the SLAM takes them
    playback_fps: float = 0.0
    # 7-Scenes only: its colour and depth images come from two cameras.  register_depth reprojects each
    # depth image into the colour camera (colour_intrinsics fx, fy, cx, cy; a depth-camera point plus
    # depth_to_colour_m is the colour-camera point) and moves the ground-truth poses (the depth
    # camera's) to the colour camera.  Measured: experiments/results/slam.md, 7-Scenes calibration
    register_depth: bool = True
    colour_intrinsics: tuple[float, float, float, float] = (526.0, 526.0, 322.0, 238.0)
    depth_to_colour_m: tuple[float, float, float] = (-0.03, 0.0, 0.0)
    # TUM only
    camera: str = "auto"  # fr1 | fr2 | fr3 | auto (from the folder name)
    max_dt: float = 0.08  # s, timestamp association tolerance
    # false: a sequence without groundtruth.txt (your own data: README, "Your own data"); frames
    # without a pose are kept and the ATE is not scored
    require_pose: bool = True
    undistort: bool = True
    # realsense only: the live camera's frame rate and serial number (empty: the one connected);
    # width and height below are its stream size
    fps: int = 30
    serial: str = ""
    # synthetic (and a live realsense camera's stream)
    width: int = 240
    height: int = 136
    n_frames: int = 100
    depth_noise_m: float = 0.0
    exposure_drift: bool = False
    motion_blur: bool = False
    seed: int = 0


@dataclass
class RenderConfig:
    # view-dependent colour bands (SH degree; the design's 2, Table 2's 3).  1 (H100, session 18): the
    # office scores alike at 0, 1 and 2 (34.37 / 34.35 / 34.34 dB held out); 7-Scenes, with the
    # reprojected keyframes and detail seeds, 24.75-24.76 dB compensated at 1, 24.76-25.01 at 2,
    # 24.54-24.62 at 0; office GPU memory with the detail seeds 2.9 / 3.4 / 4.3 GiB at 0 / 1 / 2 (issue
    # 19's bound: 4) (experiments/results/fidelity.md)
    sh_degree: int = 1
    background: tuple[float, float, float] = (0.0, 0.0, 0.0)


@dataclass
class TrackingConfig:
    # §4.2 has 30-60 Adam steps a frame at 5e-3; after the direct alignment (direct_levels) 10 steps at 1e-3
    # track as well (H100, office 1200x680 and 7-Scenes: ATE 0.41 / 4.4-4.5 cm against 0.40 / 4.2-4.4 cm) in
    # half the time (experiments/results/perf.md, session 22)
    iters: int = 10
    lr: float = 1e-3  # mean of the cosine schedule lr_k = lr (1 + cos(pi k / iters)), 2 lr down to ~0
    adam_beta1: float = 0.7  # Table 1 has 0.9 (mapping); 30 tracking steps converge with 0.7 (measured)
    adam_beta2: float = 0.999  # Table 1
    adam_eps: float = 1e-8  # PyTorch's default; far below the twist gradients (~1e-5 .. 1e-2)
    # Eq. 7-8 thresholds and the depth weight: 0.5 / 0.05 / 1.0 are provisional; on ray-traced frames
    # at 96x54 tau_alpha 0.9, tau_grad 0 or 0.02 and depth_weight 0.1-0.3 changed the error only within
    # the ~1 cm floor set by the map there (report of issue 5); depth_weight 1 gave the best rotation.
    tau_alpha: float = 0.5  # Eq. 7 opacity threshold
    tau_grad: float = 0.05  # Eq. 8 luminance-gradient threshold (intensity units per pixel); <= 0: off
    depth_weight: float = 1.0  # RGB-D depth L1 term (per metre) against the colour L1 (per channel)
    # depth term per pixel x 1 / (1 + |grad D| / (tau D)) (|grad D| metres per pixel of the observed
    # depth): splat depth is biased towards the camera on slanted surfaces; 0 = off.  0.003 by
    # measurement (experiments/results/tracking.md, slam.md: ATE 0.82 -> 0.63 cm on the office)
    depth_slope_tau: float = 0.003
    # Eq. 3 brightness model: gain (g = ratio of weighted means, b = 0; default, see kernels/tracking.py
    # solve_brightness for why), affine (Eq. 4 least squares), off (g = 1, b = 0; ablation)
    brightness: str = "gain"
    # Eq. 3-4 are solved on the pixels the map covers at least this much (partly covered pixels bias
    # the gain, and the mapper feeds the bias back: kernels/tracking.py brightness_sums); 0: Eq. 7's
    # w_alpha weights instead
    brightness_min_alpha: float = 0.98
    # The colour term compares the frame with the rendered colour / opacity (the map's colour where it
    # covers a pixel only in part) instead of the render, which the background darkens there.  Without
    # depth that darkening at the edge of the map pulls the pose: tracked from the true previous poses
    # against the map of the frames before it (H100, the office's fast turn), monocular frames were off
    # by up to 5.8 cm (experiments/results/mono.md).  auto: on in mono, off in rgbd (not measured there)
    colour_per_opacity: str = "auto"
    # The exposure (g, b) a keyframe and the frame-fill seeds are coloured with: "map" (the brightness
    # model's (g, b) against the map's render above, which the gain model reads with the bias folded
    # into the gain: under a strong drift the map's contrast drifts) or "keyframes" (affine, the reduced
    # major axis against the older keyframes' colours at the same surface points, each in the first
    # keyframe's exposure, so the map's colour stays in that exposure; RGB-D only; exposure.py). On an
    # H100 (a074fb1, 3 seeds) "keyframes" gave the office +0.19 dB but broke 7-Scenes tracking (ATE
    # median 11.5 against 4.3 cm): experiments/results/fidelity.md
    exposure_from: str = "map"
    downscale: int = 1  # tracking resolution = image / downscale
    # each step but the last renders (and differentiates) one 16x16 tile in this many (2: a checkerboard
    # that alternates between steps, so each pixel counts every other step); the last step renders every
    # tile, for the coverage, loss and exposure the frame reports.  The steps' raster work shrinks in
    # proportion (Renderer.forward's tile_stride); 1 = every tile every step; 0 = auto: 2 in rgbd, 1 in mono
    # (not measured there; the image alone constrains its steps).  H100 RGB-D, 2 against 1: tracking p50
    # office 28.8 against 37.2 ms, 7-Scenes 14.7 against 17.7 ms, the same ATE (office 0.39-0.40 against
    # 0.40-0.42 cm over 3 seeds) and PSNR; 3 gains little more (experiments/results/perf.md)
    tile_stride: int = 0
    # Direct alignment before the Adam steps (kernels/direct.py): Gauss-Newton of the frame against one
    # render of the map at the start pose, on an image pyramid of direct_levels levels (coarse to fine,
    # the finest at the tracking resolution), direct_iters steps a level, for the twist and the affine
    # brightness; the Adam steps start from its pose.  One render and a few reductions instead of a
    # rasterizer backward a step; 0 = off (then iters=30 lr=5e-3, the supplement's)
    direct_levels: int = 3
    direct_iters: int = 4
    min_valid_ratio: float = 0.2  # lost below this fraction of pixels with opacity >= tau_alpha
    max_residual: float = 0.15  # lost above this weighted mean |I - g I_hat - b| per channel
    depth_edge_spread: float = 0.05  # downscaling: block depth invalid above this relative spread
    # Motion check (tracking.py, ``motion_inconsistency``): a frame is lost when its tracked translation
    # since the last frame falls below motion_min_ratio x the constant-velocity prediction's while the
    # camera still turns (at least half the predicted rotation): the image still moves, but the pose
    # hardly travels.  That is how monocular tracking collapses
    # (issue 22: 0.01-0.72 of the true translation on the office while the rotation stayed right); a real
    # stop stops the rotation too.  auto: on in mode=mono (whose translation only the map constrains),
    # off in rgbd (measured depth pins it); on / off force it.
    motion_check: str = "auto"
    # The thresholds (docs/decisions.md, "Monocular loss detector"): the ground-truth trajectories of
    # the synthetic office / room (100 and 300 frames) and Replica office0 go as low as 0.26 (the office
    # stopping mid-turn, 100 frames) on judged frames; replayed on the 11 recorded GPU office runs of
    # issue 22 (runs 32-35), 0.2 flags 10 of them first at frames 64-81 (none before 64), where they
    # were flagged lost at 99-108 before; 0.3 flags all 11 but the truth too
    motion_min_ratio: float = 0.2
    # the check waits for a predicted step of at least this (map units a frame; mono: metres at the
    # bootstrap's scale, median depth matching.scene_depth_m) and a predicted turn of at least
    # motion_min_rotation_deg: below them tracking noise (~1 mm, 0.05 deg) is a large part of the ratio
    motion_min_step_m: float = 0.005
    motion_min_rotation_deg: float = 0.2
    # The check's run-away half: a frame is lost when its pose leaves the constant-velocity prediction by
    # more than motion_max_ratio x the predicted step plus motion_max_jump_m (or turns away from it by
    # more than motion_max_ratio x the predicted turn plus motion_max_jump_deg), or when its step is
    # longer (turns more) than motion_max_ratio x the median of the last 10 steps plus the same floors.
    # A monocular office run that turns onto surface its map lacks jumps 30-40 mm, then 140-480 mm and
    # 5-25 deg a frame against the truth's 5-8 mm and 3 deg, with no frame lost (experiments/results/
    # mono.md).  These bounds flag no frame of the synthetic paths (office, room; 100-2,000 frames) nor
    # of the shared 7-Scenes frames' ground truth (500 frames, hand-held: up to 35 mm and 2.3 deg off
    # the prediction)
    motion_max_ratio: float = 4.0
    motion_max_jump_m: float = 0.02
    motion_max_jump_deg: float = 3.0
    # Relocalisation (issue 22): a lost frame is tracked again from the last good pose and from the
    # poses of the (up to three) keyframes nearest it, and the best try that is not lost (lowest loss) is its pose;
    # the motion model then restarts there (zero velocity).  auto: on in mode=mono, off in rgbd (where a
    # lost frame is mostly one the map does not cover yet); on / off force it.
    relocalize: str = "auto"
    # The frame's Adam steps run as one captured graph (a CUDA graph on a GPU, Warp's CPU graph on the
    # CPU), replayed each frame while the map's size and the renderer's buffers stay the same, and
    # captured again when they change: one launch instead of about 15 per step.  auto: on on CUDA
    # devices, off on the CPU (where launches cost little); on / off force it.
    graph: str = "auto"
    # Monocular: the keypoint odometry (keypoint_odometry.py, its settings in the `keypoints` section; issue
    # 22) gives each frame its pose (odometry_pose, below) or tracking's start: KLT tracks, PnP against
    # landmarks triangulated over its own keyframes, and a local bundle adjustment with older keyframes held,
    # which keeps the scale that photometric tracking against the monocular map loses (on its own 0.40 cm
    # Sim(3) ATE over the office's first 150 frames at 1200x680; experiments/results/mono.md).  Not in RGB-D.
    keypoint_odometry: bool = True
    # Monocular with the keypoint odometry: a frame whose odometry pose came from PnP takes it as its pose,
    # as if given (exposure fitted, keyframe selection, mapping), without photometric tracking, which only
    # runs where the odometry lost the frame or had only a rotation; false: tracking refines every pose.
    # Photometric tracking against the monocular map pulled the odometry's poses off: H200, office 1200x680,
    # 150 frames, 1.29 cm Sim(3) ATE in 3 of 3 runs against 2.81-3.54 cm, no frame lost against 6-9, +1-2 dB
    # (experiments/results/mono.md, session 29)
    odometry_pose: bool = True


@dataclass
class KeyframeConfig:
    # Eq. 9 tau; for covisibility=reprojected (below): 0.6 (H100, office: 0.5 / 0.6 / 0.7 / 0.8 give 24 /
    # 31 / 43 / 67 keyframes, 33.2 / 35.3 / 35.9 / 35.5 dB; pixels at 0.8: 26 keyframes, 34.3 dB)
    iou_threshold: float = 0.6
    alpha_threshold: float = 0.5  # visibility mask: accumulated opacity above this
    min_translation_m: float = 0.05
    min_rotation_deg: float = 5.0
    buffer_size: int = 10  # §4.3: 8-12
    # not in the paper: also a keyframe when the frame's tracking loss exceeds this multiple of the
    # loss of the first frame tracked after the last keyframe (motion bounds still apply): the view
    # went where the map is covered but poorly fitted, which the IoU does not see; 0 = off.  On in the
    # 7-Scenes config (1.3; off: 3 of 3 runs fail at 42 cm, 1.3: 4.1-4.6 cm in 5 of 5, 1.2: 4.4-4.9);
    # off by default (office at 1.3: 0.47-0.51 cm, 32.9-33.2 dB against 0.42, 33.4; results/slam.md)
    max_loss_ratio: float = 0.0
    # what the IoU compares (keyframes.KeyframeSelector): "pixels", the two visibility masks pixel by
    # pixel (Eq. 9 as written), or "reprojected", the surface both views see (each visible pixel lifted
    # with its rendered depth into the last keyframe, shared where that keyframe's depth agrees within
    # depth_tol): a turn within a mapped room keeps the mask full, only the second sees it
    covisibility: str = "reprojected"
    depth_tol: float = 0.05


@dataclass
class MatchingConfig:
    # Numbers marked "measured" come from experiments/bench/matching_precision.py (docs/matching.md).
    backbone: str = "classic"  # classic | xfeat | dinov2 | dinov3; measured (docs/matching.md)
    weights_path: str = ""  # local weights file for dinov2 / dinov3
    classic_stride: int = 4  # classic descriptor grid = image / stride; measured
    n_neighbours: int = 3  # |N_r|
    max_view_angle_deg: float = 45.0  # neighbours: optical axes closer than this (overlap proxy)
    target_parallax_deg: float = 5.0  # neighbours: preferred parallax at scene_depth_m
    scene_depth_m: float = 2.0  # parallax of a neighbour is judged at this depth (indoor scenes)
    min_depth_m: float = 0.1  # epipolar segment without depth: from min_depth_m ...
    max_depth_m: float = 10.0  # ... to max_depth_m (indoor sensors' range)
    depth_rel_tol: float = 0.05  # with depth: segment d * (1 -/+ tol) (Kinect noise, registration)
    min_search_radius: float = 2.0  # feature px: segment extended to at least +/- this around its middle
    band: int = 1  # feature px either side of the epipolar line (pose error); measured
    max_steps: int = 512  # samples along a segment (longer ones are sampled coarser)
    refine_radius: float = 0.75  # feature px: image-resolution ZNCC refinement within +/- ceil(this * stride) px
    patch_radius_px: int = 3  # ZNCC patch (2r+1)^2; measured
    # Eq. 11-12, calibrated on Replica office0 frames 0-3 (docs/matching.md): confidence 0.5 at
    # score 2.0, i.e. for a similarity near 1 the forward-backward and epipolar terms must add to 1.
    w_sim: float = 1.0  # Eq. 11
    w_fb: float = 1.0
    w_epi: float = 1.0
    sigma_fb_px: float = 0.5  # rho_fb = exp(-e_fb^2 / (2 sigma_fb^2)), e_fb in image px; measured
    sigma_epi_px: float = 0.5  # rho_epi = exp(-d_epi^2 / (2 sigma_epi^2)), d_epi in image px; measured
    gamma0: float = 1.5  # Eq. 12; measured
    gamma1: float = 2.5
    thin_spacing: float = 2.0  # feature px between kept pixels after blue-noise thinning


@dataclass
class TriangulationConfig:
    min_parallax_deg: float = 1.0
    max_reproj_px: float = 2.0


@dataclass
class SeedingConfig:
    alpha_min: float = 0.1  # Eq. 14
    alpha_max: float = 0.9
    # Poisson-disk radius in units of the local pixel footprint (depth / focal at the reference view):
    # the seed spacing, at least the matcher's thinning spacing in image pixels
    poisson_radius_px: float = 1.0
    # Eq. 13 tangential scale s_perp in Poisson radii (measured, experiments/results/matching.md)
    tangential_scale: float = 0.8
    # plane fit (§4.5): triangulated neighbours within this many pixel footprints; the patch must be
    # wide against the depth noise (~2 footprints at 0.3 px and 10 deg parallax; measured,
    # experiments/results/matching.md).  With fewer than the minimum the normal is the viewing
    # direction (3 define a plane; 6 keep one noisy neighbour from tilting it)
    plane_radius_px: float = 8.0
    plane_min_neighbours: int = 6
    # Eq. 13 axial scale: floor of the per-point pixel-noise estimate (sub-pixel matching accuracy),
    # and the clip of s_parallel relative to s_perp (a flat disc at best, never a needle)
    min_residual_px: float = 0.25
    axial_min_ratio: float = 0.1
    axial_max_ratio: float = 1.0
    # where a keyframe gets seeds: pixels the map covers with less accumulated opacity than this, or
    # whose map depth is off the seed's by more than covered_depth_tol (relative)
    covered_alpha: float = 0.5
    covered_depth_tol: float = 0.05
    # RGB-D: triangulated seeds whose reference-view depth is off the measured depth by more than this
    # (relative) are dropped (wrong matches, low parallax); the depth fill covers them; 0 = off
    depth_consistency_tol: float = 0.05
    # RGB-D: also seed from the measured depth where the map still does not cover the keyframe after
    # the triangulated seeds (plain walls have no matches); the first keyframe always is (mono: at
    # matching.scene_depth_m)
    depth_fill: bool = True
    # RGB-D: pixels without measured depth that no seed covers (windows, far field, dark surfaces: they
    # render black) get seeds on a layer at this depth, beyond the sensor's range; 0 = off
    far_layer_m: float = 0.0
    depth_stride: int = 2  # px between depth seeds (experiments/results/slam.md: 4 -> 2 -> 1)
    # RGB-D: depth seeds also where nothing was measured, up to this many px from a measurement, at the
    # farthest nearby measured depth (kernels/seeding.py: extrapolate_depth_step): the colour border a
    # registered depth camera does not see (18 % of every 7-Scenes frame), shadows, glass; 0 = off.
    # H100, 7-Scenes, 4 seeds: +1.0-1.3 dB compensated held out, +0.5 raw, +1.1 on keyframes, same ATE,
    # 1.4x the Gaussians, 14 % fewer frames/s; the office (depth everywhere) unchanged
    # (experiments/results/fidelity.md, session 17)
    depth_extrapolate_px: int = 64
    # RGB-D: where the keyframe has detail (grey-level gradient magnitude, central differences, at least
    # detail_min_gradient per pixel), depth seeds also at this finer stride (px); 0 = off.  H100 office:
    # +1.2 dB held out, 1.4x the Gaussians (session 10, 17, 18)
    detail_stride: int = 1
    detail_min_gradient: float = 0.03
    # RGB-D: a tracked frame that is not a keyframe also gets measured-depth seeds where the map does
    # not cover it, when more than this fraction of its pixels is uncovered (new surface shows up
    # between keyframes; seen by no keyframe it would stay a hole); negative = off
    frame_fill_min_uncovered: float = 0.002
    depth_max_rel_jump: float = 0.05  # skip depth seeds on discontinuities (second difference / depth)


@dataclass
class MappingConfig:
    # K_m, per keyframe: Table 1 has 60 steps over the whole window; 120 steps of one view each fit
    # better at 40 % of the renders (H100, 3 seeds: office +0.2 dB, 7-Scenes +0.7 dB, same ATE,
    # +15-23 % frames/s; experiments/results/perf.md); 150 since `history` takes a fifth of them
    iters: int = 150
    # after each frame that is not a keyframe, this many more iterations over the current window: the
    # map keeps improving between keyframes (with asynchronous mapping this would be free); 0 = off
    frame_iters: int = 0
    # keyframe work (matching, seeding, window mapping, merge / prune) and frame_iters in a worker thread
    # while tracking goes on against the latest published map (supplement §3.2); false: each keyframe
    # is mapped before the next frame is tracked (deterministic: tests, CI, the CPU)
    asynchronous: bool = False
    # asynchronous: keyframes that may wait for the worker besides the one it maps before tracking waits
    # (0: tracking waits for each keyframe's mapping, as in the synchronous mode, with frame fills and
    # frame_iters still beside it; more: lower latency, a map further behind the camera).  timing=live
    # sets 2: with 1 the frame that became a keyframe waited 31-37 ms (median, H200, 7-Scenes) for the
    # previous keyframe's mapping to end (perf.md, session 32)
    async_queue: int = 1
    # asynchronous: frame fills (seeding.frame_fill_min_uncovered) that may wait for the worker; a frame
    # that wants a fill while this many wait or run gets none.  0: no bound.  Measured (H200, perf.md):
    # with 2 (the default until session 35) the office at 30 Hz skipped 70 % of its fills and tracked
    # 0.39-0.40 cm, 35.9-36.4 dB compensated, against 0.35-0.37 cm and 37.0-37.4 dB unbounded (synchronous at
    # the camera's rate: 0.34-0.36 cm), 7-Scenes at 60 Hz keeping its pace either way (3 runs each).  Unbounded,
    # frames handed over faster than the worker fills them pile up: 457 fills waiting in the unpaced 2,000-frame
    # office at 640x360, 2.4 GiB of frame copies, keyframes mapped 4.3 s late.  32 is about a second at 30 Hz
    # and 420 MB of frames at 1200x680: the paced 2,000-frame run peaked at 29 waiting (its start), 16 later.
    # With 32 the office at 30 Hz tracks as unbounded; a 60 Hz camera on a slower machine keeps pace with 8
    # (7-Scenes, session 36: 3 of 3 runs against 2 of 6 with 32; the office then 0.39-0.40 cm against 0.35-0.37)
    fill_queue: int = 32
    # asynchronous: the map is published once more during a keyframe's job, after this many iterations of
    # its window's mapping (0: right after its seeding, before any: its seeds and the frame fills' that
    # join the map with it), so tracking sees the new surface before the whole mapping ends (the live
    # office: about 10 frames later); -1: only at the job's end.  The extra version costs the next tracked
    # frame its graphs' capture (a new map size).  0 on an H200, timing=live (perf.md, sessions 30-31, as
    # mapping.publish_seeds): the office at 30 Hz 0.35-0.40 cm against 0.39-0.43 and +0.5 dB compensated,
    # pace kept (3 runs each); 7-Scenes at 60 Hz 0.2-0.4 cm worse in three pairs (the unmapped Kinect seeds).
    # 15 (timing=live; session 33, 3 runs each): the office 0.36-0.43 cm against 0.43-0.59 and 36.2-36.4 dB
    # compensated against 34.9-36.2; 30: 0.40-0.44 cm; 7-Scenes with 15: 4.28-4.31 cm against 4.24-4.29
    publish_after: int = -1
    # asynchronous: what of the initial window tracking waits for before the next frame.  "window": every
    # initial keyframe's mapping, as in the synchronous mode; "first": the first keyframe's mapping only, the
    # window's other keyframes mapped beside tracking as later keyframes are (the frames track against the
    # first keyframe's map until the worker publishes the next version); "seeds": the first keyframe's
    # seeds only (published before its mapping; the frames after track against them until its mapping is
    # published).  Beside tracking, an initial keyframe's mapping ends at min_iters once as many later
    # keyframes wait for the worker as async_queue lets wait before tracking does.  A 60 Hz camera does not
    # wait: 7-Scenes' window took 1.2-1.3 s on an H200, "first" 0.2-0.3 s (perf.md, sessions 31-32)
    init_wait: str = "window"
    # asynchronous: a keyframe's window mapping ends after this many iterations (instead of `iters`) when
    # the next keyframe already waits for the worker, so mapping keeps pace with the camera and tracking
    # does not wait for it; 0: every keyframe gets `iters`
    min_iters: int = 0
    # after the last frame (SLAM.finish), this many more iterations over windows of `window` keyframes
    # drawn from every keyframe of the run (host copies keep those the buffer evicted); 0 = off
    final_iters: int = 0
    window: int = 5  # keyframes in the sliding window (Table 1)
    # views of the window rendered per mapping iteration, a fresh random subset each time (0: every view,
    # Table 1's joint window step); fewer views make an iteration cheaper in proportion
    views_per_iter: int = 1
    # With one view per iteration, each window view's mapping step runs as a captured graph (a CUDA
    # graph on a GPU, Warp's CPU graph on the CPU): eagerly the first time a view is rendered in a
    # window's mapping (its render sizes the renderer for it), captured the second, replayed after; one
    # launch instead of about 30 per step.  auto: on on CUDA devices (not with asynchronous mapping,
    # densification or mapping.lr_exposure), off on the CPU; on / off force it.
    graph: str = "auto"
    # each view a mapping iteration renders is, with this probability, an older keyframe (outside the
    # window) drawn at random instead of a window view, as MonoGS and SplaTAM do: each window is
    # fitted and left, and later windows move the Gaussians earlier keyframes share; 0 = off.  With
    # iters 150 (the window keeps its 120 on average): H100, 7-Scenes +1.5 dB compensated held-out
    # PSNR, +1.9 dB on keyframes, same ATE (6 seeds); office +0.75 dB, 6 % fewer frames/s
    # (experiments/results/fidelity.md, session 14).  At 120 iterations 7-Scenes tracking suffered.
    # 0.5 (the window keeps 75 on average) against 0.2: later windows undid up to 8 dB of earlier
    # ones' fit; H200, 3 runs each (session 30): 7-Scenes +0.4 dB raw / +0.55 compensated held out,
    # +0.7 on keyframes, office +0.15 / +0.35, same ATE; in live mode the same gains, pace kept
    history: float = 0.5
    # older keyframes kept on the device for it (those the keyframe buffer evicted; when full, a
    # uniform sample of all of them, reservoir sampling), besides the buffer's own outside the window
    history_size: int = 32
    init_iters: int = 1050  # initialization (Table 1)
    init_window: int = 5  # frames of the initial window (Table 1)
    lr_color: float = 2e-3  # Table 1 (the DC colour)
    # the higher SH bands at this fraction of lr_color (3DGS's feature_rest rate, 1/20): fitted at the
    # DC's rate they explain the window's views by view dependence that other views do not share
    lr_color_rest_factor: float = 0.05
    lr_opacity: float = 2e-3  # Table 1
    lr_position: float = 1e-3  # Table 1 (metres)
    lr_rotation: float = 1e-3  # Table 1
    lr_scale: float = 1e-3  # not in Table 1: the position/rotation rate (log scale)
    lr_final_factor: float = 0.01  # cosine decay to this fraction of the base rate within a window
    # Adam on the exposure (g, b) of Eq. 3 of each window keyframe, with the map (the first keyframe's
    # stays the identity: the gauge of the map's colour); 0: the exposures stay the tracker's
    lr_exposure: float = 0.0
    adam_beta1: float = 0.9  # Table 1
    adam_beta2: float = 0.999
    lambda_dssim: float = 0.2  # Table 1: L1 + lambda_dssim (1 - SSIM)
    grad_clip: float = 1.0  # Table 1: global gradient-norm clipping
    # RGB-D: depth L1 (per metre) against the colour L1 (per channel).  0.3 (was 1): the colour steers the
    # Gaussians more (H200, 4-5 runs each: office +0.45 dB raw and compensated, ATE 0.41 -> 0.37 cm;
    # 7-Scenes' colour and ATE within their spread, its depth L1 against the Kinect's depth 3.9 -> 4.7 cm;
    # experiments/results/fidelity.md, session 27)
    depth_weight: float = 0.3
    robust_scale: float = 0.25  # Cauchy scale of the per-pixel weights (mean |residual| per channel); <= 0: off
    # regularizer (§4.5, coefficients fixed for all sequences)
    reg_elongation: float = 1e-2  # weight of relu(log(s_max / s_mid) - log(max_anisotropy))^2
    max_anisotropy: float = 10.0
    reg_opacity: float = 1e-3  # weight of relu(|opacity logit| - max_abs_opacity_logit)^2
    max_abs_opacity_logit: float = 6.0
    reg_anchor: float = 1.0  # weight of |mu - mu_EMA|^2 (m^2)
    ema_eta: float = 0.1  # Eq. 15
    # maintenance after each keyframe (§4.5)
    opacity_cull: float = 0.05  # Table 1
    max_scale_m: float = 0.5  # prune: largest axis standard deviation above this
    min_obs: int = 3  # prune hidden Gaussians only once seen in this many renders ...
    min_visibility_ratio: float = 0.1  # ... of which fewer than this fraction contributed to a pixel
    merge_footprint_px: float = 0.5  # merge: projected centres and radii closer than this (0: no merging)
    merge_color_diff: float = 0.05  # ... and colours closer than this (per channel)
    # at most this many Gaussians (bounded memory; 0 = no cap): seedings that would exceed it keep their
    # most confident seeds, and the maintenance drops the least visible Gaussians down to
    # cap_headroom x the cap, leaving room for the next keyframe's seeds
    max_gaussians: int = 0
    cap_headroom: float = 0.9


@dataclass
class DensifyConfig:
    """Residual-driven densification of ``method=baseline`` (supplement Table 2; 3DGS's adaptive
    density control, ``rgs_warp.densification``); ``method=rgs`` does not use it.  The iteration is
    the cumulative number of mapping iterations of the run (``Mapper.total_iters``).  Opacity culling
    at each densification step uses ``mapping.opacity_cull`` (Table 1, shared by both methods)."""

    grad_threshold: float = 2e-4  # Table 2: mean screen-space (NDC) gradient norm that densifies
    start: int = 500  # Table 2: densify at iterations start < it < stop ...
    stop: int = 15000
    interval: int = 100  # ... that are multiples of this (Tables 1-2)
    opacity_reset_interval: int = 3000  # Table 1; 0 = never
    # 3DGS resets to 0.01 and culls at 0.005; our culling is Table 1's 0.05, so the reset keeps 3DGS's
    # factor 2 above it (a reset to 0.01 would put every Gaussian under the cull: the map is wiped)
    opacity_reset_value: float = 0.1
    percent_dense: float = 0.01  # 3DGS: clone if the largest scale <= this x scene_extent_m, else split
    prune_scale_fraction: float = 0.1  # 3DGS: after the first reset, prune largest scale > this x extent
    # the unit of the two fractions above (3DGS: 1.1 x the cameras' spread, meaningless for a trajectory
    # that grows; MonoGS fixes cameras_extent = 6 m for indoor SLAM, as here)
    scene_extent_m: float = 6.0


@dataclass
class BootstrapConfig:
    """Monocular two-view bootstrap (``rgs_warp.bootstrap``; mode=mono only)."""

    enabled: bool = True  # False: the first keyframe is a plane at matching.scene_depth_m
    # Search.  A coarse pass matches every coarse_step-th feature pixel over the whole image; the
    # median of its distinctive matches' displacements (the global image motion, mostly camera
    # rotation) centres every query's window.  The window then only has to hold what that misses:
    # the parallax and the non-uniform part of the rotational flow (a 10 deg pan moves the image
    # centre by 0.18 f and the border of a 90 deg field of view by 0.43 f).
    coarse_step: int = 4  # feature px between the coarse pass's queries (0: no coarse pass)
    search_radius: int = 12  # feature px, window half-width around the query's moved cell
    ratio_exclusion: int = 2  # feature px: the second best is sought outside this of the best
    min_similarity: float = 0.5  # Eq. 10 of the best match
    max_ratio: float = 0.9  # Lowe's ratio of descriptor distances, best / second best
    max_fb_px: float = 1.0  # forward-backward error, image px (mutual consistency)
    refine_radius_px: int = 3  # image-resolution ZNCC refinement within +/- this (0: parabola only)
    patch_radius_px: int = 3  # ZNCC patch (2r+1)^2, as the DenseMatcher's
    # Relative pose: OpenCV's findEssentialMat (USAC_DEFAULT, fixed internal seed: the same pair always
    # gives the same pose) and recoverPose (docs/decisions.md, "Monocular essential matrix")
    ransac_iters: int = 1000  # USAC's upper bound; it stops earlier once ransac_confidence is reached
    # USAC stops when a better hypothesis is this unlikely to be missed, judging by the inlier count.  At
    # small baselines wrong poses also fit most matches: up to 0.999999 it stopped on office0 320x180
    # frames 0 / 8 with a pose 61 deg off in translation direction and 4 % fewer inliers (0.8 deg here)
    ransac_confidence: float = 0.999999999
    ransac_threshold_px: float = 1.0  # Sampson error of an inlier, image px
    min_inliers: int = 100  # fewer: the pose is not trusted
    # Below this fraction of the selected matches the pose explains too little of the image to be
    # trusted.  Measured on frame 0 with frames 1-30 of office0 / room0 (160x90, 320x180) and frames
    # 2-60 (every 2nd) of 7-Scenes redkitchen (160x120, 320x240): poses within 0.5 deg of the truth
    # had 0.81-1.0; room0 frames 18, 21 and 23-28 at 320x180 have 0.57-0.79 and are 7-27 deg off in
    # translation direction.
    min_inlier_ratio: float = 0.8
    # Of the inliers, those in front of both cameras for the chosen (R, t).  On the pairs above, every
    # accepted pose within 10 deg of the truth had 0.993-1.0; room0's wrong poses (26-32 deg off in
    # translation direction, fitting its matches as well as the truth does) had 0.93-0.965 and 0.9
    # let both sizes start 31 deg off.  Not caught: office0 frames 15-26 (36-71 deg of rotation from
    # frame 0) pass 10-52 deg off at 0.99-1.0; the caller stops at frame 6 there.
    min_cheirality_ratio: float = 0.98
    min_parallax_deg: float = 2.0  # median parallax angle of the inliers; below: wait for a later frame
    # Points: kept when their reprojection error (RMS over both views) and parallax allow a depth
    max_reproj_px: float = 1.0
    min_point_parallax_deg: float = 0.5
    # Waiting: the SLAM tries frames 1, 2, ... against frame 0 and gives up after this many, falling
    # back to a plane at matching.scene_depth_m (the gauge: median depth of the first points).  7-Scenes
    # redkitchen starts slowly (33 mm in 24 frames): frame 0 against 24 / 28 / 32 / 36 has a median
    # parallax of 0.7 / 1.0 / 1.3 / 1.6 deg, frame 40 passes (2.7 deg); with 30 the H100 run fell back to
    # the plane and lost 470 of its 500 frames, with 60 it lost 6-26 (experiments/results/mono.md).  The
    # synthetic office passes at frame 6
    max_wait_frames: int = 60


@dataclass
class KeypointsConfig:
    """Monocular keypoint odometry (``rgs_warp.keypoint_odometry``; mode=mono).  Defaults as measured in
    experiments/results/mono.md, "Keypoint front end with a local bundle adjustment" (office, first 150
    frames, its own two-view start: 0.40 cm Sim(3) ATE at 1200x680, 1.13 cm at 640x360; 300 frames at
    640x360: 16.3 cm; on session 31's package versions, solving about the cameras: 2.75 cm over 150 frames
    at 640x360 and 20-23 cm over 300 from four starts: the result hangs on float-level differences).  Pixel
    values are for 640 px of image width and scale with the width (not below half)."""

    # Tracks.  Shi-Tomasi corners kept (at 640 px width) and their least distance: the measured setting;
    # new corners every frame once fewer than redetect_fraction of them are tracked, so that new tracks
    # have parallax by the next keyframe (with kf_min_landmarks: 4.9 -> 1.4 cm, mono.md)
    max_features: int = 600
    min_distance_px: float = 12.0
    redetect_fraction: float = 0.8
    # KLT's forward-backward limit; 2 px instead changed little (4.3 -> 4.5 cm, mono.md)
    fb_px: float = 0.5
    # Pose.  PnP RANSAC's inlier limit, and the fewest inliers for a pose (else rotation-only)
    pnp_px: float = 2.0
    min_inliers: int = 15
    # A landmark track whose reprojection after the frame's pose exceeds this is dropped (it slides on a
    # stripe or an occlusion edge); 0: the pnp_px limit only, measured worse (6.3 against 4.3 cm, mono.md)
    residual_px: float = 1.5
    # A PnP pose further than this from the motion model's prediction is refused (rotation-only instead):
    # max_dev_deg of rotation, or a camera centre off by more than max_dev_step times the predicted step
    # plus max_dev_depth times the median scene depth
    max_dev_deg: float = 5.0
    max_dev_step: float = 4.0
    max_dev_depth: float = 0.01
    rotation_min_tracks: int = 20  # fewer tracks than this for a rotation-only pose: the frame is lost
    # Landmarks: a track seen in >= 2 keyframes is triangulated from all of them once its rays span
    # min_parallax_deg, kept when every reprojection is within max_reproj_px (0.7-1.0 deg did not help
    # at frames 205-235 of 300, mono.md)
    min_parallax_deg: float = 1.5
    max_reproj_px: float = 2.0
    # Keyframes: when fewer than kf_tracked_fraction of the last keyframe's tracks remain, fewer than
    # kf_landmark_fraction of its usable landmarks or fewer than kf_min_landmarks, when the median
    # parallax to it exceeds kf_parallax_deg, or the pose was rotation-only; at least kf_min_gap frames
    # apart
    kf_tracked_fraction: float = 0.7
    kf_landmark_fraction: float = 0.6
    kf_min_landmarks: int = 100
    kf_parallax_deg: float = 2.0
    kf_min_gap: int = 1
    # Local BA over the last ba_window keyframes' poses and their landmarks (0: none; without it the
    # scale drifted 0.82 -> 1.57 over 150 frames, 5.8 cm, mono.md), with up to ba_held_max older keyframes
    # that see them held (gauge and scale); Huber loss of ba_huber_px, at most ba_iters evaluations.  The
    # synthetic office wants it tight (1 px; 2-3 px: 150 frames 1.13 -> 1.3 cm at 640x360, 0.78 -> 0.84 at
    # 1200x680 from the SLAM's start); the real 7-Scenes frames wide (its config: 2.5 px, 20.3 -> 8.8 cm over
    # 500 frames from the SLAM's start; 2 and 3 alike, 1.5 worse; experiments/results/mono.md, session 29)
    ba_window: int = 8
    ba_held_max: int = 12
    ba_huber_px: float = 1.0
    ba_iters: int = 30


@dataclass
class EvalConfig:
    every: int = 5  # §3: photometric metrics on every 5th frame, keyframes excluded
    # convergence.json: mean PSNR of the window keyframes every this many mapping iterations during
    # the initialization (and always after each keyframe's mapping); 0 = only after each keyframe
    convergence_every: int = 50
    # LPIPS needs local weights (nothing is downloaded): torchvision's AlexNet
    # (alexnet-owt-7be5be79.pth) and LPIPS v0.1's linear layers (alex.pth; may stay empty when the
    # `lpips` package, which ships them, is installed). Without them LPIPS is reported as n/a.
    lpips_alexnet_path: str = ""
    lpips_linear_path: str = ""


@dataclass
class ExportConfig:
    # mesh.ply in the run folder: the TSDF fusion (voxel_m) of the map's depth and colour rendered at
    # every keyframe, the surface the mesh metrics score (also: python -m rgs_warp.export RUN_DIR)
    mesh: bool = False
    voxel_m: float = 0.01


@dataclass
class Config:
    device: str = "auto"  # auto = cuda:0 when Warp sees a GPU, else cpu
    mode: str = "rgbd"  # rgbd | mono
    # rgs: dense seeding at every keyframe + merge / prune; baseline: a dense start at the first
    # keyframe, then residual-driven densification (section `densify`) and depth seeds in uncovered
    # regions only.  Set by the method group.
    method: str = "rgs"
    seed: int = 0
    data_root: str = ""  # default: $RGS_DATA, else the current directory
    output_dir: str = "runs"
    run_name: str = ""  # default: <dataset>-<date>-<time>; a folder of that name that exists gets -2, -3, ...
    overwrite: bool = False  # true: an existing run folder of run_name is cleared and reused instead
    # a checkpoint every this many keyframes (the SLAM.save files and the run's state, written
    # atomically), from which `python -m rgs_warp.slam resume=RUN_DIR` continues a stopped run; 0 = off
    checkpoint_every: int = 10
    # the web viewer (rgs_warp.view, needs the `viewer` extra): served on viewer_port during the run
    # (0: a free port; the console gives the URL), kept up after it until Ctrl-C
    viewer: bool = False
    viewer_port: int = 8080
    # the command line on the CPU: a synthetic scene without any size key (CPU_SIZE_KEYS) given runs
    # at CPU_SIZED's sizes (README, quick start); false: the sizes as configured
    cpu_sized: bool = True
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


CHOICES = {
    "mode": ("rgbd", "mono"),
    "method": ("rgs", "baseline"),
    "tracking.brightness": ("gain", "affine", "off"),
    "tracking.exposure_from": ("map", "keyframes"),
    "keyframes.covisibility": ("pixels", "reprojected"),
    "tracking.motion_check": ("auto", "on", "off"),
    "tracking.relocalize": ("auto", "on", "off"),
    "tracking.graph": ("auto", "on", "off"),
    "mapping.graph": ("auto", "on", "off"),
    "tracking.colour_per_opacity": ("auto", "on", "off"),
    "mapping.init_wait": ("window", "first", "seeds"),
    "dataset.type": ("replica", "tum", "7scenes", "synthetic", "realsense"),
}


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


# The ZNCC refinement's patch radius (matching.patch_radius_px, bootstrap.patch_radius_px): each query
# keeps its (2r+1)^2 patch in a fixed-size local vector (kernels/matching.py, query_patch)
MAX_PATCH_RADIUS = 4
PATCH_RADIUS = Bound(0, MAX_PATCH_RADIUS)
POSITIVE = Bound(lo=0, lo_open=True)
NON_NEGATIVE = Bound(lo=0)
AT_LEAST_1 = Bound(lo=1)
FRACTION = Bound(0, 1)
ADAM_BETA = Bound(0, 1, hi_open=True)  # beta = 1 divides by zero in Adam's bias correction
SEED = Bound(0, 2**31 - 1)  # NumPy's generators refuse negative seeds

# Checked after every load (``check_config``), before anything runs: a key out of its range fails with
# its name instead of a ZeroDivisionError, an SSIM error or a run at 35 m ATE.  Every float must also be
# finite.  Keys not listed are free (e.g. tracking.tau_grad and seeding.frame_fill_min_uncovered, where
# <= 0 means off; tracking.min_valid_ratio > 1 loses every frame on purpose in a test).  Rates may be 0
# in mapping (that parameter stays fixed; mapping.lr_exposure = 0 is off) but not in tracking.
CONSTRAINTS: dict[str, Bound] = {
    "seed": SEED,
    "dataset.stride": AT_LEAST_1,
    "dataset.start": NON_NEGATIVE,
    "dataset.max_frames": AT_LEAST_1,
    "dataset.downscale": AT_LEAST_1,
    "dataset.prefetch": NON_NEGATIVE,
    "dataset.colour_intrinsics": POSITIVE,
    "dataset.max_dt": POSITIVE,
    "dataset.width": AT_LEAST_1,
    "dataset.height": AT_LEAST_1,
    "dataset.n_frames": AT_LEAST_1,
    "dataset.fps": AT_LEAST_1,
    "dataset.playback_fps": NON_NEGATIVE,
    "dataset.depth_noise_m": NON_NEGATIVE,
    "dataset.seed": SEED,
    "render.sh_degree": Bound(0, 3),
    "render.background": FRACTION,
    "tracking.iters": AT_LEAST_1,
    "tracking.lr": POSITIVE,
    "tracking.adam_beta1": ADAM_BETA,
    "tracking.adam_beta2": ADAM_BETA,
    "tracking.adam_eps": POSITIVE,
    "tracking.tau_alpha": FRACTION,
    "tracking.depth_weight": NON_NEGATIVE,
    "tracking.depth_slope_tau": NON_NEGATIVE,
    "tracking.brightness_min_alpha": FRACTION,
    "tracking.downscale": AT_LEAST_1,
    "tracking.tile_stride": NON_NEGATIVE,
    "tracking.direct_levels": NON_NEGATIVE,
    "tracking.direct_iters": AT_LEAST_1,
    "tracking.min_valid_ratio": NON_NEGATIVE,
    "tracking.max_residual": POSITIVE,
    "tracking.depth_edge_spread": NON_NEGATIVE,
    "tracking.motion_min_ratio": FRACTION,
    "tracking.motion_min_step_m": NON_NEGATIVE,
    "tracking.motion_max_ratio": NON_NEGATIVE,
    "tracking.motion_max_jump_m": POSITIVE,
    "tracking.motion_max_jump_deg": POSITIVE,
    "tracking.motion_min_rotation_deg": NON_NEGATIVE,
    "keyframes.iou_threshold": FRACTION,
    "keyframes.alpha_threshold": FRACTION,
    "keyframes.min_translation_m": NON_NEGATIVE,
    "keyframes.min_rotation_deg": NON_NEGATIVE,
    "keyframes.buffer_size": Bound(lo=2),  # triangulation needs pairs
    "keyframes.max_loss_ratio": NON_NEGATIVE,
    "keyframes.depth_tol": NON_NEGATIVE,
    "matching.classic_stride": AT_LEAST_1,
    "matching.n_neighbours": AT_LEAST_1,
    "matching.max_view_angle_deg": POSITIVE,
    "matching.target_parallax_deg": POSITIVE,
    "matching.scene_depth_m": POSITIVE,
    "matching.min_depth_m": POSITIVE,
    "matching.max_depth_m": POSITIVE,
    "matching.depth_rel_tol": NON_NEGATIVE,
    "matching.min_search_radius": NON_NEGATIVE,
    "matching.band": NON_NEGATIVE,
    "matching.max_steps": AT_LEAST_1,
    "matching.refine_radius": NON_NEGATIVE,
    "matching.patch_radius_px": PATCH_RADIUS,
    "matching.w_sim": NON_NEGATIVE,
    "matching.w_fb": NON_NEGATIVE,
    "matching.w_epi": NON_NEGATIVE,
    "matching.sigma_fb_px": POSITIVE,
    "matching.sigma_epi_px": POSITIVE,
    "matching.thin_spacing": POSITIVE,
    "triangulation.min_parallax_deg": NON_NEGATIVE,
    "triangulation.max_reproj_px": POSITIVE,
    "seeding.alpha_min": FRACTION,
    "seeding.alpha_max": FRACTION,
    "seeding.poisson_radius_px": POSITIVE,
    "seeding.tangential_scale": POSITIVE,
    "seeding.plane_radius_px": POSITIVE,
    "seeding.plane_min_neighbours": Bound(lo=3),  # three points define a plane
    "seeding.min_residual_px": NON_NEGATIVE,
    "seeding.axial_min_ratio": POSITIVE,
    "seeding.axial_max_ratio": POSITIVE,
    "seeding.covered_alpha": FRACTION,
    "seeding.covered_depth_tol": NON_NEGATIVE,
    "seeding.depth_consistency_tol": NON_NEGATIVE,
    "seeding.far_layer_m": NON_NEGATIVE,
    "seeding.depth_stride": AT_LEAST_1,
    "seeding.depth_extrapolate_px": NON_NEGATIVE,
    "seeding.detail_stride": NON_NEGATIVE,
    "seeding.detail_min_gradient": NON_NEGATIVE,
    "seeding.depth_max_rel_jump": NON_NEGATIVE,
    "mapping.iters": NON_NEGATIVE,
    "mapping.frame_iters": NON_NEGATIVE,
    "mapping.final_iters": NON_NEGATIVE,
    "mapping.async_queue": NON_NEGATIVE,
    "mapping.fill_queue": NON_NEGATIVE,
    "mapping.publish_after": Bound(lo=-1),  # -1: off
    "mapping.min_iters": NON_NEGATIVE,
    "mapping.views_per_iter": NON_NEGATIVE,
    "mapping.window": AT_LEAST_1,
    "mapping.history": FRACTION,
    "mapping.history_size": NON_NEGATIVE,
    "mapping.init_iters": AT_LEAST_1,
    "mapping.init_window": AT_LEAST_1,
    "mapping.lr_color": NON_NEGATIVE,
    "mapping.lr_color_rest_factor": NON_NEGATIVE,
    "mapping.lr_opacity": NON_NEGATIVE,
    "mapping.lr_position": NON_NEGATIVE,
    "mapping.lr_rotation": NON_NEGATIVE,
    "mapping.lr_scale": NON_NEGATIVE,
    "mapping.lr_final_factor": NON_NEGATIVE,
    "mapping.lr_exposure": NON_NEGATIVE,
    "mapping.max_gaussians": NON_NEGATIVE,  # 0 = no cap
    "mapping.cap_headroom": Bound(0, 1, lo_open=True),
    "checkpoint_every": NON_NEGATIVE,  # 0 = no checkpoints
    "viewer_port": Bound(0, 65535),  # 0 = a free port
    "export.voxel_m": POSITIVE,
    "mapping.adam_beta1": ADAM_BETA,
    "mapping.adam_beta2": ADAM_BETA,
    "mapping.lambda_dssim": NON_NEGATIVE,
    "mapping.grad_clip": POSITIVE,
    "mapping.depth_weight": NON_NEGATIVE,
    "mapping.reg_elongation": NON_NEGATIVE,
    "mapping.max_anisotropy": AT_LEAST_1,
    "mapping.reg_opacity": NON_NEGATIVE,
    "mapping.max_abs_opacity_logit": POSITIVE,
    "mapping.reg_anchor": NON_NEGATIVE,
    "mapping.ema_eta": FRACTION,
    "mapping.opacity_cull": FRACTION,
    "mapping.max_scale_m": POSITIVE,
    "mapping.min_obs": NON_NEGATIVE,
    "mapping.min_visibility_ratio": FRACTION,
    "mapping.merge_footprint_px": NON_NEGATIVE,
    "mapping.merge_color_diff": NON_NEGATIVE,
    "densify.grad_threshold": POSITIVE,
    "densify.start": NON_NEGATIVE,
    "densify.stop": NON_NEGATIVE,
    "densify.interval": AT_LEAST_1,
    "densify.opacity_reset_interval": NON_NEGATIVE,
    "densify.opacity_reset_value": Bound(0, 1, lo_open=True, hi_open=True),  # an opacity logit must exist
    "densify.percent_dense": POSITIVE,
    "densify.prune_scale_fraction": POSITIVE,
    "densify.scene_extent_m": POSITIVE,
    "bootstrap.coarse_step": NON_NEGATIVE,
    "bootstrap.search_radius": AT_LEAST_1,
    "bootstrap.ratio_exclusion": NON_NEGATIVE,
    "bootstrap.max_ratio": POSITIVE,
    "bootstrap.max_fb_px": NON_NEGATIVE,
    "bootstrap.refine_radius_px": NON_NEGATIVE,
    "bootstrap.patch_radius_px": PATCH_RADIUS,
    "bootstrap.ransac_iters": AT_LEAST_1,
    "bootstrap.ransac_confidence": Bound(0, 1, lo_open=True, hi_open=True),
    "bootstrap.ransac_threshold_px": POSITIVE,
    "bootstrap.min_inliers": Bound(lo=5),  # the five-point essential matrix
    "bootstrap.min_inlier_ratio": FRACTION,
    "bootstrap.min_cheirality_ratio": FRACTION,
    "bootstrap.min_parallax_deg": NON_NEGATIVE,
    "bootstrap.max_reproj_px": POSITIVE,
    "bootstrap.min_point_parallax_deg": NON_NEGATIVE,
    "bootstrap.max_wait_frames": AT_LEAST_1,
    "keypoints.max_features": AT_LEAST_1,
    "keypoints.min_distance_px": POSITIVE,
    "keypoints.redetect_fraction": FRACTION,
    "keypoints.fb_px": POSITIVE,
    "keypoints.pnp_px": POSITIVE,
    "keypoints.min_inliers": Bound(lo=6),  # the LM refinement on the inliers needs six
    "keypoints.residual_px": NON_NEGATIVE,  # 0 = the pnp_px limit
    "keypoints.max_dev_deg": POSITIVE,
    "keypoints.max_dev_step": NON_NEGATIVE,
    "keypoints.max_dev_depth": NON_NEGATIVE,
    "keypoints.rotation_min_tracks": Bound(lo=3),  # Kabsch needs three bearings
    "keypoints.min_parallax_deg": NON_NEGATIVE,
    "keypoints.max_reproj_px": POSITIVE,
    "keypoints.kf_tracked_fraction": FRACTION,
    "keypoints.kf_landmark_fraction": FRACTION,
    "keypoints.kf_min_landmarks": NON_NEGATIVE,
    "keypoints.kf_parallax_deg": POSITIVE,
    "keypoints.kf_min_gap": AT_LEAST_1,
    "keypoints.ba_window": NON_NEGATIVE,  # 0 = no local BA
    "keypoints.ba_held_max": Bound(lo=2),  # two held keyframes fix the gauge and the scale
    "keypoints.ba_huber_px": POSITIVE,
    "keypoints.ba_iters": AT_LEAST_1,
    "eval.every": AT_LEAST_1,
    "eval.convergence_every": NON_NEGATIVE,
}
# Pairs of keys whose first must not exceed the second, and why (appended to the message)
ORDERED_KEYS = (
    ("matching.min_depth_m", "matching.max_depth_m", ": they bound the epipolar search"),
    ("seeding.alpha_min", "seeding.alpha_max", ": Eq. 14's opacity range"),
    ("seeding.axial_min_ratio", "seeding.axial_max_ratio", ": the clip of Eq. 13's axial scale"),
    ("seeding.detail_stride", "seeding.depth_stride", ": detail seeds are the finer ones"),
    ("mapping.init_window", "mapping.init_iters", ": each initial frame gets init_iters // init_window iterations"),
    ("mapping.min_iters", "mapping.iters", ": a keyframe's window mapping may end early, not run longer"),
)
# The smallest images the pipeline runs on: mapping's SSIM has an 11x11 window (DSSIMLoss refuses
# 11 px and less; at 20x11 the office's map stayed empty, 22x12 ran: measured on CPU); tracking
# needs neighbours for its image gradients (Eq. 8).
MIN_IMAGE_PX = 16
MIN_TRACKING_PX = 4


def _config_value(cfg: Config, key: str):
    node = cfg
    for part in key.split("."):
        node = getattr(node, part)
    return node


def check_config(cfg: Config) -> Config:
    """``cfg`` if its values are usable (``CONSTRAINTS``, every float finite, and the relations
    between keys), else a ConfigError naming the key, its value and the range."""

    def walk(obj, prefix):
        for f in dataclasses.fields(obj):
            v = getattr(obj, f.name)
            if dataclasses.is_dataclass(v):
                yield from walk(v, prefix + f.name + ".")
            else:
                yield prefix + f.name, v

    for key, value in walk(cfg, ""):
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
    if cfg.mapping.min_iters > 0 and not cfg.mapping.asynchronous:
        raise ConfigError(
            f"mapping.min_iters ({cfg.mapping.min_iters}) applies to asynchronous mapping only: "
            "set mapping.asynchronous=true with it, or leave it at 0"
        )
    if cfg.mapping.publish_after >= 0 and not cfg.mapping.asynchronous:
        raise ConfigError(
            f"mapping.publish_after ({cfg.mapping.publish_after}) applies to asynchronous mapping only: set "
            "mapping.asynchronous=true with it, or leave it at -1"
        )
    if cfg.mapping.init_wait != "window" and not cfg.mapping.asynchronous:
        raise ConfigError(
            f"mapping.init_wait={cfg.mapping.init_wait} applies to asynchronous mapping only: set "
            "mapping.asynchronous=true with it, or leave it at window"
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


def _field_types(cls) -> dict[str, typing.Any]:
    return typing.get_type_hints(cls)


def _coerce(value, tp, key: str):
    origin = typing.get_origin(tp)
    args = typing.get_args(tp)
    if origin in (typing.Union, getattr(__import__("types"), "UnionType", typing.Union)):
        if value is None and type(None) in args:
            return None
        inner = [a for a in args if a is not type(None)]
        return _coerce(value, inner[0], key)
    if origin is tuple:
        if not isinstance(value, list | tuple):
            raise ConfigError(f"{key}: expected a list like [0, 0, 0], got {value!r}")
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(_coerce(v, args[0], key) for v in value)
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
        if value is None:
            return ""
        return str(value)
    raise ConfigError(f"{key}: unsupported type {tp}")


def _set_tree(obj, tree: dict, prefix: str = "") -> None:
    """Set the values of a nested dict on a dataclass tree, checking keys and types."""
    if not isinstance(tree, dict):
        raise ConfigError(f"{prefix.rstrip('.') or 'config'}: expected a mapping of keys, got {tree!r}")
    types = _field_types(type(obj))
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
    yes / no as booleans, which turned ``tracking.brightness=off`` into False."""


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
    # a section's file may also set keys of other sections for what it describes (a dataset's real
    # sensor wants other tracking settings): ``settings: {tracking: {tau_grad: 0.0}}``, applied after
    # the section itself; command-line keys still win
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
        # a copy cut short lacks the last sections; one lacking a section before others is from another
        # version of rgs_warp (a section added since)
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


def help_text() -> str:
    lines = ["Configuration groups (group=option):"]
    for group in GROUPS:
        lines.append(f"  {group}: {', '.join(group_options(group))}   (default: {DEFAULTS[group]})")
    lines.append("")
    lines.append("Keys (key=value; default shown):")

    def walk(obj, prefix):
        for f in dataclasses.fields(obj):
            v = getattr(obj, f.name)
            if dataclasses.is_dataclass(v):
                walk(v, prefix + f.name + ".")
            else:
                lines.append(f"  {prefix}{f.name} = {v!r}")

    walk(Config(), "")
    return "\n".join(lines)


# The command line's run of a synthetic scene on the CPU when the user set no size (README, quick start):
# the full default (240x136, 100 frames, 1050 initial mapping iterations) takes over half an hour on 2 cores.
# These values were measured to finish in under 3 minutes there, scene generation and kernel
# compilation on fresh caches included, and still track and map (experiments/results/perf.md, "The
# CPU-sized first run": 96x54 tracked worse, 2.3 cm; 30 frames reach a fast turn that 96x54 loses)
CPU_SIZED = {
    "dataset.width": 120,
    "dataset.height": 68,
    "dataset.max_frames": 25,
    "mapping.init_iters": 100,
    "mapping.iters": 15,
    "mapping.views_per_iter": 0,
    "mapping.window": 3,
}
# Keys that size a run: when the command line sets any of them, none of CPU_SIZED is applied (the user
# chose the size; CPU_SIZED's keys and the others that change how much is computed)
CPU_SIZE_KEYS = (
    *CPU_SIZED,
    "dataset.n_frames",
    "dataset.stride",
    "dataset.start",
    "dataset.downscale",
    "tracking.iters",
    "tracking.downscale",
    "mapping.init_window",
    "mapping.frame_iters",
    "mapping.final_iters",
)


def cpu_sized_overrides(cfg: Config, overrides, device: str) -> tuple[list[str], str]:
    """The ``key=value`` overrides that make the command line's run CPU-sized, and the message that
    says so, or ``([], "")``: only when ``device`` (resolved) is the CPU, the dataset is a synthetic
    scene (``cfg``, loaded from ``overrides``), ``cpu_sized`` is on and ``overrides`` set none of
    ``CPU_SIZE_KEYS``."""
    given = {item.split("=", 1)[0].strip() for item in overrides if "=" in item}
    if not device.startswith("cpu") or cfg.dataset.type != "synthetic" or not cfg.cpu_sized:
        return [], ""
    if given & set(CPU_SIZE_KEYS):
        return [], ""
    extra = [f"{k}={v}" for k, v in CPU_SIZED.items()]
    d, m, q = cfg.dataset, cfg.mapping, CPU_SIZED
    message = (
        f"No GPU ({device}): a CPU-sized run of synthetic/{d.name}: {q['dataset.width']}x{q['dataset.height']} "
        f"pixels, the first {q['dataset.max_frames']} of {d.n_frames} frames, "
        f"{q['mapping.init_iters']} initial and {q['mapping.iters']} per-keyframe mapping iterations "
        f"over {q['mapping.window']} keyframes (under 3 minutes on 2 cores).\n"
        f"The full run ({d.width}x{d.height}, {d.n_frames} frames, {m.init_iters} / {m.iters} mapping iterations; "
        f"over half an hour on 2 cores): add cpu_sized=false, or set any size yourself, e.g. "
        f"dataset.max_frames=40 (the rest then keeps its defaults)."
    )
    return extra, message


def resolve_device(name: str) -> str:
    """``device=auto``: ``cuda:0`` when Warp sees a GPU, else ``cpu``; any other name as given."""
    import warp as wp

    if name != "auto":
        return name
    return "cuda:0" if wp.is_cuda_available() else "cpu"
