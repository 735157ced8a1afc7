"""Frame sources of unknown length: ``CallbackSource`` (frames from any producer: a ROS subscriber, a
camera SDK) and ``RealSenseSource`` (an Intel RealSense D4xx camera, live or a recording, through
pyrealsense2).

A source has a ``camera`` and yields ``Frame``s; unlike the dataset loaders it has no length and no
random access (``rgs_warp.run.run`` keeps the frames its evaluation reads again).  ``open_dataset``
gives a ``RealSenseSource`` for ``dataset.type=realsense``; ``run(cfg, source=...)`` runs any source.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable, Iterator
from pathlib import Path

import cv2
import numpy as np

from rgs_warp.datasets.base import DatasetError
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
    undistort_maps=None,
) -> Frame:
    """A ``Frame`` from a RealSense frame pair: ``colour`` HxWx3 or 4 uint8 in ``colour_format``
    (rgb8, bgr8, rgba8, bgra8), ``depth_raw`` HxW uint16 already aligned to the colour camera, in
    units of ``depth_scale_m`` metres (0 = no depth), ``timestamp_ms`` librealsense's milliseconds;
    ``undistort_maps`` (OpenCV's remap maps) undistort both images."""
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
    if undistort_maps is not None:
        rgb = cv2.remap(rgb, *undistort_maps, cv2.INTER_LINEAR)
        if depth is not None:  # nearest: no depth between two surfaces
            depth = cv2.remap(depth, *undistort_maps, cv2.INTER_NEAREST)
    return Frame(rgb, depth, None, float(timestamp_ms) / 1000.0, index)


class RealSenseSource(CallbackSource):
    """RGB-D frames from an Intel RealSense camera through pyrealsense2: a live D4xx (``recording``
    None; ``width`` x ``height`` at ``fps``, ``serial`` picks one of several cameras) or a recording
    (``recording``: the file ``rs.recorder`` or the RealSense Viewer wrote), played back frame by
    frame (not in real time).  Depth is aligned to the colour camera by librealsense (``rs.align``),
    the camera is the colour stream's intrinsics, depth is the raw values x the device's depth scale.
    ``skip_frames`` drops the first frames of a live camera (auto-exposure settling)."""

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
        config = rs.config()
        if recording:
            path = Path(recording).expanduser()
            if not path.is_file():
                raise DatasetError(f"RealSense recording {path} does not exist")
            config.enable_device_from_file(str(path), repeat_playback=False)
            name = path.name
        else:
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
        self._live = not recording
        self._playback = None
        if recording:  # every frame, as fast as SLAM takes them: paused while SLAM works on one
            self._playback = device.as_playback()
            self._playback.set_real_time(False)
        self.depth_scale_m = float(device.first_depth_sensor().get_depth_scale())
        colour = profile.get_stream(rs.stream.color).as_video_stream_profile()
        camera = camera_from_intrinsics(colour.get_intrinsics())
        self._undistort_maps = None
        if camera.distortion:
            self._undistort_maps = cv2.initUndistortRectifyMap(
                camera.K, np.array(camera.distortion), None, camera.K, (camera.width, camera.height), cv2.CV_32FC1
            )
            camera = camera.undistorted()
        self._align = rs.align(rs.stream.color)
        self._skip = skip_frames
        self._stopped = False
        super().__init__(camera, self._next, max_frames=max_frames, name=f"realsense {name}")

    def _next(self) -> Frame | None:
        while True:
            if self._stopped:
                return None
            if self._playback is not None:
                self._playback.resume()
            ok, frames = self._pipeline.try_wait_for_frames(self._timeout_ms)
            if self._playback is not None and ok:
                self._playback.pause()
            if not ok:  # a recording's end (or a live camera that stopped sending)
                if self._live:
                    raise DatasetError(f"{self.name}: no frames for {self._timeout_ms} ms")
                self.close()
                return None
            if self._skip > 0:
                self._skip -= 1
                continue
            aligned = self._align.process(frames)
            colour, depth = aligned.get_color_frame(), aligned.get_depth_frame()
            if not colour or not depth:
                # a set without one of the two streams: librealsense's syncer learns the streams from
                # the frames it sees, so a recording's first depth image may come alone (then skipped)
                continue
            fmt = str(colour.get_profile().format()).rsplit(".", 1)[-1]
            return frame_from_images(
                np.asanyarray(colour.get_data()),
                fmt,
                np.asanyarray(depth.get_data()),
                self.depth_scale_m,
                colour.get_timestamp(),
                undistort_maps=self._undistort_maps,
            )

    def close(self) -> None:
        """Stop streaming (also at a recording's end)."""
        if not self._stopped:
            self._stopped = True
            try:
                self._pipeline.stop()
            except RuntimeError:
                pass
