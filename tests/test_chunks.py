"""Chunks bound memory and never change a value: fR's answers (cues, bounds and both promises
included) with every chunk of the cues and the plumb line cut to one image, or one lattice column,
are the defaults' bit for bit (a GPU takes larger chunks than a CPU: fr_torch.core.search.grid.chunk_budget,
fr_torch.core.reliability.cues.segment_chunk_images / profile_chunk_images)."""
import numpy as np
import pytest

import fr_torch.core.reliability.cues as cues
import fr_torch.core.search.grid as grid
from fr_torch import FREstimator
from fr_torch.core.geometry.conventions import rotation_from_angles
from fr_torch.synthetic import synthetic_segments


def _fields(result) -> dict:
    out = {"focal_px": result.focal_px, "rotation": np.asarray(result.rotation).tobytes(),
           "reliable": result.reliable, "reason": result.reason, "horizon_reliable": result.horizon_reliable}
    out.update({f"cue/{k}": v for k, v in result.cues.items()})
    out.update({f"bound/{k}": v for k, v in result.error_bound.items() if k != "limits"})
    return out


@pytest.mark.parametrize("mode", ["fast", "fr"])
def test_answers_do_not_depend_on_the_chunks(mode, monkeypatch):
    scenes = [synthetic_segments(f, rotation_from_angles(*angles).numpy(), 640, 480, n_per_family=30, seed=s)[0]
              for s, (f, angles) in enumerate([(450.0, (10.0, 5.0, 2.0)), (700.0, (-20.0, -8.0, 1.0)),
                                               (520.0, (35.0, 12.0, -3.0))])]
    sizes = [(640, 480)] * len(scenes)
    estimator = FREstimator(mode=mode)
    expected = [_fields(r) for r in estimator.calibrate_segments(scenes, sizes)]
    monkeypatch.setattr(cues, "SEGMENT_CHUNK_IMAGES", 1)
    monkeypatch.setattr(cues, "PROFILE_CHUNK_IMAGES", 1)
    monkeypatch.setattr(cues, "LATTICE_FIT_ELEMENTS", 1)
    monkeypatch.setattr(grid, "CPU_CHUNK_ELEMENTS", 40_000)  # the plumb line: one image a chunk
    assert [_fields(r) for r in estimator.calibrate_segments(scenes, sizes)] == expected
