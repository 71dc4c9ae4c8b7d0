"""Baseline calibration methods behind the common :class:`fr_torch.interface.Calibrator` interface.

Importing this package registers: ``lee2009`` (orthogonal VP triplet over a focal sweep),
``simon2018`` (a-contrario horizon-first VPs), ``ctrlc`` and ``ctrlc-retrained`` (CTRL-C through
onnxruntime, two trainings, weights supplied by the user), ``external`` and ``hold-geoffroy2018``
(per-image predictions from a CSV) and ``prior`` (60 deg HFOV, upright camera).  Shared VP
geometry lives in :mod:`baselines.vp_geometry`.
"""
from . import ctrlc, external, lee2009, prior, simon2018  # noqa: F401  (register on import)
from .ctrlc import CTRLC
from .external import ExternalPredictions
from .lee2009 import Lee2009
from .prior import Prior
from .simon2018 import Simon2018

__all__ = ["CTRLC", "ExternalPredictions", "Lee2009", "Prior", "Simon2018"]
