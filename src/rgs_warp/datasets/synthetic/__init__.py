"""Photorealistic-enough synthetic indoor RGB-D sequences, ray-cast with Warp.

Textured rooms (procedural patterns and scikit-image's bundled photographs, plus plain painted areas),
baked soft shadows and ambient occlusion, supersampled colour, exact pixel-centre z-depth, smooth
hand-held trajectories with slow pans, rapid turns and revisits; written in the Replica (NICE-SLAM)
or TUM RGB-D layout with the ground-truth mesh.
"""

from rgs_warp.datasets.synthetic.dataset import SyntheticDataset, cache_dir, ensure_sequence
from rgs_warp.datasets.synthetic.generate import SequenceRenderer, SyntheticConfig, write_sequence
from rgs_warp.datasets.synthetic.scene import SCENES, build_scene

__all__ = [
    "SCENES",
    "SequenceRenderer",
    "SyntheticConfig",
    "SyntheticDataset",
    "build_scene",
    "cache_dir",
    "ensure_sequence",
    "write_sequence",
]
