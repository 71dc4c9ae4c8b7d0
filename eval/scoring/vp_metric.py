"""Vanishing-point accuracy as CONSAC (Kluger et al., CVPR 2020) measures it, reproduced exactly.

The metric of CONSAC's ``evaluate_vp.py`` (``util/evaluation.py`` and ``util/auc.py`` of
``fkluger/consac``), written here from its definition (docs/vp.md states it in full):

1. **Directions.**  Every vanishing point (VP) becomes a unit direction in the camera frame with
   the dataset's *calibrated* intrinsics ``K`` (not the method's): ``d = K^-1 v / |K^-1 v|`` for
   a homogeneous VP ``v`` in pixels (:func:`directions_from_vps`).  Labelled VPs of a dataset
   that stores directions (YUD) are used as given.
2. **Truncation.**  A method's VPs are ranked by its own confidence, most confident first; only
   the first ``n_gt`` are scored, ``n_gt`` = the number of labelled VPs of the image.
3. **Cost.**  The angle between lines of sight, ``arccos |d_gt . d_est|`` in degrees (0-90; the
   cosine is clipped to [0, 1] against rounding, where CONSAC's code would give NaN).
4. **Matching.**  Hungarian matching of labelled to estimated VPs on that cost
   (``scipy.optimize.linear_sum_assignment``); every labelled VP left unmatched (the method
   reported fewer VPs than were labelled) counts :data:`MISSING_VP_DEG` = 90 degrees.
5. **Pooling.**  The errors of every labelled VP of every image of the split are pooled into one
   list (one error per labelled VP, :func:`match_errors`).
6. **AUC.**  :func:`consac_auc`, the area under the recall curve up to a cutoff, normalised by the
   cutoff, exactly as CONSAC's ``calc_auc`` computes it -- including its two particularities: the
   curve starts at the smallest error (no point at the origin), and the curve's value at the
   cutoff is CONSAC's ``(e_lo r_lo + e_hi r_hi) / (e_lo + e_hi)`` from the two errors around the
   cutoff (not a linear interpolation).  Reported as percentages at 5, 10 and 20 degrees.
"""
from __future__ import annotations

from typing import Sequence

import numpy as np
from scipy.optimize import linear_sum_assignment

MISSING_VP_DEG = 90.0
AUC_CUTOFFS_DEG = (5.0, 10.0, 20.0)
_TINY = 1e-16


def directions_from_vps(vps: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Unit camera-frame directions (M, 3) ``K^-1 v`` of homogeneous VPs (M, 3), pixels.

    Rows ``(x, y, w)``; ``w = 0`` is a VP at infinity.  Signs are arbitrary (the cost uses
    ``|d . d'|``).  A zero row stays zero (it then matches nothing better than 90 degrees).
    """
    vps = np.asarray(vps, np.float64).reshape(-1, 3)
    d = np.linalg.solve(np.asarray(K, np.float64), vps.T).T
    return d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), _TINY)


def angle_cost_deg(true_dirs: np.ndarray, est_dirs: np.ndarray) -> np.ndarray:
    """(G, E) angles in degrees between lines of sight, ``arccos |d_g . d_e|`` (unit rows)."""
    cosine = np.abs(np.asarray(true_dirs, np.float64) @ np.asarray(est_dirs, np.float64).T)
    return np.degrees(np.arccos(np.clip(cosine, 0.0, 1.0)))


def match_errors(true_dirs: np.ndarray, est_dirs: np.ndarray | None) -> np.ndarray:
    """One error (degrees) per labelled VP of one image (module docstring, steps 2-4).

    ``true_dirs`` (G, 3) unit labelled directions; ``est_dirs`` (E, 3) unit estimated directions
    ranked by the method's confidence (None or empty: nothing estimated).  Only the first G
    estimates are scored; labelled VPs without a partner get :data:`MISSING_VP_DEG`.  The errors
    are returned in the labelled VPs' order.
    """
    true_dirs = np.asarray(true_dirs, np.float64).reshape(-1, 3)
    errors = np.full(len(true_dirs), MISSING_VP_DEG)
    if est_dirs is None or not len(true_dirs):
        return errors
    est_dirs = np.asarray(est_dirs, np.float64).reshape(-1, 3)[: len(true_dirs)]
    if not len(est_dirs):
        return errors
    cost = angle_cost_deg(true_dirs, est_dirs)
    rows, cols = linear_sum_assignment(cost)
    errors[rows] = cost[rows, cols]
    return errors


def consac_auc(errors_deg: Sequence[float], cutoff_deg: float) -> tuple[float, np.ndarray]:
    """(AUC in [0, 1], curve points (P, 2) ``[error, recall]``) of pooled VP errors, as CONSAC.

    Recall curve: the sorted errors ``e_1 <= ... <= e_n`` with recall ``i / n``, then the point
    ``(cutoff, r_c)`` where ``r_c = 1`` if every error is below the cutoff, else
    ``(e_k r_k + e_{k+1} r_{k+1}) / (e_k + e_{k+1})`` for the last pair with
    ``e_k < cutoff < e_{k+1}`` (1 when there is none).  AUC = trapezoidal area of the points with
    error <= cutoff, divided by the cutoff.  The sort is stable (CONSAC's ``argsort`` is not; the
    order of equal errors changes nothing but an error exactly at the cutoff, never seen here).
    """
    errors = np.sort(np.asarray(errors_deg, np.float64).ravel())
    n = len(errors)
    if n == 0:
        return float("nan"), np.zeros((0, 2))
    recall = np.arange(1, n + 1) / n
    at_cutoff = 1.0
    straddle = np.flatnonzero((errors[:-1] < cutoff_deg) & (cutoff_deg < errors[1:]))
    if len(straddle):
        k = straddle[-1]
        low, high = errors[k], errors[k + 1]
        at_cutoff = (low * recall[k] + high * recall[k + 1]) / (high + low)
    if errors[-1] < cutoff_deg:
        at_cutoff = 1.0
    points = np.vstack([np.c_[errors, recall], [cutoff_deg, at_cutoff]])
    points = points[np.argsort(points[:, 0], kind="stable")]
    inside = points[points[:, 0] <= cutoff_deg]
    if len(inside) < 2:
        return 0.0, points
    area = float(np.sum(np.diff(inside[:, 0]) * (inside[1:, 1] + inside[:-1, 1]) / 2.0))
    return area / cutoff_deg, points


def auc_table(errors_deg: Sequence[float], cutoffs_deg: Sequence[float] = AUC_CUTOFFS_DEG) -> dict[str, float]:
    """``{"auc5": ..., "auc10": ..., "auc20": ...}``: :func:`consac_auc` in percent per cutoff."""
    return {f"auc{cutoff:g}": 100.0 * consac_auc(errors_deg, cutoff)[0] for cutoff in cutoffs_deg}


def recall_curve(errors_deg: Sequence[float], max_deg: float, steps: int = 401) -> tuple[np.ndarray, np.ndarray]:
    """(thresholds (steps,), recall (steps,)): share of pooled errors <= each threshold in [0, max]."""
    errors = np.sort(np.asarray(errors_deg, np.float64).ravel())
    thresholds = np.linspace(0.0, max_deg, steps)
    if not len(errors):
        return thresholds, np.full(steps, np.nan)
    return thresholds, np.searchsorted(errors, thresholds, side="right") / len(errors)
