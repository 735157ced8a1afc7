"""ATE against evo on the real 7-Scenes poses, and the top-view trajectory plot."""

import matplotlib.image as mpimg
import numpy as np
import pytest
from evo.core import metrics as evo_metrics
from evo.core.geometry import umeyama_alignment as evo_umeyama
from evo.core.trajectory import PoseTrajectory3D

from rgs_warp.app.report import plot_trajectory_topview
from rgs_warp.eval import ate, ate_keyframes_and_all, umeyama_alignment
from rgs_warp.geometry import se3_exp

TOL_M = 1e-6


@pytest.fixture(scope="module")
def gt_poses(shared_data):
    folder = shared_data / "7scenes-redkitchen"
    return np.stack([np.loadtxt(folder / f"frame-{i:06d}.pose.txt") for i in range(500)])


def _perturbed(gt: np.ndarray, scale: float, seed: int) -> np.ndarray:
    """gt with 2 cm / 1 deg noise in each camera frame, then moved by one random similarity (rigid if
    scale is 1)."""
    rng = np.random.default_rng(seed)
    noisy = np.stack([T @ se3_exp(np.r_[rng.normal(0, 0.02, 3), rng.normal(0, 0.017, 3)]) for T in gt])
    G = se3_exp(np.r_[rng.normal(0, 2.0, 3), rng.normal(0, 1.0, 3)])
    out = G @ noisy
    out[:, :3, 3] *= scale
    return out


def _evo_ape(est: np.ndarray, gt: np.ndarray, correct_scale: bool) -> tuple[dict, tuple]:
    stamps = np.arange(len(gt), dtype=np.float64)
    traj_est = PoseTrajectory3D(poses_se3=list(est), timestamps=stamps)
    traj_ref = PoseTrajectory3D(poses_se3=list(gt), timestamps=stamps)
    alignment = traj_est.align(traj_ref, correct_scale=correct_scale)
    ape = evo_metrics.APE(evo_metrics.PoseRelation.translation_part)
    ape.process_data((traj_ref, traj_est))
    return ape.get_all_statistics(), alignment


@pytest.mark.parametrize("align, scale, seed", [("se3", 1.0, 0), ("sim3", 0.37, 1), ("sim3", 2.5, 2)])
def test_ate_matches_evo(gt_poses, align, scale, seed):
    est = _perturbed(gt_poses, scale, seed)
    ours = ate(est, gt_poses, align=align)
    stats, (r, t, s) = _evo_ape(est, gt_poses, correct_scale=align == "sim3")
    for key in ("rmse", "mean", "median", "max"):
        assert abs(ours[f"{key}_cm"] / 100.0 - stats[key]) < TOL_M, key
    np.testing.assert_allclose(ours["align_T"][:3, :3], r, atol=1e-9)
    np.testing.assert_allclose(ours["align_T"][:3, 3], t, atol=1e-9)
    assert abs(ours["align_scale"] - s) < 1e-9
    # The position noise (2 cm per axis: 3.5 cm RMS) survives the alignment.
    assert 3.0 < ours["rmse_cm"] < 4.0
    assert ours["n_poses"] == 500


def test_ate_recovers_pure_offsets(gt_poses):
    offset_m = np.array([0.3, -1.2, 0.05])
    shifted = gt_poses.copy()
    shifted[:, :3, 3] += offset_m
    assert ate(shifted, gt_poses, align="se3")["rmse_cm"] < 1e-10
    unaligned = ate(shifted, gt_poses, align="none")
    assert abs(unaligned["max_cm"] - 100.0 * np.linalg.norm(offset_m)) < 1e-10
    assert abs(unaligned["rmse_cm"] - unaligned["median_cm"]) < 1e-10

    G = se3_exp(np.array([0.5, 0.1, -2.0, 0.3, -0.7, 1.1]))
    similar = G @ gt_poses
    similar[:, :3, 3] *= 3.0
    sim3 = ate(similar, gt_poses, align="sim3")
    assert sim3["rmse_cm"] < 1e-9
    assert abs(sim3["align_scale"] - 1.0 / 3.0) < 1e-12
    assert ate(similar, gt_poses, align="se3")["rmse_cm"] > 10.0


