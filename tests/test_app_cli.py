"""The command line ``python -m rgs_warp.slam`` (``rgs_warp.app.cli``): one error line and no run
folder for what cannot run (bad intrinsics, a config error, a missing evaluation package, an
unwritable output folder, a config the SLAM refuses), a monocular run's notice, and a full disk at
the final save named in one message that says what was saved."""

import errno
import os
import subprocess
import sys

import pytest

from helpers_tum import tiny_tum
from rgs_warp.app.cli import MONO_NOTICE, main
from rgs_warp.config import load_config
from rgs_warp.datasets import open_dataset
from rgs_warp.io.trajectory import read_tum_trajectory

SMALL = ["dataset=synthetic/office0", "dataset.width=160", "dataset.height=90"]


def test_cli_bad_intrinsics_one_error_no_run_folder(tmp_path, capsys):
    from rgs_warp.app.cli import main

    root = tiny_tum(tmp_path / "mine", camera={"fx": 0.0})
    out = tmp_path / "runs"
    argv = ["dataset.type=tum", f"dataset.path={root}", "dataset.require_pose=false", f"output_dir={out}"]
    assert main([*argv, "device=cpu", "mapping.init_iters=10", "dataset.max_frames=3"]) == 1
    err = capsys.readouterr().err
    assert f"error: {root / 'cam_params.json'}: fx = 0.0: a focal length" in err and "Traceback" not in err
    assert not out.exists()


def test_cli_config_error_is_one_line_and_exit_2(tmp_path):
    proc = subprocess.run(
        [sys.executable, "-m", "rgs_warp.slam", "tracking.lr=-1", f"output_dir={tmp_path / 'runs'}"],
        capture_output=True,
        text=True,
        env=os.environ.copy(),
        timeout=120,
    )
    lines = [line for line in proc.stderr.splitlines() if not line.startswith("Warp")]
    assert proc.returncode == 2 and lines == ["error: tracking.lr: -1.0 is out of range: it must be > 0"], proc.stderr
    assert not (tmp_path / "runs").exists()


def test_a_missing_evaluation_package_stops_before_any_run(tmp_path, monkeypatch, capsys):
    """The evaluation imports pytorch-msssim at the end of a run; without it the command says so at
    once (one line, no run folder) instead of after minutes of tracking."""
    import importlib.util

    from rgs_warp.app import cli as run_module
    from rgs_warp.app import suite

    find_spec = importlib.util.find_spec
    monkeypatch.setattr(
        importlib.util, "find_spec", lambda name, *a: None if name == "pytorch_msssim" else find_spec(name, *a)
    )
    small = ["dataset.max_frames=2", "mapping.init_iters=5", "device=cpu"]  # were it to run: seconds
    assert run_module.main([f"output_dir={tmp_path / 'runs'}", *small]) == 1
    assert suite.main(["--quick", "--out", str(tmp_path / "suite"), "--device", "cpu"]) == 1
    err = capsys.readouterr().err.splitlines()
    assert (
        err
        == [
            "error: the evaluation at the end of a run needs pytorch-msssim, which is not installed: "
            "pip install pytorch-msssim (nothing was run)"
        ]
        * 2
    ), err
    assert not (tmp_path / "runs").exists() and not (tmp_path / "suite").exists()


def test_an_unwritable_output_dir_is_one_error_line(tmp_path, capsys):
    """8dc16f7: a NotADirectoryError traceback.  (As root a read-only folder is writable, so the
    output folder is put under a file.)"""
    (tmp_path / "file").write_text("")
    output_dir = tmp_path / "file" / "runs"
    argv = [*SMALL, "dataset.max_frames=3", "device=cpu", f"output_dir={output_dir}"]
    open_dataset(load_config(argv))  # the scene generated beforehand: its progress bar is not the error
    capsys.readouterr()
    assert main(argv) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: cannot create the run folder") and str(output_dir) in err[0]


def test_a_monocular_run_is_told_that_the_mode_is_not_reliable_yet(tmp_path, capsys):
    """mode=mono says at its start what it does not do yet; an RGB-D run says nothing (the
    test above: its one line is the error)."""
    (tmp_path / "file").write_text("")
    argv = [*SMALL, "mode=mono", "dataset.max_frames=3", "device=cpu", f"output_dir={tmp_path / 'file' / 'runs'}"]
    open_dataset(load_config(argv))
    capsys.readouterr()
    assert main(argv) == 1  # stops at the run folder, after the notice
    err = capsys.readouterr().err.strip().splitlines()
    assert err[0] == MONO_NOTICE and err[1].startswith("error: cannot create the run folder")


def test_a_run_failing_at_start_up_leaves_no_folder(tmp_path, capsys):
    """8dc16f7 makes the folder and its config.yaml before the SLAM refuses the config."""
    assert main([*SMALL, "keyframes.buffer_size=1", "device=cpu", f"output_dir={tmp_path}"]) in (1, 2)
    assert capsys.readouterr().err.startswith("error:")
    assert list(tmp_path.iterdir()) == []


@pytest.mark.slow
def test_a_full_disk_at_the_final_save_is_one_message_saying_what_was_saved(tmp_path, capsys, monkeypatch):
    """8dc16f7: the OSError's traceback, and no trajectory (map.ply was written first)."""
    import rgs_warp.slam.storage as slam_module

    def disk_full(path, fields, num_sh):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(path))

    monkeypatch.setattr(slam_module, "write_ply", disk_full)
    argv = [*SMALL, "dataset.max_frames=3", "mapping.init_iters=8", "device=cpu"]
    assert main([*argv, f"output_dir={tmp_path}", "run_name=full"]) == 1
    err = capsys.readouterr().err
    errors = [line for line in err.splitlines() if line.startswith("error:")]  # the rest: the progress bar
    assert len(errors) == 1 and "Traceback" not in err and "map.ply: [Errno 28] No space left on device" in errors[0]
    assert "saved: trajectory.txt, keyframes.npz, config.yaml, convergence.json" in errors[0]
    assert len(read_tum_trajectory(tmp_path / "full" / "trajectory.txt")[1]) == 3


def test_a_missing_device_is_one_error_line(capsys):
    """``device=cuda:0`` without a GPU: Warp's "Invalid device identifier" became the devices there are
    and what ``device=auto`` picks."""
    import warp as wp

    missing = f"cuda:{len(wp.get_cuda_devices())}"
    assert main([f"device={missing}"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"error: device={missing}: no such device") and "device=auto" in err[0]


def test_an_output_dir_that_is_a_file_is_one_error_line(tmp_path, capsys):
    (tmp_path / "runs").write_text("")
    argv = [*SMALL, "dataset.max_frames=3", "device=cpu", f"output_dir={tmp_path / 'runs'}"]
    open_dataset(load_config(argv))  # the scene generated beforehand: its progress bar is not the error
    capsys.readouterr()
    assert main(argv) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [f"error: output_dir={tmp_path / 'runs'} is a file, not a folder" + err[0].partition("folder")[2]]
    assert "cannot be made in it" in err[0]
