"""Stage 1 coarse to fine (``SearchConfig.grid_coarse_factor``): the k^4 grid scored only inside the
best cells of the (k/s)^4 grid; every cell kept = the whole grid, bit for bit."""
from dataclasses import replace

import numpy as np
import pytest
import torch

from fr_torch import FREstimator
from fr_torch.core.geometry.conventions import focal_from_hfov
from fr_torch.core.likelihood.measures import SegmentFeatures
from fr_torch.core.likelihood.mixture import LikelihoodParams, MixtureLikelihood
from fr_torch.core.likelihood.segments import SegmentBatch
from fr_torch.core.search.grid import coarse_to_fine_scores, grid_hypotheses, score_grid, select_starts
from fr_torch.core.settings.config import SearchConfig
from fr_torch.errors import FRInputError
from fr_torch.synthetic import synthetic_segments


def _scene(seed, hfov, pan, pitch, roll):
    """Synthetic segments of a 640 x 480 Manhattan scene (angles in degrees)."""
    focal = focal_from_hfov(hfov, 640)
    p, t, r = np.radians([pan, pitch, roll])
    ry = np.array([[np.cos(p), 0, np.sin(p)], [0, 1, 0], [-np.sin(p), 0, np.cos(p)]])
    rx = np.array([[1, 0, 0], [0, np.cos(t), -np.sin(t)], [0, np.sin(t), np.cos(t)]])
    rz = np.array([[np.cos(r), -np.sin(r), 0], [np.sin(r), np.cos(r), 0], [0, 0, 1]])
    segments, _ = synthetic_segments(focal, (ry @ rx @ rz).T, 640, 480, n_per_family=30, noise_px=0.5,
                                     clutter_fraction=0.3, seed=seed)
    return segments


def _features(segment_list, dtype=torch.float32):
    batch = SegmentBatch.from_list(segment_list, [(640, 480)] * len(segment_list), "cpu", dtype)
    return SegmentFeatures.from_batch(batch, torch.tensor([(320.0, 240.0)] * len(segment_list), dtype=dtype))


@pytest.fixture(scope="module")
def scenes():
    return [_scene(21, 70.0, 15.0, 10.0, 5.0), _scene(22, 100.0, -20.0, -15.0, 2.0)]


@pytest.mark.parametrize("known", [False, True])
def test_every_cell_kept_is_the_whole_grid(scenes, known):
    config = SearchConfig.from_config(grid_points_per_dim=6, grid_coarse_factor=2, grid_coarse_cells=3 ** 4)
    model = MixtureLikelihood(LikelihoodParams.from_config("b"))
    features = _features(scenes)
    long_side = torch.tensor([640.0, 640.0], dtype=torch.float64)
    focal = torch.tensor([450.0, 300.0], dtype=torch.float64) if known else None
    hypotheses = grid_hypotheses(config, long_side, focal)
    whole = score_grid(model, features, hypotheses, config.max_chunk_elements, vertical_block=6)
    grid_scores, selectable = coarse_to_fine_scores(model, features, config, hypotheses, long_side, focal)
    assert torch.equal(selectable, whole) and torch.equal(grid_scores, whole)


@pytest.mark.parametrize("known", [False, True])
def test_fine_points_lie_in_the_best_coarse_cells(scenes, known):
    k, s, cells = 8, 2, 5
    config = SearchConfig.from_config(grid_points_per_dim=k, grid_coarse_factor=s, grid_coarse_cells=cells)
    model = MixtureLikelihood(LikelihoodParams.from_config("b"))
    features = _features(scenes)
    long_side = torch.tensor([640.0, 640.0], dtype=torch.float64)
    focal = torch.tensor([450.0, 300.0], dtype=torch.float64) if known else None
    hypotheses = grid_hypotheses(config, long_side, focal)
    grid_scores, selectable = coarse_to_fine_scores(model, features, config, hypotheses, long_side, focal)
    coarse_config = replace(config, grid_points_per_dim=k // s, grid_coarse_factor=1)
    coarse = score_grid(model, features, grid_hypotheses(coarse_config, long_side, focal), 1 << 30)
    whole = score_grid(model, features, hypotheses, 1 << 30)
    dims = 3 if known else 4
    for b in range(2):
        scored = torch.isfinite(selectable[b]).nonzero()[:, 0]
        assert len(scored) == cells * s ** dims
        assert torch.equal(selectable[b, scored], whole[b, scored])  # the fine points' own scores
        digits = torch.stack([scored // k ** 3, scored // k ** 2 % k, scored // k % k, scored % k], -1) // s
        cell = ((digits[:, 0] * (k // s) + digits[:, 1]) * (k // s) + digits[:, 2]) * (k // s) + digits[:, 3]
        best = torch.sort(coarse[b], descending=True, stable=True).indices[:cells]
        assert set(cell.tolist()) == set(best.tolist())
        every = torch.arange(hypotheses.shape[1])
        digits = torch.stack([every // k ** 3, every // k ** 2 % k, every // k % k, every % k], -1) // s
        containing = ((digits[:, 0] * (k // s) + digits[:, 1]) * (k // s) + digits[:, 2]) * (k // s) + digits[:, 3]
        rest = ~torch.isfinite(selectable[b])
        assert torch.equal(grid_scores[b, rest], coarse[b, containing[rest]])  # the coarse cell's score
    starts, _ = select_starts(config, selectable, hypotheses)
    assert torch.isfinite(starts).all()


def test_settings_checked_and_estimates_unchanged_with_every_cell(scenes):
    with pytest.raises(FRInputError):
        SearchConfig.from_config(grid_coarse_factor=2, grid_coarse_cells=0)
    with pytest.raises(FRInputError, match="must divide"):  # k = 8: checked when the setting is parsed
        SearchConfig.from_config(grid_coarse_factor=3)
    sizes = [(640, 480)] * 2
    plain = FREstimator(mode="fast", search_config=SearchConfig.from_config(grid_coarse_factor=1)
                        ).calibrate_segments(scenes, sizes)
    every = FREstimator(mode="fast",
                        search_config=SearchConfig.from_config(grid_coarse_factor=2, grid_coarse_cells=256))
    for a, b in zip(plain, every.calibrate_segments(scenes, sizes)):
        assert a.camera.focal_px == b.camera.focal_px and np.array_equal(a.camera.rotation, b.camera.rotation)


def test_the_focal_profile_with_every_cell_kept_is_the_whole_grids_profile(scenes):
    """fR's focal profile (the gap cue's known-focal searches) scores its angle grids coarse to fine:
    with every coarse cell kept it is the whole grid's profile, bit for bit."""
    from fr_torch.core.reliability.cues import focal_profile

    config = SearchConfig.from_config()
    model = MixtureLikelihood(LikelihoodParams.from_config("b"))
    features = _features(scenes)
    params = torch.tensor([[15.0, 10.0, 5.0, focal_from_hfov(70.0, 640)],
                           [-20.0, -15.0, 2.0, focal_from_hfov(100.0, 640)]], dtype=torch.float64)
    whole = focal_profile(model, features, params, config, 10)
    every = focal_profile(model, features, params, config, 10, coarse_cells=(config.grid_points_per_dim // 2) ** 3)
    assert torch.equal(whole[0], every[0]) and torch.equal(whole[1], every[1])
    fewer = focal_profile(model, features, params, config, 10, coarse_cells=16)
    assert fewer[0].shape == whole[0].shape and torch.equal(torch.isfinite(fewer[0]), torch.isfinite(whole[0]))
