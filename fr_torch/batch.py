"""``fr batch``: calibrate many images into a resumable Parquet dataset, embedded or on Ray Data.

Usage::

    fr batch photos/ --out results.parquet --fast                   # one process, no Ray needed
    fr batch manifest.csv --out results.parquet --engine ray --workers 8
    fr batch 's3://bucket/cams/**/*.jpg' --out results.parquet --engine ray --address auto

Input (:func:`collect_inputs`): folders (searched recursively for image suffixes), globs, single
files, or manifests (``.csv`` / ``.parquet`` / ``.txt``) with one image path per row.  A manifest's
path column is ``image`` (or ``path``, or the first column); its other columns (camera id, ...) are
carried through to the output; a ``focal_px`` column is the known focal length in pixels of that
row (empty / NaN = unknown) and comes back as ``known_focal_px``.  Paths with a scheme
(``s3://``, ``gs://``, ``https://``...) are read with fsspec when its filesystem package is
installed.

Output (:data:`RESULT_SCHEMA`): a folder of Parquet part files, one row per input image with the
fields of ``fr calibrate``'s JSON (:meth:`CalibrationResult.to_json`): rotation and vanishing points
are 3 x 3 nested list columns (world->camera R; row i of ``vanishing_points`` = homogeneous VP i;
null for a failed image), ``cues`` / ``predicted_error`` / ``runtime_s`` are struct columns, and a failed image is a row
with ``ok = false`` and a ``reason`` -- an image is never missing.  Non-finite numbers are stored as
null, never NaN.  Read it with ``pandas.read_parquet(OUT)``, ``duckdb.sql("FROM 'OUT/*.parquet'")``
or ``ray.data.read_parquet(OUT)``.

Resume: each finished batch is written as its own part file (written to a hidden temporary name
and renamed, so a part is either complete or absent); a re-run with the same ``--out`` reads the
``image`` column of the existing parts and skips those images, so an interrupted job loses at most
the batches in flight.

Engines: ``local`` runs :meth:`FREstimator.calibrate_images` on batches on this machine (Ray is
never imported): on a CPU in single-threaded worker processes, one per core (:func:`_run_local`),
on a GPU in this process while worker processes decode and detect ahead of it; ``ray``
(:mod:`fr_torch.batch_ray`) runs the same per-batch function (:func:`calibrate_rows`) in a Ray
Data actor pool, one estimator per actor, and this process writes the parts.  Both produce the
same columns.

Crash injection (tests only): ``FR_BATCH_CRASH=NAME:MARKER`` makes the worker that is about to
process an image whose path ends with ``NAME`` exit hard (``os._exit(1)``) once -- the first to
create the file ``MARKER``.
"""
from __future__ import annotations

import argparse
import glob as globlib
import math
import os
import sys
import time
import uuid
from pathlib import Path
from typing import Any, Iterable, Sequence

import numpy as np

from .reliability import CUE_NAMES, TARGETS

IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png", ".bmp", ".tif", ".tiff", ".webp", ".pgm", ".ppm", ".jp2")
MANIFEST_SUFFIXES = (".csv", ".parquet", ".pq", ".txt")
PATH_COLUMNS = ("image", "path", "file", "filename")
CRASH_ENV = "FR_BATCH_CRASH"

# Keys of the dict-valued result fields (struct columns); unknown keys are dropped.
RUNTIME_KEYS = ("detect", "grid", "refine", "cues", "total")
FLOAT_FIELDS = ("focal_px", "hfov_deg", "pan_deg", "tilt_deg", "roll_deg", "pitch_deg", "log_likelihood",
                "manhattan_fraction")


