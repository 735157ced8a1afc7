"""A run's peak memory is its own: the CUDA memory pool's high-water mark spans the process, and the
suite runs several runs in one process (Ray reuses its workers).  Without a reset every run after a
bigger one reported that one's peak.  No GPU here: a fake pool stands in for Warp's."""

from types import SimpleNamespace

import pytest

from rgs_warp.app import memory as memory


class FakePool:
    def __init__(self, current_mib: float, high_mib: float, resettable: bool):
        self.current, self.high, self.resettable = current_mib * 2**20, high_mib * 2**20, resettable

    def reset(self, ordinal: int) -> bool:
        if self.resettable:
            self.high = self.current
        return self.resettable

    def allocate(self, mib: float) -> None:
        self.current += mib * 2**20
        self.high = max(self.high, self.current)

    def free(self, mib: float) -> None:
        self.current -= mib * 2**20


@pytest.fixture
def pool(monkeypatch):
    def make(current_mib, high_mib, resettable):
        fake = FakePool(current_mib, high_mib, resettable)
        wp = memory.wp
        monkeypatch.setattr(wp, "get_device", lambda d=None: SimpleNamespace(is_cuda=True, ordinal=0))
        monkeypatch.setattr(wp, "is_mempool_enabled", lambda d=None: True)
        monkeypatch.setattr(wp, "get_mempool_used_mem_high", lambda d=None: fake.high)
        monkeypatch.setattr(wp, "get_mempool_used_mem_current", lambda d=None: fake.current)
        monkeypatch.setattr(memory, "reset_mempool_high", fake.reset)
        return fake

    return make


def test_a_smaller_run_after_a_bigger_one_reports_its_own_peak(pool):
    fake = pool(current_mib=100, high_mib=4800, resettable=True)  # an office baseline ran before
    floor = memory.start_peak_memory("cuda:0")
    assert floor == 0.0
    fake.allocate(2200)
    fake.free(2200)
    peak, reason = memory.run_peak_memory("cuda:0", floor)
    assert reason is None
    assert peak == pytest.approx(2300)


def test_without_a_reset_a_run_under_the_old_mark_is_na_not_the_old_peak(pool):
    fake = pool(current_mib=100, high_mib=4800, resettable=False)
    floor = memory.start_peak_memory("cuda:0")
    assert floor == pytest.approx(4800)
    fake.allocate(2200)
    peak, reason = memory.run_peak_memory("cuda:0", floor)
    assert peak is None
    assert "4800 MiB" in reason and "earlier run" in reason
    fake.allocate(5000)  # above the old mark: the mark is this run's
    peak, reason = memory.run_peak_memory("cuda:0", floor)
    assert reason is None
    assert peak == pytest.approx(7300)


def test_the_first_run_of_a_process_reports_its_peak_without_a_reset(pool):
    fake = pool(current_mib=300, high_mib=300, resettable=False)
    floor = memory.start_peak_memory("cuda:0")
    assert floor == 0.0
    fake.allocate(1000)
    assert memory.run_peak_memory("cuda:0", floor) == (pytest.approx(1300), None)


def test_cpu_has_no_peak(device):
    if device != "cpu":
        pytest.skip("the CPU case")
    assert memory.start_peak_memory("cpu") is None
    peak, reason = memory.run_peak_memory("cpu", None)
    assert peak is None
    assert "CUDA" in reason


def test_the_driver_reset_fails_quietly_without_a_driver():
    # this machine has no CUDA driver (CI neither): the reset must say so, not raise
    try:
        import ctypes

        ctypes.CDLL("libcuda.so.1")
    except OSError:
        assert memory.reset_mempool_high(0) is False
    else:
        pytest.skip("a CUDA driver is present: the reset is exercised by the GPU runs")
