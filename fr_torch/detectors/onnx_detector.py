"""Adapter for learned line-segment detectors exported to ONNX (the user supplies the model).

Model contract (what :class:`OnnxLineDetector` feeds and expects):

* **Input**: one tensor, ``float32`` of shape ``(1, C, H_in, W_in)``: the image resized (bilinear)
  to ``input_size = (W_in, H_in)``, ``C = 1`` (grey) or ``C = 3`` (``RGB`` order), values
  ``(pixel / 255 - mean) / std`` per channel (defaults ``mean = 0``, ``std = 1``, i.e. ``[0, 1]``).
  If the model declares fixed spatial dimensions they are used when ``input_size`` is not given.
* **Outputs**: ``segments`` of shape ``(1, N, 4)`` or ``(N, 4)``, ``[x1, y1, x2, y2]`` in
  pixels of the *model input* (same convention as the project: x right, y down, origin at the
  centre of the top-left pixel), and optionally ``scores`` of shape ``(1, N)`` or ``(N,)``.
  Outputs are taken by name (``segments_output`` / ``scores_output``) or, by default, as the
  first and second outputs.  Models whose coordinates are normalised to ``[0, 1]`` of the input
  width / height (``x_in = x_norm * W_in - 0.5``) set ``normalized=True``.

Segments with ``score < score_threshold`` (when scores exist) or non-finite coordinates are
dropped; the rest are rescaled to the original image (pixel centres map as
``x = (x_in + 0.5) * W / W_in - 0.5``) and returned sorted by decreasing score.
``onnxruntime`` is imported only when a detector is built.
"""
from __future__ import annotations

from pathlib import Path
from typing import Sequence

import cv2
import numpy as np

from fr_torch.core.geometry.conventions import resize_points


class OnnxLineDetector:
    """Run a user-supplied ONNX line-segment model as a project detector (see module doc)."""

    name = "onnx"

    def __init__(self, model_path: str | Path | None = None, input_size: tuple[int, int] | None = None,
                 channels: int | None = None, mean: float | Sequence[float] = 0.0,
                 std: float | Sequence[float] = 1.0, score_threshold: float = 0.0,
                 normalized: bool = False, segments_output: str | None = None,
                 scores_output: str | None = None, providers: Sequence[str] | None = None):
        if model_path is None:
            raise ValueError("OnnxLineDetector needs model_path=... (an ONNX line-segment model)")
        path = Path(model_path)
        if not path.is_file():
            raise FileNotFoundError(f"{path}: no such ONNX model")
        try:
            import onnxruntime as ort
        except ImportError as exc:  # pragma: no cover - depends on the environment
            raise RuntimeError("the 'onnx' detector needs onnxruntime (pip install onnxruntime)") from exc
        self.session = ort.InferenceSession(str(path), providers=list(providers or ["CPUExecutionProvider"]))
        inp = self.session.get_inputs()[0]
        self._input_name = inp.name
        shape = list(inp.shape)
        if len(shape) != 4:
            raise ValueError(f"{path}: expected a 4-D (1, C, H, W) input, got {shape}")
        declared_c = shape[1] if isinstance(shape[1], int) else None
        self.channels = int(channels or declared_c or 1)
        if self.channels not in (1, 3):
            raise ValueError(f"channels must be 1 (grey) or 3 (RGB), got {self.channels}")
        if input_size is None:
            if not (isinstance(shape[2], int) and isinstance(shape[3], int)):
                raise ValueError(f"{path}: input has dynamic size {shape}; pass input_size=(W, H)")
            input_size = (shape[3], shape[2])
        self.input_size = (int(input_size[0]), int(input_size[1]))
        self.mean = np.broadcast_to(np.asarray(mean, np.float32), (self.channels,)).reshape(-1, 1, 1)
        self.std = np.broadcast_to(np.asarray(std, np.float32), (self.channels,)).reshape(-1, 1, 1)
        self.score_threshold = float(score_threshold)
        self.normalized = bool(normalized)
        names = [o.name for o in self.session.get_outputs()]
        self._seg_name = segments_output or names[0]
        self._score_name = scores_output or (names[1] if len(names) > 1 else None)
        for n in (self._seg_name, self._score_name):
            if n is not None and n not in names:
                raise ValueError(f"{path}: no output named {n!r}; outputs are {names}")

    def preprocess(self, gray: np.ndarray) -> np.ndarray:
        """The model input (1, C, H_in, W_in) float32 for an image (grey or BGR uint8)."""
        image = np.asarray(gray)
        w_in, h_in = self.input_size
        if self.channels == 1:
            if image.ndim == 3:
                image = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
            image = image[None]
        else:
            if image.ndim == 2:
                image = cv2.cvtColor(image, cv2.COLOR_GRAY2RGB)
            else:
                image = cv2.cvtColor(image, cv2.COLOR_BGR2RGB)
            image = image.transpose(2, 0, 1)
        resized = np.stack([cv2.resize(c, (w_in, h_in), interpolation=cv2.INTER_LINEAR) for c in image])
        x = (resized.astype(np.float32) / 255.0 - self.mean) / self.std
        return np.ascontiguousarray(x[None], dtype=np.float32)

    def detect(self, gray: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Segments (N, 4) float64 in original-image pixels and their scores, best first."""
        gray = np.asarray(gray)
        height, width = gray.shape[:2]
        wanted = [self._seg_name] + ([self._score_name] if self._score_name else [])
        outputs = self.session.run(wanted, {self._input_name: self.preprocess(gray)})
        segments = np.asarray(outputs[0], np.float64)
        if segments.ndim == 3:
            segments = segments[0]
        segments = segments.reshape(-1, 4)
        if self._score_name:
            scores = np.asarray(outputs[1], np.float64).reshape(-1)
            if scores.shape[0] != segments.shape[0]:
                raise ValueError(f"model returned {segments.shape[0]} segments but {scores.shape[0]} scores")
        else:
            scores = np.ones(segments.shape[0])
        keep = np.isfinite(segments).all(1) & np.isfinite(scores) & (scores >= self.score_threshold)
        segments, scores = segments[keep], scores[keep]
        w_in, h_in = self.input_size
        if self.normalized:
            segments = segments * np.array([w_in, h_in, w_in, h_in], np.float64) - 0.5
        segments = resize_points(segments, (w_in, h_in), (width, height))
        order = np.argsort(-scores, kind="stable")
        return segments[order], scores[order]

    def __call__(self, gray: np.ndarray) -> np.ndarray:
        return self.detect(gray)[0]