def result_schema():
    """The Arrow schema of the output rows (without carried-through manifest columns).

    Units as in :class:`fr_torch.estimator.CalibrationResult`: pixels, degrees, seconds.
    """
    import pyarrow as pa

    f64 = pa.float64()
    # Variable-size lists, not fixed-size ones: a failed image stores null there, and pyarrow
    # before 26 cannot read a null fixed-size list back from Parquet (apache/arrow GH-35692: the
    # whole part file fails to load).  Shapes are checked on the way in (:func:`records_to_table`).
    mat3 = pa.list_(pa.list_(f64))
    return pa.schema([
        ("image", pa.string()), ("width", pa.int32()), ("height", pa.int32()),
        ("ok", pa.bool_()), ("reliable", pa.bool_()), ("reason", pa.string()),
        ("focal_px", f64), ("hfov_deg", f64), ("principal_point", pa.list_(f64)),
        ("rotation", mat3), ("vertical_axis", pa.int8()),
        ("pan_deg", f64), ("tilt_deg", f64), ("roll_deg", f64), ("pitch_deg", f64),
        ("vanishing_points", mat3), ("log_likelihood", f64), ("num_segments", pa.int32()),
        ("manhattan_fraction", f64), ("segments_per_family", pa.list_(pa.int32())),
        ("cues", pa.struct([(k, f64) for k in CUE_NAMES])),
        ("predicted_error", pa.struct([(k, f64) for k in TARGETS])),
        ("runtime_s", pa.struct([(k, f64) for k in RUNTIME_KEYS])),
    ])


# ---------------------------------------------------------------------------------------- input


def has_scheme(path: str) -> bool:
    """True for URIs such as ``s3://b/k.jpg`` (read with fsspec); False for local paths."""
    head, sep, _ = str(path).partition("://")
    return bool(sep) and head.isidentifier() and len(head) > 1 and head != "file"


def _strip_file_scheme(path: str) -> str:
    return path[len("file://"):] if path.startswith("file://") else path


def _fsspec_fs(uri: str):
    try:
        import fsspec
    except ImportError:
        raise ValueError(f"{uri}: reading URIs needs fsspec (pip install fsspec and the filesystem package)") from None
    try:
        return fsspec.core.url_to_fs(uri)
    except (ImportError, ValueError) as exc:
        raise ValueError(f"{uri}: cannot open this filesystem ({exc})") from None


def _is_image(name: str) -> bool:
    return name.lower().endswith(IMAGE_SUFFIXES)


def _read_manifest(path: str) -> list[dict[str, Any]]:
    """Rows of a manifest file: dicts with ``image`` plus the manifest's other columns."""
    import pandas as pd

    lower = path.lower()
    if lower.endswith(".txt"):
        opener = _fsspec_fs(path)[0].open if has_scheme(path) else open
        with opener(path, "r") as handle:
            lines = [line.strip() for line in handle]
        return [{"image": line} for line in lines if line and not line.startswith("#")]
    frame = pd.read_parquet(path) if lower.endswith((".parquet", ".pq")) else pd.read_csv(path)
    if frame.empty:
        return []
    column = next((c for c in PATH_COLUMNS if c in frame.columns), frame.columns[0])
    frame = frame.rename(columns={column: "image"})
    frame["image"] = frame["image"].astype(str)
    # Paths relative to the manifest's folder (local manifests only).
    base = os.path.dirname(path)
    if base and not has_scheme(path):
        frame["image"] = [p if has_scheme(p) or os.path.isabs(p) else os.path.join(base, p) for p in frame["image"]]
    frame = frame.astype(object).where(frame.notna(), None)  # missing cells -> None, not NaN
    return frame.to_dict("records")


def collect_inputs(inputs: Sequence[str]) -> list[dict[str, Any]]:
    """Expand folders, globs, files and manifests into rows ``{"image": path, <manifest columns>}``.

    Order: inputs in the order given; within a folder or glob, sorted.  Duplicate paths are kept
    once (the first row wins).  A path that does not exist is kept (it becomes a failed row); a
    glob or folder that matches nothing raises ValueError.
    """
    rows: list[dict[str, Any]] = []
    for raw in inputs:
        item = _strip_file_scheme(str(raw))
        remote = has_scheme(item)
        if item.lower().endswith(MANIFEST_SUFFIXES):
            rows += _read_manifest(item)
            continue
        if remote:
            fs, root = _fsspec_fs(item)
            protocol = item.split("://", 1)[0]
            if any(ch in item for ch in "*?["):
                found = [p for p in fs.glob(root) if _is_image(p)]
            elif fs.isdir(root):
                found = [p for p in fs.find(root) if _is_image(p)]
            else:
                rows.append({"image": item})
                continue
            if not found:
                raise ValueError(f"{item}: no images found")
            rows += [{"image": f"{protocol}://{p}" if "://" not in p else p} for p in sorted(found)]
            continue
        if os.path.isdir(item):
            found = sorted(str(p) for p in Path(item).rglob("*") if p.is_file() and _is_image(p.name))
            if not found:
                raise ValueError(f"{item}: no images found in this folder")
            rows += [{"image": p} for p in found]
        elif any(ch in item for ch in "*?[") and not os.path.exists(item):
            found = sorted(p for p in globlib.glob(item, recursive=True) if os.path.isfile(p))
            if not found:
                raise ValueError(f"{item}: the pattern matches no file")
            rows += [{"image": p} for p in found]
        else:
            rows.append({"image": item})
    seen, unique = set(), []
    for row in rows:
        if row["image"] not in seen:
            seen.add(row["image"])
            unique.append(row)
    return unique


