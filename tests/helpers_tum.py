"""A TUM-layout dataset folder of a few tiny frames (and a Replica one beside it), for the loaders' and the
command line's tests."""

import json

import cv2
import numpy as np

W, H = 64, 48


def tiny_tum(root, n_rgb=4, n_depth=4, camera=None):
    """A TUM-layout folder of n_rgb colour frames (64x48) and the first n_depth depth images."""
    (root / "rgb").mkdir(parents=True)
    (root / "depth").mkdir()
    rng = np.random.default_rng(0)
    rgb, depth = rng.random((H, W, 3), dtype=np.float32), np.full((H, W), 2.0, np.float32)
    rgb_lines, depth_lines = [], []
    for k in range(n_rgb):
        t = 100.0 + k / 30
        cv2.imwrite(str(root / "rgb" / f"{t:.6f}.png"), (np.roll(rgb, k, axis=1) * 255).astype(np.uint8))
        rgb_lines.append(f"{t:.6f} rgb/{t:.6f}.png")
        if k < n_depth:
            cv2.imwrite(str(root / "depth" / f"{t:.6f}.png"), (depth * 1000).astype(np.uint16))
            depth_lines.append(f"{t:.6f} depth/{t:.6f}.png")
    (root / "rgb.txt").write_text("\n".join(rgb_lines) + "\n")
    (root / "depth.txt").write_text("\n".join(depth_lines) + "\n")
    cam = {"w": W, "h": H, "fx": 60.0, "fy": 60.0, "cx": 31.5, "cy": 23.5, "scale": 1000} | (camera or {})
    (root / "cam_params.json").write_text(json.dumps({"camera": cam}))
    return root


def replica_with_cam_params(root, cam_params):
    """A Replica-layout folder (one empty frame) with a copy of the ``cam_params`` file: enough to open it."""
    (root / "results").mkdir(parents=True)
    (root / "results" / "frame000000.jpg").write_bytes(b"")
    (root / "cam_params.json").write_text(cam_params.read_text())
    return root
