"""Run report: ``metrics.json`` (everything, strict JSON), ``metrics.md`` (tables for people) and the
top-view trajectory plot (ground truth red, estimate green, as the paper's Figures 2-3).

A metric that could not be computed is ``None`` with its reason under ``<name>_na_reason`` in the
same dict; the Markdown shows it as "n/a (reason)". A None without a reason is refused, so a
missing number is never silent.
"""

from __future__ import annotations

import json
import math
import subprocess
from collections.abc import Sequence
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from rgs_warp.eval.ate import Alignment, umeyama_alignment  # noqa: E402
from rgs_warp.io.atomic import write_text_atomic  # noqa: E402

NA_SUFFIX = "_na_reason"
# Unit suffix of a metric name -> unit shown in the column header.
_UNITS = {"_cm": "cm", "_m": "m", "_db": "dB", "_pct": "%", "_s": "s", "_ms": "ms", "_fps": "fps", "_mib": "MiB"}


def git_commit(path: Path | str | None = None) -> str:
    """The commit of the checkout holding ``path`` (default: this package), "+changes" appended where
    tracked files differ from it (a number measured on edited code must not carry the bare commit);
    "unknown" outside a git checkout."""
    cwd = Path(path) if path is not None else Path(__file__).resolve().parent
    try:
        head = subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"], cwd=cwd, capture_output=True, text=True, timeout=10
        )
        if head.returncode != 0 or not head.stdout.strip():
            return "unknown"
        diff = subprocess.run(["git", "diff", "--quiet", "HEAD", "--"], cwd=cwd, capture_output=True, timeout=30)
    except (OSError, subprocess.SubprocessError):
        return "unknown"
    return head.stdout.strip() + ("+changes" if diff.returncode == 1 else "")


