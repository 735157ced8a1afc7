"""A robot's perception loop on rgs_warp: frames arrive as ``wp.array``s on the GPU (a camera driver
that writes device memory), ``slam.track`` tracks each in place, the pose goes on as a
``wp.transform``, and a planner looks ahead in depth rendered from the map at a pose the robot has not
been to yet.  No image goes to the host: per frame what is read back is the tracker's pose and
per-iteration history (a few kilobytes, whatever the image size), counters, and the planner's one
number (``tests/test_examples.py`` counts the reads).

    python examples/robot_loop.py                          # synthetic office, on the GPU if Warp sees one
    python examples/robot_loop.py device=cpu dataset.width=96 dataset.height=54 dataset.max_frames=12 \\
        mapping.init_iters=60 mapping.iters_per_frame=6                # a CPU-sized loop (a few minutes)
"""

from __future__ import annotations

import sys
from collections.abc import Iterator

import numpy as np
import warp as wp

from rgs_warp import SLAM, load_config, open_dataset
from rgs_warp.config import resolve_device
from rgs_warp.geometry import pose_to_transform, transform_to_pose

NO_SURFACE_M = 1.0e9  # the clearance when the map shows nothing ahead


@wp.kernel
def _nearest_surface(
    # in
    depth: wp.array2d(dtype=wp.float32),
    alpha: wp.array2d(dtype=wp.float32),
    min_alpha: float,
    # out
    nearest_out: wp.array(dtype=wp.float32),
):
    v, u = wp.tid()
    h, w = depth.shape[0], depth.shape[1]
    # the central third of the view: the corridor the robot drives into
    if v < h / 3 or v >= 2 * h / 3 or u < w / 3 or u >= 2 * w / 3:
        return
    a = alpha[v, u]
    if a > min_alpha:
        wp.atomic_min(nearest_out, 0, depth[v, u] / a)  # the renderer's depth is alpha-weighted


class Planner:
    """Looks ``lookahead_m`` ahead along the camera's optical axis: renders the map's depth there and
    returns the distance to the nearest surface in the central third of that view (metres)."""

    def __init__(self, slam: SLAM, lookahead_m: float = 0.3, min_alpha: float = 0.5):
        self.slam, self.lookahead_m, self.min_alpha = slam, lookahead_m, min_alpha
        self._nearest = wp.zeros(1, dtype=wp.float32, device=slam.device)

    def clearance(self, T_WC: wp.transform) -> float:
        ahead = transform_to_pose(T_WC)
        ahead[:3, 3] += ahead[:3, 2] * self.lookahead_m  # the camera's z axis is its viewing direction
        view = self.slam.render(ahead)  # on the device, a pose no frame was taken from
        self._nearest.fill_(NO_SURFACE_M)
        wp.launch(
            _nearest_surface,
            dim=view.depth.shape,
            inputs=[view.depth, view.alpha, self.min_alpha],
            outputs=[self._nearest],
            device=self.slam.device,
        )
        return float(self._nearest.numpy()[0])  # the one number the planner reads


def camera_driver(dataset, device) -> Iterator[tuple[wp.array, wp.array, float, np.ndarray | None]]:
    """Stands in for a camera whose driver writes each frame into device memory: one colour and one
    depth buffer on ``device``, overwritten frame after frame (the SLAM copies what it keeps)."""
    camera = dataset.camera
    rgb = wp.empty((camera.height, camera.width), dtype=wp.vec3, device=device)
    depth = wp.empty((camera.height, camera.width), dtype=wp.float32, device=device)
    for frame in dataset:
        rgb.assign(frame.rgb)  # the "DMA" from the sensor: the only host-to-device copy of the loop
        depth.assign(frame.depth)
        yield rgb, depth, frame.timestamp, frame.pose_gt


def robot_loop(slam: SLAM, frames, planner: Planner) -> list[tuple[wp.transform, float]]:
    """Per frame: track it where it lies (``wp.array``s on the SLAM's device), hand the pose on as a
    ``wp.transform`` and ask the planner for the clearance ahead; returns (pose, clearance) per frame."""
    steps = []
    for rgb, depth, timestamp, _ in frames:
        T_WC = pose_to_transform(slam.track(rgb, depth, timestamp))
        steps.append((T_WC, planner.clearance(T_WC)))
    return steps


def main(argv: list[str]) -> int:
    cfg = load_config(["dataset=synthetic/office0", *argv])
    device = resolve_device(cfg.device)
    dataset = open_dataset(cfg, device=device)
    slam = SLAM(cfg, dataset.camera, device=device, T_first_WC=dataset[0].pose_gt)
    steps = robot_loop(slam, camera_driver(dataset, device), Planner(slam))
    for i, (T_WC, clearance) in enumerate(steps):
        p = wp.transform_get_translation(T_WC)
        ahead = f"{clearance:.2f} m" if clearance < NO_SURFACE_M else "nothing mapped"
        print(f"frame {i:3d}  position ({p[0]:+.2f}, {p[1]:+.2f}, {p[2]:+.2f}) m  clearance ahead {ahead}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
