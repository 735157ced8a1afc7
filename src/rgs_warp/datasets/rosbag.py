"""ROS bags (a ROS 1 ``.bag`` file, a ROS 2 bag folder) read with the ``rosbags`` package (pure Python,
no ROS needed): colour and depth ``sensor_msgs/Image`` or ``CompressedImage`` topics, the camera from
the colour topic's ``CameraInfo``, ground truth from a ``PoseStamped``, ``Odometry`` or TF topic.

Colour frames are paired with the depth image and the pose nearest in time by ``StampPairing`` as the
messages arrive in recording order.  ``RosbagDataset`` indexes a bag that way for random access;
``RosbagSource`` plays it as a stream through ``RosFrames``, which a live ROS node's subscriber
callbacks feed the same way (its messages have the fields the decoders read), so that a recorded
robot run and a live one go through the same code.
"""

from __future__ import annotations

import bisect
import importlib
import queue
import struct
import threading
import warnings
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from rgs_warp.datasets.base import (
    DatasetError,
    DatasetWarning,
    RGBDDataset,
    check_pose,
    undistort_frame,
    undistort_maps,
)
from rgs_warp.datasets.stream import CallbackSource
from rgs_warp.geometry import pose_from_tq
from rgs_warp.types import Camera, Frame

IMAGE_TYPES = ("sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage")
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
POSE_TYPES = (
    "geometry_msgs/msg/PoseStamped",
    "geometry_msgs/msg/PoseWithCovarianceStamped",
    "geometry_msgs/msg/TransformStamped",
    "nav_msgs/msg/Odometry",
    "tf2_msgs/msg/TFMessage",
    "tf/msg/tfMessage",  # older ROS 1 bags' TF (TUM RGB-D's)
)
# sensor_msgs/Image encodings read: element type and channels
ENCODINGS = {
    "rgb8": ("u1", 3),
    "bgr8": ("u1", 3),
    "rgba8": ("u1", 4),
    "bgra8": ("u1", 4),
    "mono8": ("u1", 1),
    "16UC1": ("u2", 1),
    "32FC1": ("f4", 1),
}
TOPIC_KEYS = "dataset.rgb_topic=TOPIC dataset.depth_topic=TOPIC (and dataset.camera_info_topic, dataset.pose_topic)"


def stamp_s(msg) -> float:
    """A message's header time in seconds (ROS 2's ``sec``/``nanosec``, rospy's ``secs``/``nsecs``)."""
    t = msg.header.stamp
    if hasattr(t, "sec"):
        return int(t.sec) + 1e-9 * int(t.nanosec)
    return int(t.secs) + 1e-9 * int(t.nsecs)


def decode_image(msg) -> tuple[str, np.ndarray]:
    """What an ``Image`` or ``CompressedImage`` holds and its pixels: ``("colour", HxWx3 float32 RGB in
    [0, 1])``, ``("grey", the same with equal channels)`` or ``("depth", HxW float32 metres, 0 invalid)``.
    Depth: 16UC1 in millimetres, 32FC1 in metres; compressed: PNG 16-bit, or image_transport's
    ``compressedDepth`` (a 12-byte header before the PNG; 32FC1 quantised as inverse depth)."""
    if hasattr(msg, "format"):
        return _decode_compressed(msg)
    encoding = msg.encoding
    if encoding not in ENCODINGS:
        raise DatasetError(f"image encoding {encoding!r} is not supported: record one of {', '.join(ENCODINGS)}")
    kind, channels = ENCODINGS[encoding]
    dtype = np.dtype(kind).newbyteorder(">" if msg.is_bigendian else "<")
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    data = np.frombuffer(msg.data, np.uint8)
    row = w * channels * dtype.itemsize
    if step < row or data.size < step * h or h < 1 or w < 1:
        raise DatasetError(f"{encoding} image {w}x{h}: {data.size} bytes in rows of {step} (a row needs {row})")
    px = np.ascontiguousarray(data[: step * h].reshape(h, step)[:, :row]).view(dtype).reshape(h, w, channels)
    if encoding == "16UC1":
        return "depth", px[:, :, 0].astype(np.float32) * np.float32(0.001)
    if encoding == "32FC1":
        depth = px[:, :, 0].astype(np.float32)
        return "depth", np.where(np.isfinite(depth) & (depth > 0), depth, np.float32(0.0))
    if encoding == "mono8":
        return "grey", np.repeat(px, 3, axis=2).astype(np.float32) / np.float32(255.0)
    order = [2, 1, 0] if encoding.startswith("bgr") else [0, 1, 2]
    return "colour", np.ascontiguousarray(px[:, :, order], dtype=np.float32) / np.float32(255.0)


