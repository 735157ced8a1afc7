"""The suite's numbers: the metrics of the tables, their aggregation over repeats and benchmarks, the
convergence comparison, the header (date, commit, device, plan) and ``eval.md``."""

from __future__ import annotations

import math
import os
import platform
from collections.abc import Sequence
from dataclasses import dataclass
from datetime import datetime
from pathlib import Path

import numpy as np

from rgs_warp.app.report import NA_SUFFIX, git_commit
from rgs_warp.app.suite.plan import FULL_COMMAND, QUICK_MAX_FRAMES, row_of
from rgs_warp.config import ConfigError, load_config

# The common PSNR of the convergence table: the lowest of the methods' final initialization PSNRs
# less this margin, so that every method's curve crosses it on its way up.
CONVERGENCE_MARGIN_DB = 0.5
# eval.md's line for each default plan; a sweep is named "sweep <name>"
PLAN_TEXT = {
    "cpu": f"cpu (CPU-sized: synthetic scenes and real sequences cut short, 1 repeat; the full plan: `{FULL_COMMAND}`)",
    "full": "full (Replica-size synthetic scenes, every real sequence whole)",
    "quick": f"quick (a smoke run: {QUICK_MAX_FRAMES} frames a sequence, 1 repeat)",
}


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
    # SplaTAM's protocol: every 5th frame with the keyframes included, at the tracked exposure
    Metric(
        "psnr_every_5th_with_keyframes_db",
        ("photometric", "every_5th_with_keyframes", "psnr_tracked_exposure_db"),
        "PSNR every 5th frame with keyframes (SplaTAM's protocol, dB)",
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
            records = [r for r in runs if r["scene"] == scene and row_of(r) == method]
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
            m: [r["convergence"] for r in runs if r["scene"] == scene and row_of(r) == m and r.get("convergence")]
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


def device_of(extra_overrides: Sequence[str]) -> str:
    """The device the runs use: ``device=`` of the overrides, ``auto`` resolved (a GPU when Warp sees one)."""
    try:
        device = load_config(list(extra_overrides)).device
    except ConfigError:
        device = "auto"
    if device != "auto":
        return device
    import warp as wp

    return "cuda:0" if wp.is_cuda_available() else "cpu"


def _cpu_name() -> str:
    try:
        with open("/proc/cpuinfo") as f:
            model = next((line.split(":", 1)[1].strip() for line in f if line.startswith("model name")), "")
    except OSError:
        model = ""
    return f"{model or platform.processor() or platform.machine() or 'unknown CPU'}, {os.cpu_count()} cores"


def device_name(device: str) -> str:
    """The GPU's name, or the CPU's model and core count."""
    if device.startswith("cuda"):
        try:
            import warp as wp

            return wp.get_device(device).name
        except Exception as e:  # the header says why instead of failing the suite after the runs
            return f"unknown ({type(e).__name__}: {e})"
    return _cpu_name()


def header(methods: Sequence[str], repeats: int, extra_overrides: Sequence[str], plan: str) -> dict:
    """eval.json's header: date, commit, device and its name, plan, repeats, methods, overrides."""
    device = device_of(extra_overrides)
    return {
        "date": datetime.now().isoformat(timespec="seconds"),
        "commit": git_commit(),
        "device": device,
        "device_name": device_name(device),
        "plan": plan,
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
    plan = h["plan"]
    lines = [
        f"# rgs_warp evaluation: plan {plan} on {h['device_name']}",
        "",
        f"- date: {h['date']}",
        f"- commit: {h['commit']}",
        f"- device: {h['device']} ({h['device_name']})",
        f"- plan: {PLAN_TEXT.get(plan, plan)}",
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
        what = f"skipped: {e['skipped']}" if e.get("skipped") else "`" + " ".join(e["overrides"]) + "`"
        lines.append(f"- {e['scene']}: {what}")
    lines.append("")
    lines += ["## Runs", "", "| Scene | Method | Seed | Status | Time (s) | Folder |", "|---|---|---:|---|---:|---|"]
    for r in result["runs"]:
        status = "ok" if r["status"] == "ok" else "error " + notes.ref("run failed: " + r["error"])
        folder = Path(r["run_dir"]).name
        lines.append(f"| {r['scene']} | {row_of(r)} | {r['seed']} | {status} | {r['seconds']:.1f} | {folder} |")
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
