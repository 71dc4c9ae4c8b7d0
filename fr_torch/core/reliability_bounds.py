"""What ``reliable`` promises: calibrated bounds on the predicted errors and the limits they are held to.

The reliability model (:mod:`fr_torch.core.reliability`) predicts an image's absolute focal error (%)
and tilt error (deg) as the mean error of similar training images.  This module turns a prediction
``p`` into an upper bound ``b = s * p`` that holds for a share ``coverage`` of images (90 % by
default), and calls an estimate **reliable** when every bound is within its limit:

    reliable  <=>  s_focal * p_focal <= focal_pct  and  s_tilt * p_tilt <= tilt_deg

with the limits of ``configs/reliability.json``'s ``promise`` block (:class:`ReliabilityPromise`;
default: focal error <= 10 %, tilt error <= 3 deg, 90 % bounds) when the block says ``"enforce":
true``; with ``false`` (the shipped setting) the bounds are reported in ``error_bound`` and
``reliable`` keeps the thresholds on the predicted errors (:mod:`fr_torch.core.reliability`).  Read: "the predicted 90 % bound of
the focal error is at most 10 % and that of the tilt error at most 3 deg".

The scale ``s`` per error and estimator mode is a **split-conformal** quantile of the ratio
``actual / max(predicted, floor)`` (:func:`conformal_scale`: the ``ceil((n + 1) coverage)``-th
smallest of n ratios) over images the model did not train on.  Fitted by
``fr_eval.protocols.lodo_reliability`` across datasets: for each training dataset family the model is refitted
without it and the family's images are predicted, the quantile is taken per family, and ``s`` is
the largest of them (:func:`worst_group_scale`), so the bound held on every family when that family
was a new camera.  A prediction of NaN (missing cues) gives no bound and ``reliable = False``.
"""
from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np

from fr_torch.resources import config_dir

PROMISE_TARGETS = ("focal_pct", "tilt_deg")
DEFAULT_LIMITS = {"focal_pct": 10.0, "tilt_deg": 3.0}
DEFAULT_COVERAGE = 0.9
#: predictions are floored at this before the ratio (focal %, tilt deg): a near-zero prediction
#: would make any error an infinite ratio
PREDICTION_FLOOR = {"focal_pct": 0.5, "tilt_deg": 0.1, "roll_deg": 0.1}
UNITS = {"focal_pct": "%", "tilt_deg": "deg", "roll_deg": "deg"}


def conformal_scale(predicted: np.ndarray, actual: np.ndarray, coverage: float = DEFAULT_COVERAGE,
                    floor: float = 0.0) -> float:
    """Split-conformal scale s: ``actual <= s * max(predicted, floor)`` for a share ``coverage`` of
    the pairs, with the finite-sample correction (the ``ceil((n + 1) coverage)``-th smallest ratio;
    inf when n is too small).  Non-finite pairs are ignored; NaN for none."""
    p = np.maximum(np.asarray(predicted, np.float64), floor)
    a = np.asarray(actual, np.float64)
    good = np.isfinite(p) & np.isfinite(a) & (p > 0)
    ratios = np.sort(a[good] / p[good])
    n = ratios.size
    if n == 0:
        return math.nan
    rank = math.ceil((n + 1) * coverage)
    return float(ratios[rank - 1]) if rank <= n else math.inf


def worst_group_scale(predicted: np.ndarray, actual: np.ndarray, groups: Sequence, coverage: float = DEFAULT_COVERAGE,
                      floor: float = 0.0) -> tuple[float, dict[str, float]]:
    """(largest per-group :func:`conformal_scale`, the scale of each group)."""
    groups = np.asarray(groups)
    per_group = {str(g): conformal_scale(np.asarray(predicted)[groups == g], np.asarray(actual)[groups == g],
                                         coverage, floor) for g in dict.fromkeys(groups.tolist())}
    finite = [v for v in per_group.values() if not math.isnan(v)]
    return (max(finite) if finite else math.nan), per_group


