"""How long the SLAM waits for frames with 1, 2 or 3 loader threads (``datasets/base.py``, LOAD_THREADS).

    python experiments/bench/loader_threads.py [--path REPLICA_SEQUENCE] [--consumer-ms 15] [--repeat 12]

Reads a Replica sequence (default: the shared office0 sample, 1200x680) through the dataset's own frame
reader, the selection repeated ``--repeat`` times, with a consumer that takes ``--consumer-ms`` per frame
without holding the GIL (the GPU's work) and a second thread doing Python work (the mapping worker's host
side), and prints the wall time and the consumer's wait for frames.  Session 23 on a 2-core CPU: 7.3 ms a
frame waited with one thread (2 ahead), 3.1 with two (4 ahead), 1.3 with three (6 ahead).
"""

from __future__ import annotations

import argparse
import threading
import time
from collections import deque
from concurrent.futures import ThreadPoolExecutor

from rgs_warp.config import load_config
from rgs_warp.datasets import open_dataset


def frames(ds, threads: int, ahead: int):
    with ThreadPoolExecutor(max_workers=threads) as pool:
        pending, nxt = deque(), 0
        while nxt < len(ds) and len(pending) <= ahead:
            pending.append(pool.submit(ds.__getitem__, nxt))
            nxt += 1
        while pending:
            frame = pending.popleft().result()
            if nxt < len(ds):
                pending.append(pool.submit(ds.__getitem__, nxt))
                nxt += 1
            yield frame


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
    try:
        for threads, ahead in ((1, 2), (2, 4), (3, 6)):
            waited, t0 = 0.0, time.perf_counter()
            it = frames(ds, threads, ahead)
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
        stop.set()
        worker.join()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
