"""The command line ``python -m rgs_warp.compile``: the kernel modules compiled ahead of a run, for this
machine's GPU or, with ``--arch``, for GPUs it does not have (``rgs_warp.compile``)."""

from __future__ import annotations

import argparse
import sys
import time

import warp as wp

from rgs_warp.compile import FORMATS, compile_for_archs, preload
from rgs_warp.compile import __doc__ as kernels_doc


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="python -m rgs_warp.compile",
        description=kernels_doc,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--device", default="cuda:0", help="the GPU to compile for (default cuda:0)")
    p.add_argument("--arch", default="", help="GPU architectures without a GPU, comma separated (e.g. 80,86,89,90)")
    p.add_argument("--format", default=",".join(FORMATS), help="with --arch: cubin, ptx or both (default)")
    p.add_argument("--workers", type=int, default=None, help="modules compiled at once (default: CPU cores)")
    return p


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(sys.argv[1:] if argv is None else argv)
    wp.config.quiet = True
    wp.init()
    t0 = time.perf_counter()
    if args.arch:
        try:
            archs = [int(a) for a in args.arch.split(",") if a.strip()]
        except ValueError:
            print(f"error: --arch takes numbers like 80,86,89,90 (sm_80 ...), got {args.arch!r}", file=sys.stderr)
            return 2
        formats = tuple(f.strip() for f in args.format.split(",") if f.strip())
        unknown = [f for f in formats if f not in FORMATS]
        if unknown or not formats:
            print(f"error: --format takes {', '.join(FORMATS)} or both, got {args.format!r}", file=sys.stderr)
            return 2
        files = compile_for_archs(archs, formats, args.workers)
        what = f"{len(files)} binaries for sm_{', sm_'.join(map(str, archs))} ({', '.join(formats)})"
    else:
        if not wp.is_cuda_available():
            print(
                "error: no CUDA GPU that Warp can see; --arch 80,86,89,90 compiles for GPUs without one "
                "(CPU kernels compile on their first use)",
                file=sys.stderr,
            )
            return 2
        preload(args.device, args.workers)
        what = f"every kernel module on {args.device}"
    print(f"compiled or found {what} in {time.perf_counter() - t0:.1f} s; kernel cache: {wp.config.kernel_cache_dir}")
    return 0
