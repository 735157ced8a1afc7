"""Running the suite's runs: each (scene, method, override set, repeat) through the SLAM, one after
another here or one Ray task each (``--ray``), records kept for ``--resume``; ``run_suite`` then
aggregates them and writes ``eval.json``, ``eval.md`` and the plots."""

from __future__ import annotations

import json
import os
import shutil
import time
import traceback
from collections.abc import Callable, Sequence
from pathlib import Path

from tqdm import tqdm

from rgs_warp.app.report import to_json
from rgs_warp.app.runner import run
from rgs_warp.app.suite.plan import row_label, row_of, run_name
from rgs_warp.app.suite.plots import write_plots
from rgs_warp.app.suite.tables import (
    METRIC_BY_ID,
    METRICS,
    aggregate_runs,
    benchmark_averages,
    convergence_comparison,
    device_of,
    header,
    metric_value,
    render_markdown,
)
from rgs_warp.config import load_config

# runner(cfg, run_dir=..., progress=...) -> (run folder, metrics): the signature of rgs_warp.app.runner.run
Runner = Callable[..., tuple[Path, dict]]


def _error_text(e: BaseException) -> str:
    return f"{type(e).__name__}: {e}".strip()


RECORD_FILE = "suite_record.json"  # in a finished run's folder: what --resume reuses


def _run_spec(
    entry: dict, method: str, repeat: int, runs_dir: Path, extra: Sequence[str], variant: dict | None = None
) -> tuple[dict, list[str]]:
    """A run's record so far (who it is, where it writes) and its overrides: the plan's, the method
    and seed, the suite's own, then the sweep's override set (it is what the row varies: it wins)."""
    name = run_name(entry["scene"], method, repeat, variant)
    run_dir = runs_dir / name
    record = {"scene": entry["scene"], "method": method, "repeat": repeat, "seed": repeat, "run_dir": str(run_dir)}
    overrides = [*entry["overrides"], f"method={method}", f"seed={repeat}", *extra]
    if variant is not None:
        record["variant"] = variant["name"]
        overrides += variant["overrides"]
    overrides += [f"output_dir={runs_dir}", f"run_name={name}"]
    return record, overrides


def _save_record(record: dict, overrides: list[str]) -> None:
    """The record of a finished run in its folder, for --resume."""
    run_dir = Path(record["run_dir"])
    run_dir.mkdir(parents=True, exist_ok=True)
    (run_dir / RECORD_FILE).write_text(json.dumps(to_json({**record, "overrides": overrides}), indent=1))


def _one_run(
    entry: dict,
    method: str,
    repeat: int,
    runs_dir: Path,
    runner: Runner,
    extra: Sequence[str],
    resume: bool = False,
    variant: dict | None = None,
) -> dict:
    record, overrides = _run_spec(entry, method, repeat, runs_dir, extra, variant)
    run_dir = Path(record["run_dir"])
    if resume:
        done = _finished_record(run_dir, overrides)
        if done is not None:
            return done
    if run_dir.exists():  # a folder of an earlier suite: its files (convergence.json) must not mix in
        shutil.rmtree(run_dir)
    t0 = time.perf_counter()
    try:
        cfg = load_config(overrides)
        _, metrics = runner(cfg, run_dir=run_dir, progress=False)
    except Exception as e:  # recorded and reported; the other runs go on
        record.update(status="error", error=_error_text(e), traceback=traceback.format_exc(), metrics=None)
    else:
        record.update(status="ok", error=None, metrics=metrics)
    record["seconds"] = time.perf_counter() - t0
    record["convergence"] = _read_convergence(run_dir) if record["status"] == "ok" else None
    if record["status"] == "ok":
        _save_record(record, overrides)
    return record


def _finished_record(run_dir: Path, overrides: list[str]) -> dict | None:
    """The record of a run that finished in ``run_dir`` with exactly these overrides (--resume), with
    ``"resumed": True``; None if there is none or it was run differently."""
    try:
        record = json.loads((run_dir / RECORD_FILE).read_text())
    except (OSError, ValueError):
        return None
    if record.pop("overrides", None) != overrides or record.get("status") != "ok":
        return None
    record["resumed"] = True
    return record


def _read_convergence(run_dir: Path) -> list[dict] | None:
    """``convergence.json`` of a run (``rgs_warp.app.evaluate.write_convergence``): a list of
    ``{"iteration", "frame", "phase" ("init" | "keyframe" | "final"), "psnr_db", "gaussians"}``; points without
    a PSNR (an empty map) are left out."""
    path = run_dir / "convergence.json"
    if not path.is_file():
        return None
    try:
        points = json.loads(path.read_text())
        return [
            {
                "iteration": int(p["iteration"]),
                "frame": int(p["frame"]),
                "phase": str(p["phase"]),
                "psnr_db": float(p["psnr_db"]),
                "gaussians": int(p["gaussians"]),
            }
            for p in points
            if p.get("psnr_db") is not None
        ]
    except (ValueError, TypeError, KeyError, AttributeError):
        return None


