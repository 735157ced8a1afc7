"""Sessions: tests (the CI suite, Warp on CPU), lint (ruff), eval (the evaluation suite), bench (GPU)."""

import os

import nox

nox.options.sessions = ["tests", "lint"]
nox.options.reuse_existing_virtualenvs = True

TORCH_CPU = "torch==2.13.0"  # the CPU build; an unpinned torch pulls GBs of CUDA wheels


def _install(session):
    session.install(TORCH_CPU)
    session.install("-e", ".[dev]")


@nox.session
def tests(session):
    """The test suite on Warp's CPU device, kernel cache inside the checkout."""
    _install(session)
    env = {"WARP_CACHE_PATH": os.path.abspath(".cache/warp"), "RGS_CACHE": os.path.abspath(".cache/rgs_warp")}
    session.run("pytest", "-n", "logical", *session.posargs, env=env)


@nox.session
def lint(session):
    session.install("ruff")
    session.run("ruff", "check", ".")
    session.run("ruff", "format", "--check", ".")


@nox.session
def eval(session):
    """Evaluation tables (supplement §3): every scene x method x repeat, results in
    experiments/results/eval.md and eval.json. Without a GPU the cpu plan (CPU-sized runs, 10-15
    minutes on 2 cores), on a GPU the full plan; the suite prints its plan first. Arguments go to the
    suite, e.g. `nox -s eval -- --full`, `nox -s eval -- --quick`, `nox -s eval -- data_root=/data`
    or a sweep on Ray, `nox -s eval -- --sweep sweeps/example.yaml --ray`."""
    _install(session)
    env = {"WARP_CACHE_PATH": os.path.abspath(".cache/warp"), "RGS_CACHE": os.path.abspath(".cache/rgs_warp")}
    session.run("python", "-m", "rgs_warp.app.suite", *session.posargs, env=env)


@nox.session
def bench(session):
    """GPU benchmarks (rasterizer vs gsplat, tracking iteration, evaluation metrics, the whole system over
    2,000 frames, the viewer's cost); results as JSON under experiments/results/bench/. Needs a CUDA GPU (and
    gsplat for the comparison)."""
    _install(session)
    probe = session.run("python", "-c", "import warp as wp; wp.init(); print(wp.is_cuda_available())", silent=True)
    if "True" not in (probe or ""):
        session.error("nox -s bench needs a CUDA GPU that Warp can see (the benchmarks time GPU kernels)")
    out = os.path.abspath("experiments/results/bench")
    env = {"PYTHONPATH": os.path.abspath("src")}
    session.run("python", "experiments/bench/raster.py", "--out", out, env=env)
    session.run("python", "experiments/bench/tracking.py", "--out", out, env=env)
    session.run("python", "experiments/bench/eval_metrics.py", "--out", out, env=env)
    session.run("python", "experiments/bench/slam_fps.py", "--out", out, env=env)
    session.run("python", "experiments/bench/viewer_fps.py", "--out", out, env=env)
