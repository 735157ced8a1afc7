"""ROS bags (``dataset.type=rosbag``): bags the tests write with rosbags' writers (ROS 1 and ROS 2),
read as a dataset and as a stream, the topic choice and its errors, monocular bags, and a SLAM run
through the command line."""

import json
import sys
from types import SimpleNamespace

import cv2
import numpy as np
import pytest
from rosbags.rosbag1 import Writer as Writer1
from rosbags.rosbag2 import Writer as Writer2
from rosbags.typesys import Stores, get_typestore

from rgs_warp.config import load_config
from rgs_warp.datasets import DatasetError, DatasetWarning, RosbagDataset, RosbagSource, open_dataset
from rgs_warp.datasets.rosbag import StampPairing, camera_from_info, decode_image, frame_from_messages
from rgs_warp.geometry import matrix_to_quat
from rgs_warp.types import Camera, Frame

CAMERA = Camera(30.0, 30.0, 15.5, 11.5, 32, 24)


def scene_frames(n: int = 5, camera: Camera = CAMERA) -> list[Frame]:
    """Frames with content every pixel of which differs: a colour ramp, depth 1-2 m, a camera moving along x."""
    v, u = np.mgrid[0 : camera.height, 0 : camera.width].astype(np.float32)
    frames = []
    for k in range(n):
        rgb = np.stack([u / camera.width, v / camera.height, np.full_like(u, 0.1 * k)], axis=2)
        depth = (1.0 + 0.03 * u + 0.01 * v + 0.05 * k).astype(np.float32)
        depth[0, 0] = 0.0  # no depth there
        pose = np.eye(4)
        pose[:3, :3] = [[np.cos(0.1 * k), -np.sin(0.1 * k), 0], [np.sin(0.1 * k), np.cos(0.1 * k), 0], [0, 0, 1]]
        pose[0, 3] = 0.05 * k
        frames.append(Frame(rgb.astype(np.float32), depth, pose, 100.0 + k / 30.0, k))
    return frames


