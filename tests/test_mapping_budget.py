"""The mapping budget (rgs_warp.mapping_budget): the cost model's iterations per frame, the balance's
accounting, and a SLAM run whose mapping iterations follow the budget (counted, not timed)."""

import numpy as np
import pytest

from rgs_warp import SLAM, open_dataset
from rgs_warp.config import load_config
from rgs_warp.mapping_budget import MappingBudget, iterations_per_frame


def test_iterations_per_frame_fall_with_the_rate():
    at = [iterations_per_frame(rate) for rate in (5.0, 10.0, 20.0)]
    assert at[0] > at[1] > at[2] >= 1.0
    assert iterations_per_frame(0.0) > at[0]  # rate 0: the best map
    # 10 frames/s at 640x480: 100 ms a frame, 26 of it the frame's other work, 1.6 ms an iteration
    assert at[1] == pytest.approx((100.0 - 26.0) / (1.0 + 1.96 * 0.3072))
    assert iterations_per_frame(1000.0) == 1.0  # never less than one
    # the rate covers the final refinement: the frames get 1 / (1 + mapping.final_share) of it
    assert iterations_per_frame(10.0, 0.12) == pytest.approx(at[1] / 1.12)


def test_budget_spends_per_frame_iterations_on_keyframes_first():
    budget = MappingBudget(per_frame=10.0, keyframe_share=0.5)
    budget.start(4)  # the initial window ended at frame 4
    spent = {"keyframe": [], "refine": []}
    keyframes = {10, 16, 22, 28}
    for i in range(5, 34):
        budget.frame()
        if i in keyframes:
            spent["keyframe"].append(budget.keyframe(i))
        else:
            spent["refine"].append(budget.refine())
    # a keyframe spends half of what is expected until the next one (the mean gap so far: 6 frames)
    assert spent["keyframe"] == [30, 30, 30, 30]
    # the frames after a keyframe wait until the balance it borrowed is paid back, then spend what comes in
    assert spent["refine"] == [10] * 5 + [0, 0, 10, 10, 10] * 4
    total = sum(spent["keyframe"]) + sum(spent["refine"])
    assert total + budget.balance == pytest.approx(10.0 * 29) and 0 <= budget.balance < 1
    state = budget.state_dict()
    again = MappingBudget(10.0, 0.5)
    again.load_state_dict(state)
    assert again.keyframe(40) == budget.keyframe(40)


# CPU-sized: the synthetic room at 96x54, 14 frames
SMALL = [
    "dataset.width=96",
    "dataset.height=54",
    "dataset.max_frames=14",
    "mapping.init_iters=40",
    "mapping.window=3",
    "mapping.init_window=2",
]


def _run(device, per_frame):
    cfg = load_config([*SMALL, f"mapping.iters_per_frame={per_frame}"])
    ds = open_dataset(cfg, device=device)
    slam = SLAM(cfg, ds.camera, device=device, T_first_WC=ds[0].pose_gt)
    for frame in ds:
        slam.process(frame.rgb, frame.depth, frame.timestamp)
    slam.finish()
    return slam, ds


@pytest.mark.slow
def test_a_larger_budget_maps_more_and_better(device):
    """The mapper's iterations follow the budget (those of the initial window apart), and four times the
    budget fits the frames better."""
    runs = {n: _run(device, n) for n in (2, 8)}
    for per_frame, (slam, _) in runs.items():
        its = slam.mapping_iterations
        assert its["init"] == 40 and sum(its.values()) == slam.mapper.total_iters
        after_init = len(slam.poses) - 2
        # what the frames after the initial window added, less what the balance still holds or lent
        spent = its["keyframe"] + its["refine"]
        assert spent == pytest.approx(per_frame * after_init - slam.budget.balance, abs=1e-9)
        assert abs(slam.budget.balance) <= per_frame * slam.budget.gap
    spent = {
        n: slam.mapping_iterations["keyframe"] + slam.mapping_iterations["refine"] for n, (slam, _) in runs.items()
    }
    assert spent[8] > 3 * spent[2] > 0

    def fit_db(slam, ds):
        errors = []
        for i in range(0, len(ds), 3):
            render = slam.render(slam.poses[i]).color.numpy()
            errors.append(np.mean((render - ds[i].rgb) ** 2))
        return -10 * np.log10(np.mean(errors))

    assert fit_db(*runs[8]) > fit_db(*runs[2]) + 0.5
