"""The run folder (``output_dir/run_name``: made, cleared for ``overwrite``, or the caller's) and what a
run records of its dataset (its summary, ground-truth mesh, and the frames it reads again)."""

from __future__ import annotations

import itertools
import shutil
from datetime import datetime
from pathlib import Path

from rgs_warp.config import Config
from rgs_warp.datasets.base import RGBDDataset


class OutputError(OSError):
    """The run folder cannot be made, cleared or written; the message names it."""


def make_run_dir(cfg: Config) -> Path:
    """A new folder for a run, ``output_dir/run_name`` (default ``<dataset>-<date>-<time>``), never
    one another run uses: a name that exists gets ``-2``, ``-3``, ... (``mkdir`` fails on an existing
    folder, so two runs started in the same second cannot share one), unless ``overwrite`` is set with
    a ``run_name``: then the old run folder is cleared and reused.  Raises ``OutputError``."""
    base = Path(cfg.output_dir)
    name = cfg.run_name or f"{cfg.dataset.type}-{cfg.dataset.name}-{datetime.now():%Y%m%d-%H%M%S}"
    path = base / name
    if base.exists() and not base.is_dir():
        raise OutputError(f"output_dir={base} is a file, not a folder: the run folder {path} cannot be made in it")
    try:
        base.mkdir(parents=True, exist_ok=True)
        if cfg.overwrite and cfg.run_name:
            if path.exists():
                _clear_run_dir(path)
            path.mkdir(exist_ok=True)
            return path
        for k in itertools.count(2):
            try:
                path.mkdir()
                return path
            except FileExistsError:
                path = base / f"{name}-{k}"
    except OSError as e:
        raise OutputError(f"cannot create the run folder {path}: {e.strerror or e}") from e
    raise AssertionError("unreachable")


def _clear_run_dir(path: Path) -> None:
    """Empty an old run folder for ``overwrite=true``, so no file of the old run (metrics, renders,
    checkpoints) sits beside the new one's; a folder that is not a run's is refused, not emptied."""
    if not path.is_dir():
        raise OutputError(f"cannot reuse {path} for the run: it is not a folder")
    children = list(path.iterdir())
    if children and not (path / "config.yaml").is_file():
        raise OutputError(f"overwrite=true refused: {path} is not a run folder (no config.yaml); remove it yourself")
    for child in children:
        if child.is_dir() and not child.is_symlink():
            shutil.rmtree(child)
        else:
            child.unlink()


def own_run_dir(run_dir: Path) -> Path:
    """A run folder the caller chose (``run(cfg, run_dir=...)``, the eval suite): made if needed."""
    if run_dir.exists() and not run_dir.is_dir():
        raise OutputError(f"cannot use {run_dir} as the run folder: it is a file, not a folder")
    try:
        run_dir.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise OutputError(f"cannot create the run folder {run_dir}: {e.strerror or e}") from e
    return run_dir


def dataset_summary(ds) -> dict:
    c = ds.camera
    return {
        "dataset": repr(ds),
        "frames": None if is_stream(ds) else len(ds),  # a stream's length is known at its end
        "resolution": [c.width, c.height],
        "intrinsics": {"fx": c.fx, "fy": c.fy, "cx": c.cx, "cy": c.cy},
    }


def ground_truth_mesh(cfg: Config, ds) -> Path | None:
    """The sequence's ground-truth mesh when there is one: the synthetic scenes' ``mesh.ply``, or
    Replica's ``<scene>_mesh.ply`` next to the scene folder (the NICE-SLAM layout)."""
    path = getattr(ds, "mesh_path", None)
    if path is not None and Path(path).is_file():
        return Path(path)
    if cfg.dataset.type == "replica":
        folder = cfg.dataset_path()
        candidate = folder.parent / f"{folder.name}_mesh.ply"
        if candidate.is_file():
            return candidate
    return None


def is_stream(ds) -> bool:
    """A frame source without random access (``CallbackSource``, ``RealSenseSource``)."""
    return not hasattr(ds, "__getitem__")


def read_frames(ds, indices):
    """``ds[i]`` for each of ``indices``, read ahead in background threads where ``ds`` is a dataset
    (``RGBDDataset.frames``; a stream's ``KeptFrames`` holds the frames already)."""
    return ds.frames(indices) if isinstance(ds, RGBDDataset) else (ds[int(i)] for i in indices)