def _decode_compressed(msg) -> tuple[str, np.ndarray]:
    data = np.frombuffer(msg.data, np.uint8)
    fmt = str(msg.format)
    if "compresseddepth" in fmt.lower():
        if data.size <= 12:
            raise DatasetError(f"compressedDepth image of {data.size} bytes: no PNG after its 12-byte header")
        quant_a, quant_b = struct.unpack("<ff", data[4:12].tobytes())
        raw = cv2.imdecode(data[12:], cv2.IMREAD_UNCHANGED)
        if raw is None or raw.dtype != np.uint16 or raw.ndim != 2:
            raise DatasetError(f"compressedDepth image ({fmt!r}): not a readable 16-bit PNG")
        if fmt.lstrip().startswith("32FC1"):  # image_transport stores quant_a / depth + quant_b
            v = raw.astype(np.float32)
            with np.errstate(divide="ignore"):
                return "depth", np.where(raw > 0, np.float32(quant_a) / (v - np.float32(quant_b)), np.float32(0.0))
        return "depth", raw.astype(np.float32) * np.float32(0.001)
    img = cv2.imdecode(data, cv2.IMREAD_UNCHANGED)
    if img is None:
        raise DatasetError(f"compressed image ({fmt!r}, {data.size} bytes): not readable (corrupt or truncated)")
    if img.dtype == np.uint16 and img.ndim == 2:
        return "depth", img.astype(np.float32) * np.float32(0.001)
    if img.dtype != np.uint8:
        raise DatasetError(f"compressed image ({fmt!r}): {img.dtype} pixels, expected 8-bit colour or 16-bit depth")
    if img.ndim == 2:
        return "grey", np.repeat(img[:, :, None], 3, axis=2).astype(np.float32) / np.float32(255.0)
    return "colour", np.ascontiguousarray(img[:, :, 2::-1], dtype=np.float32) / np.float32(255.0)


def camera_from_info(msg, size: tuple[int, int] | None = None) -> Camera:
    """Our ``Camera`` from a ``sensor_msgs/CameraInfo`` (fx = K[0], fy = K[4], cx = K[2], cy = K[5]; ROS 1
    spells the fields K and D), of ``size`` (width, height) where the message gives none; non-zero
    distortion coefficients are kept (``bag_camera`` undoes them)."""
    k = np.asarray(msg.k if hasattr(msg, "k") else msg.K, dtype=np.float64).ravel()
    d = np.asarray(msg.d if hasattr(msg, "d") else msg.D, dtype=np.float64).ravel()
    if k.size != 9:
        raise ValueError(f"K has {k.size} values, expected 9")
    distortion = tuple(float(v) for v in d) if np.any(d != 0) else ()
    width, height = int(msg.width), int(msg.height)
    if width == 0 and height == 0 and size is not None:  # some drivers leave the size out
        width, height = size
    return Camera(float(k[0]), float(k[4]), float(k[2]), float(k[5]), width, height, distortion)


def poses_from_msg(msg, frame: str = "") -> list[tuple[float, np.ndarray]]:
    """(time s, 4x4 pose) from a ``PoseStamped``, ``PoseWithCovarianceStamped``, ``Odometry``,
    ``TransformStamped``, or a ``TFMessage``'s transforms whose child frame is ``frame``."""
    if hasattr(msg, "transforms"):
        want = frame.strip("/")
        return [p for tf in msg.transforms if tf.child_frame_id.strip("/") == want for p in poses_from_msg(tf)]
    if hasattr(msg, "transform"):
        position, orientation = msg.transform.translation, msg.transform.rotation
    else:
        pose = msg.pose.pose if hasattr(msg.pose, "pose") else msg.pose  # Odometry, PoseWithCovarianceStamped
        position, orientation = pose.position, pose.orientation
    t = np.array([position.x, position.y, position.z], dtype=np.float64)
    q = np.array([orientation.x, orientation.y, orientation.z, orientation.w], dtype=np.float64)
    if not np.all(np.isfinite(q)) or np.linalg.norm(q) < 1e-6:
        raise DatasetError(f"pose at {stamp_s(msg):.6f} s: the quaternion {tuple(q)} is not a rotation")
    return [(stamp_s(msg), check_pose(pose_from_tq(t, q / np.linalg.norm(q)), f"pose at {stamp_s(msg):.6f} s"))]


