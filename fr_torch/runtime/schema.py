"""The one schema of an estimate, as every output writes it: ``fr calibrate``'s JSON, ``fr batch``'s
Parquet rows and each record of ``fr track`` (``frames.csv``, the JSON lines).

:func:`result_record` is a result's record: the fields of
:meth:`fr_torch.core.result.CalibrationResult.to_json` (keys :data:`RECORD_FIELDS`), with
every cue of :data:`ALL_CUES` (null where not computed, never left out) and **no bound that is
not one written as a number**: a bound that says nothing is ``null`` and flagged ``unbounded``
(:func:`unbounded_bounds`, :func:`horizon_unbounded`).  :func:`flat_record` is the same record as
one level of columns (:data:`FLAT_COLUMNS`, ``fr track``'s CSV): nested dicts joined with ``_``
(``horizon_left_y``, ``cues_grid_entropy``), fixed-size lists indexed (``principal_point_0``,
``rotation_1_2``); ``ranked_vanishing_points`` (a list of any length) is left to the nested
outputs.  ``docs/output-schema.md`` describes every field once.
"""
from __future__ import annotations

import math
from typing import Any, Iterator

from fr_torch.core.reliability.bounds import HORIZON_BOUND_CAP_PCT, HORIZON_TILT_LIMIT_DEG, NO_INFORMATION
from fr_torch.core.reliability.model import CUE_NAMES, TARGETS
from fr_torch.core.reliability.sanity import LINE_BEND_CUES
from fr_torch.core.result import JSON_KEYS

#: Every cue a record carries, in this order: the reliability model's and the spreads
#: (:data:`fr_torch.core.reliability.model.CUE_NAMES`) and the "lines bend" check's.
ALL_CUES = CUE_NAMES + LINE_BEND_CUES
#: The targets ``error_bound`` bounds.
BOUND_TARGETS = ("focal_pct", "tilt_deg")
#: The horizon promise's bound in ``error_bound`` (% of the image height; its limit in ``limits``).
HORIZON_BOUND = "horizon_pct"
#: Stages of ``runtime_s``.
RUNTIME_STAGES = ("detect", "grid", "refine", "cues", "total")
#: A record's top-level fields, in order: ``to_json``'s, ``segments_per_family`` included.
RECORD_FIELDS = JSON_KEYS[:JSON_KEYS.index("cues")] + ("segments_per_family",) + JSON_KEYS[JSON_KEYS.index("cues"):]


def _shape(size: int, inner: Any = None) -> list:
    return [inner] * size


#: The shape of a full record: each field's nesting (dicts with their keys, fixed-size lists with
#: their lengths); :data:`FLAT_COLUMNS` is its flattening.
TEMPLATE: dict[str, Any] = {
    "image": None, "width": None, "height": None, "ok": None, "reliable": None, "reason": None,
    "horizon_reliable": None, "horizon_reason": None, "model": None,
    "focal_px": None, "hfov_deg": None, "principal_point": _shape(2), "rotation": _shape(3, _shape(3)),
    "vertical_axis": None, "pan_deg": None, "tilt_deg": None, "roll_deg": None, "pitch_deg": None,
    "vanishing_points": _shape(3, _shape(3)), "ranked_vanishing_points": None,
    "horizon": {"line": _shape(3), "left_y": None, "right_y": None, "bound_pct": None, "unbounded": None},
    "distortion": {"model": None, "k": None, "centre": _shape(2), "radius_px": None, "bow_pct": None},
    "log_likelihood": None, "num_segments": None, "manhattan_fraction": None, "segments_per_family": _shape(4),
    "cues": {name: None for name in ALL_CUES},
    "predicted_error": {name: None for name in TARGETS},
    "error_bound": {"coverage": None, **{name: None for name in BOUND_TARGETS}, HORIZON_BOUND: None,
                    "limits": {name: None for name in BOUND_TARGETS + (HORIZON_BOUND,)}, "enforced": None,
                    "unbounded": {name: None for name in BOUND_TARGETS}},
    "runtime_s": {name: None for name in RUNTIME_STAGES},
}
assert tuple(TEMPLATE) == RECORD_FIELDS, "TEMPLATE must list the record's fields in order"
#: Fields the flat record leaves out: a list of any length.
NOT_FLAT = ("ranked_vanishing_points",)


def _leaves(value: Any, prefix: str) -> Iterator[tuple[str, Any]]:
    if isinstance(value, dict):
        for key, item in value.items():
            yield from _leaves(item, f"{prefix}_{key}" if prefix else str(key))
    elif isinstance(value, (list, tuple)):
        for i, item in enumerate(value):
            yield from _leaves(item, f"{prefix}_{i}")
    else:
        yield prefix, value


