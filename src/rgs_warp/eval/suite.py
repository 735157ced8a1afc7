"""Evaluation suite: every (scene, method, repeat) through the SLAM, then the supplement's tables.

``python -m rgs_warp.eval.suite [--device cpu|cuda:0|auto] [--repeats 3] [--methods rgs,baseline]
[--out experiments/results] [--quick] [key=value ...]`` writes ``<out>/eval.json`` (every run and
aggregate), ``<out>/eval.md`` (one table per metric group: rows = metric x method, columns = the
scenes of a benchmark + "Avg.", mean ± std over the repeats, best in bold, second best underlined as
in the supplement §3, and a convergence table: the mapping iterations each method's initialization
needs to reach a PSNR common to the methods, see ``convergence_comparison``) and
``<out>/eval_*.png`` (bars per metric, the methods' convergence curves overlaid per scene); the run
folders go to ``<out>/eval_runs/``.

A run that raises (an absent dataset, a method not implemented yet) is recorded with its error and
the suite goes on; a metric a run could not compute (None with ``<name>_na_reason``, see
``eval.report``) shows as "n/a" with the reason as a footnote.

``--sweep SPEC.yaml`` runs an ablation written as one file (``load_sweep``: scenes, methods, repeats,
overrides, named override sets and/or a grid); each method with each override set is a row of the
tables. ``--ray [ADDRESS]`` runs one Ray task per run (``_run_on_ray``: a GPU each on CUDA, else a
CPU) and gathers the records back into the same tables; without it the runs go one after another
here, as they always did.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import re
import shutil
import sys
import time
import traceback
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from datetime import datetime
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import yaml  # noqa: E402
from tqdm import tqdm  # noqa: E402

from rgs_warp.config import ConfigError, group_options, load_config  # noqa: E402
from rgs_warp.eval.report import NA_SUFFIX, git_commit, to_json  # noqa: E402
from rgs_warp.run import check_evaluation_imports, run  # noqa: E402
from rgs_warp.slam import METHODS  # noqa: E402

# runner(cfg, run_dir=..., progress=...) -> (run folder, metrics): the signature of rgs_warp.run.run
Runner = Callable[..., tuple[Path, dict]]

# The shared real-data folder next to the checkout (tests/conftest.py uses the same place).
SHARED_DATA = Path(__file__).resolve().parents[3].parent / "shared" / "data"
SEVENSCENES_SAMPLE = "7scenes-redkitchen"

# CPU runs are cut to this many frames so that one finishes in minutes; --quick cuts GPU runs too.
CPU_MAX_FRAMES = 40
QUICK_MAX_FRAMES = 15
# 7-Scenes on the CPU: every 5th frame (6 Hz, still trackable) at 320x240.
CPU_SEVENSCENES = ("dataset.stride=5", "dataset.downscale=2")
# Replica (1200x680) and TUM (640x480) on the CPU: about the synthetic scenes' 240x136 / 320x240.
CPU_DOWNSCALE = {"replica": 5, "tum": 2}
# The common PSNR of the convergence table: the lowest of the methods' final initialization PSNRs
# less this margin, so that every method's curve crosses it on its way up.
CONVERGENCE_MARGIN_DB = 0.5


@dataclass(frozen=True)
class Metric:
    """One number of the tables: where it sits in ``metrics.json`` and which way is better."""

    id: str
    path: tuple[str, ...]
    label: str
    group: str
    lower_is_better: bool | None  # None: no direction (a count), never bold
    digits: int


METRICS = (
    # the supplement's ATE is on keyframes (§3); all frames is what a user of the trajectory sees
    Metric("ate_keyframes_rmse_cm", ("ate", "keyframes", "rmse_cm"), "ATE RMSE keyframes (cm)", "Tracking", True, 2),
    Metric("ate_all_rmse_cm", ("ate", "all_frames", "rmse_cm"), "ATE RMSE all frames (cm)", "Tracking", True, 2),
    # frames whose tracking was lost (the map covered too little of the view, or the residual was too
    # high): a low ATE over a run that lost frames is luck, not tracking
    Metric("lost_frames", ("tracking", "lost_frames"), "Lost frames", "Tracking", True, 1),
    # raw: the render as the map holds it; compensated: at each scored frame's exposure (one gain and
    # bias fitted to the frame, MonoGS's protocol), what a camera with auto-exposure can be fair to
    Metric("psnr_db", ("photometric", "psnr_db"), "PSNR raw (dB)", "Rendering", False, 2),
    Metric(
        "psnr_compensated_db",
        ("photometric", "psnr_compensated_db"),
        "PSNR exposure-compensated (dB)",
        "Rendering",
        False,
        2,
    ),
    # at the exposure tracking estimated for each frame: what the SLAM itself shows of the frame
    Metric(
        "psnr_tracked_exposure_db",
        ("photometric", "psnr_tracked_exposure_db"),
        "PSNR at the tracked exposure (dB)",
        "Rendering",
        False,
        2,
    ),
    Metric("ssim", ("photometric", "ssim"), "SSIM raw", "Rendering", False, 3),
    Metric("ssim_compensated", ("photometric", "ssim_compensated"), "SSIM exposure-compensated", "Rendering", False, 3),
    Metric(
        "keyframe_psnr_compensated_db",
        ("photometric", "keyframe_psnr_compensated_db"),
        "Keyframe PSNR compensated (dB)",
        "Rendering",
        False,
        2,
    ),
    # the peers' SSIMs, named apart: MonoGS's (3DGS's zero-padded) and SplaTAM's "SSIM" (MS-SSIM)
    Metric("ssim_3dgs", ("photometric", "ssim_3dgs"), "SSIM 3DGS zero-padded (MonoGS's)", "Rendering", False, 3),
    Metric("ms_ssim", ("photometric", "ms_ssim"), "MS-SSIM (SplaTAM's SSIM)", "Rendering", False, 3),
    Metric("lpips", ("photometric", "lpips"), "LPIPS AlexNet", "Rendering", True, 3),
    Metric("depth_l1_cm", ("photometric", "depth_l1_cm"), "Depth L1 (cm)", "Rendering", True, 2),
    Metric("acc_cm", ("mesh", "acc_cm"), "Acc. (cm)", "Reconstruction", True, 2),
    Metric("comp_cm", ("mesh", "comp_cm"), "Comp. (cm)", "Reconstruction", True, 2),
    Metric("comp_ratio_pct", ("mesh", "comp_ratio_pct"), "Comp. Ratio (%)", "Reconstruction", False, 2),
    Metric("fps", ("fps",), "FPS", "Speed and memory", False, 2),
    Metric("tracking_fps", ("tracking_fps",), "Tracking FPS", "Speed and memory", False, 2),
    Metric("peak_memory_mib", ("peak_memory_mib",), "Peak memory (MiB)", "Speed and memory", True, 0),
    Metric("gaussians", ("gaussians",), "Gaussians", "Speed and memory", None, 0),
)
METRIC_BY_ID = {m.id: m for m in METRICS}
PLOTS = (("ate_keyframes_rmse_cm", "eval_ate.png"), ("psnr_db", "eval_psnr.png"))


# ---------------------------------------------------------------------------------------------------
# plan


def _entry(scene: str, overrides: list[str], absent: str | None = None) -> dict:
    return {"scene": scene, "overrides": [f"dataset={scene}", *overrides], "absent": absent}


def default_plan(device: str, data_root: Path | None = None, quick: bool = False) -> list[dict]:
    """The scenes of the suite, each ``{"scene": "replica/office0", "overrides": [...], "absent":
    None or why it is skipped}``: the two synthetic scenes (Replica size on a GPU, CPU size and
    ``CPU_MAX_FRAMES`` frames on the CPU), the 7-Scenes sequence (the full ``seq-01`` under the data
    root, else the shared 500-frame sample; every 5th frame at half size on the CPU) and every Replica
    and TUM sequence of the config groups, present or not (absent ones are listed in the report).
    ``quick``: ``QUICK_MAX_FRAMES`` frames everywhere."""
    cpu = not device.startswith("cuda")
    root = [f"data_root={Path(data_root).resolve()}"] if data_root is not None else []
    limit = [f"dataset.max_frames={QUICK_MAX_FRAMES if quick else CPU_MAX_FRAMES}"] if cpu or quick else []
    suffix = "" if cpu else "_replica_size"
    plan = [_entry(f"synthetic/{name}{suffix}", limit) for name in ("room0", "office0")]

    sevenscenes = "7scenes/redkitchen"
    seven_limit = [*CPU_SEVENSCENES, *limit] if cpu else limit
    own = load_config([f"dataset={sevenscenes}", *root]).dataset_path()
    sample = SHARED_DATA / SEVENSCENES_SAMPLE
    if own.is_dir():
        plan.append(_entry(sevenscenes, [*root, *seven_limit]))
    elif sample.is_dir():
        plan.append(_entry(sevenscenes, [f"dataset.path={sample}", *seven_limit]))
    else:
        plan.append(_entry(sevenscenes, root, f"neither {own.resolve()} nor the shared sample {sample} exists"))

    for option in group_options("dataset"):
        kind = option.split("/")[0]
        if kind not in CPU_DOWNSCALE:
            continue
        path = load_config([f"dataset={option}", *root]).dataset_path()
        shrink = [f"dataset.downscale={CPU_DOWNSCALE[kind]}"] if cpu else []
        plan.append(_entry(option, [*root, *shrink, *limit], None if path.is_dir() else f"{path.resolve()} not found"))
    return plan


# ---------------------------------------------------------------------------------------------------
# sweeps

SWEEP_KEYS = ("name", "scenes", "methods", "repeats", "overrides", "variants", "grid")


def _yaml_value(value) -> str:
    return ("true" if value else "false") if isinstance(value, bool) else str(value)


def sweep_variants(variants: list[dict] | None, grid: dict | None) -> list[dict] | None:
    """The override sets of a sweep, ``[{"name", "overrides"}]``: ``variants`` as given (a set
    without a name is named by its overrides joined, or "default" when it has none), each combined
    with every point of ``grid`` (``{key: [values]}``, their product; a point is named by its
    overrides joined); None when neither is given (the rows are then the methods alone)."""
    if not variants and not grid:
        return None
    points = [[]]
    for key, values in (grid or {}).items():
        points = [[*p, f"{key}={_yaml_value(v)}"] for p in points for v in values]
    out = []
    for v in variants or [{"name": "", "overrides": []}]:
        for p in points:
            overrides = [*v.get("overrides", []), *p]
            name = " ".join(x for x in (v.get("name") or " ".join(v.get("overrides", [])), " ".join(p)) if x)
            out.append({"name": name or "default", "overrides": overrides})
    return out


def load_sweep(path: Path, device: str, data_root: Path | None = None, quick: bool = False) -> dict:
    """A sweep spec (YAML) as the suite runs it: ``{"name", "plan", "methods", "repeats",
    "variants"}``.  The spec's keys: ``scenes`` (a list; a scene of the suite's plan for ``device``
    keeps the plan's sizing, any other dataset config runs as configured; an item may be ``{scene:
    ..., overrides: [...]}`` to add overrides for that scene), ``methods`` (default ``[rgs]``),
    ``repeats`` (default 1), ``overrides`` (every run), ``variants`` (a list of ``{name,
    overrides}``) and ``grid`` (``{key: [values]}``), the override sets (``sweep_variants``), and
    ``name`` (default the file's stem).  A run's overrides, later ones winning: the plan's for the
    scene, the spec's ``overrides``, the scene's own, the method and seed, the command line's, the
    override set.  Raises ConfigError naming what is wrong; every override set is checked with
    ``load_config`` before anything runs."""
    path = Path(path)
    try:
        spec = yaml.safe_load(path.read_text())
    except (OSError, yaml.YAMLError) as e:
        raise ConfigError(f"cannot read the sweep {path}: {e}") from e
    if not isinstance(spec, dict) or not spec.get("scenes"):
        raise ConfigError(f"sweep {path}: needs a mapping with a non-empty 'scenes' list")
    unknown = sorted(set(spec) - set(SWEEP_KEYS))
    if unknown:
        raise ConfigError(f"sweep {path}: unknown key(s) {', '.join(unknown)}; valid: {', '.join(SWEEP_KEYS)}")
    methods = list(spec.get("methods") or ["rgs"])
    bad = [m for m in methods if m not in METHODS]
    if bad:
        raise ConfigError(f"sweep {path}: unknown method(s) {', '.join(map(str, bad))}; valid: {', '.join(METHODS)}")
    repeats = spec.get("repeats", 1)
    if not isinstance(repeats, int) or repeats < 1:
        raise ConfigError(f"sweep {path}: repeats must be an integer >= 1, not {repeats!r}")
    overrides = [str(o) for o in spec.get("overrides") or []]
    variants = spec.get("variants")
    grid = spec.get("grid")
    if variants is not None and not (
        isinstance(variants, list) and all(isinstance(v, dict) and set(v) <= {"name", "overrides"} for v in variants)
    ):
        raise ConfigError(f"sweep {path}: variants must be a list of {{name, overrides}}")
    if grid is not None and not (isinstance(grid, dict) and all(isinstance(v, list) and v for v in grid.values())):
        raise ConfigError(f"sweep {path}: grid must map each key to a non-empty list of values")
    sets = sweep_variants(
        [{"name": str(v.get("name") or ""), "overrides": [str(o) for o in v.get("overrides") or []]} for v in variants]
        if variants
        else None,
        grid,
    )
    slugs = [variant_slug(v["name"]) for v in sets or []]
    if len(set(slugs)) != len(slugs):
        raise ConfigError(f"sweep {path}: two override sets have the same name (as folder names: {slugs})")

    spec_root = load_config(overrides).data_root
    if data_root is None and spec_root:  # the spec's own data_root=
        data_root = Path(spec_root)
    by_scene = {e["scene"]: e for e in default_plan(device, data_root, quick)}
    root = [f"data_root={Path(data_root).resolve()}"] if data_root is not None else []
    plan = []
    for item in spec["scenes"]:
        scene, own = (item.get("scene"), item.get("overrides") or []) if isinstance(item, dict) else (item, [])
        own = [*overrides, *map(str, own)]
        if scene in by_scene:
            entry = dict(by_scene[scene])
            plan.append({**entry, "overrides": [*entry["overrides"], *own]})
        elif scene in group_options("dataset"):
            plan.append(_entry(scene, [*root, *own]))
        else:
            known = sorted(set(by_scene) | set(group_options("dataset")))
            raise ConfigError(f"sweep {path}: unknown scene {scene!r}; known: {', '.join(known)}")
    for v in sets or [{"overrides": []}]:
        load_config([*plan[0]["overrides"], *v["overrides"]])
    return {
        "name": str(spec.get("name") or path.stem),
        "plan": plan,
        "methods": methods,
        "repeats": repeats,
        "variants": sets,
    }


# ---------------------------------------------------------------------------------------------------
# running


def _run_name(scene: str, method: str, repeat: int, variant: dict | None = None) -> str:
    middle = "" if variant is None else "-" + variant_slug(variant["name"])
    return f"{scene.replace('/', '-')}-{method}{middle}-{repeat}"


def variant_slug(name: str) -> str:
    """An override set's name as a folder name component: runs of other characters than letters,
    digits and ``.=+-`` become one ``_``."""
    return re.sub(r"[^A-Za-z0-9.=+-]+", "_", name).strip("_") or "_"


def row_label(method: str, variant: str | None) -> str:
    """The tables' row of a method run with an override set of a sweep (``rgs [short tracking]``)."""
    return method if variant is None else f"{method} [{variant}]"


def _row_of(record: dict) -> str:
    return row_label(record["method"], record.get("variant"))


def _error_text(e: BaseException) -> str:
    return f"{type(e).__name__}: {e}".strip()


RECORD_FILE = "suite_record.json"  # in a finished run's folder: what --resume reuses


def _run_spec(
    entry: dict, method: str, repeat: int, runs_dir: Path, extra: Sequence[str], variant: dict | None = None
) -> tuple[dict, list[str]]:
    """A run's record so far (who it is, where it writes) and its overrides: the plan's, the method
    and seed, the suite's own, then the sweep's override set (it is what the row varies: it wins)."""
    name = _run_name(entry["scene"], method, repeat, variant)
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
    """``convergence.json`` of a run (``rgs_warp.run.write_convergence``): a list of
    ``{"iteration", "frame", "phase" ("init" | "keyframe"), "psnr_db", "gaussians"}``; points without
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
    head = f"{record['scene']} {_row_of(record)} seed={record['seed']}: "
    if record["status"] != "ok":
        return head + f"error ({record['error'].splitlines()[0][:120]}) [{record['seconds']:.0f} s]"
    parts = []
    for metric_id in ("ate_keyframes_rmse_cm", "psnr_db", "fps"):
        value, _ = metric_value(record["metrics"], METRIC_BY_ID[metric_id].path)
        if value is not None:
            parts.append(f"{METRIC_BY_ID[metric_id].label} {value:.{METRIC_BY_ID[metric_id].digits}f}")
    return head + "ok " + ", ".join(parts) + f" [{record['seconds']:.0f} s]"


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
) -> dict:
    """Run every present scene of ``plan`` with every method, ``repeats`` times (``seed=0..repeats-1``),
    aggregate and write ``out_dir/eval.json``, ``out_dir/eval.md`` and the plots; returns what
    ``eval.json`` holds. ``runner`` defaults to ``rgs_warp.run.run``; ``extra_overrides`` go to every
    run after the plan's own (``device=cuda:0``, ``tracking.iters=40``).  ``resume``: a run whose folder
    holds the record of a finished run with the same overrides is read back instead of run again (a
    suite cut short goes on where it stopped).

    ``variants``: a sweep's override sets (``[{"name", "overrides"}]``, see ``load_sweep``): every
    method runs with each, and each (method, set) is a row of the tables (``row_label``).
    ``cluster``: None runs here, one run after another; a string runs one Ray task per run (see
    ``_run_on_ray``): "" for ``ray.init()``'s default (``RAY_ADDRESS``, else a local cluster), else
    the cluster's address; ``gpus_per_task`` is what a task asks for when the device is CUDA."""
    if runner is None:
        runner = run
    out_dir = Path(out_dir)
    runs_dir = out_dir / "eval_runs"
    runs_dir.mkdir(parents=True, exist_ok=True)
    present = [e for e in plan if not e.get("absent")]
    sets = list(variants) if variants else [None]
    jobs = [(e, m, r, v) for e in present for m in methods for v in sets for r in range(repeats)]
    bar = tqdm(total=len(jobs), desc="eval", unit="run", disable=not progress)
    if cluster is None:
        runs = []
        for entry, method, repeat, variant in jobs:
            bar.set_postfix_str(_run_name(entry["scene"], method, repeat, variant))
            runs.append(_one_run(entry, method, repeat, runs_dir, runner, extra_overrides, resume, variant))
            if progress:
                bar.write(_progress_line(runs[-1]))
            bar.update(1)
    else:
        device = _device_of(extra_overrides)
        runs = _run_on_ray(jobs, runs_dir, runner, extra_overrides, resume, cluster, device, gpus_per_task, bar)
    bar.close()

    scenes = [e["scene"] for e in present]
    rows = [row_label(m, None if v is None else v["name"]) for m in methods for v in sets]
    aggregate = aggregate_runs(runs, scenes, rows)
    header = _header(methods, repeats, extra_overrides)
    if variants:
        header.update(rows=rows, variants=[{"name": v["name"], "overrides": list(v["overrides"])} for v in variants])
    result = {
        "header": header,
        "plan": plan,
        "not_present": [{"scene": e["scene"], "reason": e["absent"]} for e in plan if e.get("absent")],
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
    name = _run_name(entry["scene"], method, repeat, variant)
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


# ---------------------------------------------------------------------------------------------------
# aggregation


def metric_value(metrics: dict, path: tuple[str, ...]) -> tuple[float | None, str | None]:
    """(value, None) or (None, the reason it is n/a) of a metric at ``path`` in a run's metrics."""
    node = metrics
    for key in path:
        value = node.get(key) if isinstance(node, dict) else None
        if value is None:
            reason = node.get(key + NA_SUFFIX) if isinstance(node, dict) else None
            return None, reason or f"{'.'.join(path)} not in metrics.json"
        node = value
    return float(node), None


def _aggregate_cell(records: list[dict], path: tuple[str, ...]) -> dict:
    values, na, errors = [], [], []
    for r in records:
        if r["status"] != "ok":
            errors.append(r["error"])
            continue
        value, reason = metric_value(r["metrics"], path)
        if value is None:
            na.append(reason)
        else:
            values.append(value)
    n = len(values)
    return {
        "mean": float(np.mean(values)) if n else None,
        # sample standard deviation over the repeats; undefined for a single value
        "std": float(np.std(values, ddof=1)) if n >= 2 else None,
        "n": n,
        "runs": len(records),
        "values": values,
        "na_reasons": sorted(set(na)),
        "n_na": len(na),
        "errors": sorted(set(errors)),
        "n_failed": len(errors),
    }


def aggregate_runs(runs: list[dict], scenes: Sequence[str], methods: Sequence[str]) -> dict:
    """``{scene: {method: {metric id: {mean, std, n, runs, values, na_reasons, n_na, errors,
    n_failed}}}}`` over the repeats of each (scene, method); in a sweep ``methods`` are the rows
    (``row_label``: a method with an override set)."""
    out: dict = {}
    for scene in scenes:
        out[scene] = {}
        for method in methods:
            records = [r for r in runs if r["scene"] == scene and _row_of(r) == method]
            out[scene][method] = {m.id: _aggregate_cell(records, m.path) for m in METRICS}
    return out


def benchmark_of(scene: str) -> str:
    return scene.split("/")[0]


def benchmark_averages(aggregate: dict, scenes: Sequence[str], methods: Sequence[str]) -> dict:
    """``{benchmark: {method: {metric id: {mean, na_reason}}}}``: the mean over the benchmark's
    scenes of the per-scene means (as the supplement's "Avg."), n/a unless every scene has one."""
    out: dict = {}
    for bench in dict.fromkeys(benchmark_of(s) for s in scenes):
        members = [s for s in scenes if benchmark_of(s) == bench]
        out[bench] = {}
        for method in methods:
            out[bench][method] = {}
            for m in METRICS:
                means = [aggregate[s][method][m.id]["mean"] for s in members]
                missing = [s.split("/", 1)[1] for s, v in zip(members, means, strict=True) if v is None]
                if not missing:
                    out[bench][method][m.id] = {"mean": float(np.mean(means)), "na_reason": None}
                else:
                    reason = "no value on " + ("any scene" if len(missing) == len(members) else ", ".join(missing))
                    out[bench][method][m.id] = {"mean": None, "na_reason": reason}
    return out


def final_init_psnr(curve: list[dict]) -> float | None:
    """PSNR of a run's last initialization sample (the window after the initialization's last
    keyframe), None without one."""
    init = [p for p in curve if p["phase"] == "init"]
    return init[-1]["psnr_db"] if init else None


def iterations_to_reach(curve: list[dict], target_db: float) -> int | None:
    """The first logged initialization iteration from which on the window PSNR stays at or above
    ``target_db`` for the rest of the initialization; None if its last sample is below."""
    init = [p for p in curve if p["phase"] == "init"]
    reached = None
    for p in reversed(init):
        if p["psnr_db"] < target_db:
            break
        reached = p["iteration"]
    return reached


def convergence_comparison(runs: list[dict], scenes: Sequence[str], methods: Sequence[str]) -> dict:
    """``{scene: {"target_db", "methods": {method: {"final_init_db", "iterations", "values", "n",
    "runs"}}}}`` for every scene with convergence curves: target_db = the lowest over the methods of
    their mean final initialization PSNR (``final_init_psnr``) less ``CONVERGENCE_MARGIN_DB``;
    ``iterations`` = the mean over the repeats of ``iterations_to_reach(curve, target_db)`` (None when
    no repeat reached it), ``values`` the repeats' own, ``n`` how many reached it of ``runs`` curves.
    In a sweep ``methods`` are the rows (``row_label``)."""
    out: dict = {}
    for scene in scenes:
        curves = {
            m: [r["convergence"] for r in runs if r["scene"] == scene and _row_of(r) == m and r.get("convergence")]
            for m in methods
        }
        finals = {m: [v for v in map(final_init_psnr, c) if v is not None] for m, c in curves.items()}
        means = {m: float(np.mean(v)) for m, v in finals.items() if v}
        if not means:
            continue
        target = min(means.values()) - CONVERGENCE_MARGIN_DB
        cells = {}
        for m in methods:
            values = [it for it in (iterations_to_reach(c, target) for c in curves[m]) if it is not None]
            cells[m] = {
                "final_init_db": means.get(m),
                "iterations": float(np.mean(values)) if values else None,
                "values": values,
                "n": len(values),
                "runs": len(curves[m]),
            }
        out[scene] = {"target_db": target, "methods": cells}
    return out


# ---------------------------------------------------------------------------------------------------
# report


def _device_of(extra_overrides: Sequence[str]) -> str:
    try:
        device = load_config(list(extra_overrides)).device
    except ConfigError:
        device = "auto"
    if device != "auto":
        return device
    import warp as wp

    return "cuda:0" if wp.is_cuda_available() else "cpu"


def _device_name(device: str) -> str:
    if device.startswith("cuda"):
        try:
            import warp as wp

            return wp.get_device(device).name
        except Exception as e:  # the header says why instead of failing the suite after the runs
            return f"unknown ({_error_text(e)})"
    return platform.processor() or platform.machine() or "unknown CPU"


def _header(methods: Sequence[str], repeats: int, extra_overrides: Sequence[str]) -> dict:
    device = _device_of(extra_overrides)
    return {
        "date": datetime.now().isoformat(timespec="seconds"),
        "commit": git_commit(),
        "device": device,
        "device_name": _device_name(device),
        "repeats": repeats,
        "methods": list(methods),
        "extra_overrides": list(extra_overrides),
    }


def table_rows(result: dict) -> list[str]:
    """The rows of the tables: the methods, or in a sweep each method with each override set."""
    return result["header"].get("rows", result["header"]["methods"])


class _Footnotes:
    """Markdown footnotes ``[^k]``, one per distinct text."""

    def __init__(self):
        self.texts: dict[str, int] = {}

    def ref(self, text: str) -> str:
        text = " ".join(text.split())
        text = text if len(text) <= 300 else text[:297] + "..."
        return f"[^{self.texts.setdefault(text, len(self.texts) + 1)}]"

    def lines(self) -> list[str]:
        return [f"[^{k}]: {text}" for text, k in self.texts.items()]


def _number(value: float, digits: int) -> str:
    return f"{value:.{digits}f}" if math.isfinite(value) else str(value)


def rank_marks(means: dict[str, float | None], metric: Metric) -> dict[str, str]:
    """``{method: "best" | "second"}`` by the values as printed (ties share the mark)."""
    if metric.lower_is_better is None:
        return {}
    shown = {k: float(f"{v:.{metric.digits}f}") for k, v in means.items() if v is not None and not math.isnan(v)}
    if len(shown) < 2:  # a single number is not a comparison
        return {}
    order = sorted(set(shown.values()), reverse=not metric.lower_is_better)
    marks = {k: "best" for k, v in shown.items() if v == order[0]}
    if len(shown) >= 3 and len(marks) == 1:  # competition ranking: a tie for the best leaves no second
        marks.update({k: "second" for k, v in shown.items() if v == order[1]})
    return marks


def _mark(text: str, mark: str | None) -> str:
    return {"best": f"**{text}**", "second": f"<u>{text}</u>"}.get(mark, text)


def _scene_cell(cell: dict, metric: Metric, mark: str | None, notes: _Footnotes) -> str:
    if cell["n"]:
        text = _number(cell["mean"], metric.digits)
        if cell["std"] is not None:
            text += f" ± {_number(cell['std'], metric.digits)}"
        text = _mark(text, mark)
    elif cell["n_failed"] == cell["runs"]:
        return "error " + notes.ref("run failed: " + "; ".join(cell["errors"]))
    else:
        text = "n/a"
    refs = []
    if cell["n_failed"] and cell["n_failed"] < cell["runs"]:
        refs.append(notes.ref(f"failed in {cell['n_failed']} of {cell['runs']} runs: " + "; ".join(cell["errors"])))
    if cell["n_na"]:
        prefix = "" if not cell["n"] else f"n/a in {cell['n_na']} of {cell['runs']} runs: "
        refs.append(notes.ref(prefix + "; ".join(cell["na_reasons"])))
    return " ".join([text, *refs])


def _table(result: dict, group: str, bench: str, notes: _Footnotes) -> list[str]:
    methods = table_rows(result)
    scenes = [s for s in result["aggregate"] if benchmark_of(s) == bench]
    columns = [s.split("/", 1)[1] for s in scenes] + ["Avg."]
    lines = ["| Metric | Method | " + " | ".join(columns) + " |", "|---|---|" + "---:|" * len(columns)]
    for metric in (m for m in METRICS if m.group == group):
        arrow = {True: " ↓", False: " ↑", None: ""}[metric.lower_is_better]
        scene_marks = {
            s: rank_marks({k: result["aggregate"][s][k][metric.id]["mean"] for k in methods}, metric) for s in scenes
        }
        averages = {k: result["averages"][bench][k][metric.id] for k in methods}
        avg_marks = rank_marks({k: a["mean"] for k, a in averages.items()}, metric)
        for i, method in enumerate(methods):
            cells = [
                _scene_cell(result["aggregate"][s][method][metric.id], metric, scene_marks[s].get(method), notes)
                for s in scenes
            ]
            avg = averages[method]
            if avg["mean"] is None and not any(result["aggregate"][s][method][metric.id]["n"] for s in scenes):
                cells.append("n/a")  # the scene cells say why
            elif avg["mean"] is None:
                cells.append("n/a " + notes.ref(avg["na_reason"]))
            else:
                cells.append(_mark(_number(avg["mean"], metric.digits), avg_marks.get(method)))
            label = metric.label + arrow if i == 0 else ""
            lines.append(f"| {label} | {method} | " + " | ".join(cells) + " |")
    return lines


def render_markdown(result: dict) -> str:
    """``eval.md`` from what ``eval.json`` holds."""
    h = result["header"]
    notes = _Footnotes()
    n = h["repeats"]
    seeds = "seed 0" if n == 1 else f"seeds 0-{n - 1}"
    lines = [
        "# rgs_warp evaluation",
        "",
        f"- date: {h['date']}",
        f"- commit: {h['commit']}",
        f"- device: {h['device']} ({h['device_name']})",
        f"- repeats: {n} ({seeds}); cells: mean ± sample standard deviation over the repeats that "
        "produced the number; Avg.: mean of the scene means",
        "- best per column in **bold**, second best <u>underlined</u> (among 3 or more methods); "
        "↓ lower is better, ↑ higher is better",
        f"- methods: {', '.join(h['methods'])}",
        f"- overrides for every run: {' '.join(h['extra_overrides']) or '(none)'}",
    ]
    if h.get("variants"):
        lines.append(
            "- override sets of the sweep (rows `method [set]`; a set's overrides come after those for every run):"
        )
        lines += [
            f"  - {v['name']}: `{' '.join(v['overrides'])}`" if v["overrides"] else f"  - {v['name']}: (none)"
            for v in h["variants"]
        ]
    lines.append("")
    benches = list(dict.fromkeys(benchmark_of(s) for s in result["aggregate"]))
    for group in dict.fromkeys(m.group for m in METRICS):
        lines += [f"## {group}", ""]
        for bench in benches:
            lines += [f"### {bench}", "", *_table(result, group, bench, notes), ""]
    lines += _convergence_section(result)
    for name in result["plots"]:
        lines += [f"![{name}]({name})", ""]
    lines += ["## Scenes", ""]
    for e in result["plan"]:
        what = f"not present ({e['absent']})" if e.get("absent") else "`" + " ".join(e["overrides"]) + "`"
        lines.append(f"- {e['scene']}: {what}")
    lines.append("")
    lines += ["## Runs", "", "| Scene | Method | Seed | Status | Time (s) | Folder |", "|---|---|---:|---|---:|---|"]
    for r in result["runs"]:
        status = "ok" if r["status"] == "ok" else "error " + notes.ref("run failed: " + r["error"])
        folder = Path(r["run_dir"]).name
        lines.append(f"| {r['scene']} | {_row_of(r)} | {r['seed']} | {status} | {r['seconds']:.1f} | {folder} |")
    lines.append("")
    if notes.texts:
        lines += ["## Notes", "", *notes.lines(), ""]
    return "\n".join(lines)


def _convergence_section(result: dict) -> list[str]:
    """The convergence table of eval.md: per scene, the common PSNR and each method's iterations."""
    comparison = result["convergence"]
    if not comparison:
        return []
    methods = table_rows(result)
    lines = [
        "## Convergence",
        "",
        "Mapping iterations of the initialization (cumulative, over its growing window of keyframes) "
        "each method needs to reach a PSNR common to the methods. The common PSNR of a scene is the "
        "lowest of the methods' final initialization PSNRs (mean window PSNR after the initialization's "
        f"last keyframe, mean over the repeats) minus {CONVERGENCE_MARGIN_DB} dB; a run needs the first "
        "logged iteration from which on its mean window PSNR (exposure-corrected render against the "
        "keyframes, sampled every `eval.convergence_every` iterations and after each keyframe's mapping) "
        "stays at or above it until the end of the initialization. Cells: mean over the repeats that "
        "reached it (their count if not all), then the method's final initialization PSNR.",
        "",
        "| Scene | common PSNR (dB) | " + " | ".join(methods) + " |",
        "|---|---:|" + "---:|" * len(methods),
    ]
    for scene, entry in comparison.items():
        cells = []
        for method in methods:
            c = entry["methods"][method]
            if not c["runs"]:
                cells.append("n/a (no curve)")
                continue
            text = "not reached" if c["iterations"] is None else f"{c['iterations']:.0f}"
            if c["iterations"] is not None and c["n"] < c["runs"]:
                text += f" ({c['n']} of {c['runs']} runs)"
            if c["final_init_db"] is not None:
                text += f" ({c['final_init_db']:.2f} dB)"
            cells.append(text)
        lines.append(f"| {scene} | {entry['target_db']:.2f} | " + " | ".join(cells) + " |")
    return [*lines, ""]


# ---------------------------------------------------------------------------------------------------
# plots


def _bar_plot(result: dict, metric: Metric, path: Path) -> bool:
    """Grouped bars (scene x method) of a metric's means with std error bars; False if no numbers."""
    scenes, methods = list(result["aggregate"]), table_rows(result)
    cells = {(s, k): result["aggregate"][s][k][metric.id] for s in scenes for k in methods}
    if not any(c["n"] for c in cells.values()):
        return False
    width = 0.8 / len(methods)
    x = np.arange(len(scenes))
    fig, ax = plt.subplots(figsize=(max(6.0, 1.2 * len(scenes) + 2.0), 4.5), dpi=150)
    for i, method in enumerate(methods):
        means = [cells[s, method]["mean"] if cells[s, method]["n"] else np.nan for s in scenes]
        stds = [cells[s, method]["std"] or 0.0 for s in scenes]
        ax.bar(x + (i - (len(methods) - 1) / 2) * width, means, width, yerr=stds, capsize=3, label=method)
    ax.set_xticks(x, scenes, rotation=30, ha="right")
    better = {True: ", lower is better", False: ", higher is better", None: ""}[metric.lower_is_better]
    ax.set_ylabel(f"mean ± std over {result['header']['repeats']} repeats")
    ax.set_title(metric.label + better)
    ax.grid(True, axis="y", linewidth=0.3)
    ax.legend()
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
    return True


def _convergence_plot(result: dict, path: Path) -> bool:
    """Per scene (a column), the methods' convergence curves overlaid (a colour per method, a line per
    repeat): window PSNR against the cumulative mapping iterations with the common PSNR of the
    convergence table dashed (top), and the number of Gaussians (bottom)."""
    curves = [r for r in result["runs"] if r.get("convergence")]
    if not curves:
        return False
    scenes = list(dict.fromkeys(r["scene"] for r in curves))
    colours = {k: f"C{i}" for i, k in enumerate(table_rows(result))}
    fig, axes = plt.subplots(2, len(scenes), figsize=(4.5 * len(scenes), 6.5), dpi=150, squeeze=False, sharex="col")
    for col, scene in enumerate(scenes):
        top, bottom = axes[0, col], axes[1, col]
        labelled = set()
        for r in (r for r in curves if r["scene"] == scene):
            it = [p["iteration"] for p in r["convergence"]]
            row = _row_of(r)
            label = None if row in labelled else row
            labelled.add(row)
            style = {"color": colours.get(row, "gray"), "linewidth": 1.0, "alpha": 0.8}
            top.plot(it, [p["psnr_db"] for p in r["convergence"]], label=label, **style)
            bottom.plot(it, [p["gaussians"] for p in r["convergence"]], **style)
        target = result.get("convergence", {}).get(scene, {}).get("target_db")
        if target is not None:
            top.axhline(target, color="black", linestyle="--", linewidth=0.8, label="common PSNR")
        top.set_title(scene)
        top.set_ylabel("mean window PSNR (dB)")
        bottom.set_ylabel("Gaussians")
        bottom.set_xlabel("mapping iterations (cumulative)")
        for ax in (top, bottom):
            ax.grid(True, linewidth=0.3)
        top.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
    return True


def write_plots(result: dict, out_dir: Path) -> list[str]:
    """The PNGs next to ``eval.md``; returns their file names."""
    written = [name for metric_id, name in PLOTS if _bar_plot(result, METRIC_BY_ID[metric_id], out_dir / name)]
    if _convergence_plot(result, out_dir / "eval_convergence.png"):
        written.append("eval_convergence.png")
    return written


# ---------------------------------------------------------------------------------------------------
# command line


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="python -m rgs_warp.eval.suite",
        description="Run the evaluation suite (every scene x method x repeat) and write eval.md / eval.json.",
        epilog="Trailing key=value overrides go to every run (e.g. data_root=/data tracking.iters=40).",
    )
    p.add_argument("--device", default="auto", help="cpu, cuda:0 or auto (a GPU when Warp sees one); default auto")
    p.add_argument("--repeats", type=int, default=None, help="runs per scene and method, seeds 0.. (default 3)")
    p.add_argument("--methods", default=None, help="comma-separated methods (default rgs,baseline)")
    p.add_argument("--out", type=Path, default=None, help="output folder (default experiments/results)")
    p.add_argument("--quick", action="store_true", help=f"smoke run: 1 repeat, {QUICK_MAX_FRAMES} frames a sequence")
    p.add_argument("--scenes", default="", help="comma-separated scenes of the plan to run (default all present)")
    p.add_argument("--resume", action="store_true", help="reuse the runs of an earlier suite with the same overrides")
    p.add_argument(
        "--sweep",
        type=Path,
        default=None,
        help="a sweep spec (YAML: scenes, methods, repeats, overrides, variants / grid): its scenes, methods and "
        "repeats unless given here, one table row per method and override set; output in "
        "experiments/results/sweeps/<name> unless --out",
    )
    p.add_argument(
        "--ray",
        nargs="?",
        const="",
        default=None,
        metavar="ADDRESS",
        help="one Ray task per run (pip install 'rgs_warp[cluster]'): without ADDRESS ray.init()'s default "
        "(RAY_ADDRESS, else a local cluster), else the cluster's address (auto, ray://head:10001; a key=value "
        "right after --ray is an override, not an address)",
    )
    p.add_argument(
        "--gpus-per-task", type=float, default=1.0, help="GPUs a Ray task asks for on CUDA (default 1; 0.5 packs two)"
    )
    p.add_argument("overrides", nargs="*", metavar="key=value")
    return p


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(sys.argv[1:] if argv is None else argv)
    if args.ray and "=" in args.ray:  # "--ray key=value": argparse took the first override as the address
        args.overrides.insert(0, args.ray)
        args.ray = ""
    device = _device_of([f"device={args.device}"])
    if args.ray is not None and device.startswith("cuda:") and device != "cuda:0":
        print("error: with --ray each task sees its own GPU as cuda:0; use --device cuda:0", file=sys.stderr)
        return 2
    sweep = None
    if args.sweep is not None:
        try:
            cfg = load_config([f"device={device}", *args.overrides])
            root = Path(cfg.data_root) if cfg.data_root else None
            sweep = load_sweep(args.sweep, device, root, quick=args.quick)
        except ConfigError as e:
            print(f"error: {e}", file=sys.stderr)
            return 2
    default_repeats = sweep["repeats"] if sweep else (1 if args.quick else 3)
    repeats = args.repeats if args.repeats is not None else default_repeats
    default_methods = ",".join(sweep["methods"]) if sweep else "rgs,baseline"
    methods = [m.strip() for m in (args.methods or default_methods).split(",") if m.strip()]
    if repeats < 1 or not methods:
        print("error: need --repeats >= 1 and at least one method", file=sys.stderr)
        return 2
    unknown = [m for m in methods if m not in METHODS]
    if unknown:
        print(f"error: unknown method(s) {', '.join(unknown)}; valid: {', '.join(METHODS)}", file=sys.stderr)
        return 2
    try:
        check_evaluation_imports()
    except ImportError as e:
        print(f"error: {e}", file=sys.stderr)
        return 1
    extra = [f"device={device}", *args.overrides]
    try:
        cfg = load_config(extra)
    except ConfigError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    data_root = Path(cfg.data_root) if cfg.data_root else None
    plan = sweep["plan"] if sweep else default_plan(device, data_root, quick=args.quick)
    if args.scenes:
        wanted = [w.strip() for w in args.scenes.split(",") if w.strip()]
        known = [e["scene"] for e in plan]
        unknown = [w for w in wanted if w not in known]
        if unknown:
            print(f"error: unknown scene(s) {', '.join(unknown)}; the plan has {', '.join(known)}", file=sys.stderr)
            return 2
        plan = [e for e in plan if e["scene"] in wanted]
    default_out = Path("experiments/results") / ("sweeps/" + sweep["name"] if sweep else "")
    out = args.out if args.out is not None else default_out
    try:
        result = run_suite(
            plan,
            methods,
            repeats,
            out,
            extra_overrides=extra,
            resume=args.resume,
            variants=sweep["variants"] if sweep else None,
            cluster=args.ray,
            gpus_per_task=args.gpus_per_task,
        )
    except (ImportError, ClusterError) as e:  # --ray without Ray, or without the GPUs the runs need
        print(f"error: {e}", file=sys.stderr)
        return 1
    ok = sum(r["status"] == "ok" for r in result["runs"])
    print(f"{ok} of {len(result['runs'])} runs ok; report {out / 'eval.md'}")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
