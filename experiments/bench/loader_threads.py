"""How long the SLAM waits for frames with 1, 2 or 3 loader threads (``datasets/base.py``, LOAD_THREADS).

    python experiments/bench/loader_threads.py [--path REPLICA_SEQUENCE] [--consumer-ms 15] [--repeat 12]

Reads a Replica sequence (default: the shared office0 sample, 1200x680) through the dataset's own
prefetching iterator (``LOAD_THREADS`` and ``prefetch`` set per case), the selection repeated ``--repeat``
times, with a consumer that takes ``--consumer-ms`` per frame without holding the GIL (the GPU's work) and
a second thread doing Python work (the mapping worker's host side), and prints the wall time and the
consumer's wait for frames.  Session 23 on an otherwise idle 2-core CPU, two runs: 2.9-4.6 ms a frame
waited with one thread (2 ahead), 0.7-0.8 with two (4 ahead), 1.0-1.3 with three (6 ahead).
"""

from __future__ import annotations

import argparse
import threading
import time

import rgs_warp.datasets.base as base
from rgs_warp.config import load_config
from rgs_warp.datasets import open_dataset


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--path", default="../shared/data/replica-office0-sample/office0")
    ap.add_argument("--consumer-ms", type=float, default=15.0)
    ap.add_argument("--repeat", type=int, default=12)
    args = ap.parse_args(argv)
    ds = open_dataset(load_config(["dataset=replica/office0", f"dataset.path={args.path}"]), device="cpu")
    ds._indices = list(ds._indices) * args.repeat
    stop = threading.Event()

    def host_work():
        while not stop.is_set():
            x = 0
            for _ in range(20000):
                x += 1
            time.sleep(0.002)

    worker = threading.Thread(target=host_work)
    worker.start()
    shipped = base.LOAD_THREADS
    try:
        for threads, ahead in ((1, 2), (2, 4), (3, 6)):
            base.LOAD_THREADS, ds.prefetch = threads, ahead  # the dataset's own iterator, so configured
            waited, t0 = 0.0, time.perf_counter()
            it = iter(ds)
            while True:
                t = time.perf_counter()
                frame = next(it, None)
                waited += time.perf_counter() - t
                if frame is None:
                    break
                time.sleep(args.consumer_ms / 1e3)
            wall = time.perf_counter() - t0
            per_frame = waited / len(ds) * 1e3
            print(f"{threads} threads, {ahead} ahead: wall {wall:.2f} s, {per_frame:.1f} ms a frame waited")
    finally:
        base.LOAD_THREADS = shipped
        stop.set()
        worker.join()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
