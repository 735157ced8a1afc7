"""The suite's command, ``python -m rgs_warp.app.suite`` (``nox -s eval``): the plan for the device (or
a sweep), printed with an estimate before the first run, then ``run_suite``."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from rgs_warp.app.evaluate import check_evaluation_imports
from rgs_warp.app.suite.dispatch import ClusterError, run_suite
from rgs_warp.app.suite.plan import (
    FULL_COMMAND,
    QUICK_MAX_FRAMES,
    REPEATS,
    default_plan,
    describe_plan,
    load_sweep,
    select_scenes,
)
from rgs_warp.app.suite.tables import device_of
from rgs_warp.config import ConfigError, load_config
from rgs_warp.slam import METHODS

DEFAULT_METHODS = ("rgs", "baseline")


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="python -m rgs_warp.app.suite",
        description="Run the evaluation suite (every scene x method x repeat) and write eval.md / eval.json. "
        f"Without a GPU the cpu plan (CPU-sized runs, 10-15 minutes on 2 cores); on a GPU, or with --full "
        f"({FULL_COMMAND}), the full plan.",
        epilog="Trailing key=value overrides go to every run (e.g. data_root=/data tracking.iters=40). Real "
        "sequences are read under data_root (default $RGS_DATA, else the current directory); the plan says "
        "which are missing and how to get them.",
    )
    p.add_argument("--device", default="auto", help="cpu, cuda:0 or auto (a GPU when Warp sees one); default auto")
    p.add_argument(
        "--full",
        action="store_true",
        help="the full plan on any device (Replica-size synthetic scenes, every real sequence whole, 3 repeats); "
        "the default on a GPU, hours to days on a CPU",
    )
    p.add_argument(
        "--repeats", type=int, default=None, help="runs per scene and method, seeds 0.. (default the plan's)"
    )
    p.add_argument("--methods", default=None, help="comma-separated methods (default rgs,baseline)")
    p.add_argument("--out", type=Path, default=None, help="output folder (default experiments/results)")
    p.add_argument("--quick", action="store_true", help=f"smoke run: 1 repeat, {QUICK_MAX_FRAMES} frames a sequence")
    p.add_argument(
        "--scenes", default="", help="comma-separated scenes to run (any the suite knows; default the plan's)"
    )
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


def _error(message: str, code: int) -> int:
    print(f"error: {message}", file=sys.stderr)
    return code


def main(argv: list[str] | None = None) -> int:
    args = parser().parse_args(sys.argv[1:] if argv is None else argv)
    if args.ray and "=" in args.ray:  # "--ray key=value": argparse took the first override as the address
        args.overrides.insert(0, args.ray)
        args.ray = ""
    device = device_of([f"device={args.device}"])
    if args.ray is not None and device.startswith("cuda:") and device != "cuda:0":
        return _error("with --ray each task sees its own GPU as cuda:0; use --device cuda:0", 2)
    kind = "full" if args.full or device.startswith("cuda") else "cpu"
    extra = [f"device={device}", *args.overrides]
    wanted = [w.strip() for w in args.scenes.split(",") if w.strip()]
    try:
        data_root = load_config(extra).data_root or None
        sweep = load_sweep(args.sweep, kind, data_root, quick=args.quick) if args.sweep is not None else None
        if sweep:
            plan = sweep["plan"]
        elif wanted:
            plan = select_scenes(kind, wanted, data_root, quick=args.quick)
        else:
            plan = default_plan(kind, data_root, quick=args.quick)
    except ConfigError as e:
        return _error(str(e), 2)
    default_repeats = sweep["repeats"] if sweep else REPEATS["quick" if args.quick else kind]
    repeats = args.repeats if args.repeats is not None else default_repeats
    default_methods = ",".join(sweep["methods"] if sweep else DEFAULT_METHODS)
    methods = [m.strip() for m in (args.methods or default_methods).split(",") if m.strip()]
    if repeats < 1 or not methods:
        return _error("need --repeats >= 1 and at least one method", 2)
    unknown = [m for m in methods if m not in METHODS]
    if unknown:
        return _error(f"unknown method(s) {', '.join(unknown)}; valid: {', '.join(METHODS)}", 2)
    if sweep and wanted:
        known = [e["scene"] for e in plan]
        unknown = [w for w in wanted if w not in known]
        if unknown:
            return _error(f"unknown scene(s) {', '.join(unknown)}; the sweep has {', '.join(known)}", 2)
        plan = [e for e in plan if e["scene"] in wanted]
    try:
        check_evaluation_imports()
    except ImportError as e:
        return _error(str(e), 1)
    name = f"sweep {sweep['name']}" if sweep else ("quick" if args.quick else kind)
    variants = sweep["variants"] if sweep else None
    hint = kind == "cpu" and not sweep
    print(describe_plan(plan, name, methods, repeats, device, len(variants or [None]), extra, hint), flush=True)
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
            variants=variants,
            cluster=args.ray,
            gpus_per_task=args.gpus_per_task,
            plan_name=name,
        )
    except (ImportError, ClusterError) as e:  # --ray without Ray, or without the GPUs the runs need
        return _error(str(e), 1)
    ok = sum(r["status"] == "ok" for r in result["runs"])
    print(f"{ok} of {len(result['runs'])} runs ok; report {out / 'eval.md'}")
    return 0 if ok else 1