def _decoded(msg, where: str, what: str) -> tuple[str, np.ndarray]:
    """``decode_image(msg)``, its error naming the frame (``where``) and which of its images (``what``)."""
    try:
        return decode_image(msg)
    except DatasetError as e:
        raise DatasetError(f"{where}: {what}: {e}") from None


def frame_from_messages(colour_msg, depth_msg, pose: np.ndarray | None, where: str, undistort=None) -> Frame:
    """A ``Frame`` from a colour message, its depth message (or None) and pose (or None); ``undistort``
    (``base.undistort_maps``' maps of the camera info) undistorts both images."""
    kind, rgb = _decoded(colour_msg, where, "colour")
    if kind == "depth":
        raise DatasetError(f"{where}: the colour topic holds a depth image")
    depth = None
    if depth_msg is not None:
        kind, depth = _decoded(depth_msg, where, "depth")
        if kind != "depth":
            raise DatasetError(f"{where}: the depth topic holds a {kind} image, not 16UC1 / 32FC1 depth")
        if depth.shape != rgb.shape[:2]:
            (dh, dw), (h, w) = depth.shape, rgb.shape[:2]
            raise DatasetError(
                f"{where}: depth is {dw}x{dh}, colour {w}x{h}: depth must be registered to the colour camera "
                f"(realsense-ros: aligned_depth_to_color/image_raw)"
            )
    rgb, depth = undistort_frame(undistort, rgb, depth, source=where)
    return Frame(rgb, depth, None if pose is None else pose.copy(), stamp_s(colour_msg), 0)


class StampPairing:
    """Colour frames paired with the depth image and the pose nearest in time, within ``max_dt`` s, as
    messages arrive in recording order.  A colour frame is settled once each paired stream has passed
    its time by ``max_dt`` (no nearer message can come), once colour frames ``WAIT_S`` later arrived
    (a stream that stopped), or at ``finish``.  A depth image goes to one colour frame at most (as
    TUM's associate.py pairs them); colour frames without depth (``need_depth``) or without a pose
    (``poses``: a pose stream is read) are dropped and counted.  Each ``add_*`` returns the frames it
    settled, as (time, colour item, depth item or None, pose or None)."""

    WAIT_S = 1.0

    def __init__(self, max_dt: float, *, depth: bool, need_depth: bool, poses: bool):
        self.max_dt, self.has_depth, self.need_depth, self.has_poses = max_dt, depth, need_depth, poses
        self._colour: deque = deque()
        self._depth: list = []  # (time, item), sorted
        self._poses: list = []
        self._depth_latest = self._pose_latest = -np.inf
        self._ended = False
        self.colour_frames = self.without_depth = self.without_pose = 0

    def add_colour(self, t: float, item) -> list:
        self.colour_frames += 1
        if self._colour and t < self._colour[-1][0]:
            self._colour.insert(bisect.bisect([c[0] for c in self._colour], t), (t, item))
        else:
            self._colour.append((t, item))
        return self._settle()

    def add_depth(self, t: float, item) -> list:
        bisect.insort(self._depth, (t, id(item), item))
        self._depth_latest = max(self._depth_latest, t)
        return self._settle()

    def add_pose(self, t: float, pose: np.ndarray) -> list:
        bisect.insort(self._poses, (t, id(pose), pose))
        self._pose_latest = max(self._pose_latest, t)
        return self._settle()

    def finish(self) -> list:
        self._ended = True
        return self._settle()

    def _nearest(self, entries: list, t: float) -> int:
        best, best_dt = -1, self.max_dt
        for j, entry in enumerate(entries):
            if abs(entry[0] - t) <= best_dt:
                best, best_dt = j, abs(entry[0] - t)
        return best

    def _settle(self) -> list:
        out = []
        while self._colour:
            t, item = self._colour[0]
            late = self._ended or self._colour[-1][0] - t > self.WAIT_S
            if not late and (
                (self.has_depth and self._depth_latest <= t + self.max_dt)
                or (self.has_poses and self._pose_latest <= t + self.max_dt)
            ):
                break
            self._colour.popleft()
            j = self._nearest(self._depth, t)
            depth = self._depth.pop(j)[2] if j >= 0 else None
            k = self._nearest(self._poses, t)
            pose = self._poses[k][2] if k >= 0 else None
            # messages more than max_dt before this frame cannot pair with a later one
            self._depth = [d for d in self._depth if d[0] >= t - self.max_dt]
            self._poses = [p for p in self._poses if p[0] >= t - self.max_dt]
            if self.need_depth and depth is None:
                self.without_depth += 1
            elif self.has_poses and pose is None:
                self.without_pose += 1
            else:
                out.append((t, item, depth, pose))
        # nor can those WAIT_S older than their stream's latest (a colour frame near them settled
        # before): at most WAIT_S of messages wait, before the first colour frame too
        self._depth = [d for d in self._depth if d[0] >= self._depth_latest - self.WAIT_S]
        self._poses = [p for p in self._poses if p[0] >= self._pose_latest - self.WAIT_S]
        return out

    def dropped(self) -> str:
        """What was dropped, for a note, or ""."""
        why = [f"{self.without_depth} without a depth image"] if self.without_depth else []
        why += [f"{self.without_pose} without a pose"] if self.without_pose else []
        if not why:
            return ""
        return (
            f"{self.without_depth + self.without_pose} of {self.colour_frames} colour frames dropped: "
            f"{' and '.join(why)} within dataset.max_dt = {self.max_dt} s"
        )


