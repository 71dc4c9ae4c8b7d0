"""Reliability prediction: predicted absolute errors of roll, tilt and focal length from fR's cues.

The model follows the authors' online-fR error predictor (paper §3.4): the cues of
:meth:`fr_torch.runtime.estimator.FREstimator._cues` (the paper's three and geometric cues of ours) are
normalised, whitened, and a K-nearest-neighbour
regressor returns the **mean absolute error of the K most similar training images**, for roll
(degrees), tilt (degrees) and focal length (percent of the true focal length).

Cues (:data:`CUE_NAMES`; the first three are the paper's, :data:`PAPER_CUE_NAMES`)
------------------------------------------------------------------------------------
Every fR result reports all seven (Fast-fR results all but ``focal_profile_gap``, which would cost
Fast-fR more than half of its time); the shipped models use :func:`model_cue_names`: the paper's three,
``focal_prior_share`` and ``focal_spread`` (:data:`MODEL_CUE_NAMES`, Fast-fR), and all seven (:data:`FR_MODEL_CUE_NAMES`,
fR).

* ``min_family_segments``, ``grid_entropy``, ``mean_log_likelihood``: the paper's cues (defined in
  :meth:`fr_torch.runtime.estimator.FREstimator._cues`);
* ``focal_conditioning`` (not in the paper): how well the estimated Manhattan frame's geometry
  constrains f, from the estimated rotation alone (:func:`fr_torch.core.reliability.cues.focal_conditioning`):
  a VP whose direction makes an angle theta with the optical axis sits at ``f tan(theta)`` from the
  principal point; at theta = 0 (VP on the principal point) and theta = 90 deg (VP at infinity) its
  position says nothing about f.  The cue is ``sqrt(sum_i (sin(theta_i) cos(theta_i))^2)`` over the
  three VPs, in [0, sqrt(3)/2].  A camera panned square to a wall (one horizontal VP near the
  centre, the other and the vertical one near infinity) scores near 0.
* ``focal_prior_share`` (not in the paper; :func:`fr_torch.core.reliability.cues.focal_prior_share`): the share of
  the focal length's determination that comes from the focal prior, from a quadratic fit of the
  objective around the estimate: ``c_p / (c_p + c_l)`` with ``c_p`` the prior's curvature in log f
  and ``c_l`` the likelihood's (angles re-optimised), in [0, 1].  It sees what
  ``focal_conditioning`` sees (VPs that carry no information on f leave ``c_l`` small) and more: few
  segments, noisy ones, and narrow views whose VPs lie far outside the image, which the prior
  pulls wide (Fast-fR's log-normal, centred at 82 deg; fR's flat top from 64 deg).  0 for a given
  focal length.
* ``focal_profile_gap`` (not in the paper; :func:`fr_torch.core.reliability.cues.focal_profile_gap`; fR only): the
  objective at the estimate minus the best objective of a known-focal search at 0.6 - 1.67 times the
  estimated focal length (nats, length-weighted): how much better the estimated focal length
  explains the segments than a clearly different one.  Small or negative: a second basin nearly as
  good (or better: a search miss), the case of most large focal errors; ``focal_prior_share`` sees
  a flat profile, this cue a second peak.  0 for a given focal length.
* ``focal_spread`` (not in the paper; :func:`fr_torch.core.reliability.cues.focal_spread`): the marginal spread
  of log f (angles re-optimised, focal prior included) of the local quadratic fit that also gives
  ``focal_prior_share``, for the objective per pixel of segment length: how sharply the whole
  objective peaks along f (``focal_prior_share`` says how much of that peak is the prior's).  0 for
  a given focal length.

The shipped models' cue sets (Fast-fR: the paper's three, ``focal_prior_share`` and ``focal_spread``;
fR: all seven)
were chosen out of fold on the train splits (``results/DECISIONS.md``; ``focal_spread``: left-one-
family-out on the train splits, ``results/decisions/35.md``).  The estimator also reports the three
spread cues of :data:`fr_torch.core.reliability.cues.SPREAD_CUE_NAMES` (in :data:`CUE_NAMES`, not in a shipped
model) when a model holds a promise: its bounds rest on them.

Run-time use: the estimator's last stage calls :meth:`ReliabilityModel.annotate_many`, which sets
``predicted_error`` (this KNN) and, with a :class:`~fr_torch.core.reliability.bounds.ReliabilityPromise`
(``configs/reliability.json``'s ``promise`` block), ``error_bound`` and ``reliable`` by the promise;
without one, or with ``"enforce": false``, ``reliable`` is cleared when a predicted error exceeds its
threshold (``thresholds``: roll 2 deg, tilt 3 deg, focal 15 %).

Scope: a model predicts only for the setting it was trained on, ``meta["trained_for"]`` (deviation
measure, line detector, likelihood config; :data:`DEFAULT_TRAINED_FOR` for a file that does not say,
the shipped models' setting), and for the detectors its promise was validated on
(``validated_detectors`` in the ``promise`` block, :attr:`ReliabilityModel.detectors`).  An
estimator with another measure, likelihood or detector gets no predicted errors
(``predicted_error`` None) and ``reliable = False`` with the reason
(:meth:`ReliabilityModel.scope_gap`): a model's predictions say nothing about errors of another
setting.
"""
from __future__ import annotations