def _progress_line(record: dict) -> str:
    head = f"{record['scene']} {row_of(record)} seed={record['seed']}: "
    if record["status"] != "ok":
        return head + f"error ({record['error'].splitlines()[0][:120]}) [{record['seconds']:.0f} s]"
    parts = []
    for metric_id in ("ate_keyframes_rmse_cm", "psnr_db", "fps"):
        value, _ = metric_value(record["metrics"], METRIC_BY_ID[metric_id].path)
        if value is not None:
            parts.append(f"{METRIC_BY_ID[metric_id].label} {value:.{METRIC_BY_ID[metric_id].digits}f}")
    return head + "ok " + ", ".join(parts) + f" [{record['seconds']:.0f} s]"


class ClusterError(RuntimeError):
    """The Ray cluster cannot run the suite's tasks (no GPU for CUDA runs)."""


# Test hook of the Ray path: "RUN_NAME:N" makes the first N attempts of that run's task end their worker
# process (os._exit), as a node lost or a worker killed by the OOM killer would; the attempts are
# counted in a file next to the run folder.
KILL_ENV = "RGS_SUITE_KILL"


def _ray_task(
    entry: dict, method: str, repeat: int, runs_dir: Path, runner: Runner, extra: Sequence[str], variant: dict | None
) -> dict:
    """One run as a Ray task: ``_one_run`` (its exceptions are its record's error; --resume was settled
    by the driver), after the test hook ``KILL_ENV``."""
    hook_name, _, hook_count = os.environ.get(KILL_ENV, "").rpartition(":")
    name = run_name(entry["scene"], method, repeat, variant)
    if hook_name == name:
        attempts = Path(runs_dir) / f".{name}.attempts"
        n = int(attempts.read_text()) if attempts.is_file() else 0
        attempts.write_text(str(n + 1))
        if n < int(hook_count):
            os._exit(1)
    return _one_run(entry, method, repeat, runs_dir, runner, extra, False, variant)


def ray_task_options(device: str, gpus_per_task: float = 1.0) -> dict:
    """What a run's Ray task asks for: ``gpus_per_task`` GPUs (and a CPU) on CUDA, else one CPU; one
    retry when its worker dies (a Python exception is the run's own error, recorded, never retried:
    the CPU SLAM would fail the same way again); the test hook ``KILL_ENV`` passed on when set."""
    resources = {"num_gpus": gpus_per_task, "num_cpus": 1} if device.startswith("cuda") else {"num_cpus": 1}
    options = {**resources, "max_retries": 1, "retry_exceptions": False}
    if os.environ.get(KILL_ENV):
        options["runtime_env"] = {"env_vars": {KILL_ENV: os.environ[KILL_ENV]}}
    return options


def _run_on_ray(
    jobs: list[tuple],
    runs_dir: Path,
    runner: Runner,
    extra: Sequence[str],
    resume: bool,
    cluster: str,
    device: str,
    gpus_per_task: float,
    bar: tqdm,
) -> list[dict]:
    """The records of ``jobs`` (``(entry, method, repeat, variant)``), in their order, each run as a Ray
    task asking for ``gpus_per_task`` GPUs on CUDA (Ray shows a task its GPU as ``cuda:0``), else one
    CPU.  The driver settles --resume (finished runs are not submitted), gathers the records through
    the tasks' return values and writes each finished run's record into its own ``runs_dir``, so that
    --resume works without a filesystem shared with the workers.  A task whose worker dies is retried
    once by Ray; if the retry dies too the run is an error row, and the other runs go on."""
    try:
        import ray
    except ImportError as e:
        raise ImportError("--ray needs Ray: pip install 'rgs_warp[cluster]'") from e
    started = not ray.is_initialized()
    if started:
        ray.init(address=cluster or None)
    options = ray_task_options(device, gpus_per_task)
    runs_dir = Path(runs_dir).resolve()  # the workers' working directory is not the driver's
    task = ray.remote(_ray_task).options(**options)
    runs: list[dict | None] = [None] * len(jobs)
    pending = {}
    try:
        gpus = ray.cluster_resources().get("GPU", 0)
        if options.get("num_gpus", 0) > gpus:  # the tasks would wait for ever
            raise ClusterError(
                f"the runs ask for {options['num_gpus']} GPU each (device {device}) but the Ray cluster has "
                f"{gpus:g}: start it on GPU nodes (or check that Ray sees their GPUs), or use --device cpu"
            )
        for i, (entry, method, repeat, variant) in enumerate(jobs):
            record, overrides = _run_spec(entry, method, repeat, runs_dir, extra, variant)
            done = _finished_record(Path(record["run_dir"]), overrides) if resume else None
            if done is not None:
                runs[i] = done
                bar.update(1)
                continue
            ref = task.remote(entry, method, repeat, runs_dir, runner, list(extra), variant)
            pending[ref] = (i, record, overrides, time.perf_counter())
        while pending:
            bar.set_postfix_str(f"{len(pending)} submitted or running")
            (ref,), _ = ray.wait(list(pending), num_returns=1)
            i, record, overrides, t0 = pending.pop(ref)
            try:
                runs[i] = ray.get(ref)
            except Exception as e:  # the task's worker died twice, or Ray could not run it at all
                error = "Ray task failed: " + _error_text(e)
                record.update(status="error", error=error, traceback=traceback.format_exc(), metrics=None)
                record.update(seconds=time.perf_counter() - t0, convergence=None)
                runs[i] = record
            else:
                if runs[i]["status"] == "ok" and not (Path(runs[i]["run_dir"]) / RECORD_FILE).is_file():
                    _save_record(runs[i], overrides)
            if not bar.disable:
                bar.write(_progress_line(runs[i]))
            bar.update(1)
    finally:
        if started:
            ray.shutdown()
    return runs


