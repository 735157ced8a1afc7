"""What the suite runs: the default plans (``cpu``, ``full``, ``quick``), the sweep specs, the names of
runs and table rows, and the plan as printed before the first run (sizes, skipped scenes, an estimate)."""

from __future__ import annotations

import re
from collections.abc import Sequence
from pathlib import Path

import yaml

from rgs_warp.app.cpu_size import CPU_SIZED
from rgs_warp.config import Config, ConfigError, group_options, load_config
from rgs_warp.slam import METHODS

PLANS = ("cpu", "full")
# --quick: a smoke run of the device's plan, this many frames a sequence and one repeat
QUICK_MAX_FRAMES = 15
REPEATS = {"cpu": 1, "full": 3, "quick": 1}
SYNTHETIC = ("room0", "office0")
REAL_KINDS = ("7scenes", "replica", "tum")
# The cpu plan's real sequences, one per benchmark when its data is present; the others run in the full plan.
CPU_REAL_SCENES = ("7scenes/redkitchen", "replica/office0", "tum/fr1_desk")
# Real frames on the CPU at about CPU_SIZED's 120x68: Replica 1200x680 / 10, TUM and 7-Scenes 640x480 / 5.
CPU_DOWNSCALE = {"7scenes": 5, "replica": 10, "tum": 5}
# 7-Scenes on the CPU: every 5th frame (6 Hz, still trackable), so that CPU_SIZED's 25 frames see some motion.
CPU_STRIDE = {"7scenes": 5}
# One run of the cpu plan with its evaluation on 2 cores shared with other work, kernels compiled: 68-115 s,
# 92 s on average (the synthetic scenes and 7-Scenes, both methods: 9 min 17 s for the 6 runs); what the
# printed estimate multiplies by the number of runs.
CPU_RUN_S = 100
# A Replica-size synthetic run on an H100 with its evaluation (experiments/results/sweeps.md: 53 s for
# 300 frames); the real sequences at about this many seconds a frame.
GPU_FRAME_S = 0.18
FULL_COMMAND = "nox -s eval -- --full"
NO_DATA = "no data at"  # how a skipped scene's reason begins when its data is missing


def _entry(scene: str, overrides: list[str], skipped: str | None = None) -> dict:
    return {"scene": scene, "overrides": [f"dataset={scene}", *overrides], "skipped": skipped}


def download_hint(scene: str) -> str:
    """How to get a real sequence's data."""
    return f"python -m rgs_warp.download {scene}"


def resolved_root(data_root: Path | str | None) -> Path:
    """``data_root``, else the config's default (``$RGS_DATA``, else the current directory), absolute."""
    return Path(data_root if data_root else Config().resolved_data_root()).expanduser().resolve()


def scene_entries(plan: str, data_root: Path | str | None = None) -> list[dict]:
    """Every scene the suite knows, sized for ``plan`` (``cpu`` or ``full``), each ``{"scene",
    "overrides", "skipped"}``: the two synthetic scenes (``CPU_SIZED`` on the CPU, Replica size in the
    full plan), then every 7-Scenes, Replica and TUM sequence of the config groups under the data
    root (``data_root``, else ``$RGS_DATA``, else the current directory), ``CPU_DOWNSCALE`` /
    ``CPU_STRIDE`` and ``CPU_SIZED``'s frames and iterations on the CPU, whole in the full plan.  A
    sequence whose data is not there is skipped, saying where it looked and how to get it."""
    if plan not in PLANS:
        raise ValueError(f"plan {plan!r}: one of {', '.join(PLANS)}")
    cpu = plan == "cpu"
    cpu_sized = [f"{k}={v}" for k, v in CPU_SIZED.items()]
    suffix = "" if cpu else "_replica_size"
    out = [_entry(f"synthetic/{name}{suffix}", cpu_sized if cpu else []) for name in SYNTHETIC]
    root = resolved_root(data_root)
    options = group_options("dataset")
    for kind in REAL_KINDS:
        for scene in (o for o in options if o.split("/")[0] == kind):
            overrides = [f"data_root={root}"]
            if cpu:
                size = [f"dataset.downscale={CPU_DOWNSCALE[kind]}"]
                size += [f"dataset.stride={CPU_STRIDE[kind]}"] if kind in CPU_STRIDE else []
                overrides += size + [o for o in cpu_sized if not o.startswith(("dataset.width", "dataset.height"))]
            path = load_config([f"dataset={scene}", *overrides]).dataset_path()
            skipped = None if path.is_dir() else f"{NO_DATA} {path}; get it with `{download_hint(scene)}`"
            out.append(_entry(scene, overrides, skipped))
    return out