#: The columns of a flat record (:func:`flat_record`), in order.
FLAT_COLUMNS = tuple(key for key, _ in _leaves({k: v for k, v in TEMPLATE.items() if k not in NOT_FLAT}, ""))


def unbounded_bounds(error_bound: dict[str, Any] | None) -> dict[str, bool] | None:
    """Which bounds of an ``error_bound`` say nothing: a focal bound above 100 % or a tilt bound
    above 90 deg (:data:`fr_torch.core.reliability.bounds.NO_INFORMATION`: the photo's lines leave
    the quantity open); None without bounds."""
    if not error_bound:
        return None
    return {name: is_finite_number(error_bound.get(name)) and error_bound[name] > NO_INFORMATION[name]
            for name in BOUND_TARGETS}


def horizon_unbounded(error_bound: dict[str, Any] | None, tilt_deg: float | None, bound_pct: float | None) -> bool:
    """True when the horizon's bound says nothing: a bound at the core's cap
    :data:`~fr_torch.core.reliability.bounds.HORIZON_BOUND_CAP_PCT`; for a bound derived from the focal and
    tilt bounds (``error_bound`` without :data:`HORIZON_BOUND`), also a tilt or focal bound that is
    unbounded (:func:`unbounded_bounds`) or a tilt within its bound that reaches the horizon's limit
    of :data:`~fr_torch.core.reliability.bounds.HORIZON_TILT_LIMIT_DEG` (the horizon could be at
    infinity).  The horizon promise's own bound is unbounded only when missing or capped."""
    capped = is_finite_number(bound_pct) and bound_pct >= HORIZON_BOUND_CAP_PCT
    if error_bound and HORIZON_BOUND in error_bound:
        return bool(capped or not is_finite_number(error_bound.get(HORIZON_BOUND)))
    flags = unbounded_bounds(error_bound) or {}
    tilt_bound = (error_bound or {}).get("tilt_deg")
    reaches = (is_finite_number(tilt_bound) and is_finite_number(tilt_deg)
               and abs(tilt_deg) + tilt_bound >= HORIZON_TILT_LIMIT_DEG)
    return bool(any(flags.values()) or reaches or capped)


def is_finite_number(value: Any) -> bool:
    """True for a finite int or float (not a bool, not None): a value a record writes as a number."""
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


def complete(record: dict[str, Any]) -> dict[str, Any]:
    """A ``to_json`` record in the schema (module docstring), in place and returned: every cue
    present, unbounded bounds null and flagged.  A record already in the schema is returned as it
    is (its flags kept)."""
    cues = record.get("cues") or {}
    record["cues"] = {name: cues.get(name) for name in ALL_CUES} if record.get("ok") else {}
    bound = record.get("error_bound")
    if bound:
        given = bound.get("unbounded") or {}
        flags = {name: flag or bool(given.get(name)) for name, flag in unbounded_bounds(bound).items()}
        horizon = record.get("horizon")
        if horizon is not None:
            own = HORIZON_BOUND in bound  # the horizon promise's bound: its own flag, not the focal / tilt ones
            open_ = horizon_unbounded(bound, record.get("tilt_deg"), horizon.get("bound_pct")) \
                or bool(horizon.get("unbounded")) or (not own and any(flags.values()))
            record["horizon"] = dict(horizon, bound_pct=None if open_ else horizon.get("bound_pct"), unbounded=open_)
        record["error_bound"] = dict(bound, **{name: None for name, flag in flags.items() if flag}, unbounded=flags)
    elif record.get("horizon") is not None:
        record["horizon"] = dict(record["horizon"], unbounded=False)
    return {key: record.get(key) for key in RECORD_FIELDS} | {k: v for k, v in record.items() if k not in TEMPLATE}


def result_record(result, include_segments: bool = False) -> dict[str, Any]:
    """The record of a :class:`~fr_torch.core.result.CalibrationResult` (module docstring);
    ``include_segments``: with its segments and labels (``fr calibrate --segments``)."""
    return complete(result.to_json(include_segments=include_segments))


def flat_record(record: dict[str, Any]) -> dict[str, Any]:
    """A record (:func:`result_record`) as :data:`FLAT_COLUMNS` (None where a value is absent)."""
    flat = dict(_leaves({k: v for k, v in record.items() if k in TEMPLATE and k not in NOT_FLAT}, ""))
    return {column: flat.get(column) for column in FLAT_COLUMNS}