import functools
import json
import math
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from fr_torch.core import exact_math
from fr_torch.core.exact_math import on_array
from fr_torch.core.likelihood.mixture import LikelihoodParams
from fr_torch.core.reliability.bounds import HORIZON_CUE_NAMES, ReliabilityPromise
from fr_torch.core.reliability.cues import SPREAD_CUE_NAMES
from fr_torch.core.settings.config import Mode
from fr_torch.resources import config_dir

_config_dir = config_dir  # load_default has an argument of that name

PAPER_CUE_NAMES = ("min_family_segments", "grid_entropy", "mean_log_likelihood")  # paper §3.4
FR_MODEL_CUE_NAMES = PAPER_CUE_NAMES + ("focal_conditioning", "focal_prior_share", "focal_profile_gap",
                                         "focal_spread")  # fR's shipped model: the seven of the module docstring
MODEL_CUE_NAMES = PAPER_CUE_NAMES + ("focal_prior_share", "focal_spread")  # Fast-fR's shipped model (module docstring)
# what the estimator reports: the seven (focal_profile_gap in fr mode only) and, when the promise's
# bounds need them, the spreads (fr_torch.core.reliability.cues.SPREAD_CUE_NAMES, fr_torch.core.reliability.bounds)
CUE_NAMES = FR_MODEL_CUE_NAMES + SPREAD_CUE_NAMES
TARGETS = ("roll_deg", "tilt_deg", "focal_pct")
ERROR_COLUMNS = ("roll_err_deg", "tilt_err_deg", "focal_err_pct")  # training-record column names
LOG_EPS = np.array([0.1, 0.1, 1.0])  # CV loss: ln(error + eps)
ENTROPY_FLOOR = 1e-6
CONDITIONING_FLOOR = 1e-3
PRIOR_SHARE_FLOOR = 1e-2
SPREAD_FLOOR = 1e-4
PROFILE_GAP_SCALE = 100.0  # nats: asinh(gap / scale) is linear within +-scale, logarithmic beyond


def _sum_in_order(a: np.ndarray) -> np.ndarray:
    """Sum over the last axis from its first entry to its last, one rounding per addition: numpy's
    ``sum`` adds in an order set by its SIMD width, which differs from CPU to CPU."""
    total = a[..., 0].copy()
    for j in range(1, a.shape[-1]):
        total += a[..., j]
    return total


def _log(a) -> np.ndarray:
    """Natural log of an array through :mod:`fr_torch.core.exact_math` (numpy's runs other code on
    other CPUs)."""
    return on_array(exact_math.log, a)


