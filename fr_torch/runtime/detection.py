"""One image's line segments at the working resolution, as the pipelines hand them to the search."""
from __future__ import annotations

from typing import NamedTuple

import numpy as np


class Detection(NamedTuple):
    """One image decoded and detected at the working resolution (:func:`fr_torch.runtime.pipeline.detect_image`, or the device path of :mod:`fr_torch.runtime.device_pipeline`).

    ``segments``: (N, 4) in working pixels (empty on error); ``size``: working (width, height),
    (0, 0) on error; ``error``: the image's failure message or None; ``seconds``: decode + detect
    time; ``scale``: input pixels per working pixel (>= 1); ``input_size``: the input's (width, height).
    """

    segments: np.ndarray
    size: tuple[int, int]
    error: str | None
    seconds: float
    scale: float = 1.0
    input_size: tuple[int, int] = (0, 0)

    @classmethod
    def failed(cls, error: str, seconds: float = 0.0) -> "Detection":
        """An image that could not be decoded or detected: no segments, size (0, 0), ``error`` its
        one-line reason."""
        return cls(np.zeros((0, 4)), (0, 0), error, seconds)


def failure_reason(name: str, exc: BaseException) -> str:
    """The one-line reason of image ``name``'s unexpected failure ``exc`` (an FRInputError's own
    message is already one line and said as it is)."""
    return f"{name}: {type(exc).__name__}: {exc}".splitlines()[0]
