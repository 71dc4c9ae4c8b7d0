"""The Ray Data engine of ``fr batch`` (``--engine ray``; needs ``pip install 'fr-torch[ray]'``).

The file list becomes a Ray dataset (``ray.data.from_items``); ``map_batches`` runs
:class:`fr_torch.batch.worker.BatchWorker` in an actor pool of ``workers`` actors, one ``FREstimator`` each
(``num_gpus`` per actor with ``--device cuda``).  Actors that die are restarted and their batches
retried by Ray (``max_restarts`` / ``max_task_retries``), so every image comes back exactly once.
Output blocks stream back to the calling process, which writes them as Parquet parts (see
:class:`fr_torch.batch.table.PartWriter`) -- the rows are small (no segments), and one writer keeps the
resume bookkeeping in one place.
"""
from __future__ import annotations

import logging
import os
import pickle
from typing import Any, Iterator, Sequence

import pyarrow as pa

from fr_torch.batch.shared import calibrate_group
from fr_torch.batch.worker import CRASH_ENV, BatchWorker, options_device
from fr_torch.runtime.device import THREADS_ENV, DevicePolicy
from fr_torch.runtime.workers import keep_signal_handler


class RayBatchWorker(BatchWorker):
    """A :class:`BatchWorker` fed by Ray Data: each input row carries its manifest row pickled in
    the ``row`` column (so manifest columns of any type survive Ray's block format)."""

    def __call__(self, batch):
        rows = [pickle.loads(blob) for blob in batch.column("row").to_pylist()]
        return self.calibrate_rows(rows)


class RayGroupWorker(BatchWorker):
    """A :class:`BatchWorker` that calibrates whole groups with a shared focal length
    (:func:`fr_torch.batch.shared.calibrate_group`): each item's ``group`` column holds one group's
    manifest rows, pickled."""

    def __call__(self, batch):
        groups = [pickle.loads(blob) for blob in batch.column("group").to_pylist()]
        return pa.concat_tables([calibrate_group(self, rows) for rows in groups])


def init_ray(address: str | None, num_cpus: int | None):
    """Join ``address`` (or ``$RAY_ADDRESS``), else start a quiet local cluster with ``num_cpus``;
    ``$FR_THREADS``, when set, goes to every actor.  Returns True when this call started Ray (the
    caller then shuts it down).  A SIGTERM handler set by the caller stays in place (Ray's own
    would exit at once); either way the caller's ``ray.shutdown()`` or Ray's exit handler stops a
    local cluster this call started."""
    try:
        import ray
    except ImportError:
        raise ValueError("--engine ray needs Ray: pip install 'fr-torch[ray]' (or 'ray[data]')") from None
    if ray.is_initialized():
        return False
    address = address or os.environ.get("RAY_ADDRESS") or None
    quiet = dict(logging_level=logging.WARNING, configure_logging=True, log_to_driver=True)
    if THREADS_ENV in os.environ:  # the actors' thread policy (DevicePolicy.threads), on every node
        quiet["runtime_env"] = {"env_vars": {THREADS_ENV: os.environ[THREADS_ENV]}}
    with keep_signal_handler():  # a command's SIGTERM handling (ray.init sets sys.exit)
        if address:
            ray.init(address=address, **quiet)
        else:
            ray.init(num_cpus=num_cpus, include_dashboard=False, **quiet)
    return True


def run_ray(rows: Sequence[dict[str, Any]], options: dict[str, Any], extras, batch_size: int, workers: int | None,
            address: str | None = None, threads_per_worker: int | None = None,
            gpus_per_worker: float | None = None, groups: Sequence[Sequence[dict[str, Any]]] | None = None
            ) -> Iterator:
    """Yield one Arrow table per finished batch (in completion order), computed by Ray Data.

    ``groups``: instead of batches of ``batch_size`` rows, each group of rows is one item, searched
    with a shared focal length by one actor (``fr batch --shared-focal-by``; ``rows`` is then unused).
    """
    threads = threads_per_worker or 1
    started = init_ray(address, num_cpus=workers * threads if workers else None)
    import ray

    if not workers:
        workers = max(1, int(ray.cluster_resources().get("CPU", 1)) // threads)

    try:
        context = ray.data.DataContext.get_current()
        context.enable_progress_bars = False  # fr batch shows its own bar
        if hasattr(context, "print_on_execution_start"):
            context.print_on_execution_start = False
        logging.getLogger("ray.data").setLevel(logging.ERROR)
        gpus = 0.0
        if not DevicePolicy.parse(options_device(options)).on_cpu:
            gpus = 1.0 if gpus_per_worker is None else float(gpus_per_worker)
        if groups is not None:
            items = [{"image": str(group[0]["image"]), "group": pickle.dumps(list(group))} for group in groups]
            worker_class, batch_size = RayGroupWorker, 1
        else:
            items = [{"image": str(row["image"]), "row": pickle.dumps(row)} for row in rows]
            worker_class = RayBatchWorker
        dataset = ray.data.from_items(items)
        results = dataset.map_batches(
            worker_class, batch_size=batch_size, batch_format="pyarrow",
            compute=ray.data.ActorPoolStrategy(size=workers), num_cpus=threads, num_gpus=gpus,
            fn_constructor_kwargs={"options": options, "extras": extras, "threads": threads,
                                   "crash": os.environ.get(CRASH_ENV)})
        # Ray Data gives pool actors max_restarts=-1 and max_task_retries=-1 by default: a dead actor
        # is restarted and its in-flight batches are retried (tests/test_batch.py checks it).
        for table in results.iter_batches(batch_size=None, batch_format="pyarrow", prefetch_batches=2):
            yield table
    finally:
        if started:
            ray.shutdown()
