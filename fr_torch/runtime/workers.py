"""How worker processes start (imports no torch, so a command can start them before it loads it).

Workers are started with ``forkserver`` where available (else ``spawn``): no OpenMP state or lock
of the parent is inherited.  The fork server imports the library once (:data:`PRELOAD`) and every
worker is forked from it, already loaded, so a pool starts in milliseconds instead of each worker
importing torch (about a second and a half of CPU each).  :func:`start_worker_server` starts that
server ahead of time, e.g. while the command-line process is still importing torch itself.
"""
from __future__ import annotations

import math
import multiprocessing
import multiprocessing.forkserver
import os
from pathlib import Path

#: Modules the fork server imports once for all workers (``__main__`` as multiprocessing does).
#: Not ``torch._dynamo`` (1-2 s): the refinement no longer builds a ``torch.optim.Adam`` object,
#: whose constructor imported it (it calls torch.optim's functional Adam: fr_torch.core.search._FusedAdam).
PRELOAD = ["__main__", "fr_torch.runtime.pipeline", "fr_torch.runtime.estimator"]


def context() -> multiprocessing.context.BaseContext:
    """The multiprocessing context of every worker pool (forkserver, preloading :data:`PRELOAD`)."""
    if "forkserver" in multiprocessing.get_all_start_methods():
        ctx = multiprocessing.get_context("forkserver")
        ctx.set_forkserver_preload(PRELOAD)  # no effect once the server runs
        return ctx
    return multiprocessing.get_context("spawn")


def start_worker_server() -> None:
    """Start the fork server now (it loads the library in its own process, in parallel with the
    caller); a no-op where workers are spawned or the server already runs."""
    if context().get_start_method() == "forkserver":
        multiprocessing.forkserver.ensure_running()


def cgroup_cpu_limit(root: str | Path = "/sys/fs/cgroup") -> float | None:
    """CPUs granted by the cgroup CPU quota (a container's ``--cpus``), or None where there is no
    quota or no cgroup file (cgroup v2 ``cpu.max``, else v1 ``cpu/cpu.cfs_quota_us`` / ``_period_us``)."""
    root = Path(root)
    try:
        quota, period = (root / "cpu.max").read_text().split()[:2]
        return None if quota == "max" else int(quota) / int(period)
    except (OSError, ValueError):
        pass
    try:
        quota = int((root / "cpu" / "cpu.cfs_quota_us").read_text())
        period = int((root / "cpu" / "cpu.cfs_period_us").read_text())
    except (OSError, ValueError):
        return None
    return quota / period if quota > 0 and period > 0 else None


def usable_cores() -> int:
    """CPU cores this process may use: its affinity mask (else all cores), capped by the cgroup CPU
    quota (in a container with ``--cpus 2`` on a 64-core host that is 2, not 64)."""
    try:
        cores = len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        cores = os.cpu_count() or 1
    limit = cgroup_cpu_limit()
    return max(1, min(cores, math.ceil(limit))) if limit else cores
