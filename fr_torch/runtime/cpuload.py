"""How busy the other processes keep this process's CPUs: the measurement behind adaptive threads.

:class:`CpuLoadMonitor` reads the kernel's CPU time counters (``/proc/stat``: per-CPU busy time,
including time a hypervisor stole) over the CPUs of this process's affinity mask, subtracts this
process's own CPU time (:func:`time.process_time`, all its threads) and reports what is left as
**cores kept busy by others** over the window since the previous reading.  Before a first window
exists it falls back to the kernel's instantaneous count of runnable tasks (``procs_running``)
minus this thread.  Where there is no ``/proc/stat`` (macOS, Windows) it reports None (unknown).

The decision that follows from the figure (how many intra-op threads) is
:meth:`fr_torch.runtime.device.DevicePolicy.search_thread_count`; this module only measures.
"""
from __future__ import annotations

import os
import time
from dataclasses import dataclass
from pathlib import Path

#: Shortest window (seconds) a reading is averaged over; a call sooner than this after the previous
#: reading reuses the previous figure (``/proc/stat`` counts in clock ticks, 10 ms on most kernels).
MIN_WINDOW_S = 0.05
#: /proc/stat fields (after the CPU name) that count busy time: user, nice, system, irq, softirq,
#: steal (guest time is already inside user / nice); idle and iowait are not busy.
BUSY_FIELDS = (0, 1, 2, 5, 6, 7)


@dataclass(frozen=True)
class CpuSample:
    """One reading: ``wall_s`` (monotonic clock), ``busy_s`` (CPU-seconds the monitored CPUs were
    busy since boot, all processes), ``own_s`` (CPU-seconds this process used since it started)."""

    wall_s: float
    busy_s: float
    own_s: float


def read_proc_stat(text: str, cpus: frozenset[int] | None, ticks_per_s: float) -> tuple[float, int | None]:
    """``(busy CPU-seconds over cpus, procs_running)`` from the text of ``/proc/stat``;
    ``cpus`` None = every CPU (the aggregate ``cpu`` line).  ValueError when no CPU line matches."""
    busy_ticks, matched, running = 0, False, None
    for line in text.splitlines():
        name, _, rest = line.partition(" ")
        if name == "procs_running":
            running = int(rest)
        elif name.startswith("cpu") and (name == "cpu") == (cpus is None):
            if cpus is not None and int(name[3:]) not in cpus:
                continue
            fields = [int(v) for v in rest.split()]
            busy_ticks += sum(fields[i] for i in BUSY_FIELDS if i < len(fields))
            matched = True
    if not matched:
        raise ValueError("no matching cpu line in /proc/stat")
    return busy_ticks / ticks_per_s, running


def others_busy_cores(before: CpuSample, after: CpuSample) -> float:
    """Cores kept busy by other processes between two readings (>= 0)."""
    wall = after.wall_s - before.wall_s
    if wall <= 0:
        return 0.0
    return max(0.0, (after.busy_s - before.busy_s) - (after.own_s - before.own_s)) / wall


class CpuLoadMonitor:
    """Cores kept busy by other processes on this process's CPUs (see the module docstring).

    ``stat_path``: the counters file (``/proc/stat``).  ``cpus``: the CPU numbers watched (default
    this process's affinity mask; all CPUs where that is unknown).  One instance per process
    (:func:`process_monitor`); not thread-safe, and needs no lock: a reading is advisory.
    """

    def __init__(self, stat_path: str | Path = "/proc/stat", cpus: frozenset[int] | None = None):
        self.stat_path = Path(stat_path)
        if cpus is None:
            try:
                cpus = frozenset(os.sched_getaffinity(0))
            except (AttributeError, OSError):
                cpus = None
        self.cpus = cpus
        try:
            self.ticks_per_s = float(os.sysconf("SC_CLK_TCK"))
        except (AttributeError, ValueError, OSError):
            self.ticks_per_s = 100.0
        self._last: CpuSample | None = None
        self._estimate: float | None = None

    def _read(self) -> tuple[CpuSample, int | None] | None:
        try:
            text = self.stat_path.read_text()
            busy_s, running = read_proc_stat(text, self.cpus, self.ticks_per_s)
        except (OSError, ValueError):
            return None
        return CpuSample(time.monotonic(), busy_s, time.process_time()), running

    def others_busy(self) -> float | None:
        """Cores other processes kept busy over the window since the previous reading (at least
        :data:`MIN_WINDOW_S` long; a sooner call returns the previous figure), or before any
        window, runnable tasks other than this thread right now; None when unknown."""
        reading = self._read()
        if reading is None:
            return None
        sample, running = reading
        if self._last is None:
            self._last = sample
            self._estimate = None if running is None else float(max(0, running - 1))
        elif sample.wall_s - self._last.wall_s >= MIN_WINDOW_S:
            self._estimate = others_busy_cores(self._last, sample)
            self._last = sample
        return self._estimate

    def free_cores(self) -> float | None:
        """The watched CPUs minus :meth:`others_busy` (None when unknown).  With a cgroup quota
        smaller than the watched CPUs the caller caps it at the quota: this counts the host's
        other processes, not those sharing the quota."""
        others = self.others_busy()
        if others is None:
            return None
        watched = len(self.cpus) if self.cpus is not None else (os.cpu_count() or 1)
        return max(0.0, watched - others)


_MONITOR: dict[int, CpuLoadMonitor] = {}


def process_monitor() -> CpuLoadMonitor:
    """This process's monitor (a forked child gets its own: the key is the process id)."""
    pid = os.getpid()
    monitor = _MONITOR.get(pid)
    if monitor is None:
        _MONITOR.clear()
        monitor = _MONITOR[pid] = CpuLoadMonitor()
    return monitor
