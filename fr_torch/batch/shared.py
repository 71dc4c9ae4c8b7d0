"""``fr batch --shared-focal-by COLUMN``: the rows of each value of a manifest column (a camera id)
share one focal length (:func:`fr_torch.runtime.shared_focal.shared_from_results`).

Local engine: groups are searched one after another in this process, with one estimator (on a GPU
a group is one batch).  Ray engine (:func:`fr_torch.batch.ray.run_ray` with ``groups``): each group
is one item of the Ray dataset, searched by one actor.  Each group is written as one Arrow table,
so a group is in the output completely or not at all (resume skips whole groups).  Rows whose group value is empty (null, NaN, "") are each a
group of one (calibrated alone).  Known focal lengths (``--focal``, a manifest ``focal_px``
column) cannot be combined with it.

Output: the usual columns (each row's camera at the shared focal length) plus
``shared_focal_ok`` (bool), ``shared_focal_px`` (the group's focal length in the pixels of its
first usable photo), ``shared_focal_error_pct`` (its predicted error), ``shared_focal_images_used``
``shared_focal_reason`` (why the group has no shared value: no usable photo, or photos of
different aspect ratios, whose per-photo results are then kept), and ``shared_pp_x`` /
``shared_pp_y``: the group's estimated principal point in the pixels of its first usable photo
(null with ``--pp``, ``--fixed-pp`` or fewer than 5 usable photos; each row's camera then keeps
its own principal point).
"""
from __future__ import annotations

import math
from typing import Any, Iterable, Sequence

import pyarrow as pa

from fr_torch.batch.table import _finite_or_none, records_to_table, with_prior_columns
from fr_torch.batch.worker import BatchWorker, _failed
from fr_torch.errors import FRInputError
from fr_torch.runtime.focal_prior import group_prior, image_priors
from fr_torch.runtime.shared_focal import shared_from_results

SHARED_COLUMNS = ("shared_focal_ok", "shared_focal_px", "shared_focal_error_pct", "shared_focal_images_used",
                  "shared_focal_reason", "shared_pp_x", "shared_pp_y")


def _group_key(value) -> Any:
    """The group of a row's column value; None for an empty value (the row is a group of its own)."""
    if value is None or (isinstance(value, float) and math.isnan(value)) or (isinstance(value, str) and not value):
        return None
    return value


def group_rows(rows: Sequence[dict[str, Any]], column: str) -> list[list[dict[str, Any]]]:
    """Rows grouped by ``column``, groups in order of first appearance (empty values: one group each).
    ValueError (one line) when no row has the column."""
    if rows and not any(column in row for row in rows):
        names = sorted({key for row in rows[:100] for key in row})
        raise ValueError(f"--shared-focal-by {column}: no such manifest column (columns: {', '.join(names)})")
    groups: dict[Any, list] = {}
    singles = []
    for row in rows:
        key = _group_key(row.get(column))
        if key is None:
            singles.append([row])
        else:
            groups.setdefault(key, []).append(row)
    return list(groups.values()) + singles


def shared_groups(rows: Sequence[dict[str, Any]], options: dict[str, Any], column: str) -> list[list[dict]]:
    """The groups of ``rows`` (:func:`group_rows`); ValueError (one line) when a focal length is
    given (``--focal`` or a manifest ``focal_px`` column): a shared one is estimated."""
    if options.get("focal_px") is not None or any(_finite_or_none(row.get("focal_px")) is not None for row in rows):
        raise ValueError("--shared-focal-by estimates the focal length: it cannot be combined with --focal or a "
                         "manifest focal_px column")
    return group_rows(rows, column)


def run_shared_groups(rows: Sequence[dict[str, Any]], options: dict[str, Any], extras, column: str) -> Iterable:
    """One Arrow table per group of ``rows`` (:func:`group_rows`), in group order, in this process."""
    groups = shared_groups(rows, options, column)
    worker = BatchWorker(options, extras)
    for group in groups:
        yield calibrate_group(worker, group)


def calibrate_group(worker, rows: Sequence[dict[str, Any]]):
    """The Arrow table of one group's rows (input order): calibrated alone, then at the shared focal
    length; never raises for bad images or a refused group."""
    names = [str(row["image"]) for row in rows]
    inputs, failed = worker.read_inputs(names)
    shared_record = {"ok": False, "focal_px": None, "predicted_error_pct": None, "images_used": 0, "reason": ""}
    option = worker.options.get("focal_prior")
    prior, reasons = None, [""] * len(names)
    try:
        alone = worker.estimator.calibrate_images(inputs, names=names,
                                                  principal_point=worker.options.get("principal_point"))
        for i, reason in failed.items():
            alone[i] = _failed(names[i], reason)
        priors, reasons = image_priors(option, inputs, alone)
        prior = group_prior(priors)
        try:
            shared = shared_from_results(worker.estimator, alone, focal_prior=prior,
                                         estimate_principal_point=worker.options.get("shared_principal_point", True))
            results = shared.results
            shared_record = shared.to_json()
        except FRInputError as exc:  # photos of different aspect ratios: their own results are kept
            results = alone
            shared_record["reason"] = str(exc)
    except Exception as exc:  # a bug or resource error must not lose the group: fail its rows
        results = [_failed(name, f"calibration error: {type(exc).__name__}: {exc}") for name in names]
        shared_record["reason"] = f"calibration error: {type(exc).__name__}: {exc}"
    table = records_to_table([result.to_json() for result in results], rows, worker.extras)
    if option is not None:  # the group's prior (the first photo's that has one) on every row
        table = with_prior_columns(table, [prior] * len(rows), reasons)
    count = len(rows)
    error = shared_record.get("predicted_error_pct")
    columns = {
        "shared_focal_ok": pa.array([bool(shared_record["ok"])] * count, pa.bool_()),
        "shared_focal_px": pa.array([shared_record.get("focal_px")] * count, pa.float64()),
        "shared_focal_error_pct": pa.array([error if error is not None and math.isfinite(error) else None] * count,
                                           pa.float64()),
        "shared_focal_images_used": pa.array([int(shared_record.get("images_used") or 0)] * count, pa.int64()),
        "shared_focal_reason": pa.array([shared_record.get("reason") or ""] * count, pa.string()),
    }
    point = shared_record.get("principal_point") or (None, None)
    columns["shared_pp_x"] = pa.array([point[0]] * count, pa.float64())
    columns["shared_pp_y"] = pa.array([point[1]] * count, pa.float64())
    for name in SHARED_COLUMNS:
        table = table.append_column(name, columns[name])
    return table