class BagWriter:
    """A ROS 1 (``.bag``) or ROS 2 (folder) bag written with rosbags, its messages built in the version's
    own types (ROS 1's Header has a sequence number, its CameraInfo K and D)."""

    def __init__(self, path, ros2: bool):
        self.ros2 = ros2
        self.ts = get_typestore(Stores.ROS2_HUMBLE if ros2 else Stores.ROS1_NOETIC)
        self.writer = Writer2(path, version=9) if ros2 else Writer1(path)
        self.connections: dict = {}
        self.seq = 0

    def __enter__(self):
        self.writer.open()
        return self

    def __exit__(self, *exc):
        self.writer.close()

    def header(self, t: float, frame_id: str = "camera"):
        T = self.ts.types
        stamp = T["builtin_interfaces/msg/Time"](sec=int(t), nanosec=int(round((t - int(t)) * 1e9)))
        self.seq += 1
        if self.ros2:
            return T["std_msgs/msg/Header"](stamp=stamp, frame_id=frame_id)
        return T["std_msgs/msg/Header"](seq=self.seq, stamp=stamp, frame_id=frame_id)

    def write(self, topic: str, msg, t: float) -> None:
        msgtype = msg.__msgtype__
        if topic not in self.connections:
            self.connections[topic] = self.writer.add_connection(topic, msgtype, typestore=self.ts)
        data = self.ts.serialize_cdr(msg, msgtype) if self.ros2 else self.ts.serialize_ros1(msg, msgtype)
        self.writer.write(self.connections[topic], int(t * 1e9), data)

    def image(self, topic: str, t: float, pixels: np.ndarray, encoding: str) -> None:
        pixels = np.ascontiguousarray(pixels)
        h, w = pixels.shape[:2]
        data = pixels.view(np.uint8).reshape(-1)
        msg = self.ts.types["sensor_msgs/msg/Image"](
            header=self.header(t), height=h, width=w, encoding=encoding, is_bigendian=0, step=data.size // h, data=data
        )
        self.write(topic, msg, t)

    def compressed(self, topic: str, t: float, pixels: np.ndarray, fmt: str, ext: str = ".png") -> None:
        ok, data = cv2.imencode(ext, pixels)
        msg = self.ts.types["sensor_msgs/msg/CompressedImage"](header=self.header(t), format=fmt, data=data.ravel())
        self.write(topic, msg, t)

    def camera_info(self, topic: str, t: float, cam: Camera, distortion=(0.0,) * 5, model="plumb_bob") -> None:
        T = self.ts.types
        k = np.array([cam.fx, 0, cam.cx, 0, cam.fy, cam.cy, 0, 0, 1], dtype=np.float64)
        p = np.array([cam.fx, 0, cam.cx, 0, 0, cam.fy, cam.cy, 0, 0, 0, 1, 0], dtype=np.float64)
        matrices = dict(d=np.array(distortion, np.float64), k=k, r=np.eye(3).ravel(), p=p)
        if not self.ros2:
            matrices = {name.upper(): value for name, value in matrices.items()}
        roi = T["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)
        msg = T["sensor_msgs/msg/CameraInfo"](
            header=self.header(t),
            height=cam.height,
            width=cam.width,
            distortion_model=model,
            binning_x=0,
            binning_y=0,
            roi=roi,
            **matrices,
        )
        self.write(topic, msg, t)

    def _pose_parts(self, pose: np.ndarray):
        T = self.ts.types
        q = matrix_to_quat(pose[:3, :3])
        return T["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3]), pose[:3, 3]

    def pose_stamped(self, topic: str, t: float, pose: np.ndarray) -> None:
        T = self.ts.types
        q, p = self._pose_parts(pose)
        point = T["geometry_msgs/msg/Point"](x=p[0], y=p[1], z=p[2])
        msg = T["geometry_msgs/msg/PoseStamped"](
            header=self.header(t, "world"), pose=T["geometry_msgs/msg/Pose"](position=point, orientation=q)
        )
        self.write(topic, msg, t)

    def tf(self, topic: str, t: float, transforms: dict) -> None:
        T = self.ts.types
        stamped = []
        for child, pose in transforms.items():
            q, p = self._pose_parts(pose)
            translation = T["geometry_msgs/msg/Vector3"](x=p[0], y=p[1], z=p[2])
            stamped.append(
                T["geometry_msgs/msg/TransformStamped"](
                    header=self.header(t, "world"),
                    child_frame_id=child,
                    transform=T["geometry_msgs/msg/Transform"](translation=translation, rotation=q),
                )
            )
        self.write(topic, T["tf2_msgs/msg/TFMessage"](transforms=stamped), t)


def write_realsense_like_bag(path, frames, cam=CAMERA, *, ros2=False, depth=True, poses=True, extra_colour=False):
    """A bag as realsense-ros records one: colour rgb8 and its camera info, depth 16UC1 (mm) registered to
    colour with its own camera info, each depth image 5 ms after its colour image; ground truth as a
    PoseStamped topic at twice the frame rate."""
    with BagWriter(path, ros2) as bag:
        for f in frames:
            t = f.timestamp
            bag.image("/camera/color/image_raw", t, np.round(f.rgb * 255).astype(np.uint8), "rgb8")
            bag.camera_info("/camera/color/camera_info", t, cam)
            if extra_colour:
                bag.image("/camera2/color/image_raw", t, np.round(f.rgb * 255).astype(np.uint8), "rgb8")
            if depth:
                mm = np.round(f.depth * 1000).astype(np.uint16)
                bag.image("/camera/aligned_depth_to_color/image_raw", t + 0.005, mm, "16UC1")
                bag.camera_info("/camera/aligned_depth_to_color/camera_info", t + 0.005, cam)
            if poses:
                bag.pose_stamped("/mocap/pose", t - 0.001, f.pose_gt)
                bag.pose_stamped("/mocap/pose", t + 1 / 60, f.pose_gt)  # a pose between frames, farther off
    return path


def assert_frames_match(got: list[Frame], frames: list[Frame], depth: bool = True, poses: bool = True):
    assert len(got) == len(frames)
    for g, f in zip(got, frames, strict=True):
        np.testing.assert_allclose(g.rgb, f.rgb, atol=0.5 / 255 + 1e-6)  # 8-bit colour
        if depth:
            np.testing.assert_allclose(g.depth, f.depth, atol=0.0005 + 1e-6)  # millimetres
        else:
            assert g.depth is None
        assert g.timestamp == pytest.approx(f.timestamp, abs=1e-6)
        if poses:
            np.testing.assert_allclose(g.pose_gt, f.pose_gt, atol=1e-9)
        else:
            assert g.pose_gt is None


def test_decode_image_reads_each_encoding():
    """Each encoding, row padding (step), big-endian depth, and the compressed forms, on messages with
    a live ROS message's fields."""
    rgb = np.arange(2 * 3 * 3, dtype=np.uint8).reshape(2, 3, 3) * 10

    def image(px, encoding, step=None, big=0):
        data = np.ascontiguousarray(px).view(np.uint8).reshape(px.shape[0], -1)
        if step is not None:  # rows padded to step bytes
            data = np.pad(data, ((0, 0), (0, step - data.shape[1])))
        return SimpleNamespace(
            height=px.shape[0], width=px.shape[1], encoding=encoding, is_bigendian=big, step=data.shape[1], data=data
        )

    kind, out = decode_image(image(rgb, "rgb8", step=12))
    assert kind == "colour" and out.dtype == np.float32
    np.testing.assert_allclose(out * 255, rgb, atol=1e-4)
    np.testing.assert_allclose(decode_image(image(rgb[:, :, ::-1], "bgr8"))[1], out)
    rgba = np.concatenate([rgb, np.full((2, 3, 1), 7, np.uint8)], axis=2)
    np.testing.assert_allclose(decode_image(image(rgba, "rgba8"))[1], out)
    assert decode_image(image(rgb[:, :, 0], "mono8"))[0] == "grey"
    mm = np.array([[0, 1000, 2500], [3, 4, 65535]], np.uint16)
    kind, depth = decode_image(image(mm, "16UC1"))
    assert kind == "depth"
    np.testing.assert_allclose(depth, mm * 0.001, rtol=1e-6)
    np.testing.assert_allclose(decode_image(image(mm.astype(">u2"), "16UC1", big=1))[1], depth)
    metres = np.array([[np.nan, 1.5, -1.0], [np.inf, 0.0, 2.25]], np.float32)
    np.testing.assert_array_equal(decode_image(image(metres, "32FC1"))[1], [[0, 1.5, 0], [0, 0, 2.25]])
    with pytest.raises(DatasetError, match="'yuv422' is not supported: record one of rgb8"):
        decode_image(image(rgb, "yuv422"))
    with pytest.raises(DatasetError, match="a row needs"):
        decode_image(SimpleNamespace(height=2, width=3, encoding="rgb8", is_bigendian=0, step=9, data=b"\0" * 10))
    with pytest.raises(DatasetError, match=r"^run.bag: frame at 1.5 s: colour: image encoding 'yuv422' is not"):
        frame_from_messages(image(rgb, "yuv422"), None, None, "run.bag: frame at 1.5 s")  # a message mid-bag

    def compressed(data, fmt):
        return SimpleNamespace(format=fmt, data=np.frombuffer(data, np.uint8))

    png = cv2.imencode(".png", rgb[:, :, ::-1])[1].tobytes()
    np.testing.assert_allclose(decode_image(compressed(png, "rgb8; png compressed bgr8"))[1], out)
    png16 = cv2.imencode(".png", mm)[1].tobytes()
    np.testing.assert_allclose(decode_image(compressed(png16, "16UC1; png compressed"))[1], depth)
    header = np.array([0], "<i4").tobytes() + np.array([0.0, 0.0], "<f4").tobytes()
    np.testing.assert_allclose(decode_image(compressed(header + png16, "16UC1; compressedDepth png"))[1], depth)
    # 32FC1 compressedDepth: stored as quant_a / depth + quant_b, 0 where there is no depth
    quant_a, quant_b = 100.0 * 101.0, 1.0 - 100.0 * 101.0 / 10.0
    inverse = np.array([[0, quant_a / 1.5 + quant_b, quant_a / 2.0 + quant_b]], np.float64)
    png_inv = cv2.imencode(".png", np.round(inverse).astype(np.uint16))[1].tobytes()
    header = np.array([0], "<i4").tobytes() + np.array([quant_a, quant_b], "<f4").tobytes()
    kind, inv_depth = decode_image(compressed(header + png_inv, "32FC1; compressedDepth"))
    np.testing.assert_allclose(inv_depth, [[0.0, 1.5, 2.0]], atol=2e-3)
    with pytest.raises(DatasetError, match="not readable"):
        decode_image(compressed(png[:20], "png"))


def test_camera_from_info_reads_ros1_and_ros2_fields():
    k = [500.0, 0, 319.5, 0, 510.0, 239.5, 0, 0, 1]
    ros2 = SimpleNamespace(k=k, d=[0.0] * 5, width=640, height=480)
    assert camera_from_info(ros2) == Camera(500.0, 510.0, 319.5, 239.5, 640, 480)
    ros1 = SimpleNamespace(K=k, D=[0.1, 0.0, 0.0, 0.0, 0.0], width=0, height=0)
    cam = camera_from_info(ros1, size=(640, 480))
    assert (cam.width, cam.height, cam.fx, cam.cy) == (640, 480, 500.0, 239.5) and cam.distortion[0] == 0.1


def test_stamp_pairing_pairs_the_nearest_once_and_counts_what_it_drops():
    """Nearest depth within max_dt, each depth image given once; a frame waits until no nearer message can
    come; a frame without depth is dropped and counted."""
    pairing = StampPairing(0.02, depth=True, need_depth=True, poses=False)
    out = pairing.add_colour(1.000, "c0") + pairing.add_depth(0.990, "d0") + pairing.add_depth(1.004, "d1")
    out += pairing.add_colour(1.008, "c1")
    assert out == []  # a nearer depth image may still come until one later than 1.02 s
    out += pairing.add_depth(1.050, "d2")
    # c0 takes its nearest, d1, which is c1's nearest too: c1 gets d0, 18 ms off
    assert [(c, d) for _, c, d, _ in out] == [("c0", "d1"), ("c1", "d0")]
    assert pairing.add_colour(1.100, "c2") == [] and pairing.finish() == []  # no depth within 20 ms of c2
    assert pairing.without_depth == 1 and "1 of 3 colour frames dropped: 1 without a depth image" in pairing.dropped()
    mono = StampPairing(0.02, depth=False, need_depth=False, poses=True)
    got = mono.add_colour(2.0, "c") + mono.add_pose(1.99, "far") + mono.add_pose(2.001, "near")
    got += mono.add_pose(2.5, "later")
    assert [(c, d, p) for _, c, d, p in got] == [("c", None, "near")]


def test_ros1_bag_reads_as_recorded(tmp_path):
    """A ROS 1 bag as realsense-ros records it: nothing to name (one colour and one depth topic, their
    camera infos), the camera from CameraInfo, depth in millimetres, the poses of the named pose topic."""
    frames = scene_frames()
    bag = write_realsense_like_bag(tmp_path / "run.bag", frames)
    cfg = load_config(["dataset.type=rosbag", f"dataset.path={bag}", "dataset.pose_topic=/mocap/pose"])
    ds = open_dataset(cfg)
    assert isinstance(ds, RosbagDataset) and len(ds) == len(frames) and ds.camera == CAMERA
    assert_frames_match(list(ds), frames)
    np.testing.assert_allclose(ds.gt_poses(), [f.pose_gt for f in frames], atol=1e-9)
    assert "RosbagDataset" in repr(ds) and "5 frames, 32x24" in repr(ds)
    with pytest.warns(DatasetWarning, match=r"no ground truth read: the bag has pose topics /mocap/pose"):
        ds = open_dataset(load_config(["dataset.type=rosbag", f"dataset.path={bag}", "dataset.stride=2"]))
    assert len(ds) == 3 and ds.gt_poses() is None and ds[1].timestamp == pytest.approx(frames[2].timestamp)


def test_ros2_bag_as_a_stream_gives_the_dataset_frames(tmp_path):
    """A ROS 2 bag (compressed colour, 32FC1 depth, TF ground truth) read as a dataset and played as a
    stream (``dataset.stream=true``): the same frames, in order."""
    frames = scene_frames(6)
    with BagWriter(tmp_path / "ros2", ros2=True) as bag:
        for f in frames:
            t = f.timestamp
            bag.compressed("/cam/image_raw/compressed", t, np.round(f.rgb[:, :, ::-1] * 255).astype(np.uint8), "png")
            bag.camera_info("/cam/camera_info", t, CAMERA)
            bag.image("/cam/depth", t + 0.01, f.depth, "32FC1")
            bag.tf("/tf", t, {"camera": f.pose_gt, "base": np.eye(4)})
    keys = ["dataset.type=rosbag", f"dataset.path={tmp_path / 'ros2'}", "dataset.pose_topic=/tf"]
    with pytest.raises(DatasetError, match="transforms to base, camera: name the camera's with dataset.pose_frame"):
        open_dataset(load_config(keys))
    keys.append("dataset.pose_frame=camera")
    dataset = list(open_dataset(load_config(keys)))
    source = open_dataset(load_config([*keys, "dataset.stream=true"]))
    assert isinstance(source, RosbagSource) and source.camera == CAMERA
    streamed = list(source)
    for got in (dataset, streamed):
        assert_frames_match(got, frames)
    assert [f.index for f in streamed] == list(range(6))
    # a .db3 file names its bag folder; max_frames stops the stream early
    db3 = next((tmp_path / "ros2").glob("*.db3"))
    keys[1] = f"dataset.path={db3}"
    assert len(list(open_dataset(load_config([*keys, "dataset.max_frames=2"])))) == 2


def test_a_bag_whose_camera_info_gives_distortion_is_undistorted(tmp_path):
    """Frames recorded through a barrel lens (CameraInfo plumb_bob k1): read as a dataset and as a stream,
    both are the pinhole camera's images again, depth remapped alike (nearest); read as if the lens were
    a pinhole, the periphery is off."""
    cam, k1 = Camera(150.0, 150.0, 79.5, 59.5, 160, 120), -0.2
    v, u = np.mgrid[0:120, 0:160].astype(np.float32)
    pinhole = 0.5 + 0.4 * np.sin(u / 5.0) * np.cos(v / 4.0)
    q = np.stack([u.ravel(), v.ravel()], axis=1)[:, None, :].astype(np.float64)
    p = cv2.undistortPoints(q, cam.K, np.array([k1, 0.0, 0.0, 0.0, 0.0]), P=cam.K).reshape(120, 160, 2)
    recorded = cv2.remap(pinhole, p[..., 0].astype(np.float32), p[..., 1].astype(np.float32), cv2.INTER_LINEAR)
    depth = np.where(u < 20, 1500, 2500).astype(np.uint16)  # a step: nearest keeps both surfaces, nothing between
    for name, distortion in (("lens", (k1, 0.0, 0.0, 0.0, 0.0)), ("pinhole", (0.0,) * 5)):
        with BagWriter(tmp_path / f"{name}.bag", ros2=False) as bag:
            for t in (0.0, 0.1):
                bag.image("/rgb", t, np.repeat(np.rint(recorded * 255).astype(np.uint8)[..., None], 3, axis=2), "rgb8")
                bag.camera_info("/camera_info", t, cam, distortion)
                bag.image("/depth", t, depth, "16UC1")
    inner = (slice(6, -6), slice(6, -6))
    keys = ["dataset.type=rosbag", f"dataset.path={tmp_path / 'lens.bag'}"]
    dataset, streamed = (
        open_dataset(load_config(keys))[0],
        next(iter(open_dataset(load_config([*keys, "dataset.stream=true"])))),
    )
    as_is = RosbagDataset(tmp_path / "pinhole.bag")[0]
    err_as_is = np.abs(as_is.rgb[..., 0] - pinhole)[inner].mean()
    for f in (dataset, streamed):
        err = np.abs(f.rgb[..., 0] - pinhole)[inner].mean()
        assert err < 0.01 and err_as_is > 5 * err
        np.testing.assert_allclose(np.unique(f.depth), [1.5, 2.5], rtol=1e-6)
    assert (dataset.depth < 2.0).sum() < 0.9 * (
        as_is.depth < 2.0
    ).sum()  # the border's surface moved out as its colour did


def test_ambiguous_topics_are_listed_with_the_keys_that_choose(tmp_path):
    frames = scene_frames(3)
    bag = write_realsense_like_bag(tmp_path / "two.bag", frames, extra_colour=True)
    with pytest.raises(DatasetError) as err:
        open_dataset(load_config(["dataset.type=rosbag", f"dataset.path={bag}"]))
    message = str(err.value)
    assert "2 colour image topics (/camera/color/image_raw, /camera2/color/image_raw)" in message
    assert "dataset.rgb_topic=TOPIC dataset.depth_topic=TOPIC" in message
    assert "/camera2/color/image_raw  sensor_msgs/msg/Image  3 messages  (colour 32x24 rgb8)" in message
    assert "/camera/aligned_depth_to_color/image_raw  sensor_msgs/msg/Image  3 messages  (depth 32x24 16UC1)" in message
    assert "/mocap/pose  geometry_msgs/msg/PoseStamped  6 messages" in message
    chosen = ["dataset.type=rosbag", f"dataset.path={bag}", "dataset.rgb_topic=/camera2/color/image_raw"]
    with pytest.raises(DatasetError, match="2 CameraInfo topics .*: name one with dataset.camera_info_topic=TOPIC"):
        open_dataset(load_config(chosen))  # /camera2/color has no camera_info of its own
    chosen.append("dataset.camera_info_topic=/camera/color/camera_info")
    ds = open_dataset(load_config([*chosen, "dataset.pose_topic=/mocap/pose"]))
    assert ds.topics.colour.name == "/camera2/color/image_raw" and ds.topics.info.name == "/camera/color/camera_info"
    assert_frames_match(list(ds), frames)
    with pytest.raises(DatasetError, match="dataset.depth_topic=/nope: the bag has no such topic"):
        open_dataset(load_config([*chosen, "dataset.depth_topic=/nope"]))
    with pytest.raises(DatasetError, match="a geometry_msgs/msg/PoseStamped topic, expected sensor_msgs"):
        open_dataset(load_config([*chosen, "dataset.depth_topic=/mocap/pose"]))


def test_a_bag_without_depth_runs_monocular_when_asked(tmp_path):
    frames = scene_frames(4)
    bag = write_realsense_like_bag(tmp_path / "mono.bag", frames, depth=False, poses=False)
    keys = ["dataset.type=rosbag", f"dataset.path={bag}"]
    with pytest.raises(DatasetError, match="no depth image topic .*: run monocular with mode=mono"):
        open_dataset(load_config(keys))
    ds = open_dataset(load_config([*keys, "mode=mono"]))
    assert_frames_match(list(ds), frames, depth=False, poses=False)
    streamed = list(open_dataset(load_config([*keys, "mode=mono", "dataset.stream=true"])))
    assert_frames_match(streamed, frames, depth=False, poses=False)


def test_rosbag_errors_name_the_bag_and_the_problem(tmp_path, monkeypatch):
    frames = scene_frames(3)
    with pytest.raises(DatasetError, match="dataset.type=rosbag needs dataset.path=BAG"):
        open_dataset(load_config(["dataset.type=rosbag"]))
    with pytest.raises(DatasetError, match=r"ROS bag .*missing.bag does not exist"):
        RosbagDataset(tmp_path / "missing.bag")
    (tmp_path / "junk.bag").write_bytes(b"not a bag")
    with pytest.raises(DatasetError, match="junk.bag: not a readable ROS bag"):
        RosbagDataset(tmp_path / "junk.bag")
    with BagWriter(tmp_path / "noinfo.bag", ros2=False) as bag:
        for f in frames:
            bag.image("/rgb", f.timestamp, np.round(f.rgb * 255).astype(np.uint8), "rgb8")
            bag.image("/depth", f.timestamp, np.round(f.depth * 1000).astype(np.uint16), "16UC1")
            bag.image("/depth_small", f.timestamp, np.zeros((12, 16), np.uint16), "16UC1")
    with pytest.raises(DatasetError, match="no sensor_msgs/CameraInfo topic: /rgb's intrinsics are unknown"):
        RosbagDataset(tmp_path / "noinfo.bag", depth_topic="/depth")
    with BagWriter(tmp_path / "distorted.bag", ros2=False) as bag:
        for f in frames:
            bag.image("/rgb", f.timestamp, np.round(f.rgb * 255).astype(np.uint8), "rgb8")
            bag.camera_info("/camera_info", f.timestamp, CAMERA, (0.1, 0.0, 0.0, 0.0), model="equidistant")
            bag.image("/depth", f.timestamp, np.zeros((12, 16), np.uint16), "16UC1")
    with pytest.warns(DatasetWarning, match=r"gives distortion model 'equidistant' \(0.1, 0.0, 0.0, 0.0\): not undone"):
        ds = RosbagDataset(tmp_path / "distorted.bag")
    with pytest.raises(DatasetError, match="depth is 16x12, colour 32x24: depth must be registered to the colour"):
        ds[0]
    # an image topic in an encoding not read (here an infrared camera's) is listed, and used only if named
    with BagWriter(tmp_path / "ir.bag", ros2=False) as bag:
        for f in frames:
            bag.image("/rgb", f.timestamp, np.round(f.rgb * 255).astype(np.uint8), "rgb8")
            bag.image("/ir", f.timestamp, np.round(f.rgb * 255).astype(np.uint8), "yuv422")
            bag.camera_info("/camera_info", f.timestamp, CAMERA)
            bag.image("/depth", f.timestamp, np.round(f.depth * 1000).astype(np.uint16), "16UC1")
    assert RosbagDataset(tmp_path / "ir.bag")[0].rgb.shape == (CAMERA.height, CAMERA.width, 3)
    with pytest.raises(DatasetError, match=r"ir.bag: dataset.rgb_topic=/ir: image encoding 'yuv422' is not supp"):
        RosbagDataset(tmp_path / "ir.bag", rgb_topic="/ir")
    monkeypatch.setitem(sys.modules, "rosbags.highlevel", None)  # as if not installed
    with pytest.raises(DatasetError, match=r"pip install 'rgs_warp\[rosbag\]'"):
        RosbagDataset(tmp_path / "distorted.bag")


@pytest.mark.slow
@pytest.mark.parametrize("mode, stream", [("rgbd", False), ("rgbd", True), ("mono", False)])
def test_slam_on_a_bag_through_the_command_line(tmp_path, device, mode, stream):
    """``python -m rgs_warp.slam dataset.type=rosbag dataset.path=BAG``: a recording of the generated office
    at a CPU size, its ground truth from the pose topic, read indexed, as a stream,
    and monocular from a bag without depth; the streamed one is a ROS 2 bag, the others ROS 1."""
    from rgs_warp.app.cli import main

    scene = open_dataset(load_config(["dataset=synthetic/office0", "dataset.width=128", "dataset.height=72"]))
    frames = [scene[k] for k in range(12)]
    for k, f in enumerate(frames):
        f.timestamp = 5.0 + k / 30.0
    path = tmp_path / ("office" if stream else "office.bag")
    bag = write_realsense_like_bag(path, frames, scene.camera, ros2=stream, depth=mode == "rgbd")
    iters = (40, 2) if mode == "rgbd" else (40, 4)
    argv = [
        "dataset.type=rosbag",
        f"dataset.path={bag}",
        "dataset.pose_topic=/mocap/pose",
        f"dataset.stream={str(stream).lower()}",
        f"mode={mode}",
        f"mapping.init_iters={iters[0]}",
        f"mapping.iters_per_frame={iters[1]}",
        "mapping.window=3",
        *(f"device={device}", f"output_dir={tmp_path}", "run_name=bag"),
    ]
    assert main(argv) == 0
    metrics = json.loads((tmp_path / "bag" / "metrics.json").read_text())
    assert metrics["frames"] == 12
    # measured on CPU: RGB-D 0.43 cm and 25.6 dB indexed and streamed alike, monocular 3.6 cm (Sim(3)) and 14.1 dB
    assert metrics["ate"]["all_frames"]["rmse_cm"] < (3.0 if mode == "rgbd" else 8.0), metrics["ate"]
    assert metrics["photometric"]["psnr_db"] > (20.0 if mode == "rgbd" else 12.0)
