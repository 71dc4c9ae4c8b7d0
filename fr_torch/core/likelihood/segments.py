"""Line segments as the engine sees them: validation, filters and padded batches.

A segment is a row ``[x1, y1, x2, y2]`` in pixels (x right, y down, origin at the centre of the
top-left pixel).  The engine never depends on which detector produced the segments
(:mod:`fr_torch.detectors`).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np
import torch

from fr_torch.core.geometry.conventions import image_centre
from fr_torch.core.settings.checks import MAX_REACH_IMAGE_SIZES
from fr_torch.errors import FRInputError
from fr_torch.core import exact_math


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


def validate_segments(segments, name: str = "segments", finite: bool = True) -> np.ndarray:
    """Check user-supplied segments: an (N, 4) array of numbers, finite unless ``finite`` is False
    (then :func:`drop_absurd_segments` drops the non-finite rows).  Returns float64 (N, 4)."""
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
    if finite and not np.isfinite(array).all():
        bad = int((~np.isfinite(array)).any(1).sum())
        raise FRInputError(f"{name}: {bad} segment(s) have NaN or infinite coordinates")
    return array


def drop_absurd_segments(segments: np.ndarray, size: tuple[float, float]) -> tuple[np.ndarray, int]:
    """Drop the rows of (N, 4) ``segments`` of an image of ``size`` (width, height) pixels that no
    image of that size can hold: a non-finite coordinate, or an endpoint further than
    :data:`~fr_torch.core.settings.checks.MAX_REACH_IMAGE_SIZES` long sides from the image centre (1e20 px
    is a bug upstream, not a line; kept, it overflows the float32 search into NaN).  Returns the
    kept rows (input order) and how many were dropped."""
    width, height = float(size[0]), float(size[1])
    reach = MAX_REACH_IMAGE_SIZES * max(width, height)
    with np.errstate(invalid="ignore"):
        cx, cy = image_centre(width, height)
        keep = ((np.abs(segments[:, 0::2] - cx) <= reach) & (np.abs(segments[:, 1::2] - cy) <= reach)).all(1)
    dropped = int(len(segments) - keep.sum())
    return (segments[keep] if dropped else segments), dropped




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
        """Segment lengths in pixels, (B, N); zero for padding (``sqrt(dx^2 + dy^2)`` written out: the
        same bits on every kernel set, :mod:`fr_torch.core.exact`)."""
        d = self.endpoints[..., 2:] - self.endpoints[..., :2]
        return exact_math.sqrt(d[..., 0] * d[..., 0] + d[..., 1] * d[..., 1]) * self.mask
