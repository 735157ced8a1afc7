"""Dataset loaders: each gives ``len(ds)``, ``ds[i] -> Frame`` and ``ds.camera -> Camera``."""

from __future__ import annotations

import os

from rgs_warp.config import ConfigError, check_image_size
from rgs_warp.datasets.base import DatasetError, DatasetWarning, RGBDDataset, check_depth_scale
from rgs_warp.datasets.replica import ReplicaDataset
from rgs_warp.datasets.rosbag import RosbagDataset, RosbagSource, RosFrames
from rgs_warp.datasets.sevenscenes import SevenScenesDataset
from rgs_warp.datasets.stream import CallbackSource, RealSenseSource
from rgs_warp.datasets.synthetic import SyntheticConfig, SyntheticDataset
from rgs_warp.datasets.synthetic.dataset import sequence_dir
from rgs_warp.datasets.tum import TUMDataset

__all__ = [
    "CallbackSource",
    "DatasetError",
    "DatasetWarning",
    "RGBDDataset",
    "RealSenseSource",
    "ReplicaDataset",
    "RosFrames",
    "RosbagDataset",
    "RosbagSource",
    "SevenScenesDataset",
    "SyntheticDataset",
    "TUMDataset",
    "generates_scene",
    "open_dataset",
]

DEPTH_SCALED = ("tum", "replica", "7scenes")  # the loaders of depth PNGs in raw units (their depth_scale)


def open_dataset(cfg, device: str | None = None) -> RGBDDataset | CallbackSource:
    """The dataset named by a ``Config`` (its ``dataset`` section and ``data_root``); ``device`` is
    where a synthetic sequence is rendered if it is not cached yet.  Images that ``dataset.downscale``
    or ``tracking.downscale`` would shrink below what the pipeline needs are a ``ConfigError``.
    ``dataset.type=realsense`` gives a ``RealSenseSource`` (a stream: no length, no random access), and
    ``dataset.type=rosbag`` with ``dataset.stream`` a ``RosbagSource``.  ``dataset.depth_scale`` (> 0)
    replaces the depth images' scale; an RGB-D run's first frame whose depth it reads at an implausible
    distance is a ``DatasetError`` (``check_depth_scale``)."""
    scaled = cfg.dataset.type in DEPTH_SCALED
    if cfg.dataset.depth_scale > 0 and not scaled:
        raise ConfigError(f"dataset.depth_scale applies to {', '.join(DEPTH_SCALED)}, not {cfg.dataset.type}")
    ds = _open(cfg, device)
    camera = ds.native_camera
    check_image_size(camera.width, camera.height, cfg, native=True)
    if cfg.dataset.depth_scale > 0:
        ds.depth_scale = cfg.dataset.depth_scale
    if scaled and cfg.mode == "rgbd":
        check_depth_scale(ds)
    return ds


def _open(cfg, device: str | None) -> RGBDDataset:
    d = cfg.dataset
    if d.type == "realsense":
        recording = cfg.dataset_path() if d.path else None
        return RealSenseSource(
            recording, width=d.width, height=d.height, fps=d.fps, serial=d.serial, max_frames=d.max_frames
        )
    if d.type not in ("synthetic", "rosbag"):  # a ROS 1 bag is a file: its reader says what is missing
        path = cfg.dataset_path()
        if not path.is_dir():
            origin = (
                ("data_root=" + cfg.data_root)
                if cfg.data_root
                else (
                    "$RGS_DATA" if os.environ.get("RGS_DATA") else "the current directory (no data_root= or $RGS_DATA)"
                )
            )
            loader = {"replica": ReplicaDataset, "7scenes": SevenScenesDataset, "tum": TUMDataset}.get(d.type)
            root = f" --data-root {cfg.data_root}" if cfg.data_root else ""
            hint = (
                f"\n  expected layout: {loader.layout}\n  download it: python -m rgs_warp.download "
                f"{d.type}/{d.name}{root} (--list names them)\n  or obtain it from: {loader.source}"
                if loader
                else ""
            )
            raise DatasetError(
                f"dataset {d.type}/{d.name}: folder {path.resolve()} does not exist\n"
                f"  (dataset.path={d.path!r} relative to {origin}; set data_root=... or RGS_DATA, or an "
                f"absolute dataset.path=...){hint}"
            )
    common = dict(stride=d.stride, start=d.start, max_frames=d.max_frames, downscale=d.downscale, prefetch=d.prefetch)
    if d.type == "replica":
        return ReplicaDataset(cfg.dataset_path(), **common)
    if d.type == "7scenes":
        return SevenScenesDataset(
            cfg.dataset_path(),
            register_depth=d.register_depth,
            colour_intrinsics=d.colour_intrinsics,
            depth_to_colour_m=d.depth_to_colour_m,
            colour_distortion=d.colour_distortion,
            **common,
        )
    if d.type == "tum":
        return TUMDataset(
            cfg.dataset_path(),
            camera=d.camera,
            max_dt=d.max_dt,
            undistort=d.undistort,
            require_depth=cfg.mode == "rgbd",
            require_pose=d.require_pose,
            **common,
        )
    if d.type == "rosbag":
        if not d.path:
            raise DatasetError("dataset.type=rosbag needs dataset.path=BAG (a ROS 1 .bag file or a ROS 2 bag folder)")
        topics = dict(
            rgb_topic=d.rgb_topic,
            depth_topic=d.depth_topic,
            camera_info_topic=d.camera_info_topic,
            pose_topic=d.pose_topic,
            pose_frame=d.pose_frame,
            max_dt=d.max_dt,
            require_depth=cfg.mode == "rgbd",
        )
        if d.stream:
            return RosbagSource(cfg.dataset_path(), max_frames=d.max_frames, **topics)
        return RosbagDataset(cfg.dataset_path(), **topics, **common)
    if d.type == "synthetic":
        return SyntheticDataset(d.name, device=device, **_synthetic_options(d), **common)
    raise DatasetError(f"dataset.type {d.type!r} has no loader")


def _synthetic_options(d) -> dict:
    """The ``SyntheticConfig`` fields that a config's ``dataset`` section sets."""
    return dict(
        width=d.width,
        height=d.height,
        n_frames=d.n_frames,
        depth_noise_m=d.depth_noise_m,
        exposure_drift=d.exposure_drift,
        motion_blur=d.motion_blur,
        seed=d.seed,
    )


def generates_scene(cfg) -> bool:
    """Whether ``open_dataset(cfg)`` renders a synthetic sequence (not in ``$RGS_CACHE`` yet)."""
    if cfg.dataset.type != "synthetic":
        return False
    return not sequence_dir(SyntheticConfig(scene=cfg.dataset.name, **_synthetic_options(cfg.dataset))).is_dir()
