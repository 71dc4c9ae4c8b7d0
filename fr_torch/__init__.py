"""fR in PyTorch: reliable single-image estimation of focal length and camera rotation.

Pipeline (one module each): segments -> likelihood -> search -> reliability, wrapped by the
estimator; conventions in :mod:`fr_torch.camera`.

The names below are loaded on first use (PEP 562), so ``import fr_torch`` and the command line's
start-up do not import torch until something needs it.
"""
from __future__ import annotations

import importlib

# public name -> module that defines it
_EXPORTS = {
    "VERTICAL_AXIS": "camera", "Camera": "camera", "angles_from_rotation": "camera",
    "focal_from_hfov": "camera", "hfov_from_focal": "camera", "rotation_from_angles": "camera",
    "CalibrationResult": "estimator", "FREstimator": "estimator", "calibrate": "estimator",
    "FRInputError": "segments", "SegmentFilter": "segments", "detect_segments": "segments",
}
__all__ = sorted(_EXPORTS)
__version__ = "0.1.0"


def __getattr__(name: str):
    if name in _EXPORTS:
        value = getattr(importlib.import_module(f".{_EXPORTS[name]}", __name__), name)
        globals()[name] = value  # later lookups skip this function
        return value
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__():
    return sorted(set(globals()) | set(_EXPORTS))
