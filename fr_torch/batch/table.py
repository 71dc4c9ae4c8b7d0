"""``fr batch``'s output: the Arrow schema of a result row, records to tables, resumable part files."""
from __future__ import annotations

import math
import os
import sys
import time
import uuid
from pathlib import Path
from typing import Any, Sequence

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from fr_torch.core.reliability.model import TARGETS
from fr_torch.redaction import redact_text, redact_url
from fr_torch.runtime.schema import ALL_CUES, BOUND_TARGETS, HORIZON_BOUND, RUNTIME_STAGES, complete

# Keys of the dict-valued result fields (struct columns, :data:`fr_torch.runtime.schema.TEMPLATE`).
RUNTIME_KEYS = RUNTIME_STAGES
#: The cues of a row: every cue of the schema (:data:`fr_torch.runtime.schema.ALL_CUES`).
ROW_CUES = ALL_CUES
#: Number fields of the ``distortion`` struct (:func:`fr_torch.core.geometry.lens.distortion_record`).
DISTORTION_NUMBERS = ("k", "radius_px", "bow_pct")
#: Bounded targets of ``error_bound`` (:mod:`fr_torch.core.reliability.bounds`).
BOUND_KEYS = BOUND_TARGETS
#: Number fields of the ``horizon`` struct (:meth:`fr_torch.core.geometry.horizon.Horizon.to_json`), besides
#: ``line`` and the ``unbounded`` flag.
HORIZON_NUMBERS = ("left_y", "right_y", "bound_pct")


FLOAT_FIELDS = ("focal_px", "hfov_deg", "pan_deg", "tilt_deg", "roll_deg", "pitch_deg", "log_likelihood",
                "manhattan_fraction")


def result_schema():
    """The Arrow schema of the output rows (without carried-through manifest columns).

    Units as in :class:`fr_torch.core.result.CalibrationResult`: pixels, degrees, seconds.
    """

    f64 = pa.float64()
    # Variable-size lists, not fixed-size ones: a failed image stores null there, and pyarrow
    # before 26 cannot read a null fixed-size list back from Parquet (apache/arrow GH-35692: the
    # whole part file fails to load).  Shapes are checked on the way in (:func:`records_to_table`).
    mat3 = pa.list_(pa.list_(f64))
    return pa.schema([
        ("image", pa.string()), ("width", pa.int32()), ("height", pa.int32()),
        ("ok", pa.bool_()), ("reliable", pa.bool_()), ("reason", pa.string()),
        ("horizon_reliable", pa.bool_()), ("horizon_reason", pa.string()), ("model", pa.string()),
        ("focal_px", f64), ("hfov_deg", f64), ("principal_point", pa.list_(f64)),
        ("rotation", mat3), ("vertical_axis", pa.int8()),
        ("pan_deg", f64), ("tilt_deg", f64), ("roll_deg", f64), ("pitch_deg", f64),
        ("vanishing_points", mat3),
        ("ranked_vanishing_points", pa.list_(pa.struct([("point", pa.list_(f64)), ("support_px", f64),
                                                         ("family", pa.int8())]))),
        ("horizon", pa.struct([("line", pa.list_(f64)), *[(k, f64) for k in HORIZON_NUMBERS],
                               ("unbounded", pa.bool_())])),
        ("distortion", pa.struct([("model", pa.string()), *[(k, f64) for k in DISTORTION_NUMBERS],
                                  ("centre", pa.list_(f64))])),
        ("log_likelihood", f64), ("num_segments", pa.int32()),
        ("manhattan_fraction", f64), ("segments_per_family", pa.list_(pa.int32())),
        ("cues", pa.struct([(k, f64) for k in ROW_CUES])),
        ("predicted_error", pa.struct([(k, f64) for k in TARGETS])),
        ("error_bound", pa.struct([("coverage", f64), *[(k, f64) for k in BOUND_KEYS + (HORIZON_BOUND,)],
                                   ("limits", pa.struct([(k, f64) for k in BOUND_KEYS + (HORIZON_BOUND,)])),
                                   ("enforced", pa.bool_()),
                                   ("unbounded", pa.struct([(k, pa.bool_()) for k in BOUND_KEYS]))])),
        ("runtime_s", pa.struct([(k, f64) for k in RUNTIME_KEYS])),
    ])


def _finite_or_none(value):
    try:
        value = float(value)
    except (TypeError, ValueError):
        return None
    return value if math.isfinite(value) else None


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


