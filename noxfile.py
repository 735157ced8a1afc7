"""Sessions: tests (the CI suite, Warp on CPU), lint (ruff), eval and bench (land with their issues)."""

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
    session.run("pytest", *session.posargs, env=env)


@nox.session
def lint(session):
    session.install("ruff")
    session.run("ruff", "check", ".")
    session.run("ruff", "format", "--check", ".")


@nox.session
def eval(session):
    """Evaluation tables (issue 7): not implemented yet."""
    session.error("nox -s eval: not implemented yet (the SLAM pipeline and evaluation suite land with issue 7)")


@nox.session
def bench(session):
    """GPU benchmarks under experiments/bench (issue 4 and later): not implemented yet."""
    session.error("nox -s bench: not implemented yet (GPU benchmarks land with the rasterizer, issue 4)")
