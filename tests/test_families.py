"""Extra horizontal families inside the likelihood (SearchConfig.families, fr_torch.core.search.manhattan.fit_families):
the setting's parsing, a synthetic scene with a fourth horizontal direction at a known azimuth (found, f kept), a
Manhattan scene (no extra family), and the families' place in ranked_vanishing_points."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from fr_torch.core.estimator import SegmentEstimator
from fr_torch.core.settings.config import FamiliesConfig, SearchConfig
from fr_torch.errors import FRInputError
from fr_torch.synthetic import camera_matrix, rotation_from_angles, synthetic_segments

FOCAL = 500.0
SIZE = (640, 480)


def _rotation() -> np.ndarray:
    return rotation_from_angles(10.0, 5.0, 2.0).double().numpy()


def _fourth_family_scene(azimuth_deg: float, seed: int = 0):
    """Manhattan segments (no clutter) of camera (FOCAL, R) and 40 more of a horizontal direction at
    ``azimuth_deg`` from R[:, 0] (the first family of the world turned about its vertical); returns
    (segments (N, 4), that direction's vanishing point (x, y) in pixels)."""
    rotation = _rotation()
    manhattan, _ = synthetic_segments(FOCAL, rotation, n_per_family=60, seed=seed, clutter_fraction=0.0)
    a = math.radians(azimuth_deg)
    # world -> camera R' whose column 0 is cos a R[:, 0] + sin a R[:, 2] (column 1, the vertical, unchanged)
    turn = np.array([[math.cos(a), 0.0, -math.sin(a)], [0.0, 1.0, 0.0], [math.sin(a), 0.0, math.cos(a)]])
    turned = rotation @ turn
    extra, labels = synthetic_segments(FOCAL, turned, n_per_family=40, seed=seed + 1, clutter_fraction=0.0)
    point = camera_matrix(FOCAL, *SIZE) @ turned[:, 0]
    return np.concatenate([manhattan, extra[labels == 0]]), point[:2] / point[2]


def _estimator(families) -> SegmentEstimator:
    return SegmentEstimator(search_config=SearchConfig.from_config(families=families), reliability=None)


def test_families_setting_is_parsed_once():
    assert SearchConfig.from_config().families is None  # off by default
    assert FamiliesConfig.parse("off") is None and FamiliesConfig.parse(None) is None
    assert FamiliesConfig.parse("auto") == FamiliesConfig()
    parsed = FamiliesConfig.parse("auto:max_extra=1:penalty=4")
    assert parsed.max_extra == 1 and parsed.penalty == 4.0
    assert SearchConfig.from_config(families="max_extra=1").families.max_extra == 1
    assert SearchConfig.from_config().with_families({"prior": 0.1}).families.prior == 0.1
    for bad in ("sometimes", "max_extra=9", "prior=x", "penalty=-1", {"nope": 1}):
        with pytest.raises(FRInputError):
            FamiliesConfig.parse(bad)


def test_a_fourth_horizontal_family_is_found_and_f_kept():
    segments, truth = _fourth_family_scene(40.0)
    [result] = _estimator("auto").calibrate_segments([segments], [SIZE])
    assert result.ok
    assert result.cues["extra_families"] == 1.0
    extra = result.vanishing_point_families >= 3
    assert extra.sum() == 1
    point = result.ranked_vanishing_points[extra][0]
    found = point[:2] / point[2]
    assert np.linalg.norm(found - truth) < 0.03 * np.linalg.norm(truth - np.array([319.5, 239.5]))
    assert abs(result.focal_px / FOCAL - 1) < 0.03
    # the extra family is on the horizon of the estimate: K^-T R[:, 1] . v = 0
    horizon = result.horizon.line
    assert abs(horizon[0] * found[0] + horizon[1] * found[1] + horizon[2]) < 2.0


def test_a_manhattan_scene_keeps_three_families():
    segments, _ = synthetic_segments(FOCAL, _rotation(), n_per_family=60, seed=3, clutter_fraction=0.0)
    plain, = _estimator(None).calibrate_segments([segments], [SIZE])
    [result] = _estimator("auto").calibrate_segments([segments], [SIZE])
    assert result.cues["extra_families"] == 0.0
    assert sorted(result.vanishing_point_families) == [0, 1, 2]
    # m = 0 reports the Manhattan fit itself
    assert result.focal_px == plain.focal_px
    np.testing.assert_array_equal(result.rotation, plain.rotation)


def test_no_extra_family_beyond_the_setting():
    segments, _ = _fourth_family_scene(40.0)
    [result] = _estimator("max_extra=0").calibrate_segments([segments], [SIZE])
    assert result.cues["extra_families"] == 0.0
    assert (result.vanishing_point_families < 3).all()


def test_azimuth_windows_keep_families_apart():
    from fr_torch.core.search.manhattan import _azimuth_windows
    half = _azimuth_windows(torch.tensor([[40.0, 46.0], [170.0, 120.0]], dtype=torch.float64), 10.0)
    np.testing.assert_allclose(half.numpy(), [[3.0, 3.0], [5.0, 10.0]])
