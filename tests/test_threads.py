"""The CPU thread policy (issue 40): FR_THREADS parsing, threads chosen for the free cores, the
load monitor's arithmetic on /proc/stat text, and the per-search thread scope.  No timing."""
from __future__ import annotations

import pytest
import torch

from fr_torch.errors import FRInputError
from fr_torch.runtime import cpuload
from fr_torch.runtime import device as device_module
from fr_torch.runtime.device import DevicePolicy, parse_threads, threads_for_free_cores

STAT = """cpu  {a} 0 {b} 500 0 0 0 0 0 0
cpu0 {c0} 0 0 250 0 0 0 0 0 0
cpu1 {c1} 0 0 250 3 0 0 {s1} 0 0
intr 12345
procs_running {running}
procs_blocked 0
"""


def _stat(c0: int, c1: int, running: int = 1, steal: int = 0) -> str:
    return STAT.format(a=c0 + c1, b=steal, c0=c0, c1=c1, s1=steal, running=running)


@pytest.mark.parametrize("value, expected", [(None, "auto"), ("", "auto"), (" Auto ", "auto"), ("torch", "torch"),
                                             ("3", 3), (2, 2), ("1", 1)])
def test_parse_threads(value, expected):
    assert parse_threads(value) == expected


@pytest.mark.parametrize("value", ["0", "-2", "many", "1.5", 0, 1.5, "auto,2"])
def test_parse_threads_rejects(value):
    with pytest.raises(FRInputError, match="FR_THREADS: expected auto, torch or a positive number"):
        parse_threads(value)


def test_policy_threads_from_argument_or_environment(monkeypatch):
    monkeypatch.delenv("FR_THREADS", raising=False)
    assert DevicePolicy.resolve("cpu").threads == "auto"
    monkeypatch.setenv("FR_THREADS", "1")
    assert DevicePolicy.resolve("cpu").threads == 1
    assert DevicePolicy.parse("cuda:0").threads == 1
    assert DevicePolicy.resolve("cpu", threads="torch").threads == "torch"  # an argument wins
    monkeypatch.setenv("FR_THREADS", "lots")
    with pytest.raises(FRInputError, match="FR_THREADS"):
        DevicePolicy.resolve("cpu")
    with pytest.raises(FRInputError, match="threads: expected"):
        DevicePolicy.resolve("cpu", threads=-1)
    assert DevicePolicy(torch.device("cpu"), 2).threads == "auto"  # positional construction keeps working


@pytest.mark.parametrize("free, ceiling, expected", [
    (None, 2, 2),      # load unknown: the ceiling
    (2.0, 2, 2),       # idle 2-core machine: both cores
    (1.95, 2, 2),      # light background work
    (1.7, 2, 2),
    (1.6, 2, 1),       # a neighbour busy 40 % of the time: one thread
    (1.0, 2, 1),       # one busy neighbour on 2 cores
    (0.0, 2, 1),       # fully loaded: never fewer than one
    (15.0, 8, 8),      # never more than the ceiling
    (6.7, 16, 7),
    (6.3, 16, 6),
    (3.0, 0, 1),
])
def test_threads_for_free_cores(free, ceiling, expected):
    assert threads_for_free_cores(free, ceiling) == expected


def test_read_proc_stat():
    text = _stat(c0=1000, c1=300, running=3, steal=40)
    busy, running = cpuload.read_proc_stat(text, None, 100.0)
    assert busy == pytest.approx((1300 + 40) / 100) and running == 3  # aggregate line, steal counts as busy
    busy, _ = cpuload.read_proc_stat(text, frozenset({1}), 100.0)
    assert busy == pytest.approx((300 + 40) / 100)  # cpu1 only; idle and iowait are not busy
    with pytest.raises(ValueError):
        cpuload.read_proc_stat(text, frozenset({7}), 100.0)


def test_others_busy_cores():
    before = cpuload.CpuSample(wall_s=10.0, busy_s=100.0, own_s=5.0)
    after = cpuload.CpuSample(wall_s=11.0, busy_s=102.0, own_s=6.0)  # 2 core-s busy, 1 of them ours
    assert cpuload.others_busy_cores(before, after) == pytest.approx(1.0)
    assert cpuload.others_busy_cores(before, cpuload.CpuSample(11.0, 100.5, 6.0)) == 0.0  # never negative
    assert cpuload.others_busy_cores(after, after) == 0.0


