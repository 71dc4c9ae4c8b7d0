"""Line segments: image loading, pluggable detectors, filters, and padded batches.

A segment is a row ``[x1, y1, x2, y2]`` in pixels (x right, y down, origin at the centre of the
top-left pixel).  The estimator never depends on which detector produced the segments.

Detectors are registered by name (``lsd`` is the default).  A detector is any callable object
taking a 2-D ``uint8`` grey image and returning an ``(N, 4)`` float array; register new ones with
:func:`register_detector` or pass the object itself.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Protocol, Sequence

import cv2
import numpy as np
import torch

from .registry import Registry


class FRInputError(ValueError):
    """Bad user input (unreadable file, wrong shape, NaNs...): reported as one clear line."""


# --------------------------------------------------------------------------- images

def load_image(path: str | Path) -> np.ndarray:
    """Read an image file as an 8-bit BGR array (H, W, 3).  Raises FRInputError on any problem.

    Safe on hostile input (regular files only, declared size checked before decoding, bounded
    decode memory, EXIF orientation applied): see :mod:`fr_torch.image_io`.  A huge image (colour
    buffer > ~400 MB) comes back reduced by 2, 4 or 8; use :func:`fr_torch.image_io.read_image`
    to get the input's size as well.
    """
    from .image_io import read_image

    image, _ = read_image(path)
    return to_bgr8(image, str(path))


def to_bgr8(image: np.ndarray, name: str = "image") -> np.ndarray:
    """Normalise grey / BGR / BGRA, 8- or 16-bit or float images to 8-bit BGR (H, W, 3)."""
    image = np.asarray(image)
    if image.ndim not in (2, 3) or (image.ndim == 3 and image.shape[2] not in (1, 3, 4)):
        raise FRInputError(f"{name}: expected an H x W or H x W x {{1,3,4}} image, got shape {image.shape}")
    if image.shape[0] == 0 or image.shape[1] == 0:
        raise FRInputError(f"{name}: zero-size image {image.shape}")
    if image.dtype == np.uint16:
        image = (image / 257.0).round().astype(np.uint8)
    elif image.dtype.kind == "f":
        if not np.isfinite(image).all():
            raise FRInputError(f"{name}: image has NaN or infinite pixels")
        scale = 255.0 if image.max() <= 1.0 else 1.0
        image = np.clip(image * scale, 0, 255).round().astype(np.uint8)
    elif image.dtype == np.bool_:
        image = image.astype(np.uint8) * 255
    elif image.dtype != np.uint8:
        image = np.clip(image, 0, 255).astype(np.uint8)
    if image.ndim == 2:
        return cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)
    if image.shape[2] == 1:
        return cv2.cvtColor(image[:, :, 0], cv2.COLOR_GRAY2BGR)
    if image.shape[2] == 4:
        return cv2.cvtColor(image, cv2.COLOR_BGRA2BGR)
    return image


def to_gray8(image: np.ndarray) -> np.ndarray:
    """8-bit single-channel grey image from any image :func:`to_bgr8` accepts."""
    return cv2.cvtColor(to_bgr8(image), cv2.COLOR_BGR2GRAY)


# --------------------------------------------------------------------------- detectors

class Detector(Protocol):
    """A line-segment detector: grey uint8 (H, W) -> (N, 4) float64 [x1, y1, x2, y2] pixels."""

    name: str

    def __call__(self, gray: np.ndarray) -> np.ndarray: ...


class LSDDetector:
    """OpenCV's LSD (von Gioi et al.) with its default parameters (same as LSD 1.5)."""

    name = "lsd"

    def __init__(self, refine: int = cv2.LSD_REFINE_STD):
        factory = getattr(cv2, "createLineSegmentDetector", None)
        if factory is None:  # LSD may move to opencv-contrib's ximgproc in a later OpenCV 5.x
            factory = getattr(getattr(cv2, "ximgproc", None), "createLineSegmentDetector", None)
        if factory is None:
            raise RuntimeError("this OpenCV build has no LSD (cv2.createLineSegmentDetector)")
        self._lsd = factory(refine)

    def __call__(self, gray: np.ndarray) -> np.ndarray:
        lines = self._lsd.detect(gray)[0]
        if lines is None:  # OpenCV returns None when nothing is found
            return np.zeros((0, 4))
        return lines.reshape(-1, 4).astype(np.float64)  # OpenCV 4: (N,1,4); OpenCV 5: (N,4)


# Detectors by name: ``lsd`` here, the others from entry points of group ``fr_torch.detectors``
# (this project's ``mcmlsd`` / ``onnx`` too, see pyproject.toml), or an import path "module:attr".
DETECTORS: Registry[Detector] = Registry("detector", group="fr_torch.detectors", error=FRInputError)
DETECTORS.register("lsd", LSDDetector)


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


# --------------------------------------------------------------------------- filters

