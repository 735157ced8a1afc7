"""TUM trajectory I/O: exact round trip, evo reads what we write, malformed lines are named."""

import numpy as np
import pytest
from evo.tools import file_interface
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from rgs_warp.geometry import matrix_to_quat, pose_from_tq
from rgs_warp.io.trajectory import TrajectoryFormatError, read_tum_trajectory, write_tum_trajectory


def _random_poses(n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    # Timestamps and translations with all 17 digits significant, as a real dataset's are.
    timestamps_s = 1305031102.0 + np.sort(rng.random(n)) * 100.0
    poses = np.stack([pose_from_tq(rng.normal(size=3) * 3.0, rng.normal(size=4)) for _ in range(n)])
    return timestamps_s, poses


def test_round_trip_exact(tmp_path):
    timestamps_s, poses = _random_poses(200)
    path = tmp_path / "traj.txt"
    write_tum_trajectory(path, timestamps_s, poses)
    read_t, read_poses = read_tum_trajectory(path)
    # Timestamps and translations are written as text and come back bit-exact ...
    np.testing.assert_array_equal(read_t, timestamps_s)
    np.testing.assert_array_equal(read_poses[:, :3, 3], poses[:, :3, 3])
    np.testing.assert_array_equal(read_poses[:, 3], np.tile([0.0, 0.0, 0.0, 1.0], (200, 1)))
    # ... and so do the written quaternions; the rotation matrix goes through one conversion.
    written = np.loadtxt(path)
    expected_q = np.stack([matrix_to_quat(T[:3, :3]) for T in poses])
    np.testing.assert_array_equal(written[:, 4:], expected_q)
    np.testing.assert_allclose(read_poses[:, :3, :3], poses[:, :3, :3], rtol=0, atol=1e-15)


def test_evo_reads_what_we_write(tmp_path):
    timestamps_s, poses = _random_poses(50, seed=1)
    path = tmp_path / "traj.txt"
    write_tum_trajectory(path, timestamps_s, poses)
    traj = file_interface.read_tum_trajectory_file(str(path))
    np.testing.assert_array_equal(traj.timestamps, timestamps_s)
    np.testing.assert_allclose(np.stack(traj.poses_se3), poses, rtol=0, atol=1e-15)


def test_comments_blank_lines_and_commas(tmp_path):
    path = tmp_path / "traj.txt"
    path.write_text("# header\n\n1.0 1 2 3 0 0 0 1\n  # indented comment\n2.5,4,5,6,0,0,1,0\n")
    t, poses = read_tum_trajectory(path)
    np.testing.assert_array_equal(t, [1.0, 2.5])
    np.testing.assert_array_equal(poses[1, :3, 3], [4.0, 5.0, 6.0])
    np.testing.assert_allclose(poses[1, :3, :3], np.diag([-1.0, -1.0, 1.0]), atol=1e-15)


def test_empty_file(tmp_path):
    path = tmp_path / "traj.txt"
    path.write_text("# nothing\n")
    t, poses = read_tum_trajectory(path)
    assert t.shape == (0,) and poses.shape == (0, 4, 4)


@pytest.mark.parametrize(
    "bad_line, message",
    [
        ("1 2 3 4 0 0 0", "expected 8 values"),
        ("1 2 3 4 0 0 0 1 9", "expected 8 values"),
        ("1 2 x 4 0 0 0 1", "not a number"),
        ("1 2 nan 4 0 0 0 1", "non-finite"),
        ("inf 2 3 4 0 0 0 1", "non-finite"),
        ("1 2 3 4 0 0 0 0", "zero quaternion"),
    ],
)
def test_malformed_line_is_named(tmp_path, bad_line, message):
    path = tmp_path / "traj.txt"
    path.write_text(f"# header\n0 0 0 0 0 0 0 1\n\n{bad_line}\n")
    with pytest.raises(TrajectoryFormatError, match=message) as info:
        read_tum_trajectory(path)
    assert f"{path}:4:" in str(info.value)


def test_write_rejects_bad_input(tmp_path):
    timestamps_s, poses = _random_poses(3)
    with pytest.raises(ValueError, match="3 timestamps for 2 poses"):
        write_tum_trajectory(tmp_path / "a.txt", timestamps_s, poses[:2])
    sheared = poses.copy()
    sheared[1, 0, 1] += 0.1
    with pytest.raises(ValueError, match="pose 1"):
        write_tum_trajectory(tmp_path / "a.txt", timestamps_s, sheared)
    mirrored = poses.copy()
    mirrored[2, :3, 0] *= -1
    with pytest.raises(ValueError, match="pose 2"):
        write_tum_trajectory(tmp_path / "a.txt", timestamps_s, mirrored)
    poses[0, 0, 3] = np.nan
    with pytest.raises(ValueError, match="finite"):
        write_tum_trajectory(tmp_path / "a.txt", timestamps_s, poses)


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(st.lists(st.text(alphabet=st.sampled_from(list("0123456789.-+eE#, \tnaif")), max_size=40), max_size=6))
def test_fuzz_reader_fails_only_with_format_error(tmp_path, lines):
    path = tmp_path / "fuzz.txt"
    path.write_text("\n".join(lines) + "\n")
    try:
        t, poses = read_tum_trajectory(path)
    except TrajectoryFormatError as e:
        assert str(path) in str(e)
    else:
        assert len(t) == len(poses)
        assert np.all(np.isfinite(poses))
