"""Extra line-segment detectors, found by name through the entry points of group
``fr_torch.detectors`` declared in pyproject.toml (see :data:`fr_torch.segments.DETECTORS`).

* ``mcmlsd``: :class:`~fr_torch.detectors.mcmlsd.MCMLSDDetector` (Almazan et al., CVPR 2017).
* ``onnx``: :class:`~fr_torch.detectors.onnx_detector.OnnxLineDetector`, a learned detector
  supplied by the user as an ONNX model (``model_path=...``); needs ``onnxruntime`` only when used.
* ``torch-lines``: :class:`~fr_torch.detectors.tensor_lines.TensorLinesDetector`, orientation
  regions from batched tensor operations (CPU or GPU; ``detect_batch`` for a batch on the device).
"""
from __future__ import annotations

from .mcmlsd import MCMLSDConfig, MCMLSDDetector
from .onnx_detector import OnnxLineDetector
from .tensor_lines import TensorLinesConfig, TensorLinesDetector

__all__ = ["MCMLSDConfig", "MCMLSDDetector", "OnnxLineDetector", "TensorLinesConfig", "TensorLinesDetector"]
