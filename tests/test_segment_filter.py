"""SegmentFilter: the batched filter equals a plain per-image reference (length, border bands,
the longest max_segments with ties in input order)."""
import numpy as np
import pytest

from fr_torch.core.likelihood.segments import SegmentFilter


def _reference(f: SegmentFilter, segments: np.ndarray, width: float, height: float) -> np.ndarray:
    """Written from the docstring, one segment at a time."""
    kept = []
    for i, (x1, y1, x2, y2) in enumerate(segments):
        length = np.hypot(x2 - x1, y2 - y1)
        bx, by = f.border_fraction * width, f.border_fraction * height
        in_band = (max(x1, x2) < bx or min(x1, x2) > width - bx or max(y1, y2) < by or min(y1, y2) > height - by)
        if length > f.min_length_px and not in_band:
            kept.append((-length, i))
    if f.max_segments is not None:
        kept = sorted(kept)[: f.max_segments]  # longest first; equal lengths: the earlier index
    return segments[sorted(i for _, i in kept)].reshape(-1, 4)


@pytest.mark.parametrize("max_segments", [None, 3, 12])
def test_batched_filter_equals_reference(max_segments):
    rng = np.random.default_rng(max_segments or 0)
    f = SegmentFilter(min_length_px=4.0, border_fraction=0.1, max_segments=max_segments)
    for _ in range(40):
        sizes = [tuple(rng.integers(40, 400, 2)) for _ in range(int(rng.integers(1, 5)))]
        arrays = [np.round(rng.uniform(-0.1, 1.1, (int(rng.integers(0, 30)), 4)) * [w, h, w, h])  # rounded: ties
                  for w, h in sizes]
        got = f.many(arrays, sizes)
        assert len(got) == len(arrays)
        for array, (w, h), kept in zip(arrays, sizes, got):
            assert np.array_equal(kept, _reference(f, array, w, h))
            assert np.array_equal(f(array, w, h), kept)
    assert f.many([], []) == []
