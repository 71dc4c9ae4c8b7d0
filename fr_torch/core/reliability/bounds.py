"""What ``reliable`` promises: calibrated bounds on an estimate's focal and tilt errors and the limits
they are held to.

Each estimate carries two **spreads** that the estimator measures on its own segments
(:func:`fr_torch.core.reliability.cues.focal_cues` with ``spreads`` on), from which its error scales come:

* focal, in % of f: ``sigma_f = 100 sqrt(focal_profile_spread x focal_resample_spread)``
  (:func:`focal_sigma_pct`), the geometric mean of how far f could move before the segments notice
  at the profile points 13 % / 15 % away (:func:`fr_torch.core.reliability.cues.focal_profile_spread`) and of
  the spread of log f when the segments are resampled (:func:`fr_torch.core.reliability.cues.resample_spreads`);
  both leave the focal prior out, so a focal length that the prior set gets a wide one;
* tilt, in degrees: ``sigma_t = hypot(pitch_resample_spread, TILT_FLOOR_DEG)`` (:func:`tilt_sigma_deg`):
  the pitch's resampling spread, and a floor for what no per-photo spread sees -- chiefly the
  principal point's offset from the image centre, which tilts every estimate of a camera alike
  (about ``atan(delta_c_y / f)``: 1 deg on YorkUrbanDB, 1.5 deg on NYU-VP).

A bound is ``b = s x sigma`` (the focal sigma floored at :data:`FOCAL_SIGMA_FLOOR_PCT`), with ``s``
per error and estimator mode a **split-conformal** quantile of ``actual / sigma`` at ``coverage``
(90 %) over images of dataset families the bound is not fitted on (:func:`conformal_scale`):
``fr_eval.protocols.lodo_reliability`` predicts each training family (YUD with its crops, ZInD-fR, NYU-VP)
and keeps the largest per-family quantile (:func:`worst_group_scale`), so the bound held on every
family when that family was the new camera.  No model is fitted: the spreads come from the
estimator, the scales are the only numbers learned from data.

The **horizon promise** (:class:`HorizonPromise`, the ``horizon`` block of the ``promise``) bounds
the horizon benchmark's error (the larger vertical distance at the image borders, % of the image
height) the same way, from a scale of its own: ``sigma_h`` (:func:`horizon_sigma_pct`) is how far
the horizon's crossing of the principal point's column moves under the pitch's resampling spread
and the focal sigma, in quadrature, with a floor; its conformal scale is fitted per estimator mode
on the same families (``fr_eval.protocols.horizon_promise``).  ``horizon_reliable`` says that its
90 % bound is within ``limit_pct`` (default 5 % of the height) or, with ``or_focal_tilt`` (shipped),
that the focal / tilt promise holds: on every family the horizon errors of the photos that promise
keeps were within the limit for about nine in ten of them, and the two routes together keep more of
the good horizons than either (results/horizon/promise/).  Unlike the tilt sigma, ``sigma_h`` has no
floor for the principal point's offset: the horizon is a line in the image (through the horizontal
vanishing points), which an offset principal point moves far less than it moves the tilt.

An estimate is **reliable** when every bound is within its limit (:class:`ReliabilityPromise`;
``configs/reliability.json``'s ``promise`` block; default: focal error <= 10 %, tilt error <= 3 deg,
90 % bounds).  Read: "the 90 % bound of the focal error is at most 10 % and that of the tilt error
at most 3 deg".  With ``"enforce": false`` the bounds are reported in ``error_bound`` and
``reliable`` is the thresholds rule on the KNN's predicted errors (:mod:`fr_torch.core.reliability`).
Missing spread cues give no bound and ``reliable = False``.
"""
from __future__ import annotations

import functools
import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np

from fr_torch.core import exact_math
from fr_torch.core.exact_math import on_array
from fr_torch.resources import config_dir

PROMISE_TARGETS = ("focal_pct", "tilt_deg")
DEFAULT_LIMITS = {"focal_pct": 10.0, "tilt_deg": 3.0}
DEFAULT_COVERAGE = 0.9
#: The focal sigma is floored at this (percent) before the ratio and the bound: a near-zero spread
#: (a synthetic scene) would make any error an infinite ratio.
FOCAL_SIGMA_FLOOR_PCT = 0.3
#: The tilt sigma's floor (degrees), added in quadrature to the pitch's resampling spread (module
#: docstring; chosen on the train splits, results/decisions/44.md).
TILT_FLOOR_DEG = 0.5
#: Largest tilt sigma (deg): a pitch spread at its maximum (the likelihood has no peak there) gives a
#: bound this times the scale.  The focal sigma is not capped: a photo whose profile point scores as
#: well as the estimate (spread at its maximum) still ranks by its resampling spread.
TILT_SIGMA_CAP_DEG = 45.0
UNITS = {"focal_pct": "%", "tilt_deg": "deg"}
#: A bound above this says the photo's lines leave the quantity open (the reason says so in words
#: rather than quoting a number like 3,763 %): focal off by more than itself, tilt by more than 90 deg.
NO_INFORMATION = {"focal_pct": 100.0, "tilt_deg": 90.0}


