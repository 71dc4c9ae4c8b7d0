"""Hand-checked values of the five deviation measures, including VPs at infinity."""
import math

import pytest
import torch

from fr_torch.core.likelihood.measures import deviations

# One horizontal segment from (0, 0) to (10, 0): midpoint (5, 0), half length 5, line y = 0.
# Principal point (0, 0), f = 100 px.
SEGMENT = torch.tensor([[[0.0, 0.0, 10.0, 0.0]]], dtype=torch.float64)
PP = torch.tensor([[0.0, 0.0]], dtype=torch.float64)
FOCAL = torch.tensor([[100.0]], dtype=torch.float64)


def measure(name, vp, segment=SEGMENT):
    vps = torch.zeros(1, 1, 3, 3, dtype=torch.float64)
    vps[0, 0, :, 0] = torch.tensor(vp, dtype=torch.float64)
    vps[0, 0, :, 1] = torch.tensor([0.0, 1.0, 0.0])  # other columns irrelevant here
    vps[0, 0, :, 2] = torch.tensor([1.0, 0.0, 0.0])
    return float(deviations(name, segment, vps, FOCAL, PP)[0, 0, 0, 0])


def test_finite_vp():
    vp = [105.0, 10.0, 1.0]  # 100 px along, 10 px off the segment's line
    theta = math.atan2(10, 100)
    assert measure("a", vp) == pytest.approx(10.0, rel=1e-9)
    assert measure("b", vp) == pytest.approx(theta, rel=1e-9)
    assert math.degrees(measure("b", vp)) == pytest.approx(5.7106, abs=1e-4)
    assert measure("c", vp) == pytest.approx(5 * math.sin(theta), rel=1e-9)  # 0.49752
    assert measure("d", vp) == pytest.approx(5 * 0.1, rel=1e-9)
    # Interpretation-plane normal (0, 1, 0); VP direction K^-1 v = (1.05, 0.1, 1).
    assert measure("e", vp) == pytest.approx(math.asin(0.1 / math.sqrt(1.05 ** 2 + 0.01 + 1)), rel=1e-9)
    assert math.degrees(measure("e", vp)) == pytest.approx(3.9452, abs=1e-4)


def test_scale_and_sign_of_homogeneous_vp_do_not_matter():
    for name in "abcde":
        ref = measure(name, [105.0, 10.0, 1.0])
        assert measure(name, [-210.0, -20.0, -2.0]) == pytest.approx(ref, rel=1e-9)
        flipped = SEGMENT[..., [2, 3, 0, 1]]  # same segment, endpoints swapped
        assert measure(name, [105.0, 10.0, 1.0], flipped) == pytest.approx(ref, rel=1e-9)


def test_vp_at_infinity():
    vp = [1.0, 1.0, 0.0]  # direction at 45 degrees, at infinity
    assert measure("b", vp) == pytest.approx(math.pi / 4, rel=1e-9)
    assert measure("a", vp) == pytest.approx(2000.0)  # saturates at the background range
    assert measure("c", vp) == pytest.approx(5 * math.sin(math.pi / 4), rel=1e-9)
    assert measure("d", vp) == pytest.approx(5.0, rel=1e-6)  # clamped to the half length
    assert measure("e", vp) == pytest.approx(math.pi / 4, rel=1e-9)
    along = [1.0, 0.0, 0.0]  # VP at infinity in the segment's own direction: zero deviation
    for name in "abcde":
        assert measure(name, along) == pytest.approx(0.0, abs=1e-12)


def test_midpoint_on_vp_is_finite_with_finite_gradient():
    vp = torch.tensor([5.0, 0.0, 1.0], dtype=torch.float64, requires_grad=True)
    vps = torch.stack([vp, torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64),
                       torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64)], -1)[None, None]
    for name in "abcde":
        value = deviations(name, SEGMENT, vps, FOCAL, PP)[0, 0, 0, 0]
        assert torch.isfinite(value)
        (grad,) = torch.autograd.grad(value, vp, allow_unused=True)
        assert grad is None or torch.isfinite(grad).all()
    assert float(deviations("b", SEGMENT, vps.detach(), FOCAL, PP)[0, 0, 0, 0]) == 0.0
