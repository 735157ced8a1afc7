"""rgs_warp: RGS-SLAM (Gaussian-splatting SLAM with one-shot dense initialization) in NVIDIA Warp."""

from rgs_warp.render import Renderer, RenderResult, render
from rgs_warp.types import Camera, Frame, GaussianMap

__all__ = ["Camera", "Frame", "GaussianMap", "RenderResult", "Renderer", "render"]
__version__ = "0.1.0"
