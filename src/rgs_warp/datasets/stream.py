"""Frame sources of unknown length: ``CallbackSource`` (frames from any producer: a ROS subscriber, a
camera SDK) and ``RealSenseSource`` (an Intel RealSense D4xx camera, live or a recording, through
pyrealsense2).

A source has a ``camera`` and yields ``Frame``s; unlike the dataset loaders it has no length and no
random access (``rgs_warp.app.runner.run`` keeps the frames its evaluation reads again).  ``open_dataset``
gives a ``RealSenseSource`` for ``dataset.type=realsense``; ``run(cfg, source=...)`` runs any source.
"""

from __future__ import annotations

import importlib
import queue
import threading
from collections.abc import Callable, Iterator
from pathlib import Path

import cv2
import numpy as np

from rgs_warp.datasets.base import DatasetError, reproject_depth, undistort_frame, undistort_maps
from rgs_warp.types import Camera, Frame


class CallbackSource:
    """Frames from ``next_frame()``, called once per frame: it returns the next ``Frame`` (``rgb`` HxWx3
    float32 in [0, 1], ``depth`` HxW metres or None, ``pose_gt`` or None, ``timestamp`` in seconds;
    its ``index`` is set here) or None when the sequence ends.  It may block until a frame arrives
    (a queue filled by a subscriber's callback).  ``max_frames`` stops after that many."""

    def __init__(
        self,
        camera: Camera,
        next_frame: Callable[[], Frame | None],
        max_frames: int | None = None,
        name: str = "callback",
    ):
        if max_frames is not None and max_frames < 1:
            raise ValueError(f"max_frames must be >= 1 or None, got {max_frames}")
        self._camera, self._next_frame, self.max_frames, self.name = camera, next_frame, max_frames, name
        self.notes: list[str] = []

    @property
    def camera(self) -> Camera:
        return self._camera

    native_camera = camera

    def __iter__(self) -> Iterator[Frame]:
        index = 0
        while self.max_frames is None or index < self.max_frames:
            frame = self._next_frame()
            if frame is None:
                return
            if not isinstance(frame, Frame):
                raise TypeError(f"{self.name}: next_frame() returned {type(frame).__name__}, not a Frame or None")
            frame.index = index
            yield frame
            index += 1

    def __repr__(self) -> str:
        c = self.camera
        intrinsics = f"fx={c.fx:g} fy={c.fy:g} cx={c.cx:g} cy={c.cy:g}"
        return f"{type(self).__name__}({self.name!r}, {c.width}x{c.height}, {intrinsics})"


# ---- Intel RealSense ---------------------------------------------------------------------------------
# colour formats a D4xx streams, and the channel order that makes them RGB
_COLOUR_ORDER = {"rgb8": (0, 1, 2), "bgr8": (2, 1, 0), "rgba8": (0, 1, 2), "bgra8": (2, 1, 0)}


def import_realsense():
    """pyrealsense2, or a DatasetError that says how to install it."""
    try:
        return importlib.import_module("pyrealsense2")
    except ImportError as e:
        raise DatasetError(
            f"dataset.type=realsense needs pyrealsense2 ({e}): pip install 'rgs_warp[realsense]' (wheels for "
            f"x86_64 Linux, Windows and macOS; elsewhere build librealsense with its Python bindings)"
        ) from None


def camera_from_intrinsics(intrinsics) -> Camera:
    """Our ``Camera`` from a pyrealsense2 ``rs.intrinsics`` (width, height, ppx, ppy, fx, fy, coeffs):
    librealsense's principal point is in the same pixel-centre convention as OpenCV's and ours.
    Non-zero distortion coefficients are kept as OpenCV's (k1, k2, p1, p2, k3) for the frames to be
    undistorted (D4xx colour streams report zeros)."""
    coeffs = tuple(float(c) for c in getattr(intrinsics, "coeffs", ()) or ())
    distortion = coeffs[:5] if any(abs(c) > 0 for c in coeffs) else ()
    return Camera(
        float(intrinsics.fx),
        float(intrinsics.fy),
        float(intrinsics.ppx),
        float(intrinsics.ppy),
        int(intrinsics.width),
        int(intrinsics.height),
        distortion,
    )


