"""The evaluation suite (rgs_warp.app.suite) on a local Ray cluster (``--ray``), against the serial path:
a tiny sweep (a synthetic scene at 64x36, 6 frames, two seeds) gives the same numbers both ways, a
task whose worker dies is retried, a run whose worker dies twice is an error row, and ``--resume``
redoes only that."""

import json
from pathlib import Path

import pytest

from rgs_warp.app import suite

ray = pytest.importorskip("ray", reason="the --ray path needs Ray: pip install -e '.[cluster]'")
# one local Ray cluster for the module: its tests stay on one pytest-xdist worker (--dist loadgroup)
pytestmark = pytest.mark.xdist_group("ray")

TINY = [
    "dataset.width=64",
    "dataset.height=36",
    "dataset.max_frames=6",
    "tracking.iters=5",
    "mapping.init_iters=10",
    "mapping.iters_per_frame=2",
    "mapping.window=2",
]
# what depends on time or on the process (how many kernel modules it compiled or loaded)
TIMING = {"fps", "tracking_fps", "wall_s", "time_s", "kernels"}


def _sweep(tmp_path: Path, scenes: str) -> Path:
    spec = tmp_path / "tiny.yaml"
    spec.write_text(f"scenes: [{scenes}]\nmethods: [rgs]\nrepeats: 2\noverrides: [{', '.join(TINY)}]\n")
    return spec


@pytest.fixture(scope="module")
def cluster():
    ray.init(num_cpus=2, include_dashboard=False, object_store_memory=100 * 1024**2)
    yield
    ray.shutdown()


def _numbers(out: Path) -> tuple[dict, list, str]:
    """eval.json's aggregates and runs' metrics less the timings, and eval.md's tables of the groups
    without timings."""
    result = json.loads((out / "eval.json").read_text())
    speed = {m.id for m in suite.METRICS if m.group == "Speed and memory"}
    aggregate = {
        scene: {row: {k: v for k, v in cells.items() if k not in speed} for row, cells in rows.items()}
        for scene, rows in result["aggregate"].items()
    }
    runs = [
        (r["scene"], r["seed"], r["status"], {k: v for k, v in r["metrics"].items() if k not in TIMING})
        for r in result["runs"]
    ]
    md = (out / "eval.md").read_text()
    tables = md[md.index("## Tracking") : md.index("## Speed and memory")]
    return aggregate, runs, tables


@pytest.mark.slow
def test_ray_sweep_matches_serial_and_survives_a_killed_worker(tmp_path, cluster, monkeypatch):
    """The CPU SLAM is deterministic for a seed: the Ray run's numbers are the serial run's, to the
    last bit, although the worker of one run was killed on its first attempt (and it was retried)."""
    spec = _sweep(tmp_path, "synthetic/office0")
    common = ["--sweep", str(spec), "--device", "cpu"]
    assert suite.main([*common, "--out", str(tmp_path / "serial")]) == 0
    monkeypatch.setenv(suite.KILL_ENV, "synthetic-office0-rgs-1:1")
    assert suite.main([*common, "--out", str(tmp_path / "ray"), "--ray"]) == 0
    attempts = tmp_path / "ray" / "eval_runs" / ".synthetic-office0-rgs-1.attempts"
    assert attempts.read_text() == "2"  # killed once, retried once
    serial, on_ray = _numbers(tmp_path / "serial"), _numbers(tmp_path / "ray")
    assert len(serial[1]) == 2 and all(status == "ok" for _, _, status, _ in on_ray[1])
    assert on_ray == serial
    assert serial[0]["synthetic/office0"]["rgs"]["ate_keyframes_rmse_cm"]["n"] == 2
    # the driver wrote every finished run's record (what --resume reads) even where a worker had
    assert len(list((tmp_path / "ray" / "eval_runs").glob(f"*/{suite.RECORD_FILE}"))) == 2


@pytest.mark.slow
def test_a_run_killed_twice_is_an_error_row_and_resume_redoes_only_it(tmp_path, cluster, monkeypatch):
    spec = _sweep(tmp_path, "synthetic/room0")
    argv = ["--sweep", str(spec), "--device", "cpu", "--out", str(tmp_path), "--ray"]
    monkeypatch.setenv(suite.KILL_ENV, "synthetic-room0-rgs-1:2")
    assert suite.main(argv) == 0  # one of two runs ok: the sweep is not fatal
    first = json.loads((tmp_path / "eval.json").read_text())
    finished = tmp_path / "eval_runs" / "synthetic-room0-rgs-0" / "metrics.json"
    written = finished.stat().st_mtime_ns
    ok, killed = first["runs"]
    assert ok["status"] == "ok" and killed["status"] == "error"
    assert killed["error"].startswith("Ray task failed:") and "died" in killed["error"].lower()
    md = (tmp_path / "eval.md").read_text()
    assert "| synthetic/room0 | rgs | 1 | error [^" in md and "run failed: Ray task failed:" in md

    monkeypatch.delenv(suite.KILL_ENV)
    assert suite.main([*argv, "--resume"]) == 0
    again = json.loads((tmp_path / "eval.json").read_text())
    assert again["runs"][0]["resumed"] and again["runs"][0]["metrics"] == ok["metrics"]
    assert again["runs"][1]["status"] == "ok" and "resumed" not in again["runs"][1]
    assert finished.stat().st_mtime_ns == written  # the finished run was not run again


@pytest.mark.slow  # starting the local Ray cluster takes 6 s: with the other Ray tests
def test_cuda_runs_on_a_cluster_without_gpus_fail_at_once(tmp_path, cluster, capsys):
    """Not a sweep whose tasks wait for ever for a GPU: an error that says why, before any run."""
    spec = _sweep(tmp_path, "synthetic/room0")
    assert suite.main(["--sweep", str(spec), "--device", "cuda:0", "--out", str(tmp_path), "--ray"]) == 1
    err = capsys.readouterr().err
    assert "ask for 1.0 GPU each (device cuda:0) but the Ray cluster has 0" in err
    assert not list((tmp_path / "eval_runs").iterdir())
