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
#: whose constructor imported it (it calls torch.optim's functional Adam: fr_torch.search._FusedAdam).
PRELOAD = ["__main__", "fr_torch.pipeline", "fr_torch.estimator"]


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


#: Images per worker below which a worker pool does not pay for its start-up (about a second).
MIN_IMAGES_PER_WORKER = 32
#: Default cap on worker processes (each holds its own torch, about 300 MB).
MAX_DEFAULT_WORKERS = 8
#: Default cap on detection workers feeding a GPU (each decodes + runs LSD at ~50 images/s on a
#: 640 x 480 photo, so a device searching ~1,000 images/s needs many of them).
MAX_DEFAULT_DETECTION_WORKERS = 16


def default_workers(images: int, device: str = "cpu") -> int:
    """A sensible ``workers`` for ``images`` images on ``device`` (``fr calibrate``'s default).

    CPU: one whole-image worker per usable core, at most :data:`MAX_DEFAULT_WORKERS` and at most
    one per :data:`MIN_IMAGES_PER_WORKER` images; 0 (in-process, with intra-op threads) on one
    core or for fewer images than that.  GPU: a detection worker on every core but the one of
    the process feeding the device (at most :data:`MAX_DEFAULT_DETECTION_WORKERS`; 0 on 1-2
    cores, where they compete with it) when there are at least two images: detection, not the
    device, is the bottleneck of a GPU pipeline.
    """
    cores = usable_cores()
    if str(device).startswith("cpu"):
        count = min(cores, MAX_DEFAULT_WORKERS, images // MIN_IMAGES_PER_WORKER)
        return count if count >= 2 else 0
    return 0 if cores <= 2 or images < 2 else min(cores - 1, MAX_DEFAULT_DETECTION_WORKERS)


#: Default ``--batch-size`` (images searched together) per device type: a GPU needs large batches
#: to fill it (issue 14: H100 Fast-fR 847 images/s at batch 256, 1,196 at 1024); on a CPU a
#: batch of 16 already amortises the per-call work and keeps the first results coming early.
DEFAULT_BATCH_SIZE = {"cpu": 16, "cuda": 256}


def default_batch_size(device: str = "cpu") -> int:
    """:data:`DEFAULT_BATCH_SIZE` of ``device``'s type (``cuda:1`` -> ``cuda``; unknown -> CPU's)."""
    return DEFAULT_BATCH_SIZE.get(str(device).split(":")[0], DEFAULT_BATCH_SIZE["cpu"])


def fit_threads_to_cores() -> None:
    """Cap torch's intra-op threads and OpenCV's threads at :func:`usable_cores` (the commands call
    this).  In a container both count the host's cores, not the CPUs the quota grants, and an
    OpenMP region with more threads than CPUs stalls on every op."""
    import cv2
    import torch

    cores = usable_cores()
    if torch.get_num_threads() > cores:
        torch.set_num_threads(cores)
    if cv2.getNumThreads() > cores:
        cv2.setNumThreads(cores)