def to_json(value):
    if isinstance(value, dict):
        return {str(k): to_json(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [to_json(v) for v in value]
    if isinstance(value, np.ndarray):
        return to_json(value.tolist())
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return str(value)  # "inf" (PSNR of identical images), "nan": strict JSON has neither
    return value


def _check_reasons(metrics: dict, path: str = "") -> None:
    for key, value in metrics.items():
        if isinstance(value, dict):
            _check_reasons(value, f"{path}{key}.")
        elif value is None and not key.endswith(NA_SUFFIX) and not metrics.get(key + NA_SUFFIX):
            raise ValueError(f"metric {path}{key} is None without a reason under '{key}{NA_SUFFIX}'")


def _header(key: str) -> str:
    for suffix, unit in _UNITS.items():
        if key.endswith(suffix):
            return f"{key[: -len(suffix)]} ({unit})"
    return key


def _cell(row: dict, key: str) -> str:
    value = row.get(key)
    if value is None:
        if key not in row:
            return ""
        return f"n/a ({row[key + NA_SUFFIX]})".replace("|", "\\|")
    if isinstance(value, (bool, str)):
        return str(value)
    if isinstance(value, (int, np.integer)):
        return str(int(value))
    return f"{float(value):.4g}" if abs(float(value)) < 1e4 else f"{float(value):.6g}"


def _is_scalar(value) -> bool:
    return value is None or isinstance(value, (bool, str, int, float, np.integer, np.floating))


def _table(rows: dict[str, dict]) -> list[str]:
    """One row per entry; columns: the scalar metrics in first-seen order (arrays go to JSON only)."""
    columns: list[str] = []
    for row in rows.values():
        for key, value in row.items():
            if not key.endswith(NA_SUFFIX) and _is_scalar(value) and key not in columns:
                columns.append(key)
    lines = ["| | " + " | ".join(_header(c) for c in columns) + " |", "|---" * (len(columns) + 1) + "|"]
    lines += [f"| {name} | " + " | ".join(_cell(row, c) for c in columns) + " |" for name, row in rows.items()]
    return lines


def write_report(
    run_dir: str | Path, metrics: dict, title: str = "rgs_warp evaluation", notes: dict[str, str] | None = None
) -> tuple[Path, Path]:
    """Write ``run_dir/metrics.json`` and ``run_dir/metrics.md``; returns both paths.

    ``metrics`` maps section names to dicts of metrics (e.g. ``{"ate": {"keyframes": {...},
    "all_frames": {...}}, "photometric": {...}, "mesh": {...}}``); a section whose values are dicts
    becomes a table with one row each, a flat section a one-row table, top-level scalars a
    "summary" table. Numbers carry their unit in the key (``rmse_cm``, ``psnr_db``).  ``notes``: a line
    of text under a section's table (by section name), saying what its rows and columns mean.
    """
    _check_reasons(metrics)
    run_dir = Path(run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    json_path, md_path = run_dir / "metrics.json", run_dir / "metrics.md"
    write_text_atomic(json_path, json.dumps(to_json(metrics), indent=2, allow_nan=False) + "\n")

    lines = [f"# {title}", ""]
    summary = {k: v for k, v in metrics.items() if not isinstance(v, dict)}
    if summary:
        lines += ["## summary", "", *_table({"run": summary}), ""]
    for section, content in metrics.items():
        if not isinstance(content, dict):
            continue
        nested = {k: v for k, v in content.items() if isinstance(v, dict)}
        flat = {k: v for k, v in content.items() if not isinstance(v, dict)}
        rows = ({section: flat} if flat else {}) | nested
        lines += [f"## {section}", "", *_table(rows), ""]
        if notes and section in notes:
            lines += [notes[section], ""]
    md_path.write_text("\n".join(lines), encoding="utf-8")
    return json_path, md_path


def _positions_m(poses: np.ndarray) -> np.ndarray:
    poses = np.asarray(poses, dtype=np.float64)
    return poses[:, :3, 3] if poses.ndim == 3 else poses


def _view_basis(gt_m: np.ndarray, est_m: np.ndarray, up: np.ndarray | None) -> tuple[np.ndarray, list[str]]:
    """2x3 projection onto the top view and the axis labels."""
    if up is None:
        # Without gravity, the two world axes along which the camera moved most span the view.
        points = np.vstack([gt_m, est_m])
        axes = np.sort(np.argsort(np.ptp(points, axis=0))[-2:])
        return np.eye(3)[axes], [f"{'xyz'[a]} (m)" for a in axes]
    up = np.asarray(up, dtype=np.float64)
    up = up / np.linalg.norm(up)
    # First in-plane axis: the world axis least aligned with gravity, with gravity projected out.
    e1 = np.eye(3)[np.argmin(np.abs(up))]
    e1 = e1 - np.dot(e1, up) * up
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(up, e1)
    return np.stack([e1, e2]), ["horizontal 1 (m)", "horizontal 2 (m)"]


def write_frame_scores(
    path_csv: str | Path,
    path_png: str | Path,
    scored: Sequence[tuple[int, float, float, float | None]],
    keyframes: Sequence[tuple[int, float, float, float | None]],
    title: str = "",
    views: Sequence[tuple[int, float, float, float | None]] = (),
) -> tuple[Path, Path]:
    """The PSNR of each scored (held-out) frame, keyframe and scored frame kept as a view (kind ``view``,
    ``mapping.frame_views``: trained on, so not held out), (frame, raw dB, at the frame's exposure dB, at the
    tracked exposure dB or None), as a CSV (``frame,kind,psnr_db,psnr_compensated_db,psnr_tracked_exposure_db``,
    by frame; the last empty without tracked exposures) and a plot of the compensated PSNR against the frame
    index, keyframes in red, views in orange: where along the sequence the map renders badly (far from the
    keyframes, a region without depth) shows at a glance."""
    kinds = (("scored", scored), ("keyframe", keyframes), ("view", views))
    rows = sorted((f, kind, *s) for kind, points in kinds for f, *s in points)
    lines = ["frame,kind,psnr_db,psnr_compensated_db,psnr_tracked_exposure_db"] + [
        f"{f},{k},{r:.3f},{c:.3f}," + ("" if t is None else f"{t:.3f}") for f, k, r, c, t in rows
    ]
    path_csv, path_png = Path(path_csv), Path(path_png)
    write_text_atomic(path_csv, "\n".join(lines) + "\n")
    fig, ax = plt.subplots(figsize=(10, 3.5), dpi=110)
    for points, colour, name in (
        (scored, "tab:blue", "scored (held out)"),
        (keyframes, "red", "keyframes"),
        (views, "tab:orange", "frames kept as views"),
    ):
        if len(points):
            f, c = np.asarray([(p[0], p[2]) for p in points], dtype=np.float64).T
            ax.plot(f, c, "o", color=colour, markersize=3.5, label=f"{name}: mean {c.mean():.2f} dB")
    if len(scored):
        f, c = np.asarray([(p[0], p[2]) for p in sorted(scored)], dtype=np.float64).T
        ax.plot(f, c, color="tab:blue", linewidth=0.6, alpha=0.6)
    ax.xaxis.set_major_locator(matplotlib.ticker.MaxNLocator(integer=True))
    ax.set_xlabel("frame")
    ax.set_ylabel("PSNR at the frame's exposure (dB)")
    ax.set_title(title)
    ax.grid(True, linewidth=0.3)
    ax.legend(loc="best", fontsize=8)
    fig.tight_layout()
    fig.savefig(path_png)
    plt.close(fig)
    return path_csv, path_png


def plot_trajectory_topview(
    est: np.ndarray,
    gt: np.ndarray | None,
    path: str | Path,
    title: str = "",
    align: Alignment = "none",
    up: np.ndarray | None = None,
) -> Path:
    """Top view of estimated (green) and ground-truth (red) camera positions, saved as PNG.

    ``est``/``gt``: (N, 4, 4) camera-to-world poses or (N, 3) positions in metres (registered
    row by row when aligning); ``gt`` None: the estimate alone (a sequence without ground truth).
    ``align`` ("se3"/"sim3") first aligns the estimate onto the ground truth as the ATE does; ``up``
    (world gravity-up vector) selects the horizontal plane, otherwise the two axes of largest extent
    are shown. Circles mark the start, squares the end.
    """
    est_m = _positions_m(est)
    gt_m = est_m[:0] if gt is None else _positions_m(gt)
    if align != "none" and gt is not None:
        R, t_m, s = umeyama_alignment(est_m, gt_m, with_scale=align == "sim3")
        est_m = s * est_m @ R.T + t_m
    basis, labels = _view_basis(gt_m, est_m, up)
    gt_2d, est_2d = gt_m @ basis.T, est_m @ basis.T
    fig, ax = plt.subplots(figsize=(6, 6), dpi=150)
    for xy, colour, name in ((gt_2d, "red", "ground truth"), (est_2d, "green", "estimate")):
        if not len(xy):
            continue
        ax.plot(xy[:, 0], xy[:, 1], color=colour, linewidth=1.2, label=name)
        ax.plot(*xy[0], "o", color=colour, markeredgecolor="black", markersize=7)
        ax.plot(*xy[-1], "s", color=colour, markeredgecolor="black", markersize=7)
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel(labels[0])
    ax.set_ylabel(labels[1])
    ax.set_title(title)
    ax.grid(True, linewidth=0.3)
    ax.legend(loc="best")
    fig.tight_layout()
    path = Path(path)
    fig.savefig(path)
    plt.close(fig)
    return path
