"""The horizon benchmark's metric (Barinova et al. 2010, Lezama et al. 2014, Zhai et al. 2016), as
Lezama et al.'s published evaluation code computes it.

1. **Per photo** (:meth:`fr_torch.core.geometry.horizon.Horizon.error`): the larger of the vertical distances
   between the estimated and the labelled horizon at the left and right image borders, ``x = 0`` and
   ``x = w - 1`` (:func:`fr_torch.core.geometry.horizon.border_columns`; the code's MATLAB columns 1 and W),
   divided by the image height.  A method that gives no horizon (a failure, a vertical horizon)
   scores infinity: beyond the cutoff.
2. **AUC** (:func:`lezama_auc`, ``calc_auc.m`` of ``jlezama/VPdetection-CVPR14``, used by its
   ``yud_benchmark.m`` and ``ecd_benchmark.m``): the errors sorted and clipped at 0.25, the points
   ``(e_i, i / n)`` followed by ``(0.25, 1)``, the trapezoidal area under them divided by 0.25.  The
   curve starts at the smallest error (no point at the origin) and is linear between errors; the
   area under the exact cumulative step function is lower (fR on ``ecd-tune``: 89.7 here, 87.7 as a
   step function), so numbers are comparable only with this rule.  Kluger et al.'s horizon code
   (``calc_auc`` with a cutoff of 0.25) closes the curve differently at the cutoff; the two agree
   whenever no error lies beyond 0.25.

Ground truth (:func:`truth_horizons`): the horizon definitions a sample carries as lines in
``extra["horizons"]`` (name -> (3,) ``(a, b, c)`` in pixels; their wording in
``extra["horizon_notes"]``) and, when the sample's camera knows K and the vertical, ``frame``: that
camera's horizon ``K^-T R[:, 1]``.  Every table names the definition it scores against.
"""
from __future__ import annotations

import math
from typing import Any, Sequence

import numpy as np

from fr_torch.core.geometry.horizon import Horizon

CUTOFF = 0.25
#: The horizon of the sample's ground-truth camera (its K and vertical).
FRAME = "frame"
FRAME_NOTE = "the ground-truth camera's horizon K^-T R[:, 1] (its labelled / orthogonalised vertical)"


def lezama_auc(errors: Sequence[float], cutoff: float = CUTOFF) -> tuple[float, np.ndarray]:
    """(AUC in [0, 1], the curve's points (n + 1, 2) ``[error, share]``) of per-photo horizon errors
    (fractions of the image height), as Lezama et al.'s ``calc_auc.m`` (module docstring).  NaN or
    infinite errors count as beyond the cutoff; NaN for no errors."""
    values = np.asarray(errors, np.float64).ravel()
    n = len(values)
    if n == 0:
        return math.nan, np.zeros((0, 2))
    clipped = np.minimum(np.sort(np.where(np.isnan(values), np.inf, values)), cutoff)
    points = np.c_[np.r_[clipped, cutoff], np.r_[np.arange(1, n + 1), n] / n]
    area = float(np.sum(np.diff(points[:, 0]) * (points[1:, 1] + points[:-1, 1]) / 2.0))
    return area / cutoff, points


def truth_horizons(sample: Any) -> dict[str, Horizon]:
    """The sample's ground-truth horizons by definition name (module docstring); {} without any."""
    extra = getattr(sample, "extra", None) or {}
    width, height = int(sample.width), int(sample.height)
    out = {name: Horizon.from_line(line, width, height) for name, line in (extra.get("horizons") or {}).items()}
    camera = getattr(sample, "camera", None)
    frame = Horizon.from_camera(camera) if camera is not None else None
    if frame is not None:
        out[FRAME] = frame
    return {name: horizon for name, horizon in out.items() if horizon is not None}


def definition_notes(samples: Sequence[Any]) -> dict[str, str]:
    """Definition name -> its wording, over ``samples`` (first sample that states it)."""
    notes: dict[str, str] = {}
    for sample in samples:
        for name in truth_horizons(sample):
            stated = ((getattr(sample, "extra", None) or {}).get("horizon_notes") or {}).get(name)
            notes.setdefault(name, stated or (FRAME_NOTE if name == FRAME else name))
    return notes


def estimate_horizon(estimate: Any) -> Horizon | None:
    """The horizon of a method's estimate (a :class:`~fr_torch.plugins.interface.CameraEstimate`):
    :meth:`Horizon.from_camera` of its camera, through its division-model lens when
    ``extra["distortion"]`` has one, with fR's bound when ``extra["horizon_bound_pct"]`` holds it;
    None for a failure or an estimate without a focal length and vertical."""
    if estimate is None or not getattr(estimate, "ok", False) or estimate.camera is None:
        return None
    extra = getattr(estimate, "extra", None) or {}
    k = float((extra.get("distortion") or {}).get("k") or 0.0)
    return Horizon.from_camera(estimate.camera, k, extra.get("horizon_bound_pct"))