@dataclass
class _Topic:
    name: str
    msgtype: str
    count: int
    connections: list
    kind: str = ""  # image topics: colour, grey or depth (what the first message holds), or unreadable
    detail: str = ""  # image topics: size and encoding (unreadable: why)

    def line(self) -> str:
        what = f"  ({self.kind} {self.detail})" if self.kind else ""
        return f"    {self.name}  {self.msgtype}  {self.count} messages{what}"


@dataclass
class BagTopics:
    """The topics a bag is read from (``choose_topics``)."""

    colour: _Topic
    info: _Topic
    depth: _Topic | None = None
    pose: _Topic | None = None
    pose_frame: str = ""
    notes: list[str] = field(default_factory=list)


class BagReader:
    """A ROS 1 ``.bag`` file or ROS 2 bag folder opened with ``rosbags``; ``read`` may be called from
    several threads (the prefetching ones)."""

    def __init__(self, path: Path):
        try:
            highlevel = importlib.import_module("rosbags.highlevel")
        except ImportError as e:
            raise DatasetError(
                f"dataset.type=rosbag needs the rosbags package ({e}): pip install 'rgs_warp[rosbag]'"
            ) from None
        if not path.exists():
            raise DatasetError(f"ROS bag {path} does not exist (a ROS 1 .bag file or a ROS 2 bag folder)")
        if path.is_file() and path.suffix in (".db3", ".mcap") and (path.parent / "metadata.yaml").is_file():
            path = path.parent  # a ROS 2 bag is its folder
        self.path = path
        self._lock = threading.Lock()
        try:
            self._reader = highlevel.AnyReader([path])
            self._reader.open()
        except Exception as e:  # rosbags raises its own errors, and OSError / ValueError on damaged files
            raise DatasetError(f"{path}: not a readable ROS bag ({type(e).__name__}: {e})") from None
        self.topics = {
            name: _Topic(name, info.msgtype or "?", info.msgcount, info.connections)
            for name, info in self._reader.topics.items()
        }

    def messages(self, topics: list[_Topic]):
        """(connection, bag time ns, message) of ``topics`` in recording order (one thread at a time:
        the opening's index, a playback)."""
        connections = [c for t in topics for c in t.connections]
        for connection, t, data in self._reader.messages(connections=connections):
            yield connection, t, self._deserialize(data, connection)

    def first(self, topic: _Topic):
        """The first message of ``topic``."""
        for _, _, msg in self.messages([topic]):
            return msg
        raise DatasetError(f"{self.path}: topic {topic.name} holds no message")

    def read(self, ref: tuple):
        """The message of a reference (connection, bag time ns, ordinal among that time's messages)."""
        connection, t, ordinal = ref
        with self._lock:
            at_t = self._reader.messages(connections=[connection], start=t, stop=t + 1)
            found = [data for k, (*_, data) in enumerate(at_t) if k == ordinal]
        if not found:
            raise DatasetError(f"{self.path}: no message on {connection.topic} at {t} ns")
        return self._deserialize(found[0], connection)

    def _deserialize(self, data, connection):
        try:
            return self._reader.deserialize(data, connection.msgtype)
        except Exception as e:  # a damaged message
            raise DatasetError(f"{self.path}: a {connection.msgtype} message on {connection.topic}: {e}") from None

    def close(self) -> None:
        with self._lock:
            self._reader.close()