# Raw cue -> feature, per cue name (module docstring, "Cue normalisation").
_CUE_TRANSFORMS = {
    "min_family_segments": (lambda c: _log(1.0 + np.clip(c, 0.0, None)), "ln1p(min_family_segments)"),
    "grid_entropy": (lambda c: _log(np.clip(c, 0.0, None) + ENTROPY_FLOOR), "ln(grid_entropy + 1e-6)"),
    "mean_log_likelihood": (lambda c: c, "mean_log_likelihood"),
    "focal_conditioning": (lambda c: _log(np.clip(c, 0.0, None) + CONDITIONING_FLOOR),
                           "ln(focal_conditioning + 1e-3)"),
    "focal_prior_share": (lambda c: _log(np.clip(c, 0.0, 1.0) + PRIOR_SHARE_FLOOR), "ln(focal_prior_share + 1e-2)"),
    "focal_profile_gap": (lambda c: on_array(exact_math.asinh, np.asarray(c, np.float64) / PROFILE_GAP_SCALE),
                          "asinh(focal_profile_gap / 100)"),
    **{name: (lambda c: _log(np.clip(c, 0.0, None) + SPREAD_FLOOR), f"ln({name} + 1e-4)")
       for name in ("focal_spread",) + SPREAD_CUE_NAMES},
}

DEFAULT_THRESHOLDS = {"roll_deg": 2.0, "tilt_deg": 3.0, "focal_pct": 15.0}
#: The setting a model was trained on (``meta["trained_for"]``), where its file does not say: the
#: shipped models' (deviation measure b, LSD segments, the default likelihood config).
DEFAULT_TRAINED_FOR = {"measure": "b", "detector": "lsd", "likelihood": "default"}
#: ``focal_prior_share`` from which an unreliable focal length is explained as the prior's
#: (the prior carries at least half of the curvature along log f) and the reason says what helps.
PRIOR_SET_FOCAL_SHARE = 0.5
PRIOR_SET_FOCAL_HINT = ("the focal prior set most of the focal length (the lines barely constrain it): "
                        "give the focal length, or a FOV range, if the camera is known")
DEFAULT_K_GRID = (1, 2, 3, 5, 8, 12, 17, 25, 35, 50, 70, 90, 120, 160, 220, 300)
PREDICT_BLOCK = 4096  # query rows ranked at once against the training set (memory ~ rows x n_train)


def model_cue_names(mode: str) -> tuple[str, ...]:
    """The cues the shipped model of ``mode`` (``fr`` / ``fast``) uses: fR's all seven (Fast-fR does
    not compute ``focal_profile_gap``)."""
    return FR_MODEL_CUE_NAMES if mode == "fr" else MODEL_CUE_NAMES


def feature_version(names: Sequence[str] = FR_MODEL_CUE_NAMES) -> str:
    """Human-readable description of the features of ``names`` (stored in a model's metadata)."""
    return ", ".join(_CUE_TRANSFORMS[name][1] for name in names) + "; PCA-whitened"


def check_cue_names(names: Sequence[str]) -> tuple[str, ...]:
    """``names`` as a tuple; ValueError for an unknown or repeated cue name."""
    names = tuple(names)
    unknown = [n for n in names if n not in _CUE_TRANSFORMS]
    if unknown or len(set(names)) != len(names) or not names:
        raise ValueError(f"cue names must be distinct names from {list(_CUE_TRANSFORMS)}, got {list(names)}")
    return names


def cue_features(cues: np.ndarray | Sequence, names: Sequence[str] = FR_MODEL_CUE_NAMES) -> np.ndarray:
    """Raw cues (n, c) in the order of ``names`` -> normalised features (n, c) (module docstring)."""
    names = check_cue_names(names)
    c = np.atleast_2d(np.asarray(cues, dtype=np.float64))
    if c.shape[-1] != len(names):
        raise ValueError(f"expected cues with {len(names)} columns {list(names)}, got shape {c.shape}")
    return np.stack([_CUE_TRANSFORMS[name][0](c[:, j]) for j, name in enumerate(names)], 1)


def cues_array(cues: dict | Sequence[dict], names: Sequence[str] = FR_MODEL_CUE_NAMES) -> np.ndarray:
    """A result's ``cues`` dict (or a list of them) -> (n, c) array in the order of ``names`` (NaN
    for a cue the dict lacks, so that its prediction is NaN rather than wrong)."""
    items = [cues] if isinstance(cues, dict) else list(cues)
    return np.array([[float(d.get(name, math.nan)) for name in names] for d in items],
                    dtype=np.float64).reshape(len(items), len(names))


