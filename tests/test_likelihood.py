"""The mixture likelihood against a direct float64 computation, and where its parameters go."""
import math
from dataclasses import replace

import numpy as np
import pytest
import torch

from fr_torch.core.geometry.conventions import VERTICAL_AXIS, rotation_from_angles
from fr_torch.core.likelihood.measures import SegmentFeatures
from fr_torch.core.likelihood.mixture import LikelihoodParams, MixtureLikelihood
from fr_torch.core.likelihood.segments import SegmentBatch
from fr_torch.core.settings.fov import FovRange


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
    # the focal prior: -(gamma / 2) W (log(f / L) - log(f0 / L))^2, L = 2 * max(pp) = the long side here
    centre = math.log(0.5 / math.tan(math.radians(params.focal_prior_hfov_deg) / 2))
    evidence = weight + params.focal_prior_pseudo_length * 2 * max(pp)
    distance = max(0.0, abs(math.log(f / (2 * max(pp))) - centre) - params.focal_prior_flat_halfwidth)
    return total - 0.5 * params.focal_prior_weight * evidence * distance ** 2


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


def test_focal_prior_centre_moves_into_a_search_range_that_excludes_it():
    params = LikelihoodParams(focal_prior_weight=0.3, focal_prior_hfov_deg=82.0)
    assert params.with_prior_in_range(FovRange(30.0, 120.0)) is params
    narrow = params.with_prior_in_range(FovRange(20.0, 60.0))
    # the range's midpoint in log f: tan(c/2) = sqrt(tan(10 deg) tan(30 deg))
    expected = math.degrees(2 * math.atan(math.sqrt(math.tan(math.radians(10)) * math.tan(math.radians(30)))))
    assert narrow.focal_prior_hfov_deg == pytest.approx(expected) and 20 < expected < 60
    with pytest.raises(ValueError, match="focal_prior_hfov_deg"):
        LikelihoodParams(focal_prior_hfov_deg=float("nan"))


def test_focal_prior_peaks_at_its_centre_and_scales_with_segment_length():
    params = LikelihoodParams(focal_prior_weight=0.3, focal_prior_hfov_deg=90.0, focal_prior_pseudo_length=2.0)
    model = MixtureLikelihood(params)
    segs = np.array([[10.0, 10.0, 110.0, 10.0], [10.0, 20.0, 10.0, 70.0]])
    batch = SegmentBatch.from_list([segs], [(800, 600)], dtype=torch.float64)
    features = SegmentFeatures.from_batch(batch, torch.tensor([[400.0, 300.0]], dtype=torch.float64))
    focal = torch.tensor([[400.0, 300.0, 600.0]], dtype=torch.float64)  # 90 deg across 800 px = f 400
    value, slope = model.focal_prior(features, focal)
    assert abs(value[0, 0]) < 1e-12 and abs(slope[0, 0]) < 1e-12 and (value[0, 1:] < 0).all()
    assert value[0, 2] == pytest.approx(-0.5 * 0.3 * (150.0 + 2 * 800.0) * math.log(1.5) ** 2)  # W + W0
    assert slope[0, 1] > 0 > slope[0, 2]


def test_flat_topped_focal_prior():
    """No pull within a factor e^h of the centre; outside, the log-normal of the distance to the
    band, with the matching slope; the config's fR block selects it, Fast-fR keeps the log-normal."""
    flat = 0.2
    params = LikelihoodParams(focal_prior_weight=0.3, focal_prior_hfov_deg=90.0, focal_prior_flat_halfwidth=flat)
    gauss = MixtureLikelihood(replace(params, focal_prior_flat_halfwidth=0.0))
    model = MixtureLikelihood(params)
    segs = np.array([[10.0, 10.0, 110.0, 10.0], [10.0, 20.0, 10.0, 70.0]])
    features = SegmentFeatures.from_batch(SegmentBatch.from_list([segs], [(800, 600)], dtype=torch.float64),
                                          torch.tensor([[400.0, 300.0]], dtype=torch.float64))
    inside = torch.tensor([[400.0, 400.0 * math.exp(0.15), 400.0 * math.exp(-0.19)]], dtype=torch.float64)
    value, slope = model.focal_prior(features, inside)
    assert torch.equal(value, torch.zeros_like(value)) and torch.equal(slope, torch.zeros_like(slope))
    outside = torch.tensor([[400.0 * math.exp(0.5), 400.0 * math.exp(-0.7)]], dtype=torch.float64)
    value, slope = model.focal_prior(features, outside)
    shifted = gauss.focal_prior(features, torch.tensor([[400.0 * math.exp(0.3), 400.0 * math.exp(-0.5)]],
                                                       dtype=torch.float64))[0]
    torch.testing.assert_close(value, shifted)
    step = 1e-4 * outside
    above, below = model.focal_prior(features, outside + step)[0], model.focal_prior(features, outside - step)[0]
    numeric = (above - below) / (2 * step)
    torch.testing.assert_close(slope, numeric, rtol=1e-5, atol=1e-9)
    assert LikelihoodParams.from_config("b", mode="fr").focal_prior_flat_halfwidth > 0
    assert LikelihoodParams.from_config("b", mode="fast").focal_prior_flat_halfwidth == 0.0
    config = {"measures": {"b": {"lambda_vertical": 0.5, "lambda_horizontal": 1.5}},
              "priors": {"vertical": 0.45, "horizontal": 0.26, "background": 0.03},
              "focal_prior": {"weight": 0.3, "fr": {"flat_halfwidth": -1}}}
    for mode in ("fr", "fast", None):  # a bad override is an error whichever mode reads the file
        with pytest.raises(ValueError, match="focal_prior.fr.flat_halfwidth"):
            LikelihoodParams.from_dict(config, mode=mode)
    config["focal_prior"]["fr"] = {"flat_halfwidth": 0.5}
    assert LikelihoodParams.from_dict(config, mode="fr").focal_prior_flat_halfwidth == 0.5
    assert LikelihoodParams.from_dict(config, mode="fast").focal_prior_flat_halfwidth == 0.0
    with pytest.raises(ValueError, match="focal_prior.fast must be an object"):
        LikelihoodParams.from_dict(dict(config, focal_prior={"fast": 3}))
    with pytest.raises(ValueError, match="focal_prior_flat_halfwidth"):
        LikelihoodParams(focal_prior_flat_halfwidth=float("nan"))


def test_longest_keeps_each_images_longest_segments():
    short = np.array([[0.0, 0.0, 5.0, 0.0], [0.0, 10.0, 0.0, 60.0], [1.0, 1.0, 31.0, 1.0]])  # lengths 5, 50, 30
    other = np.array([[0.0, 0.0, 0.0, 7.0]])  # one segment: the rest is padding
    batch = SegmentBatch.from_list([short, other], [(100, 80), (100, 80)], dtype=torch.float64)
    features = SegmentFeatures.from_batch(batch, torch.tensor([[50.0, 40.0]], dtype=torch.float64))
    top = features.longest(2)
    assert top.weight.tolist() == [[50.0, 30.0], [7.0, 0.0]]
    assert top.mask.tolist() == [[True, True], [True, False]]
    assert torch.equal(top.line[0, 0], features.line[0, 1]) and torch.equal(top.half_length[0], torch.tensor([25.0, 15.0], dtype=torch.float64))
    assert features.longest(3) is features
