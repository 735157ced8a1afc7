"""Render a synthetic sequence and write it in the Replica (NICE-SLAM) or TUM RGB-D layout."""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass
from pathlib import Path

import cv2
import numpy as np
import plyfile
import warp as wp
from tqdm import tqdm

from rgs_warp.datasets.synthetic.render import SceneRenderer
from rgs_warp.datasets.synthetic.scene import build_scene
from rgs_warp.datasets.synthetic.textures import linear_to_srgb
from rgs_warp.geometry import matrix_to_quat
from rgs_warp.types import Camera

REPLICA_DEPTH_SCALE = 6553.5
TUM_DEPTH_SCALE = 5000.0
_TUM_T0 = 1305031102.175304  # timestamps shaped like TUM's (Unix seconds)
_TUM_GT_RATE_HZ = 100.0  # TUM's motion-capture rate
_TUM_DEPTH_OFFSET_S = 0.012  # depth stamped up to this far from colour, as TUM's Kinect streams are
DEFAULT_EXPOSURE_DRIFT = 0.1
DEFAULT_MOTION_BLUR = 0.5


@dataclass(frozen=True)
class SyntheticConfig:
    """Everything that determines a generated sequence (the cache key hashes all of it).

    The whole scene trajectory is always covered: ``n_frames`` sets how densely it is sampled, hence
    the inter-frame motion (see ``docs``/the module report for the numbers).  Intrinsics left at None
    follow Replica's proportions: fx = fy = width / 2, principal point at the image centre
    (cx = (width - 1) / 2 in the project's pixel-centre convention).  ``exposure_drift`` and
    ``motion_blur`` also accept a bool (True: the default strength).
    """

    scene: str = "room0"
    width: int = 240
    height: int = 136
    fx: float | None = None
    fy: float | None = None
    cx: float | None = None
    cy: float | None = None
    n_frames: int = 100
    supersample: int = 3  # n x n jittered sub-pixels per pixel
    depth_noise_m: float = 0.0  # std of additive Gaussian depth noise
    exposure_drift: float = 0.0  # std of the log-gain random walk (0: off); bias std is a fifth of it
    motion_blur: float = 0.0  # exposure time as a fraction of the frame interval (0: off)
    motion_blur_samples: int = 5
    seed: int = 0

    def __post_init__(self):
        resolved = {
            "fx": self.width / 2.0,
            "fy": self.width / 2.0,
            "cx": (self.width - 1) / 2.0,
            "cy": (self.height - 1) / 2.0,
        }
        for k, v in resolved.items():
            object.__setattr__(self, k, float(v if getattr(self, k) is None else getattr(self, k)))
        for k, strength in (("exposure_drift", DEFAULT_EXPOSURE_DRIFT), ("motion_blur", DEFAULT_MOTION_BLUR)):
            v = getattr(self, k)
            object.__setattr__(self, k, (strength if v else 0.0) if isinstance(v, bool) else float(v))
        if self.n_frames < 2 or self.supersample < 1 or self.motion_blur_samples < 1:
            raise ValueError("need n_frames >= 2, supersample >= 1, motion_blur_samples >= 1")

    @property
    def camera(self) -> Camera:
        return Camera(self.fx, self.fy, self.cx, self.cy, self.width, self.height)


def default_device() -> str:
    return "cuda:0" if wp.is_cuda_available() else "cpu"


def _exposure_walk(cfg: SyntheticConfig, rng: np.random.Generator) -> np.ndarray:
    """(n, 2) gain and bias per frame: a mean-reverting (AR(1)) random walk, smooth from frame to frame."""
    out = np.tile([1.0, 0.0], (cfg.n_frames, 1))
    if cfg.exposure_drift <= 0:
        return out
    keep = 0.9
    state = np.zeros(2)
    scale = cfg.exposure_drift * np.array([1.0, 0.2]) * np.sqrt(1 - keep**2)
    for i in range(cfg.n_frames):
        state = keep * state + scale * rng.standard_normal(2)
        out[i] = np.exp(state[0]), state[1]
    return out