@dataclass(frozen=True)
class ReliabilityPromise:
    """Bounds of the predicted errors and the limits ``reliable`` holds them to (module docstring).

    ``limits``: target -> largest allowed bound (``focal_pct`` in %, ``tilt_deg`` in deg).
    ``scales``: mode (``fr`` / ``fast``) -> target -> conformal scale s (bound = s * prediction).
    ``coverage``: the share of images each bound is meant to hold for (0.9).
    ``enforce``: True -> ``reliable`` means the promise (the thresholds on the predicted errors are not
    used); False -> the bounds are reported (``error_bound``) but ``reliable`` keeps the thresholds."""

    limits: Mapping[str, float] = field(default_factory=lambda: dict(DEFAULT_LIMITS))
    scales: Mapping[str, Mapping[str, float]] = field(default_factory=dict)
    coverage: float = DEFAULT_COVERAGE
    enforce: bool = True

    def __post_init__(self) -> None:
        if not 0.0 < self.coverage < 1.0:
            raise ValueError(f"promise coverage must be in (0, 1), got {self.coverage}")
        for name, value in self.limits.items():
            if name not in PREDICTION_FLOOR or not (float(value) > 0):
                raise ValueError(f"promise limit {name}={value!r}: need a target of {list(PREDICTION_FLOOR)} "
                                 "and a number > 0")
        for mode, per_target in self.scales.items():
            for name, value in per_target.items():
                if not (float(value) > 0):
                    raise ValueError(f"promise scale {mode}.{name}={value!r} must be > 0")

    @classmethod
    def from_config(cls, path: str | Path | None = None) -> "ReliabilityPromise | None":
        """The ``promise`` block of ``configs/reliability.json`` (None when absent)::

            "promise": {"coverage": 0.9, "limits": {"focal_pct": 10, "tilt_deg": 3}, "enforce": true,
                        "scales": {"fr": {"focal_pct": s, "tilt_deg": s}, "fast": {...}}}
        """
        path = Path(path) if path is not None else config_dir() / "reliability.json"
        if not path.is_file():
            return None
        block = json.loads(path.read_text()).get("promise")
        if not block:
            return None
        return cls(limits={k: float(v) for k, v in block.get("limits", DEFAULT_LIMITS).items()},
                   scales={m: {k: float(v) for k, v in s.items()} for m, s in block.get("scales", {}).items()},
                   coverage=float(block.get("coverage", DEFAULT_COVERAGE)), enforce=bool(block.get("enforce", True)))

    def bounds(self, predicted: Mapping[str, float], mode: str) -> dict[str, float] | None:
        """target -> bound (``scale * max(prediction, floor)``) for the limited targets; None when the
        mode has no scales."""
        scales = self.scales.get(mode)
        if not scales:
            return None
        out = {}
        for name in self.limits:
            value = float(predicted.get(name, math.nan))
            out[name] = scales.get(name, math.nan) * max(value, PREDICTION_FLOOR[name]) if math.isfinite(value) \
                else math.nan
        return out

    def violations(self, bounds: Mapping[str, float]) -> list[str]:
        """One text per bound above its limit (or not finite), e.g. ``"90 % bound of focal 14.2 % > 10 %"``."""
        out = []
        for name, limit in self.limits.items():
            value = bounds.get(name, math.nan)
            if not value <= limit:
                out.append(f"{round(100 * self.coverage):d} % bound of {name.split('_')[0]} {value:.1f} "
                           f"{UNITS[name]} > {limit:g} {UNITS[name]}")
        return out

    def describe(self) -> str:
        """The promise in words (for the JSON output and the docs)."""
        parts = [f"{name.split('_')[0]} error <= {limit:g} {UNITS[name]}" for name, limit in self.limits.items()]
        return (f"reliable = the predicted {round(100 * self.coverage):d} % bounds satisfy " + " and ".join(parts)
                + " (bounds calibrated across datasets, docs/reliability.md)")