def extra_columns(rows: Sequence[dict[str, Any]]):
    """Arrow fields of the manifest columns carried through (``focal_px`` -> ``known_focal_px``;
    a name that clashes with a result field gets the prefix ``input_``)."""
    import pyarrow as pa

    names = [k for k in dict.fromkeys(k for row in rows for k in row) if k != "image"]
    if not names:
        return []
    table = pa.Table.from_pylist([{k: row.get(k) for k in names} for row in rows])
    reserved = set(result_schema().names)
    fields = []
    for field in table.schema:
        target = output_column_name(field.name, reserved)
        kind = pa.float64() if field.name == "focal_px" else (pa.string() if pa.types.is_null(field.type) else field.type)
        fields.append((field.name, target, kind))
    return fields


def output_column_name(name: str, reserved: set[str]) -> str:
    if name == "focal_px":
        return "known_focal_px"
    return f"input_{name}" if name in reserved else name


# ---------------------------------------------------------------------------------------- work


def estimator_options(args: argparse.Namespace) -> dict[str, Any]:
    """Picklable options from the CLI arguments (shipped to every worker): ``estimator`` = the
    FREstimator keyword arguments of the shared estimator options (:mod:`fr_torch.options`), plus
    the known focal length / principal point for all images and whether reliability is on."""
    from .options import camera_options, estimator_kwargs

    focal, pp = camera_options(args)
    return {"estimator": estimator_kwargs(args), "principal_point": pp, "focal_px": focal,
            "reliability": not getattr(args, "no_reliability", False)}


def options_device(options: dict[str, Any]) -> str:
    """The estimator's device name in ``options`` (from :func:`estimator_options`; default cpu)."""
    return str(options["estimator"].get("device", "cpu"))


