"""The search's angle boxes: pan wraps around its 90-degree period (no estimate pinned at +-45),
pitch and roll found at their box's edge are flagged unreliable, and ``--pitch-range`` /
``--roll-range`` widen the boxes for cameras outside them (a traffic camera looking 50 deg down)."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from fr_torch.cli.main import attach_range_values, main
from fr_torch.core.geometry.conventions import rotation_from_angles
from fr_torch.core.search.grid import into_box
from fr_torch.core.settings.config import SearchConfig
from fr_torch.errors import FRInputError
from fr_torch.runtime.estimator import FREstimator
from fr_torch.synthetic import synthetic_segments


def _segments(pan: float, pitch: float, roll: float, focal: float = 450.0, seed: int = 0):
    rotation = rotation_from_angles(np.float64(pan), np.float64(pitch), np.float64(roll)).numpy()
    return synthetic_segments(focal, rotation, n_per_family=80, seed=seed)[0]


def test_into_box_wraps_pan_and_clamps_the_rest():
    lower = torch.tensor([-45.0, -35.0, -15.0, 100.0], dtype=torch.float64)
    upper = torch.tensor([45.0, 35.0, 15.0, 900.0], dtype=torch.float64)
    points = torch.tensor([[46.0, 40.0, -20.0, 50.0], [-47.5, 0.0, 0.0, 1000.0], [45.0, 1.0, 2.0, 300.0]],
                          dtype=torch.float64)
    wrapped = into_box(points, lower, upper, periodic_pan=True)
    assert torch.allclose(wrapped, torch.tensor([[-44.0, 35.0, -15.0, 100.0], [42.5, 0.0, 0.0, 900.0],
                                                 [-45.0, 1.0, 2.0, 300.0]], dtype=torch.float64))
    clamped = into_box(points, lower, upper, periodic_pan=False)
    assert clamped[:, 0].tolist() == [45.0, -45.0, 45.0]
    assert SearchConfig().periodic_pan and not SearchConfig(pan_range_deg=(-30.0, 30.0)).periodic_pan


@pytest.mark.parametrize("pan", [44.7, -44.7, 45.0])
def test_pan_near_the_period_edge_is_found_not_pinned(pan):
    """A camera turned 44.7 deg from a wall is the same Manhattan camera as one at -45.3 deg: the
    search wraps pan instead of stopping at the box's edge."""
    est = FREstimator(mode="fast", reliability=None)
    result = est.calibrate_segments([_segments(pan, 8.0, 2.0)], [(640, 480)])[0]
    assert result.ok and result.reliable, result.reason
    folded = (result.to_json()["pan_deg"] - pan + 45.0) % 90.0 - 45.0  # error modulo the 90-deg symmetry
    assert abs(folded) < 0.5
    assert abs(result.focal_px / 450.0 - 1) < 0.03


def test_pitch_outside_the_box_is_flagged_and_a_wider_box_finds_it():
    segments = _segments(15.0, -50.0, 2.0)
    default = FREstimator(mode="fast", reliability=None).calibrate_segments([segments], [(640, 480)])[0]
    assert default.ok and not default.reliable
    assert "at the edge of the search range" in default.reason  # pitch (or roll, bent to make up for it)
    wide = SearchConfig.from_config().with_angle_range("pitch", "-70,20")
    assert wide == SearchConfig.from_config().with_angle_range("pitch", (-70, 20))
    found = FREstimator(mode="fast", reliability=None, search_config=wide).calibrate_segments([segments],
                                                                                             [(640, 480)])[0]
    assert found.ok and found.reliable, found.reason
    assert abs(found.pitch_deg + 50.0) < 0.5 and abs(found.focal_px / 450.0 - 1) < 0.03


def test_angle_range_options(tmp_path, capsys):
    assert attach_range_values(["calibrate", "--pitch-range", "-70,20", "--roll-range", "-.5,3", "x.png"]) == \
        ["calibrate", "--pitch-range=-70,20", "--roll-range=-.5,3", "x.png"]
    assert attach_range_values(["--pitch-range", "10,20", "--fast"]) == ["--pitch-range", "10,20", "--fast"]
    with pytest.raises(FRInputError):
        SearchConfig().with_angle_range("pitch", "-95,10")
    with pytest.raises(FRInputError):
        SearchConfig().with_angle_range("roll", "5")
    with pytest.raises(FRInputError):
        SearchConfig().with_angle_range("yaw", (0, 5))
    for bad in ("-95,10", "20", "5,2", "a,b", "nan,3"):
        assert main(["calibrate", "--fast", "--pitch-range", bad, str(tmp_path / "missing.png")]) == 2
        err = capsys.readouterr().err.strip()
        assert err.startswith("fr calibrate: error: --pitch-range") and "\n" not in err