def default_plan(plan: str, data_root: Path | str | None = None, quick: bool = False) -> list[dict]:
    """The scenes of a default plan (``scene_entries``): ``full``, every scene; ``cpu``, the synthetic
    scenes and ``CPU_REAL_SCENES`` (the other sequences are listed as skipped: "full plan only").
    ``quick``: ``QUICK_MAX_FRAMES`` frames everywhere."""
    out = []
    for e in scene_entries(plan, data_root):
        if plan == "cpu" and not e["skipped"] and e["scene"].split("/")[0] in REAL_KINDS:
            if e["scene"] not in CPU_REAL_SCENES:
                e = {**e, "skipped": f"in the full plan only (`{FULL_COMMAND}`)"}
        if quick:
            e = {**e, "overrides": [*e["overrides"], f"dataset.max_frames={QUICK_MAX_FRAMES}"]}
        out.append(e)
    return out


def select_scenes(plan: str, wanted: list[str], data_root: Path | str | None = None, quick: bool = False) -> list[dict]:
    """``--scenes``: those of ``scene_entries`` (any known scene, also one the cpu plan leaves out), in
    the order given; ConfigError naming an unknown one."""
    known = {e["scene"]: e for e in scene_entries(plan, data_root)}
    unknown = [w for w in wanted if w not in known]
    if unknown:
        raise ConfigError(f"unknown scene(s) {', '.join(unknown)}; known: {', '.join(known)}")
    quick_frames = [f"dataset.max_frames={QUICK_MAX_FRAMES}"] if quick else []
    return [{**known[w], "overrides": [*known[w]["overrides"], *quick_frames]} for w in wanted]


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


def _check_spec(spec, path: Path) -> None:
    if not isinstance(spec, dict) or not spec.get("scenes"):
        raise ConfigError(f"sweep {path}: needs a mapping with a non-empty 'scenes' list")
    unknown = sorted(set(spec) - set(SWEEP_KEYS))
    if unknown:
        raise ConfigError(f"sweep {path}: unknown key(s) {', '.join(unknown)}; valid: {', '.join(SWEEP_KEYS)}")
    bad = [m for m in spec.get("methods") or [] if m not in METHODS]
    if bad:
        raise ConfigError(f"sweep {path}: unknown method(s) {', '.join(map(str, bad))}; valid: {', '.join(METHODS)}")
    repeats = spec.get("repeats", 1)
    if not isinstance(repeats, int) or repeats < 1:
        raise ConfigError(f"sweep {path}: repeats must be an integer >= 1, not {repeats!r}")
    variants, grid = spec.get("variants"), spec.get("grid")
    if variants is not None and not (
        isinstance(variants, list) and all(isinstance(v, dict) and set(v) <= {"name", "overrides"} for v in variants)
    ):
        raise ConfigError(f"sweep {path}: variants must be a list of {{name, overrides}}")
    if grid is not None and not (isinstance(grid, dict) and all(isinstance(v, list) and v for v in grid.values())):
        raise ConfigError(f"sweep {path}: grid must map each key to a non-empty list of values")


