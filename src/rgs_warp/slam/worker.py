"""Asynchronous mapping (``mapping.asynchronous``, supplement §3.2): tracking goes on against the
latest *published* map while a worker thread runs the keyframe work (seeding, window mapping,
merge / prune) on its own working map.

Three parts, each usable alone:

* ``DeviceTurns``: which thread may launch GPU work now.  Warp's current CUDA stream is a property
  of the device, shared by every thread, and the matching chain captures CUDA graphs on it
  (``sampling.loop_until_zero``): a kernel that another thread launched during a capture would be
  captured instead of run.  So the two threads take turns on the device, tracking first: the worker
  gives its turn away at safe points (between mapping iterations, between stages) whenever tracking
  waits, so a frame waits at most one mapping iteration or one stage.
* ``MapPublisher``: the published map versions tracking reads.  Publishing copies the working map's
  parameters into a buffer no reader holds (three buffers: the published one, one a reader may
  still hold, one to write), then makes it the published one.  Every buffer carries a sequence
  number that is odd while it is written; a reader that finds it odd, or changed when it is done,
  has read a map being written (``TornMapError``): the check that the tests make fail on a
  deliberately unsynchronised publisher.
* ``MappingWorker``: the thread and its queue of jobs, run in order.  An exception in a job stops
  the worker and is raised in the caller's thread at its next call (``check``, ``submit``,
  ``drain``): nothing fails silently.
"""

from __future__ import annotations

import queue
import threading
from collections.abc import Callable
from contextlib import contextmanager

from rgs_warp.types import GaussianMap


class TornMapError(RuntimeError):
    """A reader saw a map version that was being written."""


class DeviceTurns:
    """Turns on one device between the tracking thread and the mapping worker, tracking first."""

    def __init__(self):
        self._cv = threading.Condition()
        self._holder: str | None = None
        self._tracking_waits = 0

    @contextmanager
    def tracking(self):
        """Hold the device for tracking (waits for the worker's next safe point)."""
        with self._cv:
            self._tracking_waits += 1
            self._cv.wait_for(lambda: self._holder is None)
            self._tracking_waits -= 1
            self._holder = "tracking"
        try:
            yield
        finally:
            self._release()

    @contextmanager
    def mapping(self):
        """Hold the device for the worker (``pause`` inside gives it to tracking when it waits)."""
        self._acquire_mapping()
        try:
            yield
        finally:
            self._release()

    def pause(self) -> None:
        """A safe point of the worker: if tracking waits, let it run, then take the device back."""
        with self._cv:
            if self._tracking_waits == 0:
                return
        self._release()
        self._acquire_mapping()

    def _acquire_mapping(self) -> None:
        with self._cv:
            self._cv.wait_for(lambda: self._holder is None and self._tracking_waits == 0)
            self._holder = "mapping"

    def _release(self) -> None:
        with self._cv:
            self._holder = None
            self._cv.notify_all()


