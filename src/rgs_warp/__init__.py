"""rgs_warp: RGS-SLAM (Gaussian-splatting SLAM with one-shot dense initialization) in NVIDIA Warp.

from rgs_warp import SLAM, load_config, open_dataset
cfg = load_config(["dataset=replica/office0", "data_root=/data"])
dataset = open_dataset(cfg)
slam = SLAM(cfg, dataset.camera, T_first_WC=dataset[0].pose_gt)
for frame in dataset:
    T_WC = slam.track(frame.rgb, frame.depth, frame.timestamp)
"""

import warp as _wp

# Our block-cooperative (tile) kernels run with one thread per block on the CPU unless this is set,
# and then silently compute wrong results. Warp reads it at launch time and it only changes CPU
# launches that ask for block_dim > 1, so setting it here affects nobody else's correct code.
_wp.config.enable_cpu_blocks = True

from rgs_warp.config import Config, load_config  # noqa: E402 (after the Warp setting)
from rgs_warp.datasets import open_dataset  # noqa: E402
from rgs_warp.render import Renderer, RenderResult, render  # noqa: E402
from rgs_warp.slam import SLAM  # noqa: E402
from rgs_warp.types import Camera, Frame, GaussianMap  # noqa: E402

__all__ = [
    "SLAM",
    "Camera",
    "Config",
    "Frame",
    "GaussianMap",
    "RenderResult",
    "Renderer",
    "load_config",
    "open_dataset",
    "render",
]
__version__ = "0.1.0"