def load_sweep(path: Path, plan: str, data_root: Path | str | None = None, quick: bool = False) -> dict:
    """A sweep spec (YAML) as the suite runs it: ``{"name", "plan", "methods", "repeats",
    "variants"}``.  The spec's keys: ``scenes`` (a list; a scene the suite knows keeps its sizing for
    ``plan``, ``cpu`` or ``full`` (``scene_entries``), any other dataset config runs as configured; an
    item may be ``{scene: ..., overrides: [...]}`` to add overrides for that scene), ``methods``
    (default ``[rgs]``), ``repeats`` (default 1), ``overrides`` (every run), ``variants`` (a list of
    ``{name, overrides}``) and ``grid`` (``{key: [values]}``), the override sets (``sweep_variants``),
    and ``name`` (default the file's stem).  A run's overrides, later ones winning: the plan's for the
    scene, the spec's ``overrides``, the scene's own, the method and seed, the command line's, the
    override set.  Raises ConfigError naming what is wrong; every override set is checked with
    ``load_config`` before anything runs."""
    path = Path(path)
    try:
        spec = yaml.safe_load(path.read_text())
    except (OSError, yaml.YAMLError) as e:
        raise ConfigError(f"cannot read the sweep {path}: {e}") from e
    _check_spec(spec, path)
    overrides = [str(o) for o in spec.get("overrides") or []]
    variants = spec.get("variants")
    sets = sweep_variants(
        [{"name": str(v.get("name") or ""), "overrides": [str(o) for o in v.get("overrides") or []]} for v in variants]
        if variants
        else None,
        spec.get("grid"),
    )
    slugs = [variant_slug(v["name"]) for v in sets or []]
    if len(set(slugs)) != len(slugs):
        raise ConfigError(f"sweep {path}: two override sets have the same name (as folder names: {slugs})")

    data_root = data_root or load_config(overrides).data_root or None  # the spec's own data_root=
    by_scene = {e["scene"]: e for e in scene_entries(plan, data_root)}
    root = f"data_root={resolved_root(data_root)}"
    quick_frames = [f"dataset.max_frames={QUICK_MAX_FRAMES}"] if quick else []
    out = []
    for item in spec["scenes"]:
        scene, own = (item.get("scene"), item.get("overrides") or []) if isinstance(item, dict) else (item, [])
        own = [*quick_frames, *overrides, *map(str, own)]
        if scene in by_scene:
            entry = by_scene[scene]
            out.append({**entry, "overrides": [*entry["overrides"], *own]})
        elif scene in group_options("dataset"):
            out.append(_entry(scene, [*([] if scene.startswith("synthetic/") else [root]), *own]))
        else:
            known = sorted(set(by_scene) | set(group_options("dataset")))
            raise ConfigError(f"sweep {path}: unknown scene {scene!r}; known: {', '.join(known)}")
    for v in sets or [{"overrides": []}]:
        load_config([*out[0]["overrides"], *v["overrides"]])
    return {
        "name": str(spec.get("name") or path.stem),
        "plan": out,
        "methods": list(spec.get("methods") or ["rgs"]),
        "repeats": spec.get("repeats", 1),
        "variants": sets,
    }


# ---------------------------------------------------------------------------------------------------
# names


def run_name(scene: str, method: str, repeat: int, variant: dict | None = None) -> str:
    """A run's folder name: ``synthetic-room0-rgs-0``, with an override set ``...-rgs-short_tracking-0``."""
    middle = "" if variant is None else "-" + variant_slug(variant["name"])
    return f"{scene.replace('/', '-')}-{method}{middle}-{repeat}"


def variant_slug(name: str) -> str:
    """An override set's name as a folder name component: runs of other characters than letters,
    digits and ``.=+-`` become one ``_``."""
    return re.sub(r"[^A-Za-z0-9.=+-]+", "_", name).strip("_") or "_"


def row_label(method: str, variant: str | None) -> str:
    """The tables' row of a method run with an override set of a sweep (``rgs [short tracking]``)."""
    return method if variant is None else f"{method} [{variant}]"


def row_of(record: dict) -> str:
    """The tables' row of a run's record."""
    return row_label(record["method"], record.get("variant"))


# ---------------------------------------------------------------------------------------------------
# the plan as printed before the first run


def _size(entry: dict, extra: Sequence[str]) -> str:
    try:
        d = load_config([*entry["overrides"], *extra]).dataset
    except ConfigError as e:
        return f"(overrides not valid: {e})"
    if d.type == "synthetic":
        size = f"{d.width}x{d.height}"
    else:
        size = "full size" if d.downscale == 1 else f"1/{d.downscale} size"
    frames = d.max_frames or (d.n_frames if d.type == "synthetic" else None)
    every = f", every {d.stride}th frame" if d.stride > 1 else ""
    return f"{size}, {f'{frames} frames' if frames else 'all frames'}{every}"


