"""Line-segment detectors by name.

A detector is any callable object taking a 2-D ``uint8`` grey image and returning an ``(N, 4)``
float array ``[x1, y1, x2, y2]`` in pixels.  ``lsd`` is the default; the others come from entry
points of group ``fr_torch.detectors`` (this project's ``mcmlsd`` / ``onnx`` too, see
pyproject.toml) or an import path ``module:attr`` naming a detector class (a ``name`` and
``__call__``) or a factory registered here or marked ``@plugin("detector")``
(:mod:`fr_torch.registry`); register new ones with :func:`register_detector` or pass the
object itself.
"""
from __future__ import annotations

from typing import Callable, Protocol

import numpy as np

from fr_torch.core.likelihood.segments import SegmentFilter
from fr_torch.detectors.lsd import LSDDetector
from fr_torch.errors import FRInputError
from fr_torch.images.convert import to_gray8
from fr_torch.registry import Registry


class Detector(Protocol):
    """A line-segment detector: grey uint8 (H, W) -> (N, 4) float64 [x1, y1, x2, y2] pixels."""

    name: str

    def __call__(self, gray: np.ndarray) -> np.ndarray: ...


# Detectors by name: ``lsd`` here, the others from entry points of group ``fr_torch.detectors``
# (this project's ``mcmlsd`` / ``onnx`` too, see pyproject.toml), or an import path "module:attr".
def is_detector_class(cls: type) -> bool:
    """A class implementing :class:`Detector`: its instances are callable (``__call__`` defined by
    the class or a base other than ``object``) and it has a ``name``."""
    return hasattr(cls, "name") and any("__call__" in vars(base) for base in cls.__mro__ if base is not object)


DETECTORS: Registry[Detector] = Registry("detector", group="fr_torch.detectors", error=FRInputError,
                                         implements=is_detector_class,
                                         protocol="a class with a name and __call__(gray) -> (N, 4) segments")


def register_detector(name: str, factory: Callable[..., Detector]) -> None:
    """Make a detector available by name (``--detector NAME``)."""
    DETECTORS.register(name, factory)


def available_detectors() -> list[str]:
    return DETECTORS.names()


def get_detector(detector: str | Detector | None = None, **kwargs) -> Detector:
    """A detector from its name or spec (default ``lsd``; ``mcmlsd[key=value]``) or the object itself."""
    if detector is None:
        detector = "lsd"
    if not isinstance(detector, str):
        return detector
    try:
        return DETECTORS.create(detector, **kwargs)
    except ValueError as exc:  # a malformed spec
        raise FRInputError(str(exc)) from None


def detect_segments(image: np.ndarray, detector: Detector | str | None = None,
                    segment_filter: SegmentFilter | None = None) -> np.ndarray:
    """Detect and filter line segments in an image (any format :func:`to_bgr8` accepts)."""
    gray = to_gray8(image)
    raw = get_detector(detector)(gray)
    return (segment_filter or SegmentFilter())(raw, gray.shape[1], gray.shape[0])


DETECTORS.register("lsd", LSDDetector)
