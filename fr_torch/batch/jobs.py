"""``fr batch``: calibrate many images into a resumable Parquet dataset, embedded or on Ray Data.

Usage::

    fr batch photos/ --out results.parquet --fast                   # one process, no Ray needed
    fr batch manifest.csv --out results.parquet --engine ray --workers 8
    fr batch 's3://bucket/cams/**/*.jpg' --out results.parquet --engine ray --address auto

Input (:func:`fr_torch.batch.inputs.collect_inputs`): folders (searched recursively for image suffixes), globs, single
files, or manifests (``.csv`` / ``.parquet`` / ``.txt``) with one image path per row.  A manifest's
path column is ``image`` (or ``path``, or the first column); its other columns (camera id, ...) are
carried through to the output; a ``focal_px`` column is the known focal length in pixels of that
row (empty / NaN = unknown) and comes back as ``known_focal_px``.  Paths with a scheme
(``s3://``, ``gs://``, ``https://``...) are read with fsspec when its filesystem package is
installed.

Output (:func:`fr_torch.batch.table.result_schema`): a folder of Parquet part files, one row per input image with the
fields of ``fr calibrate``'s JSON (:meth:`CalibrationResult.to_json`): rotation and vanishing points
are 3 x 3 nested list columns (world->camera R; row i of ``vanishing_points`` = homogeneous VP i;
null for a failed image), ``cues`` / ``predicted_error`` / ``runtime_s`` are struct columns, and a failed image is a row
with ``ok = false`` and a ``reason`` -- an image is never missing.  Non-finite numbers are stored as
null, never NaN.  Read it with ``pandas.read_parquet(OUT)``, ``duckdb.sql("FROM 'OUT/*.parquet'")``
or ``ray.data.read_parquet(OUT)``.

Resume: each finished batch is written as its own part file (written to a hidden temporary name
and renamed, so a part is either complete or absent); a re-run with the same ``--out`` reads the
``image`` column of the existing parts and skips those images, so an interrupted job loses at most
the batches in flight.  CTRL-C and SIGTERM stop taking work, write the finished batches (with
``rows_per_part``, those gathered so far), drop the batches in flight and stop the worker
processes; after SIGKILL the workers end by themselves (:mod:`fr_torch.runtime.workers`).

Engines: ``local`` runs :meth:`FREstimator.calibrate_images` on batches on this machine (Ray is
never imported): on a CPU in single-threaded worker processes, one per core (:func:`_run_local`),
on a GPU in this process while worker processes decode and detect ahead of it; ``ray``
(:mod:`fr_torch.batch.ray`) runs the same per-batch function (:meth:`fr_torch.batch.worker.BatchWorker.calibrate_rows`) in a Ray
Data actor pool, one estimator per actor, and this process writes the parts.  Both produce the
same columns.

Crash injection (tests only): ``FR_BATCH_CRASH=NAME:MARKER`` makes the worker that is about to
process an image whose path ends with ``NAME`` exit hard (``os._exit(1)``) once -- the first to
create the file ``MARKER``.  ``FR_BATCH_STALL=NAME:SECONDS`` makes it sleep that long first (a
batch that stays in flight; set before the command starts: the workers read it).
"""
from __future__ import annotations

import os
import sys
import time
from pathlib import Path
from typing import Any, Iterable, Sequence

import pyarrow as pa
from tqdm import tqdm

from fr_torch.batch.inputs import collect_inputs, extra_columns
from fr_torch.batch.ray import run_ray
from fr_torch.batch.shared import run_shared_groups, shared_groups
from fr_torch.batch.table import PartWriter, records_to_table
from fr_torch.batch.worker import CRASH_ENV, BatchWorker, _failed, options_device
from fr_torch.redaction import redact_text, redact_url
from fr_torch.runtime.device import DevicePolicy
from fr_torch.runtime.pipeline import crash_reason, ordered_pool_map