def _cpu_sized(cfg: Config) -> bool:
    """A run no bigger than the cpu plan's: CPU_SIZED's frames and initial mapping, at most its pixels."""
    d, q = cfg.dataset, CPU_SIZED
    small = d.type != "synthetic" or d.width * d.height <= q["dataset.width"] * q["dataset.height"]
    few = d.max_frames is not None and d.max_frames <= q["dataset.max_frames"]
    return small and few and cfg.mapping.init_iters <= q["mapping.init_iters"]


def estimate(plan: list[dict], runs_per_scene: int, device: str, extra: Sequence[str] = ()) -> str:
    """A rough time for ``runs_per_scene`` runs of each scene of ``plan`` (with the overrides ``extra``)
    on ``device``: ``CPU_RUN_S`` a run of the CPU size on the CPU (a bigger one takes hours),
    ``GPU_FRAME_S`` a frame on a GPU."""
    try:
        present = [load_config([*e["overrides"], *extra]) for e in plan if not e["skipped"]]
    except ConfigError as e:
        return f"no estimate ({e})"
    if not present:
        return "nothing to run"
    if not device.startswith("cuda"):
        if all(map(_cpu_sized, present)):
            minutes = len(present) * runs_per_scene * CPU_RUN_S / 60
            return (
                f"about {max(1, round(minutes))} minutes on 2 cores ({CPU_RUN_S} s a run; the first use "
                "compiles the kernels for a few minutes more)"
            )
        return "hours to days on a CPU (runs bigger than the CPU size; a GPU takes minutes)"
    frames = [c.dataset.max_frames or (c.dataset.n_frames if c.dataset.type == "synthetic" else None) for c in present]
    minutes = runs_per_scene * sum(f for f in frames if f) * GPU_FRAME_S / 60
    text = f"about {max(1, round(minutes))} minutes on an H100"
    if not all(frames):
        text += f" plus {GPU_FRAME_S} s a frame of the whole real sequences"
    return text


def describe_plan(
    plan: list[dict],
    name: str,
    methods: Sequence[str],
    repeats: int,
    device: str,
    n_sets: int = 1,
    extra: Sequence[str] = (),
    full_hint: bool = False,
) -> str:
    """The plan as the command prints it before the first run (``extra``: the overrides of every run):
    its name and device, the runs and an estimate, each scene's size, the skipped scenes and how to get
    them, and with ``full_hint`` how to get the full plan."""
    present = [e for e in plan if not e["skipped"]]
    n_runs = len(present) * len(methods) * repeats * n_sets
    sets = f" x {n_sets} override sets" if n_sets > 1 else ""
    time = estimate(plan, len(methods) * repeats * n_sets, device, extra)
    lines = [
        f"Evaluation plan {name} on {device}: {n_runs} runs ({len(present)} scenes x {len(methods)} methods"
        f"{sets} x {repeats} repeat{'s' * (repeats != 1)}), {time}",
        *(f"  {e['scene']}: {_size(e, extra)}" for e in present),
    ]
    skipped = [e for e in plan if e["skipped"]]
    missing = [e for e in skipped if e["skipped"].startswith(NO_DATA)]
    if missing:
        root = next((o.split("=", 1)[1] for o in missing[0]["overrides"] if o.startswith("data_root=")), "?")
        lines.append(
            f"Skipped, no data under {root} (data_root= or $RGS_DATA; get a sequence with "
            f"`{download_hint('NAME')}`, NAME as listed):"
        )
        by_kind: dict[str, list[str]] = {}
        for e in missing:
            by_kind.setdefault(e["scene"].split("/")[0], []).append(e["scene"])
        lines += [f"  {' '.join(scenes)}" for scenes in by_kind.values()]
    by_reason: dict[str, list[str]] = {}
    for e in skipped:
        if e not in missing:
            by_reason.setdefault(e["skipped"], []).append(e["scene"])
    lines += [f"Skipped, {reason}: {' '.join(scenes)}" for reason, scenes in by_reason.items()]
    if full_hint:
        lines.append(
            f"The full plan (Replica-size synthetic scenes, every real sequence whole, {REPEATS['full']} repeats; "
            f"meant for a GPU): {FULL_COMMAND}"
        )
    return "\n".join(lines)