def _values(cues, name: str) -> np.ndarray:
    """Cue ``name`` of one ``cues`` dict (a float), of a mapping of cue name -> (n,) values or of a
    table with that column, as float64 (NaN where missing)."""
    if isinstance(cues, Mapping):
        value = cues.get(name, math.nan)
        return np.asarray(math.nan if value is None else value, np.float64)
    return np.asarray(cues[name], np.float64) if name in cues else np.full(len(cues), math.nan)


def focal_sigma_pct(cues) -> np.ndarray:
    """The focal error scale in % (module docstring): ``100 sqrt(focal_profile_spread x
    focal_resample_spread)``, floored at :data:`FOCAL_SIGMA_FLOOR_PCT`.  ``cues``: one result's cues
    dict (-> a 0-d array) or a table with the cue columns (-> (n,)); NaN where a cue is missing."""
    spread = np.sqrt(_values(cues, "focal_profile_spread") * _values(cues, "focal_resample_spread"))
    return np.maximum(100.0 * spread, FOCAL_SIGMA_FLOOR_PCT)


def tilt_sigma_deg(cues) -> np.ndarray:
    """The tilt error scale in degrees (module docstring): ``hypot(pitch_resample_spread,
    TILT_FLOOR_DEG)``, capped at :data:`TILT_SIGMA_CAP_DEG`.  ``cues`` as for :func:`focal_sigma_pct`."""
    return np.minimum(np.hypot(_values(cues, "pitch_resample_spread"), TILT_FLOOR_DEG), TILT_SIGMA_CAP_DEG)


SIGMAS = {"focal_pct": focal_sigma_pct, "tilt_deg": tilt_sigma_deg}

#: The largest tilt (deg) the horizon bound evaluates ``tan`` at: a tilt bound reaching 90 deg says the
#: lines leave the horizon open (the bound is then huge, not infinite).
HORIZON_TILT_LIMIT_DEG = 89.0
#: The cues :func:`horizon_sigma_pct` reads.
HORIZON_CUE_NAMES = ("pitch_resample_spread", "focal_profile_spread", "focal_resample_spread")
#: The largest horizon bound reported (% of the image height): ten image heights already say that the
#: lines leave the horizon open (a Fast-fR estimate that stopped away from a peak has a tilt bound
#: beyond 90 deg, which would read as tens of thousands of percent).
HORIZON_BOUND_CAP_PCT = 1000.0


def horizon_bound_pct(bounds: Mapping[str, float] | None, focal_px: float, tilt_deg: float,
                      height: float) -> float | None:
    """A 90 % bound of the horizon benchmark's error (the larger vertical distance at the left and
    right borders, :meth:`fr_torch.core.geometry.horizon.Horizon.error`) in % of the image height, from the
    estimate's tilt and focal bounds (:meth:`ReliabilityPromise.bounds`).

    Derivation: the horizon crosses the image column of the principal point at
    ``y = c_y + f tan(tilt)`` (:mod:`fr_torch.core.geometry.conventions`: ``tilt = atan(c_z / c_y)`` of world-up c)
    and has slope ``-tan(roll)``.  A tilt error within its bound ``b_t`` moves that crossing by at
    most ``f max_(+-) |tan(tilt +- b_t) - tan(tilt)|``, a focal error within ``b_f`` (%) by
    ``f |tan(tilt)| b_f / 100``; the bound is their sum (the horizon is off by more only when one of
    the two errors exceeds its bound, or by the roll: there is no roll bound, and a roll error
    ``d_r`` adds ``(w / 2) tan(d_r)`` at the borders; results/horizon/README.md measures the
    coverage, roll included).  A given focal length (focal bound 0) leaves the tilt part.  At most
    :data:`HORIZON_BOUND_CAP_PCT`.

    Args:
        bounds: the estimate's ``{"tilt_deg": b_t, "focal_pct": b_f, ...}`` (degrees, percent);
            None or a missing / non-finite bound -> None.
        focal_px: the estimated focal length, pixels.
        tilt_deg: the estimated (paper's) tilt, degrees.
        height: image height, pixels.

    Returns:
        The bound in % of the image height, or None.
    """
    if not bounds:
        return None
    tilt_bound, focal_bound = bounds.get("tilt_deg"), bounds.get("focal_pct")
    numbers = (tilt_bound, focal_bound, focal_px, tilt_deg, height)
    if any(v is None or not math.isfinite(float(v)) for v in numbers) or not height > 0:
        return None
    limit = math.radians(HORIZON_TILT_LIMIT_DEG)
    tilt = min(max(math.radians(tilt_deg), -limit), limit)
    reach = math.radians(min(float(tilt_bound), 2 * HORIZON_TILT_LIMIT_DEG))
    tan = functools.partial(exact_math.of, exact_math.tan)
    shift = max(abs(tan(min(tilt + reach, limit)) - tan(tilt)), abs(tan(tilt) - tan(max(tilt - reach, -limit))))
    bound = 100.0 * float(focal_px) * (shift + abs(tan(tilt)) * float(focal_bound) / 100.0) / float(height)
    return min(bound, HORIZON_BOUND_CAP_PCT)