def _namespace(topic: str) -> str:
    parts = topic.rstrip("/").split("/")
    while parts and parts[-1] in ("compressed", "compressedDepth"):
        parts.pop()
    return "/".join(parts[:-1])


def choose_topics(
    bag: BagReader,
    *,
    rgb_topic: str = "",
    depth_topic: str = "",
    camera_info_topic: str = "",
    pose_topic: str = "",
    pose_frame: str = "",
    need_depth: bool = True,
) -> BagTopics:
    """The colour, depth, camera info and pose topics of a bag: those named, else the bag's only one
    of each kind (colour: 8-bit colour, or grey where no topic has colour; depth: 16UC1 / 32FC1; camera
    info: the colour topic's ``camera_info``, else the only one).  No depth topic is an error unless
    ``need_depth`` is off (monocular); ground truth only where ``pose_topic`` names it.  An error lists
    the bag's topics and the keys that choose them."""
    topics = bag.topics
    for t in topics.values():
        if t.msgtype in IMAGE_TYPES and t.count:
            msg = bag.first(t)
            try:
                kind, px = decode_image(msg)
            except DatasetError as e:  # listed as unreadable; an error only where it is the topic named
                t.kind, t.detail = "unreadable", str(e)
                continue
            t.kind, t.detail = kind, f"{px.shape[1]}x{px.shape[0]} {getattr(msg, 'encoding', None) or msg.format}"
    listing = "\n  the bag's topics:\n" + "\n".join(t.line() for t in topics.values())

    def fail(problem: str):
        raise DatasetError(f"{bag.path}: {problem}\n  choose with: {TOPIC_KEYS}{listing}")

    def named(key: str, name: str, types: tuple[str, ...]) -> _Topic:
        t = topics.get(name)
        if t is None:
            fail(f"{key}={name}: the bag has no such topic")
        if t.msgtype not in types:
            fail(f"{key}={name}: a {t.msgtype} topic, expected {' or '.join(types)}")
        if t.kind == "unreadable":
            fail(f"{key}={name}: {t.detail}")
        return t

    def only(candidates: list[_Topic], what: str, key: str) -> _Topic | None:
        if len(candidates) > 1:
            names = ", ".join(t.name for t in candidates)
            fail(f"{len(candidates)} {what} topics ({names}): name one with {key}=TOPIC")
        return candidates[0] if candidates else None

    images = [t for t in topics.values() if t.msgtype in IMAGE_TYPES]
    if rgb_topic:
        colour = named("dataset.rgb_topic", rgb_topic, IMAGE_TYPES)
    else:
        colours = [t for t in images if t.kind == "colour"] or [t for t in images if t.kind == "grey"]
        colour = only(colours, "colour image", "dataset.rgb_topic")
        if colour is None:
            fail("no colour image topic (sensor_msgs/Image or CompressedImage, 8-bit)")
    if depth_topic:
        depth = named("dataset.depth_topic", depth_topic, IMAGE_TYPES)
    else:
        candidates = [t for t in images if t.kind == "depth"]
        depth = only(candidates, "depth image", "dataset.depth_topic") if need_depth or len(candidates) == 1 else None
        if depth is None and need_depth:
            fail(
                "no depth image topic (16UC1 or 32FC1): run monocular with mode=mono, or name the depth topic "
                "with dataset.depth_topic=TOPIC"
            )
    infos = [t for t in topics.values() if t.msgtype == CAMERA_INFO]
    if camera_info_topic:
        info = named("dataset.camera_info_topic", camera_info_topic, (CAMERA_INFO,))
    else:
        beside = topics.get(_namespace(colour.name) + "/camera_info")
        if beside is not None and beside.msgtype == CAMERA_INFO:
            info = beside
        else:
            info = only(infos, "CameraInfo", "dataset.camera_info_topic")
        if info is None:
            fail(f"no sensor_msgs/CameraInfo topic: {colour.name}'s intrinsics are unknown (record its camera_info)")
    chosen = BagTopics(colour=colour, info=info, depth=depth)
    if depth is not None:
        depth_info = topics.get(_namespace(depth.name) + "/camera_info")
        if depth_info is not None and depth_info is not info and depth_info.msgtype == CAMERA_INFO:
            a, b = camera_from_info(bag.first(info)), camera_from_info(bag.first(depth_info))
            if not np.allclose(a.K, b.K, rtol=1e-3) or (a.width, a.height) != (b.width, b.height):
                chosen.notes.append(
                    f"{depth.name}'s camera info ({depth_info.name}) differs from {info.name}'s: the depth images "
                    f"are used as if registered to the colour camera"
                )
    if pose_topic:
        chosen.pose = named("dataset.pose_topic", pose_topic, POSE_TYPES)
        chosen.pose_frame = pose_frame
        if hasattr(bag.first(chosen.pose), "transforms") and not pose_frame:
            children = sorted({tf.child_frame_id for *_, msg in bag.messages([chosen.pose]) for tf in msg.transforms})
            if len(children) != 1:
                frames = ", ".join(children) or "no frame"
                fail(f"{pose_topic} holds transforms to {frames}: name the camera's with dataset.pose_frame=FRAME")
            chosen.pose_frame = children[0]
    else:
        poses = [t.name for t in topics.values() if t.msgtype in POSE_TYPES]
        if poses:
            listed = ", ".join(poses)
            chosen.notes.append(f"no ground truth read: the bag has pose topics {listed} (dataset.pose_topic=TOPIC)")
    return chosen


