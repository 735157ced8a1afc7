"""GraphCache: launches captured once per key and replayed (Warp's CPU graphs here), replays reading
the arrays' current contents; the Seeder's depth extrapolation through it equals the eager one."""

import numpy as np
import pytest
import warp as wp

from rgs_warp.config import SeedingConfig
from rgs_warp.graph_cache import GraphCache, launch_key
from rgs_warp.keyframes import KeyframeBuffer
from rgs_warp.seeding import Seeder
from rgs_warp.types import Camera


@wp.kernel
def _axpy(a: float, x: wp.array(dtype=float), y: wp.array(dtype=float)):
    i = wp.tid()
    y[i] = a * x[i] + y[i]


def test_captured_once_per_key_and_replayed_with_current_contents():
    x = wp.array(np.arange(4, dtype=np.float32), device="cpu")
    y = wp.zeros(4, dtype=float, device="cpu")
    cache = GraphCache("cpu", size=2, enabled=True)

    def body(a):
        return lambda: wp.launch(_axpy, dim=4, inputs=[a, x, y], device="cpu")

    for _ in range(3):
        cache.run(launch_key([2.0, x, y]), body(2.0))
    np.testing.assert_array_equal(y.numpy(), 6.0 * np.arange(4))
    assert cache.counts == {"captured": 1, "replayed": 2}
    x.assign(np.ones(4, dtype=np.float32))  # a replay reads what the arrays hold now
    cache.run(launch_key([2.0, x, y]), body(2.0))
    np.testing.assert_array_equal(y.numpy(), 6.0 * np.arange(4) + 2.0)
    cache.run(launch_key([3.0, x, y]), body(3.0))  # another scalar: another graph
    cache.run(launch_key([4.0, x, y]), body(4.0))
    assert cache.counts["captured"] == 3 and len(cache) == 2  # the oldest went
    np.testing.assert_array_equal(y.numpy(), 6.0 * np.arange(4) + 9.0)
    off = GraphCache("cpu")  # the default on the CPU: launches as they come
    off.run(launch_key([1.0, x, y]), body(1.0))
    assert off.counts == {"captured": 0, "replayed": 0} and len(off) == 0
    assert not cache.run_while("loop", wp.zeros(1, dtype=wp.int32, device="cpu"), lambda: None)  # CUDA only


def test_seeder_depth_extrapolation_replayed_equals_eager():
    cam = Camera(60.0, 60.0, 31.5, 23.5, 64, 48)
    rng = np.random.default_rng(4)
    kf = KeyframeBuffer(3, cam.width, cam.height, "cpu")
    rgb = rng.uniform(0, 1, (cam.height, cam.width, 3)).astype(np.float32)
    slots = []
    for i in range(2):
        depth = rng.uniform(1.0, 3.0, (cam.height, cam.width)).astype(np.float32)
        depth[:, : 10 + 5 * i] = 0.0  # a band without depth, wider in the second
        depth[rng.uniform(size=depth.shape) < 0.3] = 0.0
        slots.append(kf.add(i, np.eye(4), rgb, depth))
    cfg = SeedingConfig(depth_extrapolate_px=6)
    eager = Seeder(cfg, cam, "cpu", mode="rgbd")
    graphs = GraphCache("cpu", size=4, enabled=True)
    replayed = Seeder(cfg, cam, "cpu", mode="rgbd", graphs=graphs)
    for rounds in range(3):
        for s in slots:
            if rounds == 2:  # new contents in the same slot: the graph reads them
                kf.depth[s].assign(np.roll(kf.depth[s].numpy(), 3, axis=0))
            expected = eager.depth_to_seed(kf, s).numpy().copy()
            got = replayed.depth_to_seed(kf, s).numpy()
            np.testing.assert_array_equal(got, expected)
            assert (got > 0).sum() > (kf.depth[s].numpy() > 0).sum() + 100  # pixels without depth got some
    assert graphs.counts == {"captured": 2, "replayed": 4}


@pytest.mark.gpu
@pytest.mark.skipif(not wp.is_cuda_available(), reason="needs a CUDA GPU")
def test_poisson_rounds_replayed_from_a_kept_loop_graph_equal_fresh_captures():
    """CUDA only (the loop is a conditional while-node; run on a GPU machine with ``pytest -m gpu``):
    Poisson-disk subsampling with its rounds' loop kept in a GraphCache and replayed gives what a
    fresh capture gives, call after call, with the points' contents changing in the same buffers."""
    from rgs_warp.sampling import poisson_disk_subsample

    dev = "cuda:0"
    rng = np.random.default_rng(7)
    n = 5000
    pts, radius, conf = (wp.zeros(n, dtype=t, device=dev) for t in (wp.vec3, float, float))
    keep_a, keep_b = wp.zeros(n, dtype=wp.int32, device=dev), wp.zeros(n, dtype=wp.int32, device=dev)
    grid_a, grid_b = wp.HashGrid(128, 128, 128, device=dev), wp.HashGrid(128, 128, 128, device=dev)
    counters_a, counters_b = wp.zeros(2, dtype=wp.int32, device=dev), wp.zeros(2, dtype=wp.int32, device=dev)
    rmax_a, rmax_b = wp.zeros(1, dtype=float, device=dev), wp.zeros(1, dtype=float, device=dev)
    cache = GraphCache(dev)
    for _ in range(4):
        pts.assign(rng.uniform(0, 1, (n, 3)).astype(np.float32))
        radius.assign(rng.uniform(0.02, 0.05, n).astype(np.float32))
        conf.assign(rng.uniform(0, 1, n).astype(np.float32))
        common = dict(cell_size=0.05)
        poisson_disk_subsample(
            pts,
            radius,
            conf,
            grid=grid_a,
            keep_out=keep_a,
            counters=counters_a,
            radius_max=rmax_a,
            graphs=cache,
            **common,
        )
        poisson_disk_subsample(
            pts, radius, conf, grid=grid_b, keep_out=keep_b, counters=counters_b, radius_max=rmax_b, **common
        )
        np.testing.assert_array_equal(keep_a.numpy(), keep_b.numpy())
        assert 100 < keep_a.numpy().sum() < n
    assert cache.counts == {"captured": 1, "replayed": 3}