def frame_from_images(
    colour: np.ndarray,
    colour_format: str,
    depth_raw: np.ndarray | None,
    depth_scale_m: float,
    timestamp_ms: float,
    index: int = 0,
    undistort=None,
) -> Frame:
    """A ``Frame`` from a RealSense frame pair: ``colour`` HxWx3 or 4 uint8 in ``colour_format``
    (rgb8, bgr8, rgba8, bgra8), ``depth_raw`` HxW uint16 already aligned to the colour camera, in
    units of ``depth_scale_m`` metres (0 = no depth), ``timestamp_ms`` librealsense's milliseconds;
    ``undistort`` (``base.undistort_maps``' maps) undistorts both images."""
    order = _COLOUR_ORDER.get(colour_format)
    if order is None:
        raise DatasetError(
            f"RealSense colour format {colour_format!r} is not supported: stream one of {', '.join(_COLOUR_ORDER)}"
        )
    if colour.dtype != np.uint8 or colour.ndim != 3 or colour.shape[2] < 3:
        raise DatasetError(f"RealSense colour: expected HxWx3 uint8, got {colour.dtype} {colour.shape}")
    rgb = np.ascontiguousarray(colour[:, :, list(order)], dtype=np.float32) / np.float32(255.0)
    depth = None
    if depth_raw is not None:
        if depth_raw.shape != rgb.shape[:2]:
            raise DatasetError(
                f"RealSense depth is {depth_raw.shape[1]}x{depth_raw.shape[0]}, colour {rgb.shape[1]}x{rgb.shape[0]}: "
                f"depth must be aligned to colour"
            )
        depth = depth_raw.astype(np.float32) * np.float32(depth_scale_m)
    rgb, depth = undistort_frame(undistort, rgb, depth, source=f"RealSense frame {index}")
    return Frame(rgb, depth, None, float(timestamp_ms) / 1000.0, index)