def test_monitor_windows(tmp_path, monkeypatch):
    """First reading: runnable tasks but this thread; then the window's busy time minus our own."""
    stat = tmp_path / "stat"
    clock = {"wall": 100.0, "own": 1.0}
    monkeypatch.setattr(cpuload.time, "monotonic", lambda: clock["wall"])
    monkeypatch.setattr(cpuload.time, "process_time", lambda: clock["own"])
    stat.write_text(_stat(c0=1000, c1=1000, running=2))
    monitor = cpuload.CpuLoadMonitor(stat, cpus=frozenset({0, 1}))
    monitor.ticks_per_s = 100.0
    assert monitor.others_busy() == 1.0 and monitor.free_cores() == 1.0  # 2 runnable: us and one other
    # 1 s later: both CPUs were busy all along (200 ticks), 1 CPU-second of it ours -> 1 core others'.
    clock.update(wall=101.0, own=2.0)
    stat.write_text(_stat(c0=1100, c1=1100, running=1))
    assert monitor.others_busy() == pytest.approx(1.0)
    # A call sooner than MIN_WINDOW_S reuses the figure; the window keeps its start.
    clock.update(wall=101.0 + cpuload.MIN_WINDOW_S / 2, own=2.0)
    stat.write_text(_stat(c0=1100, c1=1100))
    assert monitor.others_busy() == pytest.approx(1.0)
    # Next second: only our own work (1.5 CPU-seconds on 2 CPUs) -> nothing left for others.
    clock.update(wall=102.0, own=3.5)
    stat.write_text(_stat(c0=1175, c1=1175))
    assert monitor.others_busy() == pytest.approx(0.0) and monitor.free_cores() == pytest.approx(2.0)
    assert cpuload.CpuLoadMonitor(tmp_path / "missing").others_busy() is None  # no /proc/stat: unknown


class _FakeMonitor:
    def __init__(self, free):
        self.free = free

    def free_cores(self):
        return self.free


def test_search_thread_count(monkeypatch):
    before = torch.get_num_threads()
    cpu = torch.device("cpu")
    try:
        torch.set_num_threads(2)
        monkeypatch.setattr(cpuload, "process_monitor", lambda: _FakeMonitor(1.0))
        assert DevicePolicy(cpu, 2, "auto").search_thread_count() == 1  # a neighbour holds a core
        monkeypatch.setattr(cpuload, "process_monitor", lambda: _FakeMonitor(2.0))
        assert DevicePolicy(cpu, 2, "auto").search_thread_count() == 2
        assert DevicePolicy(cpu, 2, 1).search_thread_count() == 1
        assert DevicePolicy(cpu, 2, 8).search_thread_count() == 2  # never above torch's count / the cores
        assert DevicePolicy(cpu, 2, "torch").search_thread_count() is None
        assert DevicePolicy(torch.device("cuda", 0), 2, "auto").search_thread_count() is None
        torch.set_num_threads(1)  # a worker process: one thread, nothing to decide
        assert DevicePolicy(cpu, 2, "auto").search_thread_count() is None
        assert DevicePolicy(cpu, 16, 4).search_thread_count() == 1
    finally:
        torch.set_num_threads(before)


def test_search_threads_scope_restores_torch(monkeypatch):
    before = torch.get_num_threads()
    try:
        torch.set_num_threads(2)
        monkeypatch.setattr(cpuload, "process_monitor", lambda: _FakeMonitor(1.0))
        with DevicePolicy(torch.device("cpu"), 2, "auto").search_threads():
            assert torch.get_num_threads() == 1
        assert torch.get_num_threads() == 2
        with pytest.raises(RuntimeError):
            with DevicePolicy(torch.device("cpu"), 2, 1).search_threads():
                raise RuntimeError("a failing search")
        assert torch.get_num_threads() == 2
    finally:
        torch.set_num_threads(before)


def test_apply_threads_fixed_count():
    import cv2

    before, before_cv = torch.get_num_threads(), cv2.getNumThreads()
    try:
        DevicePolicy(torch.device("cpu"), 4, 1).apply_threads()
        assert torch.get_num_threads() == 1
        DevicePolicy(torch.device("cpu"), 1, 3).apply_threads()  # capped at the usable cores
        assert torch.get_num_threads() == 1
    finally:
        torch.set_num_threads(before)
        cv2.setNumThreads(before_cv)


def test_estimator_searches_within_the_policy(monkeypatch):
    """FREstimator runs its search inside the policy's thread scope (and restores torch's count)."""
    from fr_torch.core.geometry.conventions import rotation_from_angles
    from fr_torch.runtime.estimator import FREstimator
    from fr_torch.synthetic import synthetic_segments

    seen = []
    real = device_module.DevicePolicy.search_threads

    def spy(self):
        seen.append(self.threads)
        return real(self)

    monkeypatch.setattr(device_module.DevicePolicy, "search_threads", spy)
    est = FREstimator(mode="fast", device=DevicePolicy.resolve("cpu", threads=1), reliability=None)
    seg, _ = synthetic_segments(500.0, rotation_from_angles(0.0, 5.0, 0.0).numpy(), 640, 480, n_per_family=20,
                                seed=0)
    before = torch.get_num_threads()
    [result] = est.calibrate_segments([seg], [(640, 480)])
    assert seen == [1] and result.ok and torch.get_num_threads() == before


def test_contention_summary_table():
    """fr bench's contention table: medians over rounds per mode, kind and policy."""
    from fr_eval.bench.contention import summary_lines

    rows = [{"mode": "fast", "kind": "segments", "policy": "auto", "idle_s": t, "busy_s": 1.5 * t, "busy_ratio": 1.5,
             "side2_s": 1.2 * t, "side2_throughput": 1.6, "load_before": load}
            for t, load in ((0.04, 0.3), (0.05, 1.2), (0.06, 0.8))]
    lines = summary_lines(rows, (2,))
    assert len(lines) == 3 and lines[0].count("|") == lines[1].count("|") == lines[2].count("|")
    assert "| fast | segments | auto | 0.050 | 0.075 | **1.50x** | 0.060 | **1.60x** | 3 | 0.3-1.2 |" == lines[2]
