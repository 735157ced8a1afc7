"""The evaluation suite: every (scene, method, repeat) through the SLAM, then the supplement's tables.

``python -m rgs_warp.app.suite [--full] [--device cpu|cuda:0|auto] [--repeats N] [--methods rgs,baseline]
[--out experiments/results] [--quick] [key=value ...]`` (``nox -s eval``) prints its plan (runs, sizes,
an estimate, the scenes it skips and how to get them), then writes ``<out>/eval.json`` (every run and
aggregate), ``<out>/eval.md`` (the device and the plan, then one table per metric group: rows = metric
x method, columns = the scenes of a benchmark + "Avg.", mean ± std over the repeats, best in bold,
second best underlined as in the supplement §3, and a convergence table: the mapping iterations each
method's initialization needs to reach a PSNR common to the methods) and ``<out>/eval_*.png``; the run
folders go to ``<out>/eval_runs/``.

The plans (``plan``): without a GPU ``cpu``, CPU-sized runs (the synthetic scenes at
``app.cpu_size.CPU_SIZED``, one real sequence per benchmark cut short where its data is present, both
methods, 1 repeat; 10-15 minutes on 2 cores); on a GPU, or with ``--full``, ``full`` (Replica-size
synthetic scenes, every real sequence under the data root whole, 3 repeats); ``--quick`` cuts either
to a smoke run. Real sequences come from the data root (``data_root=``, else ``$RGS_DATA``); one
without data is listed as skipped with the command that downloads it.

A run that raises (a method not implemented yet) is recorded with its error and the suite goes on;
a metric a run could not compute (None with ``<name>_na_reason``, see ``app.report``) shows as "n/a"
with the reason as a footnote. ``--sweep SPEC.yaml`` runs an ablation written as one file
(``plan.load_sweep``); ``--ray [ADDRESS]`` runs one Ray task per run (``dispatch``).
"""

from rgs_warp.app.suite.cli import main
from rgs_warp.app.suite.dispatch import KILL_ENV, RECORD_FILE, ClusterError, ray_task_options, run_suite
from rgs_warp.app.suite.plan import (
    CPU_REAL_SCENES,
    QUICK_MAX_FRAMES,
    default_plan,
    describe_plan,
    load_sweep,
    row_label,
    scene_entries,
    select_scenes,
    sweep_variants,
    variant_slug,
)
from rgs_warp.app.suite.tables import METRIC_BY_ID, METRICS, Metric, aggregate_runs, rank_marks, render_markdown

__all__ = [
    "CPU_REAL_SCENES",
    "KILL_ENV",
    "METRICS",
    "METRIC_BY_ID",
    "QUICK_MAX_FRAMES",
    "RECORD_FILE",
    "ClusterError",
    "Metric",
    "aggregate_runs",
    "default_plan",
    "describe_plan",
    "load_sweep",
    "main",
    "ray_task_options",
    "rank_marks",
    "render_markdown",
    "row_label",
    "run_suite",
    "scene_entries",
    "select_scenes",
    "sweep_variants",
    "variant_slug",
]
