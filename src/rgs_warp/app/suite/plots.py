"""The suite's plots next to ``eval.md``: bars per metric (scene x row, std error bars) and the
methods' convergence curves overlaid per scene."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from rgs_warp.app.suite.plan import row_of  # noqa: E402
from rgs_warp.app.suite.tables import METRIC_BY_ID, PLOTS, Metric, table_rows  # noqa: E402


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
            row = row_of(r)
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
