"""The SLAM system (supplement §4.6): ``SLAM`` (``system.py``) chains the stages frame by frame; the
monocular start (``mono_start.py``), where mapping jobs run (``worker.py``), and save / load
(``storage.py``) are its parts.  ``python -m rgs_warp.slam`` (``__main__.py``) runs it on a dataset."""

from rgs_warp.slam.frame_result import FrameResult
from rgs_warp.slam.system import METHODS, SLAM

__all__ = ["METHODS", "SLAM", "FrameResult"]