class RealSenseSource(CallbackSource):
    """RGB-D frames from an Intel RealSense camera through pyrealsense2: a live D4xx (``recording``
    None; ``width`` x ``height`` at ``fps``, ``serial`` picks one of several cameras) or a recording
    (``recording``: the file ``rs.recorder`` or the RealSense Viewer wrote), played back frame by
    frame (not in real time).  The camera is the colour stream's intrinsics (undistorted where it
    reports distortion), depth is the raw values x the device's depth scale, registered to the colour
    camera: by librealsense (``rs.align``) for a live camera; for a recording by ``reproject_depth``
    with the recorded intrinsics and extrinsics, on every frame pair the file holds
    (``RecordingFrames``).  ``skip_frames`` drops the first frames of a live camera (auto-exposure
    settling)."""

    def __init__(
        self,
        recording: str | Path | None = None,
        *,
        width: int = 640,
        height: int = 480,
        fps: int = 30,
        serial: str = "",
        max_frames: int | None = None,
        skip_frames: int = 0,
        timeout_ms: int = 5000,
        rs=None,
    ):
        rs = import_realsense() if rs is None else rs
        self._timeout_ms = timeout_ms
        self._skip = skip_frames
        self._stopped = False
        self._recording = self._pipeline = None
        if recording:
            path = Path(recording).expanduser()
            if not path.is_file():
                raise DatasetError(f"RealSense recording {path} does not exist")
            self._recording = RecordingFrames(rs, path, timeout_ms)
            self.depth_scale_m = self._recording.depth_scale_m
            camera = camera_from_intrinsics(self._recording.colour_intrinsics)
            name = path.name
        else:
            config = rs.config()
            if serial:
                config.enable_device(serial)
            config.enable_stream(rs.stream.depth, width, height, rs.format.z16, fps)
            config.enable_stream(rs.stream.color, width, height, rs.format.rgb8, fps)
            name = f"live {serial or 'camera'}"
            self._pipeline = rs.pipeline()
            try:
                profile = self._pipeline.start(config)
            except RuntimeError as e:
                raise DatasetError(f"RealSense {name}: cannot start streaming: {e}") from None
            device = profile.get_device()
            self.depth_scale_m = float(device.first_depth_sensor().get_depth_scale())
            colour = profile.get_stream(rs.stream.color).as_video_stream_profile()
            camera = camera_from_intrinsics(colour.get_intrinsics())
            self._align = rs.align(rs.stream.color)
        self._undistort_maps = undistort_maps(camera, camera.distortion, f"RealSense {name} colour distortion")
        camera = camera.undistorted()
        super().__init__(camera, self._next, max_frames=max_frames, name=f"realsense {name}")

    def _next(self) -> Frame | None:
        if self._stopped:
            return None
        if self._recording is not None:
            pair = self._recording.next_pair()
            if pair is None:  # the recording's end
                self.close()
                return None
            depth, colour = pair
            fmt = str(colour.get_profile().format()).rsplit(".", 1)[-1]
            frame = frame_from_images(
                np.asanyarray(colour.get_data()),
                fmt,
                None,
                1.0,
                colour.get_timestamp(),
                undistort=self._undistort_maps,
            )
            frame.depth = self._recording.registered_depth(depth, self.camera)
            return frame
        while True:
            ok, frames = self._pipeline.try_wait_for_frames(self._timeout_ms)
            if not ok:
                raise DatasetError(f"{self.name}: no frames for {self._timeout_ms} ms")
            if self._skip > 0:
                self._skip -= 1
                continue
            aligned = self._align.process(frames)
            colour, depth = aligned.get_color_frame(), aligned.get_depth_frame()
            if not colour or not depth:
                continue  # a set without one of the two streams
            fmt = str(colour.get_profile().format()).rsplit(".", 1)[-1]
            return frame_from_images(
                np.asanyarray(colour.get_data()),
                fmt,
                np.asanyarray(depth.get_data()),
                self.depth_scale_m,
                colour.get_timestamp(),
                undistort=self._undistort_maps,
            )

    def close(self) -> None:
        """Stop streaming (also at a recording's end)."""
        if not self._stopped:
            self._stopped = True
            if self._recording is not None:
                self._recording.close()
                return
            try:
                self._pipeline.stop()
            except RuntimeError:
                pass


