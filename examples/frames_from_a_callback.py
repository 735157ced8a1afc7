"""SLAM on frames that a callback delivers (a ROS subscriber, a camera SDK's frame callback), through
``rgs_warp.datasets.CallbackSource`` and ``rgs_warp.app.runner.run``: the callback puts each frame in a queue,
the source takes them out in order, and the run tracks, maps, saves and evaluates as on a dataset.

    python examples/frames_from_a_callback.py               # a publisher thread replays the synthetic office
    python examples/frames_from_a_callback.py device=cpu dataset.width=96 dataset.height=54 dataset.max_frames=12

With ROS 2 (rclpy, message_filters, cv_bridge), the callback is the synchronised colour + depth one:

    def on_images(colour_msg, depth_msg):                  # message_filters.ApproximateTimeSynchronizer
        rgb = bridge.imgmsg_to_cv2(colour_msg, "rgb8").astype(np.float32) / 255
        depth = bridge.imgmsg_to_cv2(depth_msg).astype(np.float32) / 1000   # 16UC1 millimetres
        stamp = colour_msg.header.stamp.sec + 1e-9 * colour_msg.header.stamp.nanosec
        subscriber.on_frame(rgb, depth, stamp)

with the ``Camera`` from the colour topic's ``CameraInfo`` (fx = k[0], fy = k[4], cx = k[2], cy = k[5]) and
depth registered to colour (``aligned_depth_to_color`` of realsense-ros).
"""

from __future__ import annotations

import queue
import sys
import threading

import numpy as np

from rgs_warp import load_config, open_dataset
from rgs_warp.app.runner import run
from rgs_warp.datasets import CallbackSource
from rgs_warp.types import Frame


class Subscriber:
    """What a subscriber's callback needs: ``on_frame`` queues a frame (called on the middleware's
    thread), ``next_frame`` hands them to the SLAM in order (blocking until one comes) and None once
    ``on_end`` was called (the bag ended, the node shut down)."""

    def __init__(self, max_queued: int = 30):
        self._queue: queue.Queue = queue.Queue(maxsize=max_queued)

    def on_frame(self, rgb: np.ndarray, depth: np.ndarray | None, stamp_s: float) -> None:
        self._queue.put(Frame(rgb, depth, None, stamp_s, 0))  # blocks when SLAM falls behind

    def on_end(self) -> None:
        self._queue.put(None)

    def next_frame(self) -> Frame | None:
        return self._queue.get()


def publish(dataset, subscriber: Subscriber) -> threading.Thread:
    """A publisher on another thread, as a ROS bag or a camera would be: the dataset's frames, then
    the end."""

    def replay():
        for frame in dataset:
            subscriber.on_frame(frame.rgb, frame.depth, frame.timestamp)
        subscriber.on_end()

    thread = threading.Thread(target=replay, name="publisher", daemon=True)
    thread.start()
    return thread


def main(argv: list[str]) -> tuple:
    cfg = load_config(["dataset=synthetic/office0", *argv])
    dataset = open_dataset(cfg)  # here only the publisher's source of images and the camera
    subscriber = Subscriber()
    publish(dataset, subscriber)
    source = CallbackSource(dataset.camera, subscriber.next_frame, name="subscriber")
    run_dir, metrics = run(cfg, source=source)
    print(f"{metrics['frames']} frames from the subscriber; run folder {run_dir}")
    return run_dir, metrics


if __name__ == "__main__":
    main(sys.argv[1:])