def load_thresholds(path: Path | None = None) -> dict[str, float]:
    """Thresholds (roll deg, tilt deg, focal %) from ``configs/reliability.json`` (defaults if absent)."""
    path = Path(path) if path is not None else _config_dir() / "reliability.json"
    out = dict(DEFAULT_THRESHOLDS)
    if path.is_file():
        out.update({k: float(v) for k, v in json.loads(path.read_text()).get("thresholds", {}).items()})
    return out


def _cv_loss(y_true: np.ndarray, y_pred: np.ndarray) -> float:
    y_true, y_pred = np.atleast_2d(y_true), np.atleast_2d(y_pred)
    return float(np.mean((np.log(y_pred + LOG_EPS) - np.log(y_true + LOG_EPS)) ** 2))


@dataclass
class ReliabilityModel:
    """Whitening of c cues + KNN regressor of |roll error| (deg), |tilt error| (deg), |focal error| (%).

    The cues, in order, are ``meta["cue_names"]`` (:attr:`cue_names`; a file without the key holds
    the paper's three)."""

    train_cues: np.ndarray  # (n, c) raw cues, columns in the order of cue_names
    train_errors: np.ndarray  # (n, 3) absolute errors: roll deg, tilt deg, focal %
    feature_mean: np.ndarray  # (c,)
    feature_components: np.ndarray  # (c, c) rows = eigenvectors, descending eigenvalue
    feature_variance: np.ndarray  # (c,) eigenvalues
    k: int
    meta: dict[str, Any] = field(default_factory=dict)
    thresholds: dict[str, float] = field(default_factory=lambda: dict(DEFAULT_THRESHOLDS))
    # when set (and it has scales for the mode and enforces), `reliable` means the promise, not the thresholds
    promise: ReliabilityPromise | None = None

    def __post_init__(self) -> None:
        self.train_cues = np.asarray(self.train_cues, np.float64)
        self.train_errors = np.asarray(self.train_errors, np.float64)
        self.feature_mean = np.asarray(self.feature_mean, np.float64)
        self.feature_components = np.asarray(self.feature_components, np.float64)
        self.feature_variance = np.asarray(self.feature_variance, np.float64)
        self.k = int(min(self.k, len(self.train_cues)))
        self.cue_names = check_cue_names(self.meta.get("cue_names", PAPER_CUE_NAMES))
        if self.train_cues.ndim != 2 or self.train_cues.shape[1] != len(self.cue_names):
            raise ValueError(f"train_cues of shape {self.train_cues.shape} do not match the cue names "
                             f"{list(self.cue_names)}")
        self._train_w = self.whiten(self.train_cues)

    # ------------------------------------------------------------------ fitting

    @classmethod
    def fit(cls, cues: np.ndarray, errors: np.ndarray, groups: Sequence | None = None,
            k_grid: Sequence[int] | None = None, folds: int = 5, seed: int = 0,
            meta: dict | None = None, thresholds: dict | None = None,
            cue_names: Sequence[str] = MODEL_CUE_NAMES) -> "ReliabilityModel":
        """Fit on raw cues (n, c) -- columns in the order of ``cue_names`` -- and absolute errors
        (n, 3); K by ``folds``-fold CV (scikit-learn).

        ``groups`` (n,): images of one group (panorama, scene) stay in one fold.
        """
        # Training only: importing scikit-learn would add about 1.5 s to every command's start.
        from sklearn.decomposition import PCA
        from sklearn.model_selection import GroupKFold, KFold

        cues = np.asarray(cues, np.float64)
        errors = np.asarray(errors, np.float64)
        good = np.isfinite(cues).all(1) & np.isfinite(errors).all(1)
        cues, errors = cues[good], errors[good]
        groups = None if groups is None else np.asarray(groups)[good]
        n = len(cues)
        if n < 2 * folds:
            raise ValueError(f"need at least {2 * folds} training images, got {n}")
        cue_names = check_cue_names(cue_names)
        features = cue_features(cues, cue_names)
        if groups is not None and len(np.unique(groups)) >= folds:
            # GroupKFold is deterministic; shuffle group order through a seeded relabelling.
            _, inverse = np.unique(groups, return_inverse=True)
            perm = np.random.default_rng(seed).permutation(inverse.max() + 1)
            splits = list(GroupKFold(n_splits=folds).split(features, errors, perm[inverse]))
            cv_name = "GroupKFold"
        else:
            splits = list(KFold(n_splits=folds, shuffle=True, random_state=seed).split(features))
            cv_name = "KFold(shuffle)"
        min_train = min(len(train) for train, _ in splits)
        grid = sorted({int(k) for k in (k_grid or DEFAULT_K_GRID) if 1 <= int(k) <= min_train}) or [1]
        # One neighbour ranking per fold serves every K: the prediction for K is the mean of the
        # first K ranked training errors (what KNeighborsRegressor(K, algorithm="brute") returns).
        sq_err = np.zeros(len(grid))
        for train, test in splits:
            pca = PCA(n_components=len(cue_names), whiten=True).fit(features[train])
            wt, wv = pca.transform(features[train]), pca.transform(features[test])
            order = np.argsort(((wv[:, None] - wt[None]) ** 2).sum(-1), axis=1, kind="stable")[:, :grid[-1]]
            running = np.cumsum(errors[train][order], axis=1)  # (n_test, K_max, 3)
            for j, k in enumerate(grid):
                sq_err[j] += _cv_loss(errors[test], running[:, k - 1] / k) * len(test)
        losses = sq_err / n
        k = int(grid[int(np.argmin(losses))])
        pca = PCA(n_components=len(cue_names)).fit(features)
        info = dict(meta or {})
        info.update(n_train=int(n), k=k, k_grid=grid, folds=folds,
                    cv=cv_name,
                    cv_loss={str(g): float(v) for g, v in zip(grid, losses)},
                    cv_loss_definition="mean over images and targets of (ln(pred + eps) - ln(actual + eps))^2, "
                                       f"eps = {LOG_EPS.tolist()}",
                    features=feature_version(cue_names), cue_names=list(cue_names), targets=list(TARGETS),
                    train_error_median=dict(zip(TARGETS, np.median(errors, 0).tolist())),
                    train_error_mean=dict(zip(TARGETS, errors.mean(0).tolist())))
        return cls(cues, errors, pca.mean_, pca.components_, pca.explained_variance_, k, info,
                   dict(thresholds) if thresholds else load_thresholds())

    # ------------------------------------------------------------------ prediction (plain numpy)

    def whiten(self, cues: np.ndarray) -> np.ndarray:
        """Raw cues (n, c) in the order of :attr:`cue_names` -> whitened features (n, c)."""
        x = cue_features(cues, self.cue_names) - self.feature_mean
        # per row, a sum over the cues in one order (a matrix product's order would depend on n)
        return _sum_in_order(x[:, None, :] * self.feature_components[None]) / np.sqrt(self.feature_variance)

    def predict(self, cues: np.ndarray | dict | Sequence[dict]) -> np.ndarray:
        """Predicted absolute errors (n, 3) [roll deg, tilt deg, focal %] from raw cues (n, c) in the
        order of :attr:`cue_names` or from ``cues`` dicts; NaN rows for missing or non-finite cues.

        Queries are ranked against the training set in blocks of :data:`PREDICT_BLOCK` rows (bounded
        memory for any n; the same answer as one by one)."""
        if isinstance(cues, dict) or (isinstance(cues, (list, tuple)) and cues and isinstance(cues[0], dict)):
            cues = cues_array(cues, self.cue_names)
        w = self.whiten(np.asarray(cues, np.float64))
        out = np.full((len(w), 3), np.nan)
        good = np.flatnonzero(np.isfinite(w).all(1))
        for b0 in range(0, len(good), PREDICT_BLOCK):
            rows = good[b0:b0 + PREDICT_BLOCK]
            d2 = _sum_in_order((w[rows, None, :] - self._train_w[None]) ** 2)
            idx = np.argsort(d2, axis=1, kind="stable")[:, :self.k]
            out[rows] = _sum_in_order(np.moveaxis(self.train_errors[idx], 1, -1)) / self.k
        return out

    @property
    def trained_for(self) -> dict[str, str]:
        """The setting the model was trained on: ``measure`` (deviation measure), ``detector``
        (name of the line detector) and ``likelihood`` (likelihood config name, ``default`` =
        ``configs/likelihood.json``); :data:`DEFAULT_TRAINED_FOR` where the file does not say."""
        return {**DEFAULT_TRAINED_FOR, **self.meta.get("trained_for", {})}

    @property
    def detectors(self) -> tuple[str, ...]:
        """Names of the line detectors whose segments the model applies to: the one it was trained
        on (``trained_for["detector"]``) and those its promise was validated on
        (:attr:`~fr_torch.core.reliability.bounds.ReliabilityPromise.validated_detectors`)."""
        validated = self.promise.validated_detectors if self.promise is not None else ()
        return tuple(dict.fromkeys([self.trained_for["detector"], *validated]))

    def scope_gap(self, likelihood_params, likelihood_name: str, detector: str | None = None,
                  mode: str | None = None) -> str | None:
        """Why this model's predictions do not apply to an estimator's results, or None when they do.

        The cues, and the errors they predict, depend on the deviation measure, the likelihood and
        the segments' detector: a model predicts only for the setting it was trained on
        (:attr:`trained_for`).  ``likelihood_params``: the estimator's
        :class:`~fr_torch.core.likelihood.mixture.LikelihoodParams` (before its FOV range is applied), compared
        with those of the trained measure and likelihood config in ``mode``; ``likelihood_name``: what
        the message calls them.  ``detector``: the name of the detector that produced the segments,
        None when they came from the caller (not checked); it must be one of :attr:`detectors`, and
        the message then names them."""
        trained = self.trained_for
        gaps = []
        if likelihood_params.measure != trained["measure"]:
            gaps.append(f"measure {likelihood_params.measure}")
        elif likelihood_params != _trained_params(trained["measure"], trained["likelihood"], mode):
            gaps.append(f"likelihood {likelihood_name}")
        valid = self.detectors
        if detector is not None and detector not in valid:
            gaps.append(f"detector {detector}")
        if not gaps:
            return None
        message = (f"reliability model not trained for {' and '.join(gaps)} (trained for measure {trained['measure']}, "
                   f"detector {trained['detector']}, likelihood {trained['likelihood']}): no predicted error")
        if detector is not None and detector not in valid:
            message += f"; for a trusted `reliable`, detect with {' or '.join(valid)} (--detector)"
        return message

    @property
    def needs_spreads(self) -> bool:
        """True when the model holds a promise: its bounds rest on the spread cues
        (:data:`fr_torch.core.reliability.cues.SPREAD_CUE_NAMES`), which the estimator then computes."""
        return self.promise is not None

    def predict_dict(self, cues: dict) -> dict[str, float]:
        return dict(zip(TARGETS, (float(v) for v in self.predict(cues)[0])))

    def annotate(self, result, mode: str | None = None):
        """:meth:`annotate_many` for one result."""
        self.annotate_many([result], mode)
        return result

    def annotate_many(self, results: Sequence, mode: str | None = None,
                      focal_known: Sequence[bool] | None = None) -> None:
        """:meth:`annotate` for many results with one prediction call (results with ``ok`` False are
        left alone): ``predicted_error`` from the KNN, ``error_bound`` from the promise's bounds
        (:meth:`~fr_torch.core.reliability.bounds.ReliabilityPromise.bounds`, from the result's
        spread cues) and ``reliable = False`` with the reason when a bound exceeds its limit (the
        promise enforced) or a predicted error its threshold (not enforced, or no promise).
        ``focal_known`` (one bool per result): the focal length was given, not estimated; its
        predicted error and bound are then 0 (the estimate's focal length *is* the given one,
        whatever its own error)."""
        mine = self.meta.get("mode")
        if mode is not None and mine is not None and mode != mine:
            raise ValueError(f"reliability model was trained for mode {mine!r}, result comes from {mode!r}")
        known = [False] * len(results) if focal_known is None else [bool(k) for k in focal_known]
        if len(known) != len(results):
            raise ValueError(f"focal_known has {len(known)} entries for {len(results)} results")
        todo = [(r, k) for r, k in zip(results, known) if getattr(r, "ok", False)]
        if not todo:
            return
        predictions = self.predict(cues_array([r.cues for r, _ in todo], self.cue_names))
        horizon_bounds = self._horizon_bounds(todo, mode or mine)
        for (result, given), row, horizon_bound in zip(todo, predictions.tolist(), horizon_bounds):
            predicted = dict(zip(TARGETS, row))
            if given:
                predicted["focal_pct"] = 0.0
            result.predicted_error = predicted
            bounds = self.promise.bounds(result.cues, mode or mine, given) if self.promise is not None else None
            if bounds is not None:
                result.error_bound = {"coverage": self.promise.coverage,  # None: no bound (missing cues)
                                      **{k: (v if math.isfinite(v) else None) for k, v in bounds.items()},
                                      "limits": dict(self.promise.limits), "enforced": self.promise.enforce}
                self._horizon_promise(result, float(horizon_bound))
                if not self.promise.enforce:
                    bounds = None  # reported only: `reliable` keeps the thresholds below
            if bounds is not None:
                over = self.promise.violations(bounds)
            else:
                over = [f"{name.split('_')[0]} {predicted[name]:.1f}{' %' if name == 'focal_pct' else ' deg'} > "
                        f"{limit:g}{' %' if name == 'focal_pct' else ' deg'}"
                        for name, limit in self.thresholds.items()
                        if not (predicted.get(name, math.nan) <= limit)]
            if over:
                message = ("outside the promise: " if bounds is not None
                           else "predicted error above threshold: ") + ", ".join(over)
                focal_over = (not bounds.get("focal_pct", 0.0) <= self.promise.limits.get("focal_pct", math.inf)) \
                    if bounds is not None \
                    else not predicted["focal_pct"] <= self.thresholds.get("focal_pct", math.inf)
                if (not given and focal_over
                        and result.cues.get("focal_prior_share", 0.0) >= PRIOR_SET_FOCAL_SHARE):
                    message += f"; {PRIOR_SET_FOCAL_HINT}"
                result.reliable = False
                result.reason = f"{result.reason}; {message}" if result.reason else message

    def _horizon_bounds(self, todo: Sequence, mode: str) -> list[float]:
        """The horizon promise's bounds (% of the height; NaN: none) of ``todo`` ((result,
        focal given) pairs), computed for all of them at once."""
        horizon = self.promise.horizon if self.promise is not None else None
        if horizon is None:
            return [math.nan] * len(todo)

        def column(values) -> np.ndarray:
            return np.array([math.nan if v is None else float(v) for v in values], np.float64)

        cues = {name: column(r.cues.get(name) for r, _ in todo) for name in HORIZON_CUE_NAMES}
        return horizon.bounds(cues, mode, column(r.focal_px for r, _ in todo), column(r.tilt_deg for r, _ in todo),
                              column(r.height for r, _ in todo), np.array([given for _, given in todo], bool)).tolist()

    def _horizon_promise(self, result, bound: float) -> None:
        """The horizon promise of one result (before the focal / tilt promise touches ``reliable``)
        given its bound (:meth:`_horizon_bounds`): ``error_bound["horizon_pct"]`` and its limit,
        ``horizon_reliable`` (the sanity checks passed -- ``reliable`` still True -- and the bound
        within its limit or, with ``or_focal_tilt``, the focal / tilt bounds within theirs) and
        ``horizon_reason``.  No-op without a horizon block in the promise."""
        horizon = self.promise.horizon
        if horizon is None:
            return
        result.error_bound["horizon_pct"] = bound if math.isfinite(bound) else None
        result.error_bound["limits"]["horizon_pct"] = horizon.limit_pct
        focal_tilt = {k: v if v is not None else math.nan for k, v in result.error_bound.items() if k in self.promise.limits}
        why = horizon.violation(bound, self.promise.coverage, focal_tilt_kept=not self.promise.violations(focal_tilt))
        result.horizon_reliable = bool(result.reliable) and why is None
        reasons = ("" if result.reliable else result.reason, f"outside the horizon promise: {why}" if why else "")
        result.horizon_reason = "; ".join(r for r in reasons if r)

    # ------------------------------------------------------------------ storage

    def save(self, path: str | Path) -> Path:
        """Write ``path`` (.npz, no pickled objects) and the metadata sidecar ``path.with_suffix('.json')``."""
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        meta = dict(self.meta, k=self.k)
        np.savez(path, train_cues=self.train_cues, train_errors=self.train_errors, feature_mean=self.feature_mean,
                 feature_components=self.feature_components, feature_variance=self.feature_variance,
                 k=np.array(self.k, np.int64), meta_json=np.array(json.dumps(meta, sort_keys=True)))
        sidecar = dict(meta, arrays={"train_cues": list(self.train_cues.shape),
                                     "train_errors": list(self.train_errors.shape),
                                     "feature_mean": self.feature_mean.tolist(),
                                     "feature_components": self.feature_components.tolist(),
                                     "feature_variance": self.feature_variance.tolist()})
        path.with_suffix(".json").write_text(json.dumps(sidecar, indent=1, sort_keys=True) + "\n")
        return path

    @classmethod
    def load(cls, path: str | Path, thresholds: dict | None = None,
             promise: ReliabilityPromise | None = None) -> "ReliabilityModel":
        with np.load(Path(path), allow_pickle=False) as data:
            arrays = {key: data[key] for key in data.files}
        meta = json.loads(str(arrays["meta_json"]))
        return cls(arrays["train_cues"], arrays["train_errors"], arrays["feature_mean"],
                   arrays["feature_components"], arrays["feature_variance"], int(arrays["k"]), meta,
                   dict(thresholds) if thresholds else load_thresholds(), promise)

    @classmethod
    def load_default(cls, mode: str | None = None, config_dir: str | Path | None = None):
        """Default models from ``configs/``: with ``mode`` the :class:`ReliabilityModel` of that mode,
        without it a :class:`ReliabilitySet` of the modes present; None when no model file exists
        (or a file cannot be read: a warning goes to stderr)."""
        folder = Path(config_dir) if config_dir is not None else _config_dir()
        thresholds = load_thresholds(folder / "reliability.json")
        try:
            promise = ReliabilityPromise.from_config(folder / "reliability.json")
        except (OSError, ValueError, KeyError, TypeError) as exc:
            print(f"fr: warning: cannot read the reliability promise in {folder / 'reliability.json'}: {exc}",
                  file=sys.stderr)
            promise = None
        models = {}
        for m in ([mode] if mode else [str(m) for m in Mode]):
            path = folder / f"reliability_{m}.npz"
            if path.is_file():
                try:
                    models[m] = cls.load(path, thresholds, promise)
                except (OSError, ValueError, KeyError) as exc:
                    print(f"fr: warning: cannot read reliability model {path}: {exc}", file=sys.stderr)
        if not models:
            return None
        return models[mode] if mode else ReliabilitySet(models)


