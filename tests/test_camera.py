"""Camera conventions: rotation construction, angle definitions, focal <-> FOV."""
import math

import numpy as np
import pytest
import torch
from kornia.geometry.conversions import axis_angle_to_rotation_matrix

from fr_torch.core.geometry.conventions import (
    angles_from_rotation,
    focal_from_hfov,
    hfov_from_focal,
    horizon_angles,
    rotation_from_angles,
    vanishing_points,
)


def _axis(angle_deg, k):
    aa = torch.zeros(angle_deg.shape + (3,), dtype=torch.float64)
    aa[..., k] = torch.deg2rad(angle_deg)
    return axis_angle_to_rotation_matrix(aa)


def test_rotation_matches_elementary_composition():
    g = torch.Generator().manual_seed(0)
    pan, pitch, roll = (torch.rand(256, generator=g, dtype=torch.float64) * 2 - 1) * torch.tensor([180, 80, 40]).view(3, 1)
    expected = (_axis(pan, 1) @ _axis(pitch, 0) @ _axis(roll, 2)).transpose(-1, -2)
    got = rotation_from_angles(pan, pitch, roll)
    assert torch.allclose(got, expected, atol=1e-12)
    assert torch.allclose(torch.linalg.det(got), torch.ones(256, dtype=torch.float64))


def test_angle_definitions_and_signs():
    R = rotation_from_angles(torch.tensor(20.0, dtype=torch.float64), 30.0, 10.0)
    a = angles_from_rotation(R)
    assert float(a["pan_deg"]) == pytest.approx(20.0, abs=1e-9)
    assert float(a["roll_deg"]) == pytest.approx(10.0, abs=1e-9)
    assert float(a["pitch_deg"]) == pytest.approx(30.0, abs=1e-9)
    # tan(tilt) = tan(pitch) / cos(roll): 30.38 deg (fr_torch/core/geometry/conventions.py module docstring)
    expected_tilt = math.degrees(math.atan(math.tan(math.radians(30)) / math.cos(math.radians(10))))
    assert float(a["tilt_deg"]) == pytest.approx(expected_tilt, abs=1e-9)
    assert float(a["tilt_deg"]) == pytest.approx(30.38, abs=0.01)
    # Looking up: the vertical VP lies above the image (negative y); the horizon below the centre.
    vp = vanishing_points(torch.tensor(500.0, dtype=torch.float64), torch.tensor([320.0, 240.0], dtype=torch.float64),
                          rotation_from_angles(torch.tensor(0.0, dtype=torch.float64), 20.0, 0.0))
    v = vp[:, 1] / vp[2, 1]
    assert v[1] < 0
    # Positive roll: world-up leans to the image left (vertical VP above and to the left).
    vp = vanishing_points(torch.tensor(500.0, dtype=torch.float64), torch.tensor([320.0, 240.0], dtype=torch.float64),
                          rotation_from_angles(torch.tensor(0.0, dtype=torch.float64), 20.0, 5.0))
    v = vp[:, 1] / vp[2, 1]
    assert v[0] < 320 and v[1] < 0


def test_pan_is_folded_by_manhattan_symmetry():
    R = rotation_from_angles(torch.tensor([100.0, -50.0], dtype=torch.float64), 0.0, 0.0)
    assert np.allclose(angles_from_rotation(R)["pan_deg"].numpy(), [10.0, 40.0])
    # Sign of the vertical column does not change roll / tilt.
    R = rotation_from_angles(torch.tensor(5.0, dtype=torch.float64), 12.0, -4.0)
    flipped = R.clone()
    flipped[:, 1] *= -1
    flipped[:, 0] *= -1
    a, b = horizon_angles(R), horizon_angles(flipped)
    assert all(torch.allclose(a[k], b[k]) for k in a)


def test_focal_fov_round_trip():
    assert focal_from_hfov(90.0, 640) == pytest.approx(320.0)
    assert hfov_from_focal(674.918, 640) == pytest.approx(50.73, abs=0.01)
    f = torch.tensor([150.0, 400.0, 900.0], dtype=torch.float64)
    assert torch.allclose(focal_from_hfov(hfov_from_focal(f, 640), 640), f)
