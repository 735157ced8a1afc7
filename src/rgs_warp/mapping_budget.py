"""The mapping budget: how many mapping iterations a run spends, and on what.

The user gives a rate (``mapping.rate_fps``: frames/s of a 640x480 run on one H100; a larger frame spends the
same iterations, each costing more, so its run is slower about in proportion to its pixels) or asks for the best
map (``0``); ``mapping.iters_per_frame`` gives the iterations directly.  The rate covers the final refinement
after the last frame (``mapping.final_share`` of the run's iterations) too.  A cost model of the renderer turns the
rate into mapping iterations per frame, so an offline run does the same iterations on any machine (the same config
gives the same map); live, the worker's stop policies end a job early when a keyframe waits, and between keyframes
it refines whenever it would idle (``WorkerMapping.refine_iters``).

Each frame adds ``per_frame`` iterations to a balance.  A new keyframe spends first: ``mapping.keyframe_share``
of the iterations expected until the next keyframe (the mean gap between keyframes so far), borrowed from the
frames to come; each frame after it spends what the balance then holds on the window and the older keyframes.
So the newest keyframe is fitted at once, the map goes on improving between keyframes with what is left, and
the run spends ``per_frame`` iterations a frame on average.
"""

from __future__ import annotations

import math

# A mapping iteration's cost on one H100 (ms: fixed, per megapixel; one view forward and backward and the Adam
# step) and a 640x480 frame's other work (tracking, seeding, maintenance, checkpoints; ms), from runs of 7-Scenes
# (640x480) and the synthetic office (1200x680): experiments/results/fidelity.md, "Mapping budget".
ITERATION_MS = (1.0, 1.96)
REFERENCE_FRAME_MS = 26.0
REFERENCE_PX = 640 * 480
BEST_RATE_FPS = 1.0  # rate_fps = 0, the best map: the budget of a 1 frame/s run
FIRST_GAP = 8.0  # frames between keyframes expected before the second keyframe comes


def iterations_per_frame(rate_fps: float, final_share: float = 0.0) -> float:
    """The mapping iterations a frame may spend at ``rate_fps`` (0: the best map) by the cost model: what a
    640x480 frame at that rate leaves after its other work, over an iteration's cost at that size, of which
    the frames get 1 / (1 + ``final_share``) and the final refinement after the last frame the rest
    (``mapping.final_share``); at least one.  A frame of another size spends as many (the rate scales with its
    pixel count)."""
    mapping_ms = 1000.0 / (rate_fps or BEST_RATE_FPS) - REFERENCE_FRAME_MS
    return max(1.0, mapping_ms / (ITERATION_MS[0] + ITERATION_MS[1] * REFERENCE_PX / 1e6) / (1.0 + final_share))


class MappingBudget:
    """The balance of mapping iterations (module docstring): ``frame()`` after every frame, ``keyframe(i)``
    for keyframe ``i``'s window mapping, ``refine()`` between keyframes; each returns iterations to run."""

    def __init__(self, per_frame: float, keyframe_share: float):
        self.per_frame, self.keyframe_share = float(per_frame), float(keyframe_share)
        self.balance = 0.0
        self.frames = 0  # frames the budget was given (after the initial window)
        self.gap = FIRST_GAP  # mean frames between keyframes so far
        self.gaps = 0  # gaps measured (keyframes after the first that the budget mapped, less one)
        self.keyframes = 0  # keyframes the budget mapped
        self.last_keyframe = -1

    def start(self, index: int) -> None:
        """Frame ``index`` is a keyframe of the initial window (mapped by ``mapping.init_iters``): the gap to
        the next keyframe counts from it."""
        self.last_keyframe = index

    def frame(self) -> None:
        self.frames += 1
        self.balance += self.per_frame

    def given(self) -> float:
        """The iterations the frames so far were given: what an offline run spends on them."""
        return self.per_frame * self.frames

    def keyframe(self, index: int) -> int:
        if self.last_keyframe >= 0:
            self.gaps += 1
            self.gap += (index - self.last_keyframe - self.gap) / self.gaps
        self.last_keyframe = index
        self.keyframes += 1
        iters = max(1, round(self.keyframe_share * self.per_frame * self.gap))
        self.balance -= iters
        return iters

    def refine(self) -> int:
        iters = max(0, math.floor(self.balance))
        self.balance -= iters
        return iters

    def state_dict(self) -> dict:
        names = ("balance", "frames", "gap", "gaps", "keyframes", "last_keyframe")
        return {name: getattr(self, name) for name in names}

    def load_state_dict(self, state: dict) -> None:
        self.balance, self.gap = float(state["balance"]), float(state["gap"])
        names = ("frames", "gaps", "keyframes", "last_keyframe")
        self.frames, self.gaps, self.keyframes, self.last_keyframe = (int(state[k]) for k in names)