# CameraInfo distortion models whose coefficients are OpenCV's (k1, k2, p1, p2, k3[, k4, k5, k6])
PINHOLE_DISTORTION_MODELS = ("plumb_bob", "rational_polynomial")


def bag_camera(bag: BagReader, topics: BagTopics) -> tuple[Camera, tuple | None, list[str]]:
    """The colour camera from the camera info topic's first message (the images' size where it gives
    none), as the images will be: undistorted onto the same intrinsics by the remap maps returned
    (None: nothing to undo); and notes (a distortion model that is not undone)."""
    msg = bag.first(topics.info)
    _, px = decode_image(bag.first(topics.colour))
    h, w = px.shape[:2]
    try:
        camera = camera_from_info(msg, (w, h))
    except ValueError as e:
        raise DatasetError(f"{bag.path}: {topics.info.name}: {e}") from None
    if (camera.width, camera.height) != (w, h):
        raise DatasetError(
            f"{bag.path}: {topics.info.name} is for {camera.width}x{camera.height} images, "
            f"{topics.colour.name}'s are {w}x{h}"
        )
    notes, maps = [], None
    if camera.distortion:
        model = str(getattr(msg, "distortion_model", "") or "plumb_bob")
        if model in PINHOLE_DISTORTION_MODELS:
            maps = undistort_maps(camera, camera.distortion, f"{bag.path}: {topics.info.name} distortion")
        else:
            notes.append(
                f"{topics.info.name} gives distortion model {model!r} {camera.distortion}: not undone (only "
                f"{' and '.join(PINHOLE_DISTORTION_MODELS)} are), the images are used as recorded"
            )
    return camera.undistorted(), maps, notes


