"""rgs_warp: RGS-SLAM (Gaussian-splatting SLAM with one-shot dense initialization) in NVIDIA Warp."""

from rgs_warp.types import Camera, Frame

__all__ = ["Camera", "Frame"]
__version__ = "0.1.0"