def _clean_ranked(value):
    """The JSON's ``ranked_vanishing_points`` (list of {point, support_px, family}) with finite
    3-vector points, else None."""
    if not value:
        return None
    out = []
    for item in value:
        point = _clean_nested(item.get("point"), (3,))
        if point is None:
            return None
        out.append({"point": point, "support_px": _clean_float(item.get("support_px")),
                    "family": int(item.get("family", -1))})
    return out


def records_to_table(records: Sequence[dict[str, Any]], rows: Sequence[dict[str, Any]], extras=()):
    """JSON records (``CalibrationResult.to_json``, put in the schema by
    :func:`fr_torch.runtime.schema.complete`) + their input rows -> Arrow table of the output
    schema plus the carried manifest columns ``extras`` (from :func:`extra_columns`)."""

    schema = result_schema()
    clean = []
    for record in records:
        record = complete(dict(record))
        out = {name: record.get(name) for name in schema.names}
        out["image"] = redact_url(str(out["image"]))  # never a URL's secret in a row (the resume compares these)
        out["reason"] = redact_text(str(out["reason"] or ""))
        out["horizon_reason"] = redact_text(str(out["horizon_reason"] or ""))
        for key in FLOAT_FIELDS:
            out[key] = _clean_float(out[key])
        for key, shape in NESTED_SHAPES.items():
            out[key] = _clean_nested(out[key], shape)
        out["ranked_vanishing_points"] = _clean_ranked(out["ranked_vanishing_points"])
        for key, keys in (("cues", ROW_CUES), ("predicted_error", TARGETS), ("runtime_s", RUNTIME_KEYS)):
            value = out[key]
            out[key] = None if not value else {k: _clean_float(value.get(k)) for k in keys}
        horizon = out["horizon"]
        if horizon:
            out["horizon"] = {"line": _clean_nested(horizon.get("line"), (3,)),
                              **{k: _clean_float(horizon.get(k)) for k in HORIZON_NUMBERS},
                              "unbounded": bool(horizon.get("unbounded"))}
        lens = out["distortion"]
        if lens:
            out["distortion"] = {"model": str(lens.get("model")), **{k: _clean_float(lens.get(k)) for k in DISTORTION_NUMBERS},
                                 "centre": _clean_nested(lens.get("centre"), (2,))}
        bound = out["error_bound"]
        if bound:
            limits = bound.get("limits") or {}
            out["error_bound"] = {"coverage": _clean_float(bound.get("coverage")),
                                  **{k: _clean_float(bound.get(k)) for k in BOUND_KEYS + (HORIZON_BOUND,)},
                                  "limits": {k: _clean_float(limits.get(k)) for k in BOUND_KEYS + (HORIZON_BOUND,)},
                                  "enforced": bool(bound.get("enforced")),
                                  "unbounded": {k: bool((bound.get("unbounded") or {}).get(k)) for k in BOUND_KEYS}}
        clean.append(out)
    table = pa.Table.from_pylist(clean, schema=schema)
    for source, target, kind in extras:
        values = [row.get(source) for row in rows]
        if source == "focal_px":
            values = [_finite_or_none(v) for v in values]
        table = table.append_column(pa.field(target, kind), pa.array(values, type=kind, from_pandas=True))
    return table


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

        done: set[str] = set()
        for part in sorted(self.out.glob("part-*.parquet")):
            try:
                done.update(pq.read_table(part, columns=["image"]).column("image").to_pylist())
            except Exception as exc:  # an unreadable part (should not happen: parts are atomic)
                print(f"fr batch: warning: ignoring unreadable part {part} ({exc})", file=sys.stderr)
        return done

    def write(self, table) -> Path:
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


#: Columns ``fr batch --focal-prior`` adds (only then): the prior each row's photo got, or why none.
PRIOR_COLUMNS = ("focal_prior_px", "focal_prior_sigma_pct", "focal_prior_source", "focal_prior_reason")


def with_prior_columns(table, priors: Sequence, reasons: Sequence[str]):
    """``table`` with :data:`PRIOR_COLUMNS` appended: per row the focal prior used
    (:class:`~fr_torch.runtime.focal_prior.FocalPrior`: centre in the row's pixels, width in %,
    ``user`` / ``exif``), null where none, and the reason there is none ("" otherwise)."""
    columns = {
        "focal_prior_px": pa.array([None if p is None else float(p.focal_px) for p in priors], pa.float64()),
        "focal_prior_sigma_pct": pa.array([None if p is None else float(p.sigma_pct) for p in priors], pa.float64()),
        "focal_prior_source": pa.array([None if p is None else p.source for p in priors], pa.string()),
        "focal_prior_reason": pa.array([str(r or "") for r in reasons], pa.string()),
    }
    for name in PRIOR_COLUMNS:
        table = table.append_column(name, columns[name])
    return table
