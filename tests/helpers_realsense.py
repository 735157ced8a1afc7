"""A RealSense recording written without a camera: pyrealsense2's software device plays a D4xx (a
depth sensor, z16 in depth units, and a colour sensor) and ``rs.recorder`` records what it streams,
as the RealSense Viewer records a real camera (librealsense 2.59 writes ROS 2 ``.db3`` files)."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np


def _intrinsics(rs, camera):
    intr = rs.intrinsics()
    intr.width, intr.height = camera.width, camera.height
    intr.fx, intr.fy, intr.ppx, intr.ppy = camera.fx, camera.fy, camera.cx, camera.cy
    intr.model, intr.coeffs = rs.distortion.none, [0.0] * 5
    return intr


def write_recording(
    path: Path,
    camera,
    frames,
    depth_units_m: float = 0.001,
    colour_format: str = "bgr8",
    fps=30,
    depth_to_colour=None,
):
    """Record ``frames`` (our ``Frame``s: rgb float in [0, 1], depth metres) as a RealSense camera
    would stream them: colour as 8-bit ``colour_format``, depth as uint16 in ``depth_units_m``, both
    with ``camera``'s intrinsics, and ``depth_to_colour`` (R, t: a depth-camera point p is R p + t in
    the colour camera's coordinates; default none) as the depth stream's extrinsics.  Returns the file's path."""
    import pyrealsense2 as rs

    device = rs.software_device()
    sensors, profiles = [], []
    for uid, (name, kind, fmt, bpp) in enumerate(
        (("Depth", rs.stream.depth, rs.format.z16, 2), ("Color", rs.stream.color, getattr(rs.format, colour_format), 3))
    ):
        sensor = device.add_sensor(name)
        stream = rs.video_stream()
        stream.type, stream.index, stream.uid = kind, 0, uid
        stream.width, stream.height, stream.fps, stream.bpp, stream.fmt = camera.width, camera.height, fps, bpp, fmt
        stream.intrinsics = _intrinsics(rs, camera)
        profiles.append(sensor.add_video_stream(stream))
        sensors.append(sensor)
    sensors[0].add_read_only_option(rs.option.depth_units, depth_units_m)
    extrinsics = rs.extrinsics()
    R, t = depth_to_colour if depth_to_colour is not None else (np.eye(3), np.zeros(3))
    # librealsense stores the rotation column-major
    extrinsics.rotation, extrinsics.translation = [float(v) for v in np.asarray(R).T.ravel()], [float(v) for v in t]
    profiles[0].register_extrinsics_to(profiles[1], extrinsics)
    device.create_matcher(rs.matchers.default)
    recorder = rs.recorder(str(path), device)
    queue = rs.frame_queue(64)
    for sensor, profile in zip(sensors, profiles, strict=True):
        sensor.open(profile)
        sensor.start(queue)
    for k, frame in enumerate(frames):
        depth = np.round(frame.depth / depth_units_m).astype(np.uint16)
        colour = np.round(np.clip(frame.rgb, 0.0, 1.0) * 255.0).astype(np.uint8)
        if colour_format == "bgr8":
            colour = np.ascontiguousarray(colour[:, :, ::-1])
        for sensor, profile, image, bpp in ((sensors[0], profiles[0], depth, 2), (sensors[1], profiles[1], colour, 3)):
            sw = rs.software_video_frame()
            sw.pixels, sw.stride, sw.bpp = image, camera.width * bpp, bpp
            sw.timestamp, sw.domain, sw.frame_number = k * 1000.0 / fps, rs.timestamp_domain.hardware_clock, k
            sw.profile = profile.as_video_stream_profile()
            if bpp == 2:
                sw.depth_units = depth_units_m
            sensor.on_video_frame(sw)
        time.sleep(0.02)  # the recorder writes from its own thread
    for sensor in sensors:
        sensor.stop()
        sensor.close()
    del recorder  # closes the file
    return Path(path)