@dataclass(frozen=True)
class SegmentFilter:
    """Segment filters of the fR pipeline.

    ``min_length_px``: drop segments whose length is <= this (pixels).  ``border_fraction``: drop
    segments whose *both* endpoints lie in the same border band of this width (fraction of the
    image width for left/right, of the height for top/bottom).  ``max_segments``: keep at most this
    many, the longest (None = all): bounds the search time whatever the image (a 1024 x 768 street
    photo gives ~2,000 LSD segments, most of them short texture edges with little weight).
    """

    min_length_px: float = 1.0
    border_fraction: float = 0.01
    max_segments: int | None = 500

    def __call__(self, segments: np.ndarray, width: int, height: int) -> np.ndarray:
        """The kept segments (M, 4) float64 of one image, in input order."""
        return self.many([segments], [(width, height)])[0]

    def many(self, segment_list: Sequence[np.ndarray], sizes: Sequence[tuple[float, float]]) -> list[np.ndarray]:
        """:meth:`__call__` for many images at once (one set of array operations for the batch).

        ``segment_list``: one (N_i, 4) array [x1, y1, x2, y2] per image; ``sizes``: (width, height)
        per image, pixels.  Returns the kept (M_i, 4) float64 arrays, input order kept; with more
        than ``max_segments`` left, the longest (ties: the earlier one).
        """
        arrays = [np.asarray(a, dtype=np.float64).reshape(-1, 4) for a in segment_list]
        if not arrays:
            return []
        counts = np.array([len(a) for a in arrays])
        segments = np.concatenate(arrays)
        owner = np.repeat(np.arange(len(arrays)), counts)
        width, height = np.asarray(sizes, dtype=np.float64).reshape(-1, 2).T
        bx, by = self.border_fraction * width, self.border_fraction * height
        x1, y1, x2, y2 = segments.T
        length = np.hypot(x2 - x1, y2 - y1)
        # Both endpoints in one border band: left, right, top or bottom.
        in_band = ((np.maximum(x1, x2) < np.repeat(bx, counts))
                   | (np.minimum(x1, x2) > np.repeat(width - bx, counts))
                   | (np.maximum(y1, y2) < np.repeat(by, counts))
                   | (np.minimum(y1, y2) > np.repeat(height - by, counts)))
        keep = (length > self.min_length_px) & ~in_band
        if self.max_segments is not None:
            kept = np.flatnonzero(keep)
            kept_owner = owner[kept]
            if np.bincount(kept_owner, minlength=len(arrays)).max(initial=0) > self.max_segments:
                # Rank each image's kept segments, longest first (stable: ties keep input order).
                order = kept[np.lexsort((-length[kept], kept_owner))]
                first = np.searchsorted(owner[order], np.arange(len(arrays)))
                rank = np.arange(len(order)) - first[owner[order]]
                keep[order[rank >= self.max_segments]] = False
        kept_counts = np.bincount(owner[keep], minlength=len(arrays))
        return np.split(segments[keep], np.cumsum(kept_counts)[:-1])


def validate_segments(segments, name: str = "segments") -> np.ndarray:
    """Check user-supplied segments: an (N, 4) array of finite numbers.  Returns float64 (N, 4)."""
    if torch.is_tensor(segments):
        segments = segments.detach().cpu().numpy()
    try:
        array = np.asarray(segments, dtype=np.float64)
    except (TypeError, ValueError):
        raise FRInputError(f"{name}: not a numeric array") from None
    if array.ndim == 1 and array.size == 0:
        array = array.reshape(0, 4)
    if array.ndim != 2 or array.shape[1] != 4:
        raise FRInputError(f"{name}: expected shape (N, 4) [x1, y1, x2, y2], got {array.shape}")
    if not np.isfinite(array).all():
        bad = int((~np.isfinite(array)).any(1).sum())
        raise FRInputError(f"{name}: {bad} segment(s) have NaN or infinite coordinates")
    return array


def detect_segments(image: np.ndarray, detector: Detector | str | None = None,
                    segment_filter: SegmentFilter | None = None) -> np.ndarray:
    """Detect and filter line segments in an image (any format :func:`to_bgr8` accepts)."""
    gray = to_gray8(image)
    raw = get_detector(detector)(gray)
    return (segment_filter or SegmentFilter())(raw, gray.shape[1], gray.shape[0])


# --------------------------------------------------------------------------- batches

@dataclass
class SegmentBatch:
    """Segments of B images padded to a common count.

    ``endpoints``: (B, N, 4) pixels; ``mask``: (B, N) bool, True for real segments;
    ``image_size``: (B, 2) [width, height] pixels.
    """

    endpoints: torch.Tensor
    mask: torch.Tensor
    image_size: torch.Tensor

    @classmethod
    def from_list(cls, segments: Sequence[np.ndarray], image_sizes: Sequence[tuple[int, int]],
                  device: str | torch.device = "cpu", dtype: torch.dtype = torch.float32) -> "SegmentBatch":
        # Padding is done in NumPy (one host array, no per-image tensors) and moved to the device
        # with one transfer per tensor.
        counts = np.array([len(s) for s in segments], dtype=np.int64)
        count = max(int(counts.max(initial=0)), 1)
        np_dtype = np.float64 if dtype == torch.float64 else np.float32
        endpoints = np.zeros((len(segments), count, 4), dtype=np_dtype)
        for b, seg in enumerate(segments):
            if counts[b]:
                endpoints[b, : counts[b]] = np.asarray(seg).reshape(-1, 4)
        mask = np.arange(count)[None, :] < counts[:, None]
        size = np.asarray(image_sizes, dtype=np.float64).reshape(-1, 2)
        return cls(torch.from_numpy(endpoints).to(device=device, dtype=dtype), torch.from_numpy(mask).to(device),
                   torch.from_numpy(size).to(device=device, dtype=dtype))

    @property
    def lengths(self) -> torch.Tensor:
        """Segment lengths in pixels, (B, N); zero for padding."""
        d = self.endpoints[..., 2:] - self.endpoints[..., :2]
        return torch.linalg.vector_norm(d, dim=-1) * self.mask