class BatchWorker:
    """Holds one estimator; :meth:`__call__` turns a batch of input rows into an Arrow table.

    This is the unit of work of both engines (a Ray Data actor is one ``BatchWorker``).
    ``options``: from :func:`estimator_options`; ``extras``: from :func:`extra_columns`;
    ``threads``: torch intra-op and OpenCV threads (None = leave as is).
    """

    def __init__(self, options: dict[str, Any], extras=(), threads: int | None = None, crash: str | None = None):
        import torch

        from .estimator import FREstimator
        if threads:  # torch and OpenCV: oversubscribed threads stall on a loaded machine
            import cv2

            torch.set_num_threads(int(threads))
            cv2.setNumThreads(int(threads))
        self.options = dict(options)
        self.estimator = FREstimator(**options["estimator"],
                                     reliability="default" if options.get("reliability", True) else None)
        self.extras = list(extras)
        self.crash = crash if crash is not None else os.environ.get(CRASH_ENV)

    def __call__(self, batch):
        """Ray Data entry point: ``batch`` is a ``pyarrow.Table`` of input rows."""
        return self.calibrate_rows(batch.to_pylist())

    def calibrate_rows(self, rows: Sequence[dict[str, Any]]):
        """Calibrate the images of ``rows`` (dicts with ``image`` and manifest columns) -> Arrow table,
        one output row per input row, in order.  Never raises for a bad image."""
        self._maybe_crash(rows)
        names, focal = self._names_and_focal(rows)
        inputs, failed = self.read_inputs(names)
        try:
            results = self.estimator.calibrate_images(inputs, names=names, focal_px=focal,
                                                      principal_point=self.options.get("principal_point"))
        except Exception as exc:  # a bug or resource error must not lose the batch: fail its rows
            results = [_failed(name, f"calibration error: {type(exc).__name__}: {exc}") for name in names]
        for i, reason in failed.items():
            results[i] = _failed(names[i], reason)
        return records_to_table([result.to_json() for result in results], rows, self.extras)

    @staticmethod
    def read_inputs(names: Sequence[str]) -> tuple[list, dict[int, str]]:
        """(inputs for the estimator: local paths as they are, URIs read into arrays; {row index:
        reason} for URIs that could not be read, whose input is a 1 x 1 placeholder)."""
        inputs, failed = [], {}
        for i, name in enumerate(names):
            if has_scheme(name):
                try:
                    inputs.append(read_remote_image(name))
                except Exception as exc:  # any fsspec / network / decode error -> failed row
                    failed[i] = f"{name}: cannot read ({type(exc).__name__}: {exc})"
                    inputs.append(np.zeros((1, 1), np.uint8))
            else:
                inputs.append(name)
        return inputs, failed

    def calibrate_rows_pipelined(self, rows: Sequence[dict[str, Any]], batch_size: int, workers: int):
        """Arrow tables of at most ``batch_size`` rows, in input order, like :meth:`calibrate_rows`
        on each batch, but ``workers`` processes decode and detect the next images while this
        process searches (:func:`fr_torch.pipeline.calibrate_paths` without whole-image workers:
        the way to feed a GPU).  Rows with a URI (fsspec) go through :meth:`calibrate_rows`.  If a
        search raises, the rest of the rows go through :meth:`calibrate_rows` batch by batch (a
        batch that raises again becomes failed rows); a worker that dies fails only its image."""
        from .pipeline import calibrate_paths

        rows = list(rows)
        if workers < 1 or any(has_scheme(str(row["image"])) for row in rows):
            for begin in range(0, len(rows), batch_size):
                yield self.calibrate_rows(rows[begin:begin + batch_size])
            return
        names, focal = self._names_and_focal(rows)
        done = 0
        try:
            batches = calibrate_paths(self.estimator, names, batch_size, workers, focal,
                                      self.options.get("principal_point"), names=names, whole_images=False)
            for chunk, results in batches:
                batch_rows = rows[done:done + len(chunk)]
                self._maybe_crash(batch_rows)
                table = records_to_table([result.to_json() for result in results], batch_rows, self.extras)
                done += len(chunk)
                yield table
        except Exception:  # a search error: the remaining rows in-process, failing only what fails again
            for begin in range(done, len(rows), batch_size):
                yield self.calibrate_rows(rows[begin:begin + batch_size])

    def _names_and_focal(self, rows: Sequence[dict[str, Any]]) -> tuple[list[str], list]:
        """Image names and per-row known focal lengths (a manifest's ``focal_px`` wins over ``--focal``)."""
        names = [str(row["image"]) for row in rows]
        default_focal = self.options.get("focal_px")
        focal = [_finite_or_none(row.get("focal_px")) for row in rows]
        return names, [default_focal if f is None else f for f in focal]

    def _maybe_crash(self, rows) -> None:
        if not self.crash or ":" not in self.crash:
            return
        name, marker = self.crash.split(":", 1)
        if any(str(row["image"]).endswith(name) for row in rows):
            try:
                fd = os.open(marker, os.O_CREAT | os.O_EXCL | os.O_WRONLY)
            except FileExistsError:
                return
            os.close(fd)
            os._exit(1)


def _failed(name: str, reason: str):
    from .estimator import CalibrationResult

    return CalibrationResult(image=name, width=0, height=0, ok=False, reason=reason)


def _finite_or_none(value):
    try:
        value = float(value)
    except (TypeError, ValueError):
        return None
    return value if math.isfinite(value) else None