class RecordingFrames:
    """Every depth and colour frame of a RealSense recording, in order, paired by time.

    The recording plays back as fast as it is read (``set_real_time(False)``) into each sensor's
    callback, which hands the frame to a queue of ``QUEUE`` frames and waits while it is full: the
    playback waits for the reader, so no frame is dropped however slowly the SLAM takes them.  (The
    pipeline API drops what its one-set queue cannot hold, and pausing the playback between sets
    lost or repeated sets now and then.)  The playback is paused while the
    sensors start, so the first frames of the stream started last are not read before it listens.
    A depth and a colour frame within half a frame period of each other are a pair; a frame left
    without a partner (a stream that skipped one) is dropped."""

    QUEUE = 4

    def __init__(self, rs, path: Path, timeout_ms: int = 5000):
        self._rs, self.path, self._timeout_s = rs, path, timeout_ms / 1000.0
        try:
            self._device = rs.context().load_device(str(path))
        except RuntimeError as e:
            raise DatasetError(f"RealSense recording {path}: cannot open it: {e}") from None
        self._playback = self._device.as_playback()
        self._playback.set_real_time(False)
        chosen: dict = {}  # stream type -> (sensor, profile)
        for sensor in self._device.query_sensors():
            for profile in sensor.get_stream_profiles():
                kind = profile.stream_type()
                if kind in (rs.stream.depth, rs.stream.color) and kind not in chosen:
                    chosen[kind] = (sensor, profile)
        missing = [
            name for kind, name in ((rs.stream.depth, "depth"), (rs.stream.color, "colour")) if kind not in chosen
        ]
        if missing:
            raise DatasetError(f"RealSense recording {path}: it holds no {' and no '.join(missing)} stream")
        (depth_sensor, depth_profile), (colour_sensor, colour_profile) = (
            chosen[rs.stream.depth],
            chosen[rs.stream.color],
        )
        self.depth_scale_m = float(depth_sensor.as_depth_sensor().get_depth_scale())
        self.depth_intrinsics = depth_profile.as_video_stream_profile().get_intrinsics()
        self.colour_intrinsics = colour_profile.as_video_stream_profile().get_intrinsics()
        extrinsics = depth_profile.get_extrinsics_to(colour_profile)
        # librealsense's rotation is column-major: a depth-camera point p is R p + t in the colour camera's
        self._rotation = np.array(extrinsics.rotation, dtype=np.float64).reshape(3, 3).T
        self._translation = np.array(extrinsics.translation, dtype=np.float64)
        self._depth_camera = camera_from_intrinsics(self.depth_intrinsics)
        cam = self._depth_camera
        self._depth_undistort = undistort_maps(cam, cam.distortion, f"{path} depth distortion")
        self._depth_camera = cam.undistorted()
        self._half_period_ms = 500.0 / max(float(colour_profile.fps()), 1.0)
        self._queue: queue.Queue = queue.Queue(maxsize=self.QUEUE)
        self._closed = threading.Event()
        self._sensors = []
        for sensor in (depth_sensor, colour_sensor):
            if sensor not in self._sensors:
                self._sensors.append(sensor)
        for sensor in self._sensors:
            sensor.open([p for (s, p) in chosen.values() if s == sensor])
        self._playback.pause()
        for sensor in self._sensors:
            sensor.start(self._hand_over)
        self._playback.resume()
        self._pending: dict = {rs.stream.depth: None, rs.stream.color: None}

    def _hand_over(self, frame) -> None:
        """A sensor's callback (librealsense's thread): keep the frame and queue it, waiting while the
        queue is full (the playback waits meanwhile) unless the reader closed."""
        frame.keep()
        while not self._closed.is_set():
            try:
                self._queue.put(frame, timeout=0.1)
                return
            except queue.Full:
                continue

    def next_pair(self):
        """The next (depth frame, colour frame) of one instant, or None at the recording's end."""
        rs, pending = self._rs, self._pending
        waited = 0.0
        while True:
            try:
                frame = self._queue.get(timeout=0.05)
            except queue.Empty:
                if self._playback.current_status() == rs.playback_status.stopped and self._queue.empty():
                    return None
                waited += 0.05
                if waited > self._timeout_s:
                    raise DatasetError(f"RealSense recording {self.path}: no frame for {self._timeout_s:g} s") from None
                continue
            waited = 0.0
            pending[frame.get_profile().stream_type()] = frame
            depth, colour = pending[rs.stream.depth], pending[rs.stream.color]
            if depth is None or colour is None:
                continue
            lag_ms = depth.get_timestamp() - colour.get_timestamp()
            if abs(lag_ms) <= self._half_period_ms:
                pending[rs.stream.depth] = pending[rs.stream.color] = None
                return depth, colour
            pending[rs.stream.depth if lag_ms < 0 else rs.stream.color] = None  # the older one has no partner

    def registered_depth(self, depth_frame, colour_camera: Camera) -> np.ndarray:
        """``depth_frame`` in metres, registered to ``colour_camera`` (the colour stream's, undistorted)."""
        depth = np.asanyarray(depth_frame.get_data()).astype(np.float32) * np.float32(self.depth_scale_m)
        if self._depth_undistort is not None:  # nearest: no depth between two surfaces
            depth = cv2.remap(depth, *self._depth_undistort, cv2.INTER_NEAREST)
        same = (
            np.allclose(self._rotation, np.eye(3), atol=1e-9)
            and not np.any(self._translation)
            and self._depth_camera == colour_camera
        )
        if same:
            return depth
        return reproject_depth(depth, self._depth_camera, colour_camera, self._translation, self._rotation)

    def close(self) -> None:
        self._closed.set()
        for sensor in self._sensors:
            for stop in (sensor.stop, sensor.close):
                try:
                    stop()
                except RuntimeError:
                    pass
