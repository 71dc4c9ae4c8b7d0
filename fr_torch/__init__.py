"""fR in PyTorch: reliable single-image estimation of focal length and camera rotation.

Layers, each importing only those below it:

* :mod:`fr_torch.core` -- the tensor engine: camera conventions, settings (FOV range, modes,
  search configuration), the mixture likelihood, the two-stage search, reliability cues and the
  error model, and :class:`~fr_torch.core.estimator.SegmentEstimator` over padded segment batches.
* :mod:`fr_torch.images`, :mod:`fr_torch.detectors` -- decoding untrusted image files, colour
  conversion, line-segment detectors by name, overlays.
* :mod:`fr_torch.runtime` -- the public :class:`FREstimator` on images, the decode + detect +
  search pipeline over worker processes, the device policy, result output.
* :mod:`fr_torch.batch`, :mod:`fr_torch.video` -- ``fr batch`` jobs (local or Ray) and online
  recalibration over a video.
* :mod:`fr_torch.plugins` -- the common calibrator interface and registries; :mod:`fr_torch.cli`
  -- the ``fr`` command.

The names below are loaded on first use (PEP 562), so ``import fr_torch`` and the command line's
start-up do not import torch until something needs it.
"""
from __future__ import annotations

import importlib

# public name -> module that defines it
_EXPORTS = {
    "VERTICAL_AXIS": "core.geometry.conventions", "Camera": "core.geometry.camera",
    "angles_from_rotation": "core.geometry.conventions", "focal_from_hfov": "core.geometry.conventions",
    "hfov_from_focal": "core.geometry.conventions", "rotation_from_angles": "core.geometry.conventions",
    "FovRange": "core.settings.fov", "Mode": "core.settings.config", "SearchConfig": "core.settings.config",
    "CalibrationResult": "core.result", "SegmentEstimator": "core.estimator",
    "FREstimator": "runtime.estimator", "calibrate": "runtime.estimator", "DevicePolicy": "runtime.device",
    "FRInputError": "errors", "SegmentFilter": "core.likelihood.segments", "detect_segments": "detectors.registry",
    "calibrate_shared": "runtime.shared_focal", "FocalPrior": "runtime.focal_prior",
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