def read_remote_image(uri: str) -> np.ndarray:
    """Read and decode an image at an fsspec URI -> 8-bit BGR (H, W, 3)."""
    import cv2

    from .segments import FRInputError, to_bgr8

    fs, path = _fsspec_fs(uri)
    with fs.open(path, "rb") as handle:
        data = np.frombuffer(handle.read(), np.uint8)
    if data.size == 0:
        raise FRInputError(f"{uri}: empty file")
    image = cv2.imdecode(data, cv2.IMREAD_UNCHANGED)
    if image is None:
        raise FRInputError(f"{uri}: not a readable image")
    return to_bgr8(image, uri)


def _clean_float(value):
    if value is None:
        return None
    value = float(value)
    return value if math.isfinite(value) else None


#: Shapes of the nested-list columns (any other shape, or a non-finite entry, is stored as null).
NESTED_SHAPES = {"rotation": (3, 3), "vanishing_points": (3, 3), "principal_point": (2,)}


def _clean_nested(value, shape: tuple[int, ...]):
    """``value`` as nested lists of floats when it has ``shape`` and is finite, else None."""
    if value is None:
        return None
    try:
        array = np.asarray(value, np.float64)
    except (TypeError, ValueError):
        return None
    if array.shape != shape or not np.isfinite(array).all():
        return None
    return array.tolist()


def records_to_table(records: Sequence[dict[str, Any]], rows: Sequence[dict[str, Any]], extras=()):
    """JSON records (``CalibrationResult.to_json``) + their input rows -> Arrow table of the output
    schema plus the carried manifest columns ``extras`` (from :func:`extra_columns`)."""
    import pyarrow as pa

    schema = result_schema()
    clean = []
    for record in records:
        out = {name: record.get(name) for name in schema.names}
        for key in FLOAT_FIELDS:
            out[key] = _clean_float(out[key])
        for key, shape in NESTED_SHAPES.items():
            out[key] = _clean_nested(out[key], shape)
        for key, keys in (("cues", CUE_NAMES), ("predicted_error", TARGETS), ("runtime_s", RUNTIME_KEYS)):
            value = out[key]
            out[key] = None if not value else {k: _clean_float(value.get(k)) for k in keys}
        clean.append(out)
    table = pa.Table.from_pylist(clean, schema=schema)
    for source, target, kind in extras:
        values = [row.get(source) for row in rows]
        if source == "focal_px":
            values = [_finite_or_none(v) for v in values]
        table = table.append_column(pa.field(target, kind), pa.array(values, type=kind, from_pandas=True))
    return table


# ---------------------------------------------------------------------------------------- output


class PartWriter:
    """Writes a Parquet dataset as one part file per batch, atomically (hidden temp file + rename).

    ``out``: the dataset folder (created).  Readers (pyarrow, pandas, DuckDB, Ray) ignore names
    starting with ``.`` or ``_``, so a half-written temp file is never read.
    """

    def __init__(self, out: str | Path):
        self.out = Path(out)
        if self.out.exists() and not self.out.is_dir():
            raise ValueError(f"{self.out}: exists and is not a folder (the output is a folder of Parquet parts)")
        self.out.mkdir(parents=True, exist_ok=True)
        self.run_id = time.strftime("%Y%m%dT%H%M%S") + "-" + uuid.uuid4().hex[:8]
        self.count = 0

    def done_images(self) -> set[str]:
        """``image`` values of the rows already written (resume)."""
        import pyarrow.parquet as pq

        done: set[str] = set()
        for part in sorted(self.out.glob("part-*.parquet")):
            try:
                done.update(pq.read_table(part, columns=["image"]).column("image").to_pylist())
            except Exception as exc:  # an unreadable part (should not happen: parts are atomic)
                print(f"fr batch: warning: ignoring unreadable part {part} ({exc})", file=sys.stderr)
        return done

    def write(self, table) -> Path:
        import pyarrow.parquet as pq

        self.count += 1
        final = self.out / f"part-{self.run_id}-{self.count:06d}.parquet"
        temp = self.out / f".{final.name}.tmp"
        pq.write_table(table, temp)
        os.replace(temp, final)
        return final

    def cleanup(self) -> None:
        """Remove temp files left by an interrupted run."""
        for temp in self.out.glob(".part-*.tmp"):
            try:
                temp.unlink()
            except OSError:
                pass


