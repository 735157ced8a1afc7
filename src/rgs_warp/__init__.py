"""rgs_warp: RGS-SLAM (Gaussian-splatting SLAM with one-shot dense initialization) in NVIDIA Warp."""

import warp as _wp

# Our block-cooperative (tile) kernels run with one thread per block on the CPU unless this is set,
# and then silently compute wrong results. Warp reads it at launch time and it only changes CPU
# launches that ask for block_dim > 1, so setting it here affects nobody else's correct code.
_wp.config.enable_cpu_blocks = True

from rgs_warp.render import Renderer, RenderResult, render  # noqa: E402 (after the Warp setting)
from rgs_warp.types import Camera, Frame, GaussianMap  # noqa: E402

__all__ = ["Camera", "Frame", "GaussianMap", "RenderResult", "Renderer", "render"]
__version__ = "0.1.0"
