"""Where the SLAM's mapping jobs run (keyframes, frame fills, refinements between keyframes): at once in
the caller's thread (``InlineMapping``), or, with ``mapping.asynchronous`` (supplement §3.2), in a worker
thread on the working map while tracking goes on against the latest *published* version of it
(``WorkerMapping``).  The two have the same methods, so the SLAM holds one and does not ask which: they
run or queue a job, copy the images a queued job keeps, publish, give tracking the map it reads, and
hold the wait policies of the asynchronous mode (when a frame waits for the worker, when a mapping job
ends early for one waiting behind it).

``WorkerMapping`` is built from three parts, each usable alone:

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

import math
import queue
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager

import numpy as np
import warp as wp

from rgs_warp.config import MappingConfig
from rgs_warp.render import Renderer
from rgs_warp.types import GaussianMap

# asynchronous: a refinement between keyframes asks for this many frames' budget at least (ended early when a
# keyframe waits), so the worker maps whenever tracking leaves the device free
IDLE_REFINE_FRAMES = 4


class TornMapError(RuntimeError):
    """A reader saw a map version that was being written."""


class DeviceTurns:
    """Turns on one device between the tracking thread and the mapping worker, tracking first."""

    def __init__(self):
        self._cv = threading.Condition()
        self._holder: str | None = None
        self._tracking_waits = 0
        # seconds each thread has held the device ("tracking", "mapping"), and when the holder took it
        self._held_s = {"tracking": 0.0, "mapping": 0.0}
        self._since = 0.0

    @contextmanager
    def tracking(self):
        """Hold the device for tracking (waits for the worker's next safe point)."""
        with self._cv:
            self._tracking_waits += 1
            self._cv.wait_for(lambda: self._holder is None)
            self._tracking_waits -= 1
            self._holder, self._since = "tracking", time.perf_counter()
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

    def seconds(self) -> dict[str, float]:
        """Seconds each thread has held the device so far ("tracking", "mapping"; a turn held now counts
        once it is given back)."""
        with self._cv:
            return dict(self._held_s)

    @property
    def tracking_waits(self) -> bool:
        """Whether tracking waits for the device now."""
        with self._cv:
            return self._tracking_waits > 0

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
            self._holder, self._since = "mapping", time.perf_counter()

    def _release(self) -> None:
        with self._cv:
            if self._holder is not None:
                self._held_s[self._holder] += time.perf_counter() - self._since
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


def _never(done: int) -> bool:
    return False


class InlineMapping:
    """Synchronous mapping: each job runs at once in the caller's thread, on the working map ``map``,
    which tracking reads too; nothing is queued, published or waited for."""

    def __init__(self, working: GaussianMap, renderer: Renderer):
        self.map = working
        self.renderer = renderer  # renders in tracking's turn: keyframe selection, ``SLAM.render``

    def run(self, kind: str, job: Callable, *args) -> None:
        job(*args)

    def own(self, image):
        """The image a job keeps: itself, since the job has run before the caller reuses it."""
        return image

    def queued(self, kind: str) -> int:
        return 0

    def pause(self) -> None:
        """A safe point of a mapping job: nothing to give way to."""

    def publish(self) -> int:
        """Nothing to publish (tracking reads the working map): 0."""
        return 0

    @contextmanager
    def tracking_map(self, check: bool = False) -> Iterator[GaussianMap]:
        yield self.map

    def turn_seconds(self) -> dict[str, float] | None:
        """No turns: one thread does everything."""
        return None

    def after_frame(self, index: int, init_window_end: int) -> None:
        """Nothing to wait for: the frame's jobs have run."""

    def drain(self, check: bool = True, hurry: bool = False) -> None:
        """Every job has run."""

    def prepare_tracking(self, tracker, T_WC: np.ndarray) -> None:
        """After a keyframe: the next frame's tracking graphs for the grown map, captured now, not in its
        latency (``Tracker.prepare``)."""
        tracker.prepare(self.map, T_WC)

    def working_alpha(self, alpha: wp.array) -> wp.array | None:
        """``alpha`` of tracking's last render, which was of the working map: a frame fill takes it
        instead of rendering again."""
        return alpha

    def refine_iters(self, budget: int, per_frame: float) -> int:
        """A refinement between keyframes runs what the budget holds (``mapping.rate_fps``)."""
        return budget

    def refine_stop(self, done: int) -> bool:
        """A refinement between keyframes runs all its iterations."""
        return False

    def begin_window(self, init: bool) -> tuple[Callable[[], None], Callable[[int], bool]]:
        """A keyframe's window mapping starts: its (pause, stop), which run it whole."""
        return self.pause, _never


class WorkerMapping:
    """Asynchronous mapping (``mapping.asynchronous``): jobs queue for the worker thread (``worker``), which
    maps the working map ``map``; tracking reads the versions ``publisher`` holds, in its turn on the
    device (``turns``), and renders with ``renderer`` (not the mapping jobs')."""

    def __init__(self, working: GaussianMap, renderer: Renderer, cfg: MappingConfig, sh_degree: int, device):
        self.map, self.renderer, self.cfg = working, renderer, cfg
        self.turns = DeviceTurns()
        self.publisher = MapPublisher(sh_degree, device)
        self.worker = MappingWorker(self.turns)

    def run(self, kind: str, job: Callable, *args) -> None:
        """Queue ``job(*args)`` for the worker (the initial window's jobs are "init": they do not hold tracking
        back as later keyframes' may, ``mapping.async_queue``)."""
        self.worker.submit(kind, lambda: job(*args))

    def own(self, image):
        """A copy of ``image`` that a queued job may hold while the caller and the tracker reuse their
        buffers (NumPy or ``wp.array``; None stays None)."""
        if image is None:
            return None
        return wp.clone(image) if isinstance(image, wp.array) else np.array(image, dtype=np.float32, copy=True)

    def queued(self, kind: str) -> int:
        return self.worker.queued(kind)

    def pause(self) -> None:
        """A safe point of a mapping job: tracking may take the device (in the worker's thread only: the
        monocular bootstrap seeds in tracking's own turn)."""
        if self.worker.is_current():
            self.turns.pause()

    def publish(self) -> int:
        """The working map published for tracking; returns its version."""
        return self.publisher.publish(self.map)

    @contextmanager
    def tracking_map(self, check: bool = False) -> Iterator[GaussianMap]:
        """Tracking's turn on the device, holding the latest published map (a loaded or resumed map is
        published first); ``check``: a failed job's exception is raised first."""
        if check:
            self.worker.check()
        with self.turns.tracking():
            if self.publisher.version == 0 and len(self.map):
                self.publish()
            with self.publisher.read() as published:
                yield published

    def turn_seconds(self) -> dict[str, float]:
        """Seconds tracking and the worker have each held the device's turn so far (the rest of the run
        neither did: the worker had no job and no frame was being processed)."""
        return self.turns.seconds()

    def after_frame(self, index: int, init_window_end: int) -> None:
        """The waits before frame ``index`` returns: the initial window (frames below ``init_window_end``) is
        mapped before the next frame, as in sync mode (``mapping.init_wait``: only the first keyframe's
        mapping, or its seeds); with no version published yet there is nothing to track against; then at most
        ``mapping.async_queue`` keyframes wait for the worker."""
        wait = self.cfg.init_wait
        waited = {"window": init_window_end, "first": 1, "seeds": 0}[wait]
        if wait == "seeds" and self.publisher.version == 0:
            self._wait_for_first_version()
        elif index < waited or self.publisher.version == 0:
            self.worker.drain()
        self.worker.wait_until_fewer("keyframe", self.cfg.async_queue + 1)

    def _wait_for_first_version(self) -> None:
        """``mapping.init_wait=seeds``: return once the worker has published the first keyframe's seeds (or
        has no initial job left, or failed: raised)."""
        while self.publisher.version == 0 and self.worker.queued("init") > 0:
            self.worker.check()
            time.sleep(0.001)
        self.worker.check()

    def drain(self, check: bool = True, hurry: bool = False) -> None:
        """``MappingWorker.drain``: every job queued so far has run."""
        self.worker.drain(check, hurry)

    def prepare_tracking(self, tracker, T_WC: np.ndarray) -> None:
        """Nothing: the map the next frame tracks is a version the worker has yet to publish."""

    def working_alpha(self, alpha: wp.array) -> None:
        """None: tracking rendered a published version, not the working map a frame fill seeds into."""
        return None

    def refine_iters(self, budget: int, per_frame: float) -> int:
        """A refinement between keyframes maps while the worker would idle: at least ``IDLE_REFINE_FRAMES``
        frames' budget, ended early when a keyframe waits (``refine_stop``); the next frame queues another
        once it has run.  The camera's rate is the budget: the map gets whatever time tracking leaves."""
        return max(budget, math.ceil(IDLE_REFINE_FRAMES * per_frame))

    def refine_stop(self, done: int) -> bool:
        """Whether a refinement between keyframes (the budget's, ``mapping.rate_fps``) ends after ``done``
        iterations: as soon as a keyframe or a checkpoint waits for the worker (it uses idle time only)."""
        w = self.worker
        return w.queued("keyframe") + w.queued("init") > 0 or w.hurry.is_set()

    def begin_window(self, init: bool) -> tuple[Callable[[], None], Callable[[int], bool]]:
        """A keyframe's window mapping starts (``init``: one of the initial window): its seeds published first
        where tracking is to see them before the mapping (``mapping.publish_after`` 0, or the first keyframe's
        with ``mapping.init_wait`` seeds), a safe point; returns the mapping's (pause, stop): the pause
        publishes once more after ``mapping.publish_after`` iterations, if that is above 0."""
        after = -1 if init else self.cfg.publish_after
        if init and self.publisher.version == 0 and self.cfg.init_wait == "seeds":
            after = 0  # the first keyframe's seeds, which tracking waits for
        if after == 0:
            self.publish()
        self.pause()
        pause = self.pause if after <= 0 else self._publishing_pause(after)
        return pause, self._later_keyframe_waits if init else self._next_keyframe_waits

    def _publishing_pause(self, after: int) -> Callable[[], None]:
        """A mapping job's ``pause`` that publishes the map once, after ``after`` iterations, then pauses as
        ``pause`` does."""
        done = 0

        def pause() -> None:
            nonlocal done
            done += 1
            if done == after:
                self.publish()
            self.pause()

        return pause

    def _next_keyframe_waits(self, done: int) -> bool:
        """Whether a keyframe's window mapping ends after ``done`` iterations (``mapping.min_iters``): once it
        had that many and the next keyframe, or a checkpoint (``SLAM.snapshot(hurry=True)``), waits."""
        n, w = self.cfg.min_iters, self.worker
        return 0 < n <= done and (w.queued("keyframe") > 1 or w.hurry.is_set())

    def _later_keyframe_waits(self, done: int) -> bool:
        """Whether an initial keyframe's mapping ends after ``done`` iterations (``mapping.min_iters``): once it
        had that many and as many later keyframes wait as may wait before tracking does
        (``mapping.async_queue``, at least one), or a checkpoint waits.  Only with ``mapping.init_wait`` first or
        seeds: otherwise tracking waits for the initial window's mappings and no later keyframe comes
        meanwhile."""
        n, w = self.cfg.min_iters, self.worker
        waiting = max(1, self.cfg.async_queue)
        return 0 < n <= done and (w.queued("keyframe") >= waiting or w.hurry.is_set())
