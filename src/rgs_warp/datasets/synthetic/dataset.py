"""``SyntheticDataset``: a generated sequence, cached on disk, read back by the Replica loader."""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import tempfile
from dataclasses import asdict
from pathlib import Path

from rgs_warp.datasets.replica import ReplicaDataset
from rgs_warp.datasets.synthetic.generate import SyntheticConfig, write_sequence

# Bump when the generator's output changes for the same config, so stale caches are not reused.
GENERATOR_VERSION = 1


def cache_dir() -> Path:
    return Path(os.environ.get("RGS_CACHE", "~/.cache/rgs_warp")).expanduser() / "synthetic"


def cache_key(cfg: SyntheticConfig) -> str:
    blob = json.dumps({"generator": GENERATOR_VERSION, **asdict(cfg)}, sort_keys=True)
    return hashlib.sha256(blob.encode()).hexdigest()[:12]


def sequence_dir(cfg: SyntheticConfig, root: Path | None = None) -> Path:
    """Where the sequence for ``cfg`` is cached (under ``root``, default ``cache_dir()``)."""
    return (Path(root) if root is not None else cache_dir()) / f"{cfg.scene}-{cache_key(cfg)}"


def ensure_sequence(
    cfg: SyntheticConfig, device: str | None = None, root: Path | None = None, progress: bool = True
) -> Path:
    """Folder of the Replica-layout sequence for ``cfg``, generated on first use.

    Generation goes to a temporary sibling folder that is renamed into place only when complete, so
    an interrupted run never leaves a folder that a later run would take for a finished one.
    """
    final = sequence_dir(cfg, root)
    if final.is_dir():
        return final
    root = final.parent
    root.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{final.name}.", suffix=".partial", dir=root))
    try:
        write_sequence(cfg, tmp, "replica", device=device, progress=progress)
        tmp.chmod(0o755)
        try:
            tmp.rename(final)
        except OSError:
            if not final.is_dir():  # not a concurrent generator finishing first: a real error
                raise
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return final


class SyntheticDataset(ReplicaDataset):
    """A generated indoor RGB-D sequence, e.g. ``SyntheticDataset("room0", width=240, n_frames=60)``.

    Keyword options are ``SyntheticConfig`` fields (the scene is ``name``) plus the loader's
    ``stride``, ``start``, ``max_frames``, ``downscale``, ``prefetch``; ``device`` picks where to
    render (default: the GPU when Warp sees one) and ``cache_root`` overrides ``$RGS_CACHE/synthetic``.
    Adds ``config`` (the resolved ``SyntheticConfig``) and ``mesh_path`` (ground-truth mesh, PLY).
    """

    def __init__(
        self,
        name: str = "room0",
        *,
        stride: int = 1,
        start: int = 0,
        max_frames: int | None = None,
        downscale: int = 1,
        prefetch: int = 6,
        device: str | None = None,
        cache_root: Path | str | None = None,
        progress: bool = True,
        **options,
    ):
        self.config = SyntheticConfig(scene=name, **options)
        folder = ensure_sequence(self.config, device=device, root=cache_root, progress=progress)
        super().__init__(
            folder, stride=stride, start=start, max_frames=max_frames, downscale=downscale, prefetch=prefetch
        )
        self.mesh_path = folder / "mesh.ply"