class MapPublisher:
    """Published versions of a ``GaussianMap`` (its parameters and count) for readers in another
    thread.  ``publish(working)`` copies; ``read()`` holds the latest version while tracking uses it.

    ``buffers``: 3 keeps a reader's version intact while the next two are written (one more is made
    when readers hold all but the published one); 1 writes the version readers hold, in place: the
    unsynchronised variant, for the test that shows the check catches it."""

    def __init__(self, sh_degree: int, device, buffers: int = 3):
        self._maps = [GaussianMap(1024, sh_degree=sh_degree, device=device) for _ in range(buffers)]
        self._seq = [0] * buffers  # odd while buffer i is written
        self._held = [0] * buffers  # readers holding buffer i
        self._lock = threading.Lock()
        self._front = 0
        self.version = 0  # publications so far

    def publish(self, working: GaussianMap, write_hook: Callable[[], None] | None = None) -> int:
        """Copy ``working``'s live parameters into a free buffer and publish it; returns the version.
        ``write_hook`` runs while the buffer is marked as being written (tests widen that window)."""
        with self._lock:
            free = [i for i in range(len(self._maps)) if i != self._front and not self._held[i]]
            if free or len(self._maps) == 1:
                b = free[0] if free else self._front
            else:  # every other version held by a reader: one more buffer
                self._maps.append(GaussianMap(1024, sh_degree=self._maps[0].sh_degree, device=self._maps[0].device))
                self._seq.append(0)
                self._held.append(0)
                b = len(self._maps) - 1
            self._seq[b] += 1
        try:
            self._maps[b].assign_parameters(working)
            if write_hook is not None:
                write_hook()
        finally:
            with self._lock:
                self._seq[b] += 1
                self._front = b
                self.version += 1
        return self.version

    @contextmanager
    def read(self):
        """The latest published map, held (not rewritten) until the block ends; raises
        ``TornMapError`` if it was being written when taken or was written meanwhile."""
        with self._lock:
            b = self._front
            self._held[b] += 1
            seq = self._seq[b]
        try:
            if seq % 2:
                raise TornMapError("tracking took a map version that was being written")
            yield self._maps[b]
        finally:
            with self._lock:
                self._held[b] -= 1
                changed = self._seq[b] != seq
        if changed:
            raise TornMapError("the map version tracking read was rewritten while tracking used it")


class MappingWorker:
    """A thread running jobs (callables) in order, each holding the device's mapping turn.  Jobs
    carry a kind ("init", "keyframe", "fill", "refine"); ``queued(kind)`` counts those not finished, and
    ``wait_until_fewer(kind, n)`` is the caller's back-pressure."""

    def __init__(self, turns: DeviceTurns, name: str = "rgs_warp-mapping"):
        self.turns = turns
        self._jobs: queue.Queue = queue.Queue()
        self._cv = threading.Condition()
        self._queued: dict[str, int] = {}
        self._error: BaseException | None = None
        # set while a caller waits in ``drain(hurry=True)``: jobs that can end early do (SLAM: at
        # ``mapping.min_iters``), since the caller waits for them (a run's checkpoint)
        self.hurry = threading.Event()
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        self._thread.start()

    def submit(self, kind: str, job: Callable[[], None]) -> None:
        self.check()
        with self._cv:
            self._queued[kind] = self._queued.get(kind, 0) + 1
        self._jobs.put((kind, job))

    def queued(self, kind: str) -> int:
        """Jobs of ``kind`` submitted and not finished."""
        with self._cv:
            return self._queued.get(kind, 0)

    def wait_until_fewer(self, kind: str, n: int) -> None:
        """Block until fewer than ``n`` jobs of ``kind`` are unfinished (or a job failed)."""
        with self._cv:
            self._cv.wait_for(lambda: self._queued.get(kind, 0) < n or self._error is not None)
        self.check()

    def drain(self, check: bool = True, hurry: bool = False) -> None:
        """Wait until every submitted job has run; with ``check``, raise the first job's exception; with
        ``hurry``, ``self.hurry`` is set meanwhile."""
        if hurry:
            self.hurry.set()
        try:
            self._jobs.join()
        finally:
            self.hurry.clear()
        if check:
            self.check()

    def is_current(self) -> bool:
        """Whether the calling thread is the worker's."""
        return threading.current_thread() is self._thread

    def check(self) -> None:
        if self._error is not None:
            raise RuntimeError(f"the mapping worker failed: {self._error!r}") from self._error

    def _run(self) -> None:
        while True:
            kind, job = self._jobs.get()
            try:
                if self._error is None:  # after a failure the rest are dropped (drain still returns)
                    with self.turns.mapping():
                        job()
            except BaseException as e:  # noqa: BLE001 - raised again in the caller's thread
                self._error = e
            finally:
                with self._cv:
                    self._queued[kind] -= 1
                    self._cv.notify_all()
                self._jobs.task_done()