class SequenceRenderer:
    """One scene on one device; yields the frames of a ``SyntheticConfig`` (also used by the tests)."""

    def __init__(self, cfg: SyntheticConfig, device: str | None = None):
        self.cfg = cfg
        self.scene = build_scene(cfg.scene, cfg.seed)
        self.trajectory = self.scene.trajectory(cfg.seed)
        self.renderer = SceneRenderer(self.scene, device or default_device())
        self.times = np.linspace(0.0, self.trajectory.duration, cfg.n_frames)
        self.poses = self.trajectory.poses(self.times)
        self.exposure = _exposure_walk(cfg, np.random.default_rng([cfg.seed, 1]))

    def render(self, i: int, depth_time: float | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Frame ``i``: sRGB float32 HxWx3 in [0, 1] and z-depth float32 HxW metres (noise included).

        ``depth_time`` renders the depth at another instant (TUM's depth and colour are not simultaneous)."""
        cfg = self.cfg
        t = self.times[i]
        if cfg.motion_blur > 0:
            dt = self.trajectory.duration / (cfg.n_frames - 1)
            offsets = (np.linspace(0, 1, cfg.motion_blur_samples) - 0.5) * cfg.motion_blur * dt
            colour_poses = self.trajectory.poses(t + offsets)
        else:
            colour_poses = self.poses[i : i + 1]
        depth_pose = self.poses[i] if depth_time is None else self.trajectory.pose(depth_time)
        rgb_lin, depth = self.renderer.render(
            cfg.camera, colour_poses, depth_pose, n_ss=cfg.supersample, seed=cfg.seed * 100003 + i
        )
        gain, bias = self.exposure[i]
        rgb = np.clip(gain * linear_to_srgb(rgb_lin) + bias, 0.0, 1.0).astype(np.float32)
        if cfg.depth_noise_m > 0:
            noise = np.random.default_rng([cfg.seed, 2, i]).standard_normal(depth.shape) * cfg.depth_noise_m
            depth = np.where(depth > 0, np.maximum(depth + noise, 0.0), 0.0).astype(np.float32)
        return rgb, depth

    def mesh(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Ground-truth mesh with shared vertices: (V, 3) float32 points, (V, 3) uint8 sRGB, (F, 3) int32."""
        corners = self.scene.positions.reshape(-1, 3)
        colours = (linear_to_srgb(self.renderer.corner_colours()) * 255 + 0.5).astype(np.uint8)
        key = np.round(corners.astype(np.float64) * 1e5).astype(np.int64)
        _, first, inverse = np.unique(key, axis=0, return_index=True, return_inverse=True)
        return corners[first].astype(np.float32), colours[first], inverse.reshape(-1, 3).astype(np.int32)


def _write_ply(path: Path, points: np.ndarray, colours: np.ndarray, faces: np.ndarray) -> None:
    vertex = np.empty(
        len(points),
        [("x", "f4"), ("y", "f4"), ("z", "f4"), ("red", "u1"), ("green", "u1"), ("blue", "u1"), ("alpha", "u1")],
    )
    for k, name in enumerate("xyz"):
        vertex[name] = points[:, k]
    for k, name in enumerate(("red", "green", "blue")):
        vertex[name] = colours[:, k]
    vertex["alpha"] = 255
    face = np.empty(len(faces), [("vertex_indices", "i4", (3,))])
    face["vertex_indices"] = faces
    plyfile.PlyData(
        [
            plyfile.PlyElement.describe(vertex, "vertex"),
            plyfile.PlyElement.describe(face, "face", len_types={"vertex_indices": "u1"}),
        ],
        text=False,
        comments=["rgs_warp synthetic scene ground truth (z up, metres)"],
    ).write(str(path))


def _depth_png(depth: np.ndarray, scale: float) -> np.ndarray:
    raw = np.round(depth.astype(np.float64) * scale)
    return np.where((raw > 0) & (raw <= 65535), raw, 0).astype(np.uint16)


def _write_rgb(path: Path, rgb: np.ndarray) -> None:
    bgr = (np.clip(rgb, 0, 1)[..., ::-1] * 255 + 0.5).astype(np.uint8)
    params = [cv2.IMWRITE_JPEG_QUALITY, 95] if path.suffix == ".jpg" else []
    if not cv2.imwrite(str(path), bgr, params):
        raise OSError(f"cannot write {path}")


def _write_depth(path: Path, depth: np.ndarray, scale: float) -> None:
    if not cv2.imwrite(str(path), _depth_png(depth, scale)):
        raise OSError(f"cannot write {path}")


def _cam_params(cfg: SyntheticConfig, scale: float) -> str:
    c = {"w": cfg.width, "h": cfg.height, "fx": cfg.fx, "fy": cfg.fy, "cx": cfg.cx, "cy": cfg.cy, "scale": scale}
    return json.dumps({"camera": c}, indent=4) + "\n"


def write_sequence(
    cfg: SyntheticConfig, out: Path, layout: str = "replica", device: str | None = None, progress: bool = True
) -> Path:
    """Render ``cfg`` into ``out`` in the Replica (NICE-SLAM) or TUM RGB-D layout; returns ``out``.

    Both layouts also get ``mesh.ply`` (ground-truth mesh, vertex colours), ``cam_params.json``,
    ``synthetic.json`` (the config) and ``exposure.txt`` (per-frame gain and bias applied to the colour).
    """
    if layout not in ("replica", "tum"):
        raise ValueError(f"layout must be 'replica' or 'tum', got {layout!r}")
    out = Path(out)
    seq = SequenceRenderer(cfg, device)
    out.mkdir(parents=True, exist_ok=True)
    _write_ply(out / "mesh.ply", *seq.mesh())
    (out / "synthetic.json").write_text(json.dumps(asdict(cfg), indent=2) + "\n")
    np.savetxt(out / "exposure.txt", seq.exposure, fmt="%.6f", header="gain bias (rgb = gain * rendered + bias)")
    frames = tqdm(range(cfg.n_frames), desc=f"synthetic {cfg.scene}", unit="frame", disable=not progress)
    if layout == "replica":
        (out / "cam_params.json").write_text(_cam_params(cfg, REPLICA_DEPTH_SCALE))
        (out / "results").mkdir(exist_ok=True)
        for i in frames:
            rgb, depth = seq.render(i)
            _write_rgb(out / "results" / f"frame{i:06d}.jpg", rgb)
            _write_depth(out / "results" / f"depth{i:06d}.png", depth, REPLICA_DEPTH_SCALE)
        with open(out / "traj.txt", "w") as f:
            for T in seq.poses:
                f.write(" ".join(f"{v:.18e}" for v in T.ravel()) + "\n")
        return out

    (out / "cam_params.json").write_text(_cam_params(cfg, TUM_DEPTH_SCALE))
    (out / "rgb").mkdir(exist_ok=True)
    (out / "depth").mkdir(exist_ok=True)
    offsets = np.random.default_rng([cfg.seed, 3]).uniform(-_TUM_DEPTH_OFFSET_S, _TUM_DEPTH_OFFSET_S, cfg.n_frames)
    rgb_lines, depth_lines = [], []
    for i in frames:
        t_rgb = seq.times[i]
        t_depth = t_rgb + offsets[i]  # the path is at rest at its ends, so stepping past them is harmless
        rgb, depth = seq.render(i, depth_time=t_depth)
        s_rgb, s_depth = f"{_TUM_T0 + t_rgb:.6f}", f"{_TUM_T0 + t_depth:.6f}"
        _write_rgb(out / "rgb" / f"{s_rgb}.png", rgb)
        _write_depth(out / "depth" / f"{s_depth}.png", depth, TUM_DEPTH_SCALE)
        rgb_lines.append(f"{s_rgb} rgb/{s_rgb}.png")
        depth_lines.append(f"{s_depth} depth/{s_depth}.png")
    bag = f"rgbd_dataset_synthetic_{cfg.scene}.bag"
    (out / "rgb.txt").write_text(
        f"# color images\n# file: '{bag}'\n# timestamp filename\n" + "\n".join(rgb_lines) + "\n"
    )
    (out / "depth.txt").write_text(
        f"# depth maps\n# file: '{bag}'\n# timestamp filename\n" + "\n".join(depth_lines) + "\n"
    )
    gt_times = np.arange(-0.05, seq.trajectory.duration + 0.05, 1.0 / _TUM_GT_RATE_HZ)
    with open(out / "groundtruth.txt", "w") as f:
        f.write(f"# ground truth trajectory\n# file: '{bag}'\n# timestamp tx ty tz qx qy qz qw\n")
        for t in gt_times:
            T = seq.trajectory.pose(t)
            q = matrix_to_quat(T[:3, :3])
            f.write(f"{_TUM_T0 + t:.6f} " + " ".join(f"{v:.9f}" for v in (*T[:3, 3], *q)) + "\n")
    return out
