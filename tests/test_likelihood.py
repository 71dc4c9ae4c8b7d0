"""The mixture likelihood against a direct float64 computation, and where its parameters go."""
import math

import numpy as np
import pytest
import torch

from fr_torch.camera import VERTICAL_AXIS, rotation_from_angles
from fr_torch.likelihood import LikelihoodParams, MixtureLikelihood, SegmentFeatures
from fr_torch.segments import SegmentBatch


def _direct_objective(segments, R, f, pp, params):
    """Loop-based measure-b mixture: sum_i len_i log(sum_k pi_k exp(-x/lambda_k)/lambda_k + pi_bg 2/pi)."""
    K = np.array([[f, 0, pp[0]], [0, f, pp[1]], [0, 0, 1.0]])
    total = weight = 0.0
    for x1, y1, x2, y2 in segments:
        m = np.array([(x1 + x2) / 2, (y1 + y2) / 2])
        d = np.array([x2 - x1, y2 - y1])
        length = np.linalg.norm(d)
        p = params.prior_background * 2 / math.pi
        for k in range(3):
            v = K @ R[:, k]
            w = v[:2] - m * v[2]
            angle = math.acos(min(1.0, abs(d @ w) / (length * np.linalg.norm(w))))
            lam = params.scale_vertical if k == VERTICAL_AXIS else params.scale_horizontal
            prior = params.prior_vertical if k == VERTICAL_AXIS else params.prior_horizontal
            p += prior * math.exp(-angle / lam) / lam
        total += length * math.log(p)
        weight += length
    return total - params.focal_prior_weight * weight * math.log(f)  # the focal prior -beta W log f


def test_objective_matches_direct_computation():
    rng = np.random.default_rng(0)
    params = LikelihoodParams.from_config("b")
    model = MixtureLikelihood(params)
    segs = rng.uniform(0, 640, (40, 4))
    batch = SegmentBatch.from_list([segs], [(640, 480)], dtype=torch.float64)
    pp = torch.tensor([[320.0, 240.0]], dtype=torch.float64)
    features = SegmentFeatures.from_batch(batch, pp)
    angles = rng.uniform(-30, 30, (5, 3))
    R = rotation_from_angles(*torch.tensor(angles.T, dtype=torch.float64))
    f = torch.tensor(rng.uniform(200, 700, 5), dtype=torch.float64)
    got = model.objective(features, R[None], f[None])[0].numpy()
    expected = [_direct_objective(segs, R[h].numpy(), float(f[h]), (320, 240), params) for h in range(5)]
    assert np.allclose(got, expected, rtol=1e-9)
    # float32 path agrees to 1e-5 relative
    got32 = model.objective(SegmentFeatures.from_batch(SegmentBatch.from_list([segs], [(640, 480)]), pp.float()),
                            R[None].float(), f[None].float())[0].double().numpy()
    assert np.allclose(got32, expected, rtol=1e-5)


def test_padding_does_not_change_the_objective_and_posteriors_sum_to_one():
    rng = np.random.default_rng(1)
    model = MixtureLikelihood()
    a, b = rng.uniform(0, 640, (30, 4)), rng.uniform(0, 640, (7, 4))
    pp = torch.tensor([[320.0, 240.0]] * 2, dtype=torch.float64)
    R = rotation_from_angles(torch.tensor([[3.0, 10.0]], dtype=torch.float64).expand(2, 2), 5.0, 1.0)
    f = torch.full((2, 2), 400.0, dtype=torch.float64)
    both = model.objective(SegmentFeatures.from_batch(SegmentBatch.from_list([a, b], [(640, 480)] * 2, dtype=torch.float64), pp), R, f)
    alone = model.objective(SegmentFeatures.from_batch(SegmentBatch.from_list([b], [(640, 480)], dtype=torch.float64), pp[:1]), R[:1], f[:1])
    assert torch.allclose(both[1], alone[0], rtol=1e-12)
    posterior, _ = model.posteriors(SegmentFeatures.from_batch(SegmentBatch.from_list([a], [(640, 480)], dtype=torch.float64), pp[:1]), R[:1], f[:1])
    assert torch.allclose(posterior.sum(-1), torch.ones(1, 2, 30, dtype=torch.float64))


def test_vertical_parameters_sit_on_the_vertical_column():
    """A segment pointing exactly at the vertical VP is explained with the tight vertical lambda."""
    params = LikelihoodParams.from_config("b")
    model = MixtureLikelihood(params)
    R = rotation_from_angles(torch.tensor(10.0, dtype=torch.float64), 0.0, 0.0)[None, None]
    # Level camera: the vertical VP is at infinity straight down, so a vertical segment fits it.
    segs = np.array([[100.0, 100.0, 100.0, 200.0]])
    features = SegmentFeatures.from_batch(SegmentBatch.from_list([segs], [(640, 480)], dtype=torch.float64),
                                          torch.tensor([[320.0, 240.0]], dtype=torch.float64))
    log_p = model.posteriors(features, R, torch.tensor([[500.0]], dtype=torch.float64))[1]
    # The horizontal VPs are ~80 deg or more off this segment, so their terms are below 1e-20.
    expected = math.log(params.prior_vertical / params.scale_vertical + params.prior_background * 2 / math.pi)
    assert float(log_p) == pytest.approx(expected, abs=1e-9)
    swapped = math.log(params.prior_horizontal / params.scale_horizontal + params.prior_background * 2 / math.pi)
    assert abs(float(log_p) - swapped) > 0.5  # it would differ clearly with the MATLAB column choice