def test_positions_and_poses_agree(gt_poses):
    est = _perturbed(gt_poses, 1.0, 3)
    a, b = ate(est, gt_poses), ate(est[:, :3, 3], gt_poses[:, :3, 3])
    assert a["rmse_cm"] == b["rmse_cm"] and a["max_cm"] == b["max_cm"]


def test_umeyama_reflection_gives_a_rotation(gt_poses):
    # A mirrored trajectory: the best orthogonal fit is a reflection; Umeyama must return a rotation.
    points_m = gt_poses[:, :3, 3]
    mirrored_m = points_m * np.array([-1.0, 1.0, 1.0])
    for with_scale in (False, True):
        R, t, s = umeyama_alignment(mirrored_m, points_m, with_scale)
        assert abs(np.linalg.det(R) - 1.0) < 1e-12
        r_evo, t_evo, s_evo = evo_umeyama(mirrored_m.T, points_m.T, with_scale)
        np.testing.assert_allclose(R, r_evo, atol=1e-9)
        np.testing.assert_allclose(t, t_evo, atol=1e-9)
        assert abs(s - s_evo) < 1e-9


def test_keyframes_and_all(gt_poses):
    est = _perturbed(gt_poses, 1.0, 4)
    keyframes = np.arange(0, 500, 37)
    both = ate_keyframes_and_all(est, gt_poses, keyframes)
    assert both["keyframes"]["rmse_cm"] == ate(est[keyframes], gt_poses[keyframes])["rmse_cm"]
    assert both["keyframes"]["n_poses"] == len(keyframes)
    assert both["all_frames"]["rmse_cm"] == ate(est, gt_poses)["rmse_cm"]


def test_ate_errors(gt_poses):
    with pytest.raises(ValueError, match="est has 10 poses, gt has 11"):
        ate(gt_poses[:10], gt_poses[:11])
    with pytest.raises(ValueError, match="at least 3"):
        ate(gt_poses[:2], gt_poses[:2])
    with pytest.raises(ValueError, match="align must be"):
        ate(gt_poses, gt_poses, align="SE3")
    with pytest.raises(ValueError, match=r"\(N, 3\)"):
        ate(gt_poses[:, :3, :], gt_poses[:, :3, :])
    with pytest.raises(ValueError, match="not all identical"):
        ate(np.zeros((5, 3)), gt_poses[:5], align="sim3")


def _colour_pixels(png, rgb) -> int:
    image = mpimg.imread(png)[..., :3]
    return int(np.sum(np.all(np.abs(image - np.array(rgb)) < 0.15, axis=-1)))


def test_topview_plot(gt_poses, tmp_path):
    # The estimate is a shrunk copy: the long red (ground truth) path must dominate the green one.
    est = gt_poses[:, :3, 3] * 0.2
    png = plot_trajectory_topview(est, gt_poses, tmp_path / "traj.png", title="redkitchen")
    red, green = _colour_pixels(png, (1, 0, 0)), _colour_pixels(png, (0, 0.5, 0))
    assert green > 100 and red > 2 * green
    aligned = plot_trajectory_topview(
        _perturbed(gt_poses, 0.5, 5), gt_poses, tmp_path / "aligned.png", align="sim3", up=(0.0, -1.0, 0.0)
    )
    assert _colour_pixels(aligned, (1, 0, 0)) > 100 and _colour_pixels(aligned, (0, 0.5, 0)) > 100


def test_keyframes_fewer_than_three(gt_poses):
    """A monocular start that falls back to one keyframe and loses every frame after it still gets
    its all-frames ATE and a reason for the keyframes' (it raised, and the run ended without metrics)."""
    est = _perturbed(gt_poses, 1.0, 4)
    both = ate_keyframes_and_all(est, gt_poses, [0], align="sim3")
    assert both["keyframes"] is None and "1 keyframe" in both["keyframes_na_reason"]
    assert both["all_frames"]["rmse_cm"] == ate(est, gt_poses, "sim3")["rmse_cm"]