class RosbagDataset(RGBDDataset):
    """A ROS bag with random access: the bag is read once at opening for the messages' times, colour
    paired with depth and pose by ``StampPairing``, and each frame read back by reference when asked."""

    layout = (
        "a ROS 1 .bag file or a ROS 2 bag folder (metadata.yaml, .db3 or .mcap) with a colour image topic, "
        "its CameraInfo, and a depth image topic registered to the colour camera"
    )
    source = "a recording of the camera's topics (ros2 bag record / rosbag record)"

    def __init__(
        self,
        path,
        *,
        rgb_topic: str = "",
        depth_topic: str = "",
        camera_info_topic: str = "",
        pose_topic: str = "",
        pose_frame: str = "",
        max_dt: float = 0.08,
        require_depth: bool = True,
        **selection,
    ):
        self._bag = BagReader(Path(path).expanduser())
        bag = self._bag.path
        super().__init__(bag if bag.is_dir() else bag.parent, **selection)  # the base wants a folder
        self.root = bag
        self.topics = choose_topics(
            self._bag,
            rgb_topic=rgb_topic,
            depth_topic=depth_topic,
            camera_info_topic=camera_info_topic,
            pose_topic=pose_topic,
            pose_frame=pose_frame,
            need_depth=require_depth,
        )
        self._native_camera, self._undistort_maps, notes = bag_camera(self._bag, self.topics)
        for message in self.topics.notes + notes:
            self.note(message)
        pairing = StampPairing(
            max_dt, depth=self.topics.depth is not None, need_depth=require_depth, poses=self.topics.pose is not None
        )
        depth_name = self.topics.depth.name if self.topics.depth else None
        pose_name = self.topics.pose.name if self.topics.pose else None
        seen: dict = {}
        read = [t for t in (self.topics.colour, self.topics.depth, self.topics.pose) if t is not None]
        for connection, t_ns, msg in self._bag.messages(read):
            if connection.topic == pose_name:
                for t, pose in poses_from_msg(msg, self.topics.pose_frame):
                    self._items += pairing.add_pose(t, pose)
                continue
            ordinal = seen[(connection.id, t_ns)] = seen.get((connection.id, t_ns), -1) + 1
            add = pairing.add_depth if connection.topic == depth_name else pairing.add_colour
            self._items += add(stamp_s(msg), (connection, t_ns, ordinal))
        self._items += pairing.finish()
        if pairing.dropped():
            self.note(pairing.dropped())
        if not self._items and pairing.colour_frames:
            raise DatasetError(f"{self.root}: {pairing.dropped()}")
        self._select()

    def _load_full(self, item) -> Frame:
        t, colour_ref, depth_ref, pose = item
        colour = self._bag.read(colour_ref)
        depth = self._bag.read(depth_ref) if depth_ref is not None else None
        return frame_from_messages(colour, depth, pose, f"{self.root}: frame at {t:.6f} s", self._undistort_maps)

    def _gt_pose(self, item):
        return None if item[3] is None else item[3].copy()

    def close(self) -> None:
        self._bag.close()


