"""A run's checkpoints (written beside it, resumed from by ``resume``) and its final save."""

from __future__ import annotations

import json
import shutil
import threading
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from rgs_warp.app.evaluate import write_convergence
from rgs_warp.config import Config
from rgs_warp.io.atomic import SaveError, write_text_atomic
from rgs_warp.slam import SLAM

CHECKPOINT = "checkpoint.json"  # in the run folder: the latest complete checkpoint's folder


def save_run(
    cfg: Config, slam: SLAM, run_dir: Path, refine: bool = True, stop: Callable[[int], bool] | None = None
) -> FinalSave:
    """The end of a run: the waiting frame-fill seeds join the map (and ``refine``: the final
    refinement, ``stop`` ending it early as ``SLAM.finish``'s), the convergence files, and what
    ``SLAM.save`` writes gathered into host memory: the returned ``FinalSave`` writes it (``start`` in a
    thread, ``write`` here); one ``SaveError`` names what failed and what was saved."""
    slam.finish(refine, stop)
    failed = {}
    try:
        write_convergence(run_dir, slam.convergence, title=f"{cfg.dataset.type}/{cfg.dataset.name} ({cfg.method})")
    except OSError as e:
        failed["convergence.json"] = e
    return FinalSave(run_dir, slam.snapshot(), failed)


class FinalSave:
    """A run's last ``SLAM.save`` (``trajectory.txt``, ``keyframes.npz``, ``map.ply``, ``config.yaml``), from
    a snapshot: ``start`` writes it in a thread (the compressed keyframes of a 1200x680 run take seconds)
    while the run is evaluated, ``write`` waits for it, or writes it here if not started, and raises
    the ``SaveError`` naming what failed.  ``seconds``: the writing's."""

    def __init__(self, run_dir: Path, snapshot, failed: dict):
        self.run_dir, self.snapshot, self.failed = run_dir, snapshot, failed
        self.seconds = 0.0
        self._thread: threading.Thread | None = None
        self._error: BaseException | None = None

    def _write(self) -> None:
        t0 = time.perf_counter()
        try:
            self.snapshot.write(self.run_dir)
        except BaseException as e:  # noqa: BLE001 (raised again by write, in the run's thread)
            self._error = e
        self.seconds = time.perf_counter() - t0

    def start(self) -> None:
        self._thread = threading.Thread(target=self._write, name="rgs-save", daemon=False)
        self._thread.start()

    def join(self) -> None:
        if self._thread is not None:
            self._thread.join()

    def write(self) -> None:
        if self._thread is None:
            self._write()
        self.join()
        failed = dict(self.failed)
        if self._error is not None and not isinstance(self._error, SaveError):
            raise self._error
        if self._error is not None:
            failed.update(self._error.failed)
        if failed:
            names = ["trajectory.txt", "keyframes.npz", "map.ply", "config.yaml", "convergence.json"]
            raise SaveError(self.run_dir, [n for n in names if n not in failed], failed)


class CheckpointWriter:
    """A run's checkpoints, written beside it: ``write`` gathers the SLAM's state into host memory (the
    only part in the frame's time; ``SLAM.snapshot``) and returns; a thread then writes the folder
    ``checkpoints/frameNNNNNN/`` (``SLAM.save(..., state=True)``'s files and ``run_state.json``),
    replaces ``checkpoint.json`` to name it, and removes the older ones, in that order, so a kill at any
    moment leaves ``checkpoint.json`` naming a complete checkpoint.  One checkpoint at a time: ``write``
    first waits for the one before, ``close`` for the last.  A checkpoint that cannot be written (full
    disk) is reported through ``warn`` and the run goes on.  ``seconds``: the writing's, in the thread."""

    def __init__(self, run_dir: Path, warn=None):
        self.run_dir, self.warn = run_dir, warn or print
        self.seconds = 0.0
        self._thread: threading.Thread | None = None

    def write(self, slam: SLAM, state) -> None:
        """Checkpoint ``slam`` with the run's ``RunState`` ``state``."""
        self.close()
        snapshot = slam.snapshot(state=True, hurry=True)  # live: the camera does not wait for full windows
        run_state = json.dumps(state.to_json(), default=_plain)
        self._thread = threading.Thread(
            target=self._write, args=(snapshot, run_state, state.next_frame), name="rgs-checkpoint", daemon=False
        )
        self._thread.start()

    def close(self) -> None:
        if self._thread is not None:
            self._thread.join()
            self._thread = None

    def _write(self, snapshot, run_state: str, next_frame: int) -> None:
        t0 = time.perf_counter()
        write_checkpoint(self.run_dir, snapshot, run_state, next_frame, warn=self.warn)
        self.seconds += time.perf_counter() - t0


def write_checkpoint(run_dir: Path, snapshot, run_state: str, next_frame: int, warn=None) -> Path | None:
    """A checkpoint of the run in ``run_dir``: ``checkpoints/frameNNNNNN/`` gets the files of the
    snapshot (``SLAM.snapshot(state=True)``) and ``run_state.json`` (``RunState.to_json``, as JSON),
    then ``checkpoint.json`` is replaced to name it (each file written atomically), then the older
    checkpoints go.  A kill at any moment leaves ``checkpoint.json`` naming a complete checkpoint.  A
    checkpoint that cannot be written (full disk) is reported through ``warn`` and the run goes on;
    returns its folder or None."""
    folder = run_dir / "checkpoints" / f"frame{next_frame:06d}"
    try:
        if folder.exists():  # the leftover of a checkpoint that failed before its pointer was written
            shutil.rmtree(folder)
        snapshot.write(folder)
        write_text_atomic(folder / "run_state.json", run_state)
        pointer = {"folder": str(folder.relative_to(run_dir)), "next_frame": next_frame}
        write_text_atomic(run_dir / CHECKPOINT, json.dumps(pointer) + "\n")
    except OSError as e:
        shutil.rmtree(folder, ignore_errors=True)
        (warn or print)(f"warning: checkpoint at frame {next_frame} not written ({e}); the run goes on")
        return None
    for old in (run_dir / "checkpoints").iterdir():
        if old != folder:
            shutil.rmtree(old, ignore_errors=True)
    return folder


def _plain(value):
    """NumPy scalars as Python numbers for ``json.dumps`` (which keeps NaN and inf, unlike strict JSON:
    a lost frame's loss may be either)."""
    if isinstance(value, np.generic):
        return value.item()
    raise TypeError(f"{type(value).__name__} is not JSON serialisable")


def remove_checkpoints(run_dir: Path) -> None:
    """A finished run's checkpoints go (its folder holds the final state): the pointer first, so it
    never names a folder that is gone."""
    (run_dir / CHECKPOINT).unlink(missing_ok=True)
    shutil.rmtree(run_dir / "checkpoints", ignore_errors=True)