#: The horizon promise's default limit: the 90 % bound of the horizon error, % of the image height.
HORIZON_LIMIT_PCT = 5.0


def horizon_sigma_pct(cues, focal_px, tilt_deg, height, floor_pct: float, focal_known=False) -> np.ndarray:
    """The horizon error scale ``sigma_h`` in % of the image height (module docstring).

    The horizon crosses the principal point's column at ``y = c_y + f tan(tilt)``; a pitch error
    ``d_t`` moves it by ``f sec^2(tilt) d_t`` and a relative focal error ``d_f`` by ``f |tan(tilt)|
    d_f``.  ``sigma_h = 100 / h sqrt((f sec^2(t) s_p)^2 + (f |tan t| s_f)^2) (+) floor_pct`` with
    ``s_p`` the pitch's resampling spread (radians, ``pitch_resample_spread``), ``s_f`` the focal
    sigma (:func:`focal_sigma_pct` / 100; 0 for a given focal length) and the floor added in
    quadrature (% of h).  The tilt is clamped to :data:`HORIZON_TILT_LIMIT_DEG`; at most
    :data:`HORIZON_BOUND_CAP_PCT`.

    Args:
        cues: one result's cues dict, a mapping of cue name -> (n,) values or a table with the
            cue columns (:data:`HORIZON_CUE_NAMES`).
        focal_px: estimated focal length(s), pixels.
        tilt_deg: estimated (paper's) tilt(s), degrees.
        height: image height(s), pixels.
        floor_pct: the floor, % of the image height.
        focal_known: the focal length was given (bool or (n,) bools).

    Returns:
        float64 array (0-d for one result's cues, (n,) for n); NaN where a cue or number is missing.
    """
    limit = math.radians(HORIZON_TILT_LIMIT_DEG)
    tilt = np.clip(np.radians(np.asarray(tilt_deg, np.float64)), -limit, limit)
    focal = np.asarray(focal_px, np.float64)
    pitch = np.radians(np.minimum(_values(cues, "pitch_resample_spread"), 2 * HORIZON_TILT_LIMIT_DEG))
    focal_sigma = np.where(np.asarray(focal_known, bool), 0.0, focal_sigma_pct(cues) / 100.0)
    shift = np.hypot(focal * pitch / on_array(exact_math.cos, tilt) ** 2,
                     focal * np.abs(on_array(exact_math.tan, tilt)) * focal_sigma)
    with np.errstate(divide="ignore", invalid="ignore"):
        sigma = np.hypot(100.0 * shift / np.asarray(height, np.float64), floor_pct)
    return np.minimum(sigma, HORIZON_BOUND_CAP_PCT)


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
class HorizonPromise:
    """The horizon's 90 % bound and the limit ``horizon_reliable`` holds it to (module docstring).

    ``limit_pct``: the largest allowed bound, % of the image height.  ``scales``: mode (``fr`` /
    ``fast``) -> conformal scale s (bound = s * :func:`horizon_sigma_pct`).  ``floor_pct``: the floor
    of ``sigma_h`` (% of the height).  ``or_focal_tilt``: the horizon is also trusted where the focal /
    tilt promise holds (its bounds within their limits), whatever its own bound."""

    limit_pct: float = HORIZON_LIMIT_PCT
    scales: Mapping[str, float] = field(default_factory=dict)
    floor_pct: float = 0.0
    or_focal_tilt: bool = False

    def __post_init__(self) -> None:
        if not float(self.limit_pct) > 0 or not float(self.floor_pct) >= 0:
            raise ValueError(f"horizon promise limit_pct={self.limit_pct!r} floor_pct={self.floor_pct!r}: need a "
                             "limit > 0 and a floor >= 0")
        for mode, value in self.scales.items():
            if not float(value) > 0:
                raise ValueError(f"horizon promise scale {mode}={value!r}: need a number > 0")

    @classmethod
    def from_block(cls, block: Mapping | None) -> "HorizonPromise | None":
        """``{"limit_pct": 5, "floor_pct": F, "scales": {"fr": s, "fast": s}, "or_focal_tilt": true}`` ->
        the promise (None for no block)."""
        if not block:
            return None
        return cls(limit_pct=float(block.get("limit_pct", HORIZON_LIMIT_PCT)),
                   scales={m: float(v) for m, v in block.get("scales", {}).items()},
                   floor_pct=float(block.get("floor_pct", 0.0)), or_focal_tilt=bool(block.get("or_focal_tilt", False)))

    def bounds(self, cues, mode: str, focal_px, tilt_deg, height, focal_known=False) -> np.ndarray:
        """The 90 % bounds of estimates' horizon errors, % of the image height (at most
        :data:`HORIZON_BOUND_CAP_PCT`), for a batch at once: ``cues`` a mapping of cue name -> (n,)
        values (or one result's cues dict), the numbers (n,) (NaN for a missing one), as
        :func:`horizon_sigma_pct`.  Returns float64 (n,) (0-d for one result); NaN where the mode has
        no scale or a number is missing."""
        scale = self.scales.get(mode)
        sigma = horizon_sigma_pct(cues, focal_px, tilt_deg, height, self.floor_pct, focal_known)
        if scale is None:
            return np.full_like(sigma, math.nan)
        return np.where(np.isfinite(sigma), np.minimum(scale * sigma, HORIZON_BOUND_CAP_PCT), math.nan)

    def violation(self, bound: float, coverage: float = DEFAULT_COVERAGE, focal_tilt_kept: bool = False) -> str | None:
        """Why the horizon promise does not hold (None when it does): its bound, e.g. ``"90 % bound of
        the horizon 7.3 % of the height > 5 %"``, and with :attr:`or_focal_tilt` that the focal / tilt
        promise does not hold either (``focal_tilt_kept``: it holds -> None)."""
        if self.or_focal_tilt and focal_tilt_kept:
            return None
        percent = round(100 * coverage)
        if not math.isfinite(bound):
            why = f"no {percent:d} % bound of the horizon (its cues are missing)"
        elif bound >= HORIZON_BOUND_CAP_PCT:
            why = f"the lines do not bound the horizon ({percent:d} % bound > {HORIZON_BOUND_CAP_PCT:g} % of the height)"
        elif not bound <= self.limit_pct:
            why = f"{percent:d} % bound of the horizon {bound:.1f} % of the height > {self.limit_pct:g} %"
        else:
            return None
        return why + (" and the focal / tilt promise does not hold" if self.or_focal_tilt else "")


