"""GaussianMap: construction, growth by doubling, append, in-place compaction."""

import numpy as np
import pytest
import warp as wp

from rgs_warp.types import GaussianMap


def _rows(rng, n, num_sh=9):
    q = rng.normal(size=(n, 4))
    return (
        rng.normal(size=(n, 3)),
        q / np.linalg.norm(q, axis=1, keepdims=True),
        rng.normal(size=(n, 3)),
        rng.normal(size=n),
        rng.normal(size=(n, num_sh, 3)),
    )


def _assert_rows(gmap, rows):
    fields = gmap.to_numpy()
    for name, expected in zip(fields, rows, strict=True):
        np.testing.assert_array_equal(fields[name], np.asarray(expected, np.float32))


def test_from_numpy_round_trip(device):
    rows = _rows(np.random.default_rng(0), 7)
    gmap = GaussianMap.from_numpy(*rows, device=device)
    assert len(gmap) == 7 and gmap.sh_degree == 2 and gmap.sh.shape == (7, 9)
    _assert_rows(gmap, rows)


def test_append_grows_by_doubling(device):
    rng = np.random.default_rng(1)
    gmap = GaussianMap(capacity=4, sh_degree=1, device=device)
    a, b = _rows(rng, 3, 4), _rows(rng, 6, 4)
    gmap.append(*a)
    assert gmap.capacity == 4
    gmap.append(wp.array(b[0].astype(np.float32), dtype=wp.vec3, device=device), *b[1:])
    assert len(gmap) == 9 and gmap.capacity == 16
    _assert_rows(gmap, [np.concatenate([x, y]) for x, y in zip(a, b, strict=True)])


def test_remove_compacts_in_place(device):
    rng = np.random.default_rng(2)
    rows = _rows(rng, 50)
    gmap = GaussianMap.from_numpy(*rows, device=device, capacity=64)
    means_array = gmap.means
    mask = rng.random(50) < 0.4
    gmap.remove(mask)
    assert len(gmap) == (~mask).sum() and gmap.means is means_array
    _assert_rows(gmap, [x[~mask] for x in rows])
    gmap.remove(wp.array(np.r_[1, np.zeros(len(gmap) - 1)].astype(np.int32), device=device))
    _assert_rows(gmap, [x[~mask][1:] for x in rows])


def test_columns_grow_fill_and_compact_with_the_map(device):
    # the registry: every column grows with the map, new rows get their column's fill, a removal
    # compacts every column but scratch in one pass
    rng = np.random.default_rng(3)
    rows = _rows(rng, 6)
    gmap = GaussianMap.from_numpy(*rows, device=device, capacity=8)
    count = gmap.add_column("count", wp.int32)
    ema = gmap.add_column("ema", wp.vec3, fill="means")  # registered on a map with rows: filled at once
    moment = gmap.add_column("moment", wp.vec3, (9,))
    gmap.add_column("scratch", wp.float32, scratch=True)
    np.testing.assert_array_equal(ema.numpy()[:6], rows[0].astype(np.float32))
    count.assign(np.arange(8, dtype=np.int32) + 1)
    moment.fill_(wp.vec3(1.0, 2.0, 3.0))
    gmap.column("scratch").fill_(7.0)
    more = _rows(rng, 5)
    gmap.append(*more)  # grows 8 -> 16: every column, live rows kept, new rows filled
    assert gmap.capacity == 16 and all(gmap.column(c).shape[0] == 16 for c in ("count", "ema", "moment", "scratch"))
    np.testing.assert_array_equal(gmap.column("count").numpy()[:11], np.r_[np.arange(6) + 1, np.zeros(5)])
    np.testing.assert_array_equal(gmap.column("ema").numpy()[6:11], more[0].astype(np.float32))
    assert not gmap.column("moment").numpy()[6:11].any() and gmap.column("moment").numpy()[:6].all()
    np.testing.assert_array_equal(gmap.column("scratch").numpy()[:6], 7.0)  # kept through growth, never filled
    mask = np.zeros(11, bool)
    mask[[0, 7, 10]] = True
    before = {c: gmap.column(c).numpy()[:11].copy() for c in ("count", "ema", "moment", "means", "sh")}
    scratch_before = gmap.column("scratch").numpy().copy()
    gmap.remove(mask)
    assert len(gmap) == 8
    for c, value in before.items():
        np.testing.assert_array_equal(gmap.column(c).numpy()[:8], value[~mask], err_msg=c)
    np.testing.assert_array_equal(gmap.column("scratch").numpy(), scratch_before)  # not compacted
    gmap.count = 10  # rows written elsewhere (a kernel) become live: fills apply
    np.testing.assert_array_equal(gmap.column("ema").numpy()[8:10], gmap.means.numpy()[8:10])
    assert not gmap.column("count").numpy()[8:10].any()


def test_column_registration_errors(device):
    gmap = GaussianMap(4, sh_degree=1, device=device)
    assert gmap.add_column("c", wp.float32) is gmap.add_column("c", wp.float32)  # same layout: the same column
    with pytest.raises(ValueError, match="another layout"):
        gmap.add_column("c", wp.int32)
    with pytest.raises(ValueError, match="fill 'nope'"):
        gmap.add_column("d", wp.float32, fill="nope")
    with pytest.raises(KeyError, match="no column 'e'"):
        gmap.column("e")
    with pytest.raises(ValueError, match="reserve first"):
        gmap.count = 5
    with pytest.raises(ValueError, match="removal mask has 2 entries for 0"):
        gmap.remove(np.zeros(2, bool))
