"""Evaluation metrics (as in the fR paper's experiments): per-image errors and mean +- standard error summaries.

Per image (``image_errors``):

* ``roll_err_deg`` / ``tilt_err_deg``: ``|est - gt|`` in degrees, both angles with the paper's
  horizon definitions (:func:`fr_torch.core.geometry.conventions.horizon_angles`; an estimate that only gives a
  rotation gets its roll / tilt from it).
* ``fov_err_pct``: ``100 |hfov_est - hfov_gt| / hfov_gt``; ``focal_err_pct``:
  ``100 |f_est - f_gt| / f_gt`` (normalised by the ground truth).  An estimate giving only one of
  focal / hfov gets the other from the image width.
* ``frame_err_deg``: ``min_{P in G24} angle(R_gt, R_est P)`` over the 24 proper signed permutation
  matrices (the rotation group of the cube), i.e. the rotation error up to relabelling of the
  Manhattan axes.

Summaries (``summarize``): mean and standard error ``SE = std(ddof=1) / sqrt(n)`` over the images
where the method succeeded and reported the quantity.  Failed estimates (``None`` or
``ok == False``) are **counted** (``failures``, ``failure_pct``), never silently dropped; a quantity
a method never reports is "n/a" (NaN mean, ``n = 0``).  ``valid_pct`` is the share of images with a
valid (non-failed) result; an estimate reporting NaN / inf counts as a failure.  A method whose every estimate failed with a reason starting ``"n/a ("``
(weights / predictions not supplied, e.g. CTRL-C without its ONNX file) is marked
``na_reason = NOT_SUPPLIED``: the tables then show "n/a (not supplied)" in every cell of its row.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Iterable, Sequence

import numpy as np

from fr_torch.core.geometry.conventions import (
    MANHATTAN_SYMMETRIES,
    focal_from_hfov,
    hfov_from_focal,
    manhattan_frame_error_deg,
    manhattan_symmetries,
    rotation_angle_deg,
    rotation_angles,
)
from fr_torch.registry import NOT_SUPPLIED, is_not_supplied

METRICS = ("runtime_s", "roll_err_deg", "tilt_err_deg", "fov_err_pct", "focal_err_pct", "frame_err_deg")


_G24 = MANHATTAN_SYMMETRIES  # the 24 proper signed permutations (fr_torch.core.geometry.conventions)
proper_signed_permutations = manhattan_symmetries


def frame_error_deg(r_gt: np.ndarray, r_est: np.ndarray) -> float:
    """Frame error (degrees): min over the 24 proper signed permutations P of angle(R_gt, R_est P).

    Both matrices must be proper rotations (det +1); a left-handed input raises ValueError.
    """
    r_gt = np.asarray(r_gt, dtype=np.float64)
    r_est = np.asarray(r_est, dtype=np.float64)
    for name, r in (("ground truth", r_gt), ("estimate", r_est)):
        if r.shape != (3, 3) or not np.isfinite(r).all():
            raise ValueError(f"frame error: {name} rotation must be a finite 3x3 matrix")
        if np.linalg.det(r) < 0:
            raise ValueError(f"frame error: {name} rotation is left-handed (det < 0)")
    return manhattan_frame_error_deg(r_gt, r_est)


def mean_se(values: Iterable[float]) -> tuple[float, float, int]:
    """(mean, standard error = std(ddof=1)/sqrt(n), n) over the finite values; NaNs for n = 0."""
    arr = np.asarray([v for v in values if v is not None], dtype=np.float64)
    arr = arr[np.isfinite(arr)]
    n = int(arr.size)
    if n == 0:
        return math.nan, math.nan, 0
    se = float(arr.std(ddof=1) / math.sqrt(n)) if n > 1 else math.nan
    return float(arr.mean()), se, n


def _get(obj: Any, name: str):
    if obj is None:
        return None
    if isinstance(obj, dict):
        return obj.get(name)
    return getattr(obj, name, None)


def _finite(x) -> float | None:
    if x is None:
        return None
    x = float(x)
    return x if math.isfinite(x) else None


def estimate_quantities(est: Any, width: int) -> dict[str, Any]:
    """roll / tilt / pitch / hfov / focal / rotation of an estimate, derived where possible.

    ``est`` is a :class:`fr_torch.plugins.interface.CameraEstimate` (or dict with the same keys).  Roll and
    tilt come from the estimate's own fields if given, else from its rotation; focal and hfov are
    converted into each other with the image width.
    """
    rotation = _get(est, "rotation")
    rotation = None if rotation is None else np.asarray(rotation, dtype=np.float64).reshape(3, 3)
    out = {k: _finite(_get(est, k)) for k in ("roll_deg", "tilt_deg", "pitch_deg", "focal_px", "hfov_deg")}
    if rotation is not None and np.isfinite(rotation).all():
        angles = rotation_angles(rotation)
        for key in ("roll_deg", "tilt_deg", "pitch_deg"):
            if out[key] is None:
                out[key] = float(angles[key])
    else:
        rotation = None
    if out["hfov_deg"] is None and out["focal_px"] is not None and out["focal_px"] > 0:
        out["hfov_deg"] = hfov_from_focal(out["focal_px"], width)
    if out["focal_px"] is None and out["hfov_deg"] is not None and 0 < out["hfov_deg"] < 180:
        out["focal_px"] = focal_from_hfov(out["hfov_deg"], width)
    out["rotation"] = rotation
    return out


NON_FINITE_REASON = "non-finite estimate (NaN/inf)"
_NUMERIC_FIELDS = ("focal_px", "hfov_deg", "roll_deg", "tilt_deg", "pitch_deg", "pan_deg")


def has_non_finite(est: Any) -> bool:
    """True when an estimate reports a NaN / inf number (a scalar field or an entry of its rotation)."""
    if est is None:
        return False
    for key in _NUMERIC_FIELDS:
        value = _get(est, key)
        if value is not None:
            try:
                if not math.isfinite(float(value)):
                    return True
            except (TypeError, ValueError):
                return True
    rotation = _get(est, "rotation")
    if rotation is not None:
        try:
            return not bool(np.isfinite(np.asarray(rotation, dtype=np.float64)).all())
        except (TypeError, ValueError):
            return True
    return False


def is_failure(est: Any) -> bool:
    """True for a missing estimate (None), one flagged ``ok == False``, or one with a NaN / inf in a
    reported quantity (:func:`has_non_finite`): a non-finite estimate is a counted failure, never a
    valid result whose errors are silently dropped."""
    return est is None or _get(est, "ok") is False or has_non_finite(est)


def failure_reason(est: Any) -> str:
    """Why :func:`is_failure` holds ("" if it does not)."""
    if est is None:
        return "no estimate"
    if _get(est, "ok") is False:
        return _get(est, "reason") or "failed"
    return NON_FINITE_REASON if has_non_finite(est) else ""


def image_errors(sample: Any, est: Any) -> dict[str, float | None]:
    """Per-image errors of estimate ``est`` against ground-truth ``sample`` (None = not available).

    ``sample`` has ``width``, ``rotation``, ``roll_deg``, ``tilt_deg``, ``hfov_deg``, ``focal_px``
    (a :class:`fr_eval.datasets.registry.CalibrationSample`).  A failed estimate gives all None.
    """
    keys = ("roll_err_deg", "tilt_err_deg", "fov_err_pct", "focal_err_pct", "frame_err_deg")
    out: dict[str, float | None] = dict.fromkeys(keys)
    if is_failure(est):
        return out
    q = estimate_quantities(est, int(_get(sample, "width")))
    gt_roll, gt_tilt = _finite(_get(sample, "roll_deg")), _finite(_get(sample, "tilt_deg"))
    gt_hfov, gt_focal = _finite(_get(sample, "hfov_deg")), _finite(_get(sample, "focal_px"))
    gt_rot = _get(sample, "rotation")
    if q["roll_deg"] is not None and gt_roll is not None:
        out["roll_err_deg"] = abs(q["roll_deg"] - gt_roll)
    if q["tilt_deg"] is not None and gt_tilt is not None:
        out["tilt_err_deg"] = abs(q["tilt_deg"] - gt_tilt)
    if q["hfov_deg"] is not None and gt_hfov:
        out["fov_err_pct"] = 100.0 * abs(q["hfov_deg"] - gt_hfov) / gt_hfov
    if q["focal_px"] is not None and gt_focal:
        out["focal_err_pct"] = 100.0 * abs(q["focal_px"] - gt_focal) / gt_focal
    if q["rotation"] is not None and gt_rot is not None:
        r = q["rotation"]
        if np.linalg.det(r) < 0:  # sign-free VP columns: make a left-handed answer proper
            r = r.copy()
            r[:, 0] = -r[:, 0]
        out["frame_err_deg"] = frame_error_deg(gt_rot, r)
    return out


@dataclass
class Summary:
    """Mean +- SE of each metric for one method; ``n[m]`` images entered metric m."""

    method: str
    n_images: int
    failures: int
    mean: dict[str, float]
    se: dict[str, float]
    n: dict[str, int]
    group: str | None = None  # e.g. the FOV bin of a per-FOV breakdown
    na_reason: str = ""  # NOT_SUPPLIED when the method's weights / predictions are absent

    @property
    def failure_pct(self) -> float:
        return 100.0 * self.failures / self.n_images if self.n_images else math.nan

    @property
    def n_valid(self) -> int:
        return self.n_images - self.failures

    @property
    def valid_pct(self) -> float:
        """Share (%) of the images with a valid (non-failed) result."""
        return 100.0 * self.n_valid / self.n_images if self.n_images else math.nan

    @property
    def not_supplied(self) -> bool:
        return bool(self.na_reason)

    def as_row(self, group_label: str | None = None) -> dict[str, Any]:
        row: dict[str, Any] = {"method": self.method}
        if group_label is not None:
            row[group_label] = self.group
        row.update({"n": self.n_images, "failures": self.failures, "failure_pct": self.failure_pct,
                    "n_valid": self.n_valid, "valid_pct": self.valid_pct, "status": self.na_reason})
        for m in METRICS:
            row[f"{m}_mean"] = self.mean[m]
            row[f"{m}_se"] = self.se[m]
            row[f"{m}_n"] = self.n[m]
        return row


def all_not_supplied(rows: Sequence[dict[str, Any]]) -> bool:
    """True when every row failed with an "n/a (...)" reason (weights / predictions absent; see
    :func:`fr_torch.registry.not_supplied`)."""
    return bool(rows) and all(r.get("failed") and is_not_supplied(r.get("reason")) for r in rows)


def summarize(method: str, rows: Sequence[dict[str, Any]], group: str | None = None) -> Summary:
    """Summary of per-image rows (dicts with ``failed`` and the METRICS keys) for one method.

    A method that was not supplied (:func:`all_not_supplied`) gets NaN means (never a made-up number)
    and ``na_reason = NOT_SUPPLIED``.
    """
    failures = sum(1 for r in rows if r.get("failed"))
    na = all_not_supplied(rows)
    mean, se, n = {}, {}, {}
    for m in METRICS:
        values = [] if na else [r.get(m) for r in rows if not r.get("failed") or m == "runtime_s"]
        mean[m], se[m], n[m] = mean_se(values)
    return Summary(method=method, n_images=len(rows), failures=failures, mean=mean, se=se, n=n, group=group,
                   na_reason=NOT_SUPPLIED if na else "")


def group_sort_key(value: Any) -> tuple:
    """Sort key putting numeric group labels in numeric order, then the others alphabetically."""
    try:
        return (0, float(value), "")
    except (TypeError, ValueError):
        return (1, 0.0, str(value))


def summarize_groups(method: str, rows: Sequence[dict[str, Any]], key: str = "group") -> list[Summary]:
    """One :class:`Summary` per distinct value of ``row[key]`` (rows without a value are skipped),
    in :func:`group_sort_key` order.  A method not supplied (:func:`all_not_supplied`) gets a single
    summary with group ``"all"`` (one "n/a (not supplied)" row instead of one per group)."""
    if all_not_supplied(rows):
        return [summarize(method, rows, group="all")]
    groups: dict[str, list[dict[str, Any]]] = {}
    for r in rows:
        value = r.get(key)
        if value is None or (isinstance(value, float) and not math.isfinite(value)) or value == "":
            continue
        groups.setdefault(str(value), []).append(r)
    return [summarize(method, groups[value], group=value) for value in sorted(groups, key=group_sort_key)]


def risk_coverage(score: Sequence[float], error: Sequence[float]) -> tuple[np.ndarray, np.ndarray]:
    """The risk-coverage curve of ranking images by ``score`` (ascending: kept first): (share kept
    (n,) in (0, 1], mean ``error`` of the kept images (n,)).  Ties keep their input order; a NaN
    score ranks last.  Images with a non-finite error are left out."""
    score = np.asarray(score, np.float64)
    error = np.asarray(error, np.float64)
    good = np.isfinite(error)
    score, error = np.where(np.isfinite(score[good]), score[good], np.inf), error[good]
    kept = error[np.argsort(score, kind="stable")]
    count = np.arange(1, kept.size + 1)
    return count / max(kept.size, 1), np.cumsum(kept) / count


def aurc(score: Sequence[float], error: Sequence[float]) -> float:
    """Area under :func:`risk_coverage` (the mean over k of the mean error of the k images ranked
    first), in the error's units; the oracle ranks by ``error`` itself.  NaN without images."""
    _, risk = risk_coverage(score, error)
    return float(risk.mean()) if risk.size else math.nan