# ---------------------------------------------------------------------------------------- driver


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
    ``batch_size``: images per batch and per part file (None = :func:`fr_torch.workers.default_batch_size`
    of the device: 16 on a CPU, 256 on a GPU, where a large batch costs about as much as a small one).
    ``rows_per_part``: 0 = one part file per batch (an interruption loses only the batches in
    flight); N = gather finished batches into parts of at least N rows (fewer files for millions
    of images; a hard kill loses up to N rows, CTRL-C writes what is finished).
    ``shared_focal_by``: a manifest column; the rows of each of its values share one focal length
    (:mod:`fr_torch.batch_shared`; local engine only).
    """
    import pyarrow as pa

    from tqdm import tqdm

    from .workers import default_batch_size

    device = options_device(options)
    batch_size = default_batch_size(device) if batch_size is None else batch_size
    if batch_size < 1:
        raise ValueError("--batch-size must be at least 1")
    on_gpu = engine == "local" and not device.startswith("cpu")
    if workers is not None and workers < (0 if on_gpu else 1):
        raise ValueError("--workers must be at least 1"
                         + (" (0 on a GPU: no detection processes)" if on_gpu else ""))
    rows = collect_inputs(inputs)
    writer = PartWriter(out)
    writer.cleanup()
    done = writer.done_images()
    todo = [row for row in rows if row["image"] not in done]
    extras = extra_columns(rows)
    summary = {"total": len(rows), "skipped": len(rows) - len(todo), "processed": 0, "failed": 0,
               "engine": engine, "workers": workers, "batch_size": batch_size}
    start = time.perf_counter()
    pending: list = []

    def flush():
        if pending:
            writer.write(pa.concat_tables(pending))
            pending.clear()

    bar = tqdm(total=len(todo), unit="img", desc="fr batch", disable=not progress or not todo, smoothing=0.1,
               file=sys.stderr)
    try:
        if todo:
            if shared_focal_by:
                from .batch_shared import run_shared_groups

                if engine != "local":
                    raise ValueError("--shared-focal-by runs on the local engine only (not yet on Ray)")
                tables = run_shared_groups(todo, options, extras, shared_focal_by)
            elif engine == "local":
                tables = _run_local(todo, options, extras, batch_size, workers)
            elif engine == "ray":
                from .batch_ray import run_ray

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
                summary["failed"] += table.num_rows - sum(table.column("ok").to_pylist())
                bar.update(table.num_rows)
    finally:
        flush()
        bar.close()
    seconds = time.perf_counter() - start
    summary["seconds"] = seconds
    summary["images_per_s"] = summary["processed"] / seconds if seconds > 0 and summary["processed"] else 0.0
    return summary


def _run_local(rows: Sequence[dict], options, extras, batch_size: int, workers: int | None) -> Iterable:
    """Arrow tables of at most ``batch_size`` rows, in input order, for the local engine.

    CPU: ``workers`` >= 2 single-threaded worker processes, one :class:`BatchWorker` each (None =
    :func:`fr_torch.workers.default_workers`: one per core, up to 8, for 32+ images each); 1 =
    this process with one thread (a default of no workers: torch's threads).  GPU: this process
    searches while ``workers`` processes decode and detect (None = ``default_workers``: every core
    but one, up to 16; :meth:`BatchWorker.calibrate_rows_pipelined`).  A worker that dies fails
    only the image it was on.
    """
    from .workers import default_workers

    device = options_device(options)
    on_cpu = device.startswith("cpu")
    if workers is None:
        workers = default_workers(len(rows), device)
    if not on_cpu:
        yield from BatchWorker(options, extras).calibrate_rows_pipelined(rows, batch_size, workers)
        return
    if workers < 2:
        worker = BatchWorker(options, extras, threads=workers or None)
        for begin in range(0, len(rows), batch_size):
            yield worker.calibrate_rows(rows[begin:begin + batch_size])
        return
    import pyarrow as pa

    from .pipeline import ordered_pool_map

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
        from .pipeline import crash_reason

        name = str(row["image"])
        return records_to_table([_failed(name, crash_reason(name)).to_json()], [row], self.extras)


# ---------------------------------------------------------------------------------------- CLI


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments of ``fr batch``."""
    parser.add_argument("inputs", nargs="+", metavar="INPUT",
                        help="folders (recursive), globs, image files or manifests (.csv/.parquet/.txt); "
                             "fsspec URIs (s3://...) when the filesystem package is installed")
    parser.add_argument("--out", required=True, type=Path, help="output Parquet dataset (a folder of part files)")
    parser.add_argument("--engine", choices=("local", "ray"), default="local",
                        help="local: this machine (default); ray: Ray Data actor pool (pip install 'fr-torch[ray]')")
    parser.add_argument("--workers", type=int, default=None,
                        help="ray: number of actors, one estimator each (default: the cluster's CPUs); "
                             "local on a CPU: single-threaded worker processes (default: one per core, up to 8, "
                             "for 32+ images each; 1 = this process), on a GPU: decode + detection processes "
                             "feeding the search (default: every core but one, up to 16; 0 = none)")
    parser.add_argument("--address", default=None,
                        help="ray: cluster to join (e.g. auto, ray://host:10001); default $RAY_ADDRESS, "
                             "else a local cluster (--workers CPUs, default all)")
    parser.add_argument("--threads-per-worker", type=int, default=None,
                        help="ray: CPUs (torch threads) per actor (default 1)")
    parser.add_argument("--gpus-per-worker", type=float, default=None,
                        help="ray with --device cuda: GPUs per actor (default 1; 0.5 puts two actors on a GPU)")
    parser.add_argument("--batch-size", type=int, default=None,
                        help="images per batch (= per part file; default 16 on a CPU, 256 on a GPU)")
    parser.add_argument("--rows-per-part", type=int, default=0, metavar="N",
                        help="gather batches into part files of at least N rows (default 0: one part per batch)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    parser.add_argument("--no-reliability", action="store_true",
                        help="do not add predicted errors (fR then skips the focal_profile_gap cue: about "
                             "twice the images per second)")
    # Estimator options, shared with `fr calibrate` and `fr track`.
    from .options import add_estimator_arguments

    add_estimator_arguments(parser)
    parser.add_argument("--focal", type=float, default=None, metavar="PX",
                        help="known focal length in pixels for all images (a manifest's focal_px column wins)")
    parser.add_argument("--pp", type=str, default=None, metavar="X,Y", help="principal point (default: centre)")
    parser.add_argument("--shared-focal-by", default=None, metavar="COLUMN",
                        help="manifest column (e.g. a camera id): the rows of each value share one focal length "
                             "(docs/shared-focal.md; local engine, groups searched in this process)")


def run(args: argparse.Namespace) -> int:
    """``fr batch``: prints a one-line summary; exit 0 even when some images failed (they are rows
    with ok=false), non-zero on a usage error."""
    on_cpu = str(args.device).startswith("cpu")
    if args.engine == "local" and (args.workers is None or args.workers > (1 if on_cpu else 0)):
        from .workers import start_worker_server

        start_worker_server()  # in case there are workers: they load the library while this process does
    try:
        import pyarrow  # noqa: F401
    except ImportError:
        raise ValueError("fr batch writes Parquet and needs pyarrow: pip install 'fr-torch[batch]'") from None
    options = estimator_options(args)
    if args.engine == "local":  # a device that cannot run is a one-line error before any work
        from .validate import resolve_device

        resolve_device(args.device)
    from .workers import fit_threads_to_cores

    fit_threads_to_cores()  # this process's threads (an explicit local --workers 1 still sets its own)
    summary = run_batch([str(p) for p in args.inputs], args.out, options, engine=args.engine,
                        workers=args.workers, batch_size=args.batch_size, address=args.address,
                        progress=not args.no_progress, threads_per_worker=args.threads_per_worker,
                        gpus_per_worker=args.gpus_per_worker, rows_per_part=args.rows_per_part,
                        shared_focal_by=getattr(args, "shared_focal_by", None))
    print(f"fr batch: {summary['total']} images, {summary['skipped']} already done, {summary['processed']} "
          f"processed ({summary['failed']} failed) in {summary['seconds']:.1f} s "
          f"({summary['images_per_s']:.1f} img/s) -> {args.out}", file=sys.stderr)
    return 0