@functools.lru_cache(maxsize=32)
def _trained_params(measure: str, likelihood: str, mode: str | None):
    """The likelihood parameters of a model's training setting (:meth:`ReliabilityModel.scope_gap`)."""

    return LikelihoodParams.from_config(measure, None if likelihood == "default" else likelihood,
                                        mode=None if mode is None else str(mode))


@dataclass
class ReliabilitySet:
    """The default models per estimator mode (``fr``, ``fast``); :meth:`annotate` picks by mode."""

    models: dict[str, ReliabilityModel]

    def annotate(self, result, mode: str = "fr"):
        model = self.models.get(mode)
        return model.annotate(result, mode) if model is not None else result

    def annotate_many(self, results: Sequence, mode: str = "fr", focal_known: Sequence[bool] | None = None) -> None:
        model = self.models.get(mode)
        if model is not None:
            model.annotate_many(results, mode, focal_known)

    def predict(self, cues, mode: str = "fr") -> np.ndarray:
        return self.models[mode].predict(cues)

    @property
    def needs_spreads(self) -> bool:
        """True when a model of the set holds a promise (:attr:`ReliabilityModel.needs_spreads`)."""
        return any(model.needs_spreads for model in self.models.values())

    def scope_gap(self, likelihood_params, likelihood_name: str, detector: str | None = None,
                  mode: str = "fr") -> str | None:
        """:meth:`ReliabilityModel.scope_gap` of the model of ``mode`` (None without one)."""
        model = self.models.get(mode)
        return None if model is None else model.scope_gap(likelihood_params, likelihood_name, detector, mode)