def run_batch(inputs: Sequence[str], out: str | Path, options: dict[str, Any], engine: str = "local",
              workers: int | None = None, batch_size: int | None = None, address: str | None = None,
              progress: bool = True, threads_per_worker: int | None = None, gpus_per_worker: float | None = None,
              rows_per_part: int = 0, shared_focal_by: str | None = None) -> dict[str, Any]:
    """Calibrate every image of ``inputs`` not yet in ``out``; returns a summary dict
    (``total``, ``skipped``, ``processed``, ``failed``, ``seconds``, ``images_per_s``).

    ``workers``: local engine on a CPU: worker processes (None = one per core, up to 8, for 32+
    images each; 1 = this process, one thread; see :func:`_run_local`), on a GPU: decode + detection
    processes feeding this process's search (0 = none); ray engine: actors (None = the cluster's
    CPUs / ``threads_per_worker``).
    ``batch_size``: images per batch and per part file (None = the device's
    :attr:`~fr_torch.runtime.device.DevicePolicy.default_batch_size`: 16 on a CPU, 256 on a GPU).
    ``summary["failed_images"]``: the images of this run that failed (each also one line on stderr).
    ``rows_per_part``: 0 = one part file per batch (an interruption loses only the batches in
    flight); N = gather finished batches into parts of at least N rows (fewer files for millions
    of images; a hard kill loses up to N rows, CTRL-C writes what is finished).
    ``shared_focal_by``: a manifest column; the rows of each of its values share one focal length
    (:mod:`fr_torch.batch.shared`; either engine).
    """

    device = options_device(options)
    # Local: this machine runs the search.  Ray: the actors resolve the device on their nodes.
    policy = DevicePolicy.resolve(device) if engine == "local" else DevicePolicy.parse(device)
    batch_size = policy.default_batch_size if batch_size is None else batch_size
    if batch_size < 1:
        raise ValueError("--batch-size must be at least 1")
    on_gpu = engine == "local" and not policy.on_cpu
    if workers is not None and workers < (0 if on_gpu else 1):
        raise ValueError("--workers must be at least 1"
                         + (" (0 on a GPU: no detection processes)" if on_gpu else ""))
    rows = collect_inputs(inputs)
    writer = PartWriter(out)
    writer.cleanup()
    done = writer.done_images()
    todo = [row for row in rows if redact_url(str(row["image"])) not in done]  # the parts hold redacted URLs
    extras = extra_columns(rows)
    summary = {"total": len(rows), "skipped": len(rows) - len(todo), "processed": 0, "failed": 0, "failed_images": [],
               "engine": engine, "workers": workers, "batch_size": batch_size}
    start = time.perf_counter()
    pending: list = []

    def flush():
        if pending:
            writer.write(pa.concat_tables(pending))
            pending.clear()

    bar = tqdm(total=len(todo), unit="img", desc="fr batch", smoothing=0.1,
               disable=not progress or not todo or not sys.stderr.isatty(),
               file=sys.stderr)
    try:
        if todo:
            if shared_focal_by and engine == "local":
                tables = run_shared_groups(todo, options, extras, shared_focal_by)
            elif shared_focal_by and engine == "ray":
                tables = run_ray(todo, options, extras, batch_size, workers, address=address,
                                 threads_per_worker=threads_per_worker, gpus_per_worker=gpus_per_worker,
                                 groups=shared_groups(todo, options, shared_focal_by))
            elif engine == "local":
                tables = _run_local(todo, options, extras, batch_size, workers, policy)
            elif engine == "ray":

                tables = run_ray(todo, options, extras, batch_size, workers, address=address,
                                 threads_per_worker=threads_per_worker, gpus_per_worker=gpus_per_worker)
            else:
                raise ValueError(f"unknown engine {engine!r} (local or ray)")
            for table in tables:
                if table.num_rows == 0:
                    continue
                pending.append(table)
                if sum(t.num_rows for t in pending) >= rows_per_part:
                    flush()
                summary["processed"] += table.num_rows
                for image, ok, reason in zip(*(table.column(k).to_pylist() for k in ("image", "ok", "reason"))):
                    if not ok:  # one line per failed image, named (the row's image and reason are redacted)
                        summary["failed"] += 1
                        summary["failed_images"].append(image)
                        bar.write(redact_text(f"fr batch: failed: {image}: {reason}"), file=sys.stderr)
                bar.update(table.num_rows)
    except KeyboardInterrupt as interrupt:  # CTRL-C, SIGTERM: what the command's one-line report adds
        interrupt.add_note(f"{summary['skipped'] + summary['processed']} of {summary['total']} images are in "
                           f"{out}; the same command again does the rest")
        raise
    finally:
        flush()
        bar.close()
    seconds = time.perf_counter() - start
    summary["seconds"] = seconds
    summary["images_per_s"] = summary["processed"] / seconds if seconds > 0 and summary["processed"] else 0.0
    return summary


def _run_local(rows: Sequence[dict], options, extras, batch_size: int, workers: int | None,
               policy: DevicePolicy) -> Iterable:
    """Arrow tables of at most ``batch_size`` rows, in input order, for the local engine.

    CPU: ``workers`` >= 2 single-threaded worker processes, one :class:`BatchWorker` each (None =
    :meth:`~fr_torch.runtime.device.DevicePolicy.default_workers`: one per core, up to 8, for 32+ images each); 1 =
    this process with one thread (a default of no workers: torch's threads).  GPU: this process
    searches while ``workers`` processes decode and detect (None = ``default_workers``: every core
    but one, up to 16; :meth:`BatchWorker.calibrate_rows_pipelined`).  A worker that dies fails
    only the image it was on.
    """
    if workers is None:
        workers = policy.default_workers(len(rows))
    if not policy.whole_image_workers:
        yield from BatchWorker(options, extras).calibrate_rows_pipelined(rows, batch_size, workers)
        return
    if workers < 2:
        worker = BatchWorker(options, extras, threads=workers or None)
        for begin in range(0, len(rows), batch_size):
            yield worker.calibrate_rows(rows[begin:begin + batch_size])
        return

    rows = list(rows)
    crash = os.environ.get(CRASH_ENV)  # tests: read here, the workers' fork server may predate it
    one_row_tables = ordered_pool_map(_calibrate_rows_task, rows, batch_size, workers, _init_batch_worker,
                                      (options, extras, crash), _CrashedRow(extras))
    try:
        for begin in range(0, len(rows), batch_size):
            count = min(batch_size, len(rows) - begin)
            yield pa.concat_tables([next(one_row_tables) for _ in range(count)])
    finally:  # stop the pool now when the caller stops early (CTRL-C, an error writing a part)
        one_row_tables.close()


_BATCH_WORKER: dict = {}


def _init_batch_worker(options, extras, crash) -> None:
    _BATCH_WORKER["worker"] = BatchWorker(options, extras, threads=1, crash=crash or "")


def _calibrate_rows_task(rows):
    """In a worker process: one one-row table per row (so a crash retry can regroup them)."""
    table = _BATCH_WORKER["worker"].calibrate_rows(rows)
    return [table.slice(i, 1) for i in range(table.num_rows)]


class _CrashedRow:
    """The output row of an input row whose worker process died on it."""

    def __init__(self, extras):
        self.extras = extras

    def __call__(self, row):
        name = str(row["image"])
        return records_to_table([_failed(name, crash_reason(name)).to_json()], [row], self.extras)


# ---------------------------------------------------------------------------------------- CLI


