"""The machine a measurement ran on (CPU model, cores, torch, threads, device, load), recorded beside
every timing: on a shared machine timings are noisy, so runs compare only on the same machine; and
what its processes hold (``/proc``: a process's memory, the processes of a session)."""
from __future__ import annotations

import os
import platform
from pathlib import Path

from fr_torch.runtime.workers import usable_cores


def cpu_model() -> str:
    """The CPU's model name (``/proc/cpuinfo``; the platform's name where it is missing)."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def machine_description(device: str) -> dict:
    """The record of the machine a measurement ran on: CPU model, cores (all and usable), torch
    version and threads, ``FR_THREADS``, ``device`` (and its GPU's name), Python, platform, load average,
    and oneMKL's code branch (:func:`fr_torch.core.likelihood.native.mkl_branch`: machines on other
    branches give other bits)."""
    import torch

    from fr_torch.core.likelihood.native import mkl_branch

    info = {"cpu": cpu_model(), "cores": os.cpu_count(), "usable_cores": usable_cores(), "torch": torch.__version__,
            "threads": torch.get_num_threads(), "fr_threads": os.environ.get("FR_THREADS", "auto"), "device": device, "python": platform.python_version(),
            "platform": platform.platform(), "mkl_branch": mkl_branch()}
    try:
        info["load_average"] = [round(x, 2) for x in os.getloadavg()]
    except OSError:
        pass
    if device.startswith("cuda"):
        try:
            info["gpu"] = torch.cuda.get_device_name(device)
        except (AssertionError, RuntimeError):  # no CUDA here: the record says so instead of failing
            info["gpu"] = "none available"
    return info


def proc_status_kb(key: str, pid: int | str = "self") -> int | None:
    """A ``/proc/PID/status`` size field in KiB (``VmRSS``, ``VmHWM``, ...); None where it cannot
    be read (no /proc, the process gone)."""
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith(key + ":"):
                return int(line.split()[1])
    except (OSError, ValueError):
        pass
    return None


def session_processes(session: int) -> list[int]:
    """Live (not zombie) processes of the session ``session`` other than its leader, from /proc: a
    command started as its own session (``start_new_session``) keeps every process it started in
    it, orphans included."""
    found = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit() or int(entry.name) == session:
            continue
        try:
            stat = (entry / "stat").read_text()
        except OSError:  # gone meanwhile
            continue
        state, _ppid, _group, sid = stat[stat.rindex(")") + 2:].split()[:4]
        if int(sid) == session and state not in ("Z", "X"):
            found.append(int(entry.name))
    return found


def session_cpu_s(session: int) -> float:
    """CPU seconds (user + system) used so far by the leader of the session ``session`` and its
    live processes (:func:`session_processes`), from /proc (0 for a process gone)."""
    total = 0
    for pid in [session] + session_processes(session):
        try:
            fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
            total += int(fields[11]) + int(fields[12])  # utime, stime (clock ticks)
        except (OSError, IndexError, ValueError):
            pass
    return total / os.sysconf("SC_CLK_TCK")
