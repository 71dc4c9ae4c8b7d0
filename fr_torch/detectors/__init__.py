"""Line-segment detectors, found by name (:mod:`fr_torch.detectors.registry`).

* ``lsd``: :class:`~fr_torch.detectors.lsd.LSDDetector`, OpenCV's LSD (the default).
* ``mcmlsd``: :class:`~fr_torch.detectors.mcmlsd.MCMLSDDetector` (Almazan et al., CVPR 2017).
* ``onnx``: :class:`~fr_torch.detectors.onnx_detector.OnnxLineDetector`, a learned detector
  supplied by the user as an ONNX model (``model_path=...``); needs ``onnxruntime`` only when used.
* ``torch-lines``: :class:`~fr_torch.detectors.tensor_lines.TensorLinesDetector`, orientation
  regions from batched tensor operations (CPU or GPU; ``detect_batch`` for a batch on the device).
"""