class RosFrames:
    """Frames from ROS messages as they arrive: ``colour``, ``depth`` and ``pose`` take messages on the
    producer's thread (a bag playing, a live node's subscriber callbacks), ``end`` says the stream
    ended, ``fail`` that it broke.  They are paired (``StampPairing``) and decoded there;
    ``next_frame`` (a ``CallbackSource``'s) hands the frames over in order, None after the end, and
    re-raises a failure.  The producer waits while ``QUEUE`` frames wait for the SLAM; ``undistort``
    (``base.undistort_maps``' maps) undistorts the frames, for a camera that reports distortion.

        camera = camera_from_info(info_msg)
        frames = RosFrames(max_dt=0.02, undistort=undistort_maps(camera, camera.distortion, "camera_info"))
        node.create_subscription(Image, "/camera/color/image_raw", frames.colour, 10)
        node.create_subscription(Image, "/camera/aligned_depth_to_color/image_raw", frames.depth, 10)
        run(cfg, source=CallbackSource(camera.undistorted(), frames.next_frame))
    """

    QUEUE = 4

    def __init__(
        self,
        max_dt: float = 0.08,
        *,
        depth: bool = True,
        need_depth: bool = True,
        poses: bool = False,
        pose_frame: str = "",
        name: str = "ros",
        undistort=None,
    ):
        self.pose_frame, self.name, self.undistort = pose_frame, name, undistort
        self.pairing = StampPairing(max_dt, depth=depth, need_depth=need_depth, poses=poses)
        self._queue: queue.Queue = queue.Queue(maxsize=self.QUEUE)
        self._closed = threading.Event()
        self._lock = threading.Lock()  # subscriber callbacks may come on several threads

    def colour(self, msg) -> None:
        with self._lock:
            self._hand_over(self.pairing.add_colour(stamp_s(msg), msg))

    def depth(self, msg) -> None:
        with self._lock:
            self._hand_over(self.pairing.add_depth(stamp_s(msg), msg))

    def pose(self, msg) -> None:
        with self._lock:
            for t, pose in poses_from_msg(msg, self.pose_frame):
                self._hand_over(self.pairing.add_pose(t, pose))

    def end(self) -> None:
        with self._lock:
            self._hand_over(self.pairing.finish())
        if self.pairing.dropped():
            warnings.warn(f"{self.name}: {self.pairing.dropped()}", DatasetWarning, stacklevel=2)
        self._put(None)

    def fail(self, error: BaseException) -> None:
        self._put(error)

    @property
    def closed(self) -> bool:
        return self._closed.is_set()

    def close(self) -> None:
        """The SLAM stopped taking frames: producers stop waiting."""
        self._closed.set()

    def next_frame(self) -> Frame | None:
        item = self._queue.get()
        if isinstance(item, BaseException):
            raise item
        return item

    def _hand_over(self, settled: list) -> None:
        for t, colour, depth, pose in settled:
            self._put(frame_from_messages(colour, depth, pose, f"{self.name}: frame at {t:.6f} s", self.undistort))

    def _put(self, item) -> None:
        while not self._closed.is_set():
            try:
                self._queue.put(item, timeout=0.1)
                return
            except queue.Full:
                continue


class RosbagSource(CallbackSource):
    """A ROS bag played as a stream: from the first frame asked for, a thread reads the bag's messages
    in recording order into ``RosFrames``, as a live node's subscriber callbacks would (the playback
    waits while the SLAM works).  Topics and camera as ``RosbagDataset``; ``max_frames`` stops early."""

    def __init__(
        self,
        path,
        *,
        rgb_topic: str = "",
        depth_topic: str = "",
        camera_info_topic: str = "",
        pose_topic: str = "",
        pose_frame: str = "",
        max_dt: float = 0.08,
        require_depth: bool = True,
        max_frames: int | None = None,
    ):
        self._bag = BagReader(Path(path).expanduser())
        self.topics = choose_topics(
            self._bag,
            rgb_topic=rgb_topic,
            depth_topic=depth_topic,
            camera_info_topic=camera_info_topic,
            pose_topic=pose_topic,
            pose_frame=pose_frame,
            need_depth=require_depth,
        )
        camera, undistort, notes = bag_camera(self._bag, self.topics)
        name = self._bag.path.name
        self.frames = RosFrames(
            max_dt,
            depth=self.topics.depth is not None,
            need_depth=require_depth,
            poses=self.topics.pose is not None,
            pose_frame=self.topics.pose_frame,
            name=name,
            undistort=undistort,
        )
        self._playback: threading.Thread | None = None
        super().__init__(camera, self._next, max_frames=max_frames, name=name)
        for message in self.topics.notes + notes:
            self.notes.append(message)
            warnings.warn(f"{self._bag.path}: {message}", DatasetWarning, stacklevel=2)

    def _next(self) -> Frame | None:
        if self._playback is None:
            self._playback = threading.Thread(target=self._play, name="rosbag-playback", daemon=True)
            self._playback.start()
        return self.frames.next_frame()

    def _play(self) -> None:
        t = self.topics
        handlers = {t.colour.name: self.frames.colour}
        if t.depth is not None:
            handlers[t.depth.name] = self.frames.depth
        if t.pose is not None:
            handlers[t.pose.name] = self.frames.pose
        try:
            for connection, _, msg in self._bag.messages([x for x in (t.colour, t.depth, t.pose) if x is not None]):
                if self.frames.closed:
                    return
                handlers[connection.topic](msg)
            self.frames.end()
        except DatasetError as e:
            self.frames.fail(e)

    def close(self) -> None:
        """Stop the playback and close the bag."""
        self.frames.close()
        if self._playback is not None:
            self._playback.join()
        self._bag.close()
