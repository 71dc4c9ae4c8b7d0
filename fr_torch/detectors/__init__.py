"""Extra line-segment detectors, registered with :func:`fr_torch.segments.register_detector`.

* ``mcmlsd``: :class:`~fr_torch.detectors.mcmlsd.MCMLSDDetector` (Almazan et al., CVPR 2017).
* ``onnx``: :class:`~fr_torch.detectors.onnx_detector.OnnxLineDetector`, a learned detector
  supplied by the user as an ONNX model (``model_path=...``); needs ``onnxruntime`` only when used.
"""
from __future__ import annotations

from ..segments import register_detector
from .mcmlsd import MCMLSDConfig, MCMLSDDetector
from .onnx_detector import OnnxLineDetector

register_detector("mcmlsd", MCMLSDDetector)
register_detector("onnx", OnnxLineDetector)

__all__ = ["MCMLSDConfig", "MCMLSDDetector", "OnnxLineDetector"]