@dataclass(frozen=True)
class ReliabilityPromise:
    """Bounds of an estimate's errors and the limits ``reliable`` holds them to (module docstring).

    ``limits``: target -> largest allowed bound (``focal_pct`` in %, ``tilt_deg`` in deg).
    ``scales``: mode (``fr`` / ``fast``) -> target -> conformal scale s (bound = s * sigma).
    ``coverage``: the share of images each bound is meant to hold for (0.9).
    ``enforce``: True (default) -> ``reliable`` means the promise; False -> the bounds are reported
    (``error_bound``) but ``reliable`` is the thresholds rule on the predicted errors.
    ``validated_detectors``: names of line detectors (:mod:`fr_torch.detectors.registry`) whose
    segments the promise was measured to hold for besides the reliability model's own
    (:attr:`fr_torch.core.reliability.model.ReliabilityModel.detectors`; results/decisions/45.md).
    ``horizon``: the horizon promise (:class:`HorizonPromise`; None: no ``horizon_reliable``)."""

    limits: Mapping[str, float] = field(default_factory=lambda: dict(DEFAULT_LIMITS))
    scales: Mapping[str, Mapping[str, float]] = field(default_factory=dict)
    coverage: float = DEFAULT_COVERAGE
    enforce: bool = True
    validated_detectors: tuple[str, ...] = ()
    horizon: HorizonPromise | None = None

    def __post_init__(self) -> None:
        if not 0.0 < self.coverage < 1.0:
            raise ValueError(f"promise coverage must be in (0, 1), got {self.coverage}")
        for name, value in self.limits.items():
            if name not in SIGMAS or not (float(value) > 0):
                raise ValueError(f"promise limit {name}={value!r}: need a target of {list(SIGMAS)} and a number > 0")
        for mode, per_target in self.scales.items():
            for name, value in per_target.items():
                if name not in SIGMAS or not (float(value) > 0):
                    raise ValueError(f"promise scale {mode}.{name}={value!r}: need a target of {list(SIGMAS)} "
                                     "and a number > 0")
        if not isinstance(self.validated_detectors, (list, tuple)) or not all(
                isinstance(name, str) and name for name in self.validated_detectors):
            raise ValueError(f"promise validated_detectors={self.validated_detectors!r}: need a list of detector names")
        object.__setattr__(self, "validated_detectors", tuple(self.validated_detectors))

    @classmethod
    def from_config(cls, path: str | Path | None = None) -> "ReliabilityPromise | None":
        """The ``promise`` block of ``configs/reliability.json`` (None when absent)::

            "promise": {"coverage": 0.9, "limits": {"focal_pct": 10, "tilt_deg": 3}, "enforce": true,
                        "scales": {"fr": {"focal_pct": s, "tilt_deg": s}, "fast": {...}},
                        "validated_detectors": ["torch-lines"],
                        "horizon": {"limit_pct": 5, "floor_pct": F, "scales": {"fr": s, "fast": s}}}
        """
        path = Path(path) if path is not None else config_dir() / "reliability.json"
        if not path.is_file():
            return None
        block = json.loads(path.read_text()).get("promise")
        if not block:
            return None
        return cls(limits={k: float(v) for k, v in block.get("limits", DEFAULT_LIMITS).items()},
                   scales={m: {k: float(v) for k, v in s.items()} for m, s in block.get("scales", {}).items()},
                   coverage=float(block.get("coverage", DEFAULT_COVERAGE)), enforce=bool(block.get("enforce", True)),
                   validated_detectors=block.get("validated_detectors", ()),
                   horizon=HorizonPromise.from_block(block.get("horizon")))

    def bounds(self, cues: Mapping[str, float], mode: str, focal_known: bool = False) -> dict[str, float] | None:
        """target -> bound (``scale * sigma``, :data:`SIGMAS`) of one estimate from its ``cues`` dict, for the
        limited targets; NaN where a cue is missing; a given focal length (``focal_known``) has a focal
        bound of 0.  None when the mode has no scales."""
        scales = self.scales.get(mode)
        if not scales:
            return None
        out = {}
        for name in self.limits:
            if name == "focal_pct" and focal_known:
                out[name] = 0.0
                continue
            sigma = float(SIGMAS[name](cues))
            out[name] = scales.get(name, math.nan) * sigma if math.isfinite(sigma) else math.nan
        return out

    def violations(self, bounds: Mapping[str, float]) -> list[str]:
        """One text per bound above its limit (or missing), saying by how much, e.g.
        ``"90 % bound of focal 14.2 % > 10 % (4.2 % over)"``, or for a bound above
        :data:`NO_INFORMATION` ``"the lines do not bound the focal (90 % bound > 100 %)"``."""
        out = []
        for name, limit in self.limits.items():
            value, unit, what = bounds.get(name, math.nan), UNITS[name], name.split("_")[0]
            if not math.isfinite(value):
                out.append(f"no {round(100 * self.coverage):d} % bound of {what} (its cues are missing)")
            elif value > NO_INFORMATION[name]:  # e.g. a focal length the prior set: no number to quote
                out.append(f"the lines do not bound the {what} ({round(100 * self.coverage):d} % bound > "
                           f"{NO_INFORMATION[name]:g} {unit})")
            elif not value <= limit:
                digits = 1 if value - limit >= 0.05 else 3  # "3.004 deg > 3 deg (0.004 deg over)", not "3.0 > 3"
                out.append(f"{round(100 * self.coverage):d} % bound of {what} {value:.{digits}f} {unit} > {limit:g} "
                           f"{unit} ({value - limit:.{digits}f} {unit} over)")
        return out

    def describe(self) -> str:
        """The promise in words (for the JSON output and the docs)."""
        parts = [f"{name.split('_')[0]} error <= {limit:g} {UNITS[name]}" for name, limit in self.limits.items()]
        return (f"reliable = the {round(100 * self.coverage):d} % bounds satisfy " + " and ".join(parts)
                + " (bounds from the estimate's own spreads, calibrated across datasets: docs/reliability.md)")
