"""The per-batch work of ``fr batch``, the same for the local engine and for a Ray actor."""
from __future__ import annotations

import os
import time
from typing import Any, Sequence

import cv2
import numpy as np
import torch

from fr_torch.batch.inputs import has_scheme, read_remote_image
from fr_torch.batch.table import _finite_or_none, records_to_table, with_prior_columns
from fr_torch.core.result import CalibrationResult
from fr_torch.runtime.estimator import FREstimator
from fr_torch.runtime.focal_prior import image_priors
from fr_torch.runtime.pipeline import calibrate_paths
from fr_torch.runtime.workers import settle_heap
from fr_torch.runtime.shared_focal import apply_focal_priors

CRASH_ENV = "FR_BATCH_CRASH"
STALL_ENV = "FR_BATCH_STALL"


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
        if threads:  # torch and OpenCV: oversubscribed threads stall on a loaded machine

            torch.set_num_threads(int(threads))
            cv2.setNumThreads(int(threads))
        self.options = dict(options)
        self.estimator = FREstimator(**options["estimator"],
                                     reliability="default" if options.get("reliability", True) else None)
        settle_heap()
        self.extras = list(extras)
        self.crash = crash if crash is not None else os.environ.get(CRASH_ENV)

    def __call__(self, batch):
        """Ray Data entry point: ``batch`` is a ``pyarrow.Table`` of input rows."""
        return self.calibrate_rows(batch.to_pylist())

    def calibrate_rows(self, rows: Sequence[dict[str, Any]]):
        """Calibrate the images of ``rows`` (dicts with ``image`` and manifest columns) -> Arrow table,
        one output row per input row, in order.  Never raises for a bad image."""
        self._inject_faults(rows)
        names, focal = self._names_and_focal(rows)
        inputs, failed = self.read_inputs(names)
        try:
            results = self.estimator.calibrate_images(inputs, names=names, focal_px=focal,
                                                      principal_point=self.options.get("principal_point"))
        except Exception as exc:  # a bug or resource error must not lose the batch: fail its rows
            results = [_failed(name, f"calibration error: {type(exc).__name__}: {exc}") for name in names]
        for i, reason in failed.items():
            results[i] = _failed(names[i], reason)
        return self._table(inputs, focal, results, rows)

    def _table(self, inputs: Sequence, focal: Sequence, results: list, rows: Sequence[dict[str, Any]]):
        """The Arrow table of ``results`` (one per row), after the ``--focal-prior`` option
        (``options["focal_prior"]``, a :class:`~fr_torch.runtime.focal_prior.FocalPriorOption`) where
        set: each photo without a known focal length searched again with its prior, and the prior
        columns (:func:`~fr_torch.batch.table.with_prior_columns`) appended."""
        option = self.options.get("focal_prior")
        if option is None:
            return records_to_table([result.to_json() for result in results], rows, self.extras)
        priors, reasons = image_priors(option, inputs, results)
        for i, known in enumerate(focal):
            if known is not None:  # a manifest focal_px (or --focal) fixes f: no prior
                priors[i], reasons[i] = None, "focal length given"
        try:
            results = apply_focal_priors(self.estimator, results, priors)
        except Exception as exc:  # the photos keep their own estimates; the reason says why
            reasons = [f"focal prior not applied: {type(exc).__name__}: {exc}" if p is not None else r
                       for p, r in zip(priors, reasons)]
            priors = [None] * len(priors)
        table = records_to_table([result.to_json() for result in results], rows, self.extras)
        return with_prior_columns(table, priors, reasons)

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
        process searches (:func:`fr_torch.runtime.pipeline.calibrate_paths` without whole-image workers:
        the way to feed a GPU).  Rows with a URI (fsspec) go through :meth:`calibrate_rows`.  If a
        search raises, the rest of the rows go through :meth:`calibrate_rows` batch by batch (a
        batch that raises again becomes failed rows); a worker that dies fails only its image."""

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
                self._inject_faults(batch_rows)
                table = self._table(chunk, focal[done:done + len(chunk)], list(results), batch_rows)
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

    def _inject_faults(self, rows) -> None:
        """Tests only (``fr batch``'s module docstring): exit hard (``crash``) or sleep (``$FR_BATCH_STALL``,
        read here, in the worker) before calibrating ``rows`` when one of them is the chosen image."""
        stall, _, seconds = os.environ.get(STALL_ENV, "").partition(":")
        if stall and any(str(row["image"]).endswith(stall) for row in rows):
            time.sleep(float(seconds or 60))
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
    return CalibrationResult(image=name, width=0, height=0, ok=False, reason=reason)