def _run_here(
    jobs: list[tuple], runs_dir: Path, runner: Runner, extra: Sequence[str], resume: bool, bar: tqdm
) -> list[dict]:
    """The records of ``jobs`` (``(entry, method, repeat, variant)``), run one after another here."""
    runs = []
    for entry, method, repeat, variant in jobs:
        bar.set_postfix_str(run_name(entry["scene"], method, repeat, variant))
        runs.append(_one_run(entry, method, repeat, runs_dir, runner, extra, resume, variant))
        if not bar.disable:
            bar.write(_progress_line(runs[-1]))
        bar.update(1)
    return runs


def run_suite(
    plan: list[dict],
    methods: Sequence[str] = ("rgs", "baseline"),
    repeats: int = 3,
    out_dir: Path = Path("experiments/results"),
    runner: Runner | None = None,
    extra_overrides: Sequence[str] = (),
    progress: bool = True,
    resume: bool = False,
    variants: Sequence[dict] | None = None,
    cluster: str | None = None,
    gpus_per_task: float = 1.0,
    plan_name: str = "custom",
) -> dict:
    """Run every scene of ``plan`` that is not skipped with every method, ``repeats`` times
    (``seed=0..repeats-1``), aggregate and write ``out_dir/eval.json``, ``out_dir/eval.md`` and the
    plots; returns what ``eval.json`` holds. ``runner`` defaults to ``rgs_warp.app.runner.run``;
    ``extra_overrides`` go to every run after the plan's own (``device=cuda:0``,
    ``tracking.iters=40``).  ``resume``: a run whose folder holds the record of a finished run with
    the same overrides is read back instead of run again (a suite cut short goes on where it stopped).

    ``variants``: a sweep's override sets (``[{"name", "overrides"}]``, see ``load_sweep``): every
    method runs with each, and each (method, set) is a row of the tables (``row_label``).
    ``cluster``: None runs here, one run after another; a string runs one Ray task per run (see
    ``_run_on_ray``): "" for ``ray.init()``'s default (``RAY_ADDRESS``, else a local cluster), else
    the cluster's address; ``gpus_per_task`` is what a task asks for when the device is CUDA.
    ``plan_name``: what the tables call the plan (``cpu``, ``full``, ``quick``, ``sweep NAME``)."""
    if runner is None:
        runner = run
    out_dir = Path(out_dir)
    runs_dir = out_dir / "eval_runs"
    runs_dir.mkdir(parents=True, exist_ok=True)
    present = [e for e in plan if not e.get("skipped")]
    sets = list(variants) if variants else [None]
    jobs = [(e, m, r, v) for e in present for m in methods for v in sets for r in range(repeats)]
    bar = tqdm(total=len(jobs), desc="eval", unit="run", disable=not progress)
    if cluster is None:
        runs = _run_here(jobs, runs_dir, runner, extra_overrides, resume, bar)
    else:
        device = device_of(extra_overrides)
        runs = _run_on_ray(jobs, runs_dir, runner, extra_overrides, resume, cluster, device, gpus_per_task, bar)
    bar.close()

    scenes = [e["scene"] for e in present]
    rows = [row_label(m, None if v is None else v["name"]) for m in methods for v in sets]
    aggregate = aggregate_runs(runs, scenes, rows)
    head = header(methods, repeats, extra_overrides, plan_name)
    if variants:
        head.update(rows=rows, variants=[{"name": v["name"], "overrides": list(v["overrides"])} for v in variants])
    result = {
        "header": head,
        "plan": plan,
        "skipped": [{"scene": e["scene"], "reason": e["skipped"]} for e in plan if e.get("skipped")],
        "metrics": [
            {"id": m.id, "label": m.label, "group": m.group, "lower_is_better": m.lower_is_better} for m in METRICS
        ],
        "aggregate": aggregate,
        "averages": benchmark_averages(aggregate, scenes, rows),
        "convergence": convergence_comparison(runs, scenes, rows),
        "runs": runs,
    }
    result["plots"] = write_plots(result, out_dir)
    result = to_json(result)
    (out_dir / "eval.json").write_text(json.dumps(result, indent=2, allow_nan=False) + "\n", encoding="utf-8")
    (out_dir / "eval.md").write_text(render_markdown(result), encoding="utf-8")
    return result
