"""The horizon fit (fr_torch.core.search.horizon) and the per-photo choice of fit (SearchConfig.fit)."""
import json
import math

import numpy as np
import pytest
import torch

from fr_torch import FREstimator
from fr_torch.core.geometry.camera import Camera
from fr_torch.core.geometry.conventions import rotation_from_angles
from fr_torch.core.geometry.horizon import Horizon
from fr_torch.core.geometry.params import CameraParams
from fr_torch.core.likelihood.measures import SegmentFeatures
from fr_torch.core.search.choice import mixture_loss
from fr_torch.core.likelihood.mixture import LikelihoodParams, MixtureLikelihood
from fr_torch.core.likelihood.segments import SegmentBatch
from fr_torch.core.search.choice import CHOICE_FEATURES, HorizonChooser, fit_on_horizon, horizon_of
from fr_torch.core.search.grid import parameter_box
from fr_torch.core.search.horizon import fit_horizon, horizon_vote
from fr_torch.core.settings.config import HorizonFitConfig, SearchConfig
from fr_torch.errors import FRInputError
from fr_torch.synthetic import synthetic_segments
from tests.conftest import cpu_kernel_sets, fresh_process_records

SEARCH = SearchConfig.from_config().resolve("fr")


def _street(focal=900.0, pan=20.0, pitch=4.0, roll=-2.0, size=(1024, 768), seed=0, inclined=0):
    """Segments of a Manhattan scene (and ``inclined`` segments of a family that rises 15 degrees out
    of the horizontal plane: a street on a hill) with the true horizon."""
    rotation = rotation_from_angles(np.float64(pan), np.float64(pitch), np.float64(roll)).numpy()
    segments, _ = synthetic_segments(focal, rotation, *size, n_per_family=70, noise_px=0.4, clutter_fraction=0.15,
                                     seed=seed)
    if inclined:
        slope = np.radians(15.0)
        direction = rotation @ np.array([np.cos(slope), -np.sin(slope), 0.0])  # world y is down: rising
        camera = Camera(size[0], size[1], focal, None, rotation)
        point = camera.K @ direction
        rng = np.random.default_rng(seed + 100)
        starts = rng.uniform([0, 0], size, (inclined, 2))
        toward = point[:2] - starts * point[2]
        toward /= np.linalg.norm(toward, axis=1, keepdims=True)
        ends = starts + toward * rng.uniform(40, 160, (inclined, 1))
        segments = np.concatenate([segments, np.c_[starts, ends]])
    truth = Horizon.from_camera(Camera(size[0], size[1], focal, None, rotation))
    return segments, size, truth


def _features(photos):
    batch = SegmentBatch.from_list([p[0] for p in photos], [p[1] for p in photos])
    centre = torch.tensor([Camera(w, h, 1.0).principal_point for _, (w, h), _ in photos], dtype=torch.float32)
    features = SegmentFeatures.from_batch(batch, centre)
    long_side = torch.tensor([float(max(size)) for _, size, _ in photos], dtype=torch.float64)
    lower, upper = parameter_box(SEARCH, long_side, None)
    return features, lower, upper


def _horizon(params, size):
    camera = Camera(size[0], size[1], float(params[3]), None, CameraParams(params).rotation().numpy())
    return Horizon.from_camera(camera)


def test_the_horizon_fit_finds_the_horizon_of_street_cameras_narrow_to_wide_and_portrait():
    photos = [_street(focal=f, pan=p, pitch=t, roll=r, size=s, seed=i) for i, (f, p, t, r, s) in enumerate(
        [(900.0, 20.0, 4.0, -2.0, (1024, 768)), (2400.0, -10.0, 1.0, 1.0, (1280, 960)),
         (420.0, 35.0, -8.0, 3.0, (640, 480)), (800.0, 5.0, 12.0, -4.0, (768, 1024))])]
    features, lower, upper = _features(photos)
    fit = fit_horizon(features, lower, upper, SEARCH.horizon, SEARCH.periodic_pan)
    assert fit.found.all()
    for params, (_, size, truth) in zip(fit.params, photos):
        assert _horizon(params, size).error(truth) < 0.015  # within 1.5 % of the height (the narrow view errs most)
    vote = horizon_vote(features, fit.params[:, None])[:, 0]
    assert torch.isfinite(vote).all() and (vote > 0).all()


def test_an_inclined_family_does_not_drag_the_horizon():
    photo = _street(focal=1100.0, pan=10.0, pitch=2.0, roll=0.5, inclined=120, seed=3)
    features, lower, upper = _features([photo])
    fit = fit_horizon(features, lower, upper, SEARCH.horizon, SEARCH.periodic_pan)
    assert _horizon(fit.params[0], photo[1]).error(photo[2]) < 0.01


def test_the_camera_on_the_horizon_keeps_the_horizon_and_the_manhattan_focal_length_and_pan():
    photos = [_street(focal=900.0, seed=5), _street(focal=600.0, pan=-30.0, pitch=-5.0, roll=2.0, seed=6)]
    features, lower, upper = _features(photos)
    fit = fit_horizon(features, lower, upper, SEARCH.horizon, SEARCH.periodic_pan)
    likelihood = MixtureLikelihood(LikelihoodParams.from_config(mode="fr").with_prior_in_range(SEARCH.fov_range))
    manhattan = torch.tensor([[19.0, 3.0, -2.5, 880.0], [-31.0, -4.0, 2.2, 610.0]], dtype=torch.float64)
    held, scores = fit_on_horizon(likelihood, features, fit.params, manhattan, lower, upper)
    assert torch.isfinite(scores).all()
    long_side = features.long_side.double()

    def unit(line):  # a line up to scale
        line = line / line.norm(dim=-1, keepdim=True)
        return line * torch.sign(line[:, 1:2])

    torch.testing.assert_close(unit(horizon_of(held, long_side)), unit(horizon_of(fit.params, long_side)), rtol=0,
                               atol=1e-9)
    assert torch.equal(held[:, 3], manhattan[:, 3])
    assert (held[:, 0] - manhattan[:, 0]).abs().max() < 1.0  # the least rotation: pan nearly kept
    # the smooth vote is largest near the truth
    truth = torch.tensor([[20.0, 4.0, -2.0, 900.0], [20.0, 4.0, -2.0, 1200.0]], dtype=torch.float64)
    votes = horizon_vote(features.images(0, 1), truth[None])
    assert votes[0, 0] > votes[0, 1]


def test_no_vertical_evidence_keeps_the_manhattan_fit():
    """Only horizontal lines: the horizon fit finds no vertical and the choice keeps fR's answer,
    finite, with the reason of fR's checks."""
    rng = np.random.default_rng(0)
    x = rng.uniform(0, 600, (60, 1))
    y = rng.uniform(0, 440, (60, 1))
    segments = np.c_[x, y, x + rng.uniform(20, 60, (60, 1)), y + rng.uniform(-3, 3, (60, 1))]
    manhattan = FREstimator(mode="fast", reliability=None).calibrate_segments([segments], [(640, 480)])[0]
    [chosen] = FREstimator(mode="fast", reliability=None,
                           search_config=SearchConfig.from_config(fit="choose")).calibrate_segments([segments],
                                                                                                   [(640, 480)])
    assert chosen.model == "manhattan" and chosen.focal_px == manhattan.focal_px
    assert json.loads(json.dumps(chosen.to_json()))["model"] == "manhattan"


def test_the_choice_names_its_model_and_gives_one_answer_alone_and_in_a_batch():
    photos = [_street(seed=1), _street(focal=500.0, size=(640, 480), seed=2, inclined=40)]
    estimator = FREstimator(mode="fast", search_config=SearchConfig.from_config(fit="choose"))
    batch = estimator.calibrate_segments([p[0] for p in photos], [p[1] for p in photos])
    for i, photo in enumerate(photos):
        [alone] = estimator.calibrate_segments([photo[0]], [photo[1]], names=[f"image{i}"])
        record = {k: v for k, v in alone.to_json().items() if k != "runtime_s"}
        assert record == {k: v for k, v in batch[i].to_json().items() if k != "runtime_s"}
        assert alone.model in ("manhattan", "horizon")
        assert np.isfinite(alone.focal_px)
    [horizon] = FREstimator(mode="fast", search_config=SearchConfig.from_config(fit="horizon")).calibrate_segments(
        [photos[0][0]], [photos[0][1]])
    assert horizon.model == "horizon"
    assert horizon.horizon.error(photos[0][2]) < 0.01


def _kernel_sets():
    return [k for k in cpu_kernel_sets() if k in ("default", "avx2")]


@pytest.mark.parametrize("kernels", _kernel_sets())
def test_the_horizon_fit_gives_the_same_bits_under_every_kernel_set(kernels):
    """Two streets (one on a hill) fitted with ``fit=horizon`` in a process with another
    ATEN_CPU_CAPABILITY and one thread (:func:`tests.conftest.fresh_process_records`): bit for bit the
    records of this process, with its own kernels and thread count."""
    photos = [_street(seed=1), _street(focal=500.0, size=(640, 480), seed=2, inclined=40)]
    here = FREstimator(mode="fast", search_config=SearchConfig.from_config(fit="horizon")).calibrate_segments(
        [p[0] for p in photos], [p[1] for p in photos])  # this process: its own kernels and thread count
    expected = json.loads(json.dumps([{k: v for k, v in r.to_json().items() if k != "runtime_s"} for r in here]))
    assert fresh_process_records(kernels)["horizon"] == expected
    assert [r["model"] for r in expected] == ["horizon", "horizon"]


@pytest.mark.parametrize("kernels", _kernel_sets())
def test_the_choice_of_fit_gives_the_same_bits_under_every_kernel_set(kernels):
    """The reproducibility photos fitted with ``fit=choose`` (both fits and the choice's evidence,
    ``cues.choice_*``) and the evidence ``mixture_loss`` on 20,000 values, in a process with another
    ATEN_CPU_CAPABILITY and one thread: bit for bit what this process gives."""
    from tests.test_reproducibility import _photos, _record

    photos = _photos()
    here = FREstimator(mode="fast", search_config=SearchConfig.from_config(fit="choose")).calibrate_segments(
        [p[0] for p in photos], [p[1] for p in photos])
    expected = [_record(r) for r in here]
    assert fresh_process_records(kernels)["choose"] == expected
    assert all(any(key.startswith("choice_") for key in r["cues"]) for r in expected)
    assert fresh_process_records(kernels)["mixture_loss"] == mixture_loss(*_loss_inputs()).tolist()


def _loss_inputs() -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """20,000 objectives of two fits and total lengths spanning what photos give (the choice's
    ``mixture_loss`` evidence over many values, beyond the few photos above)."""
    generator = torch.Generator().manual_seed(67)
    uniform = torch.rand(3, 20000, generator=generator, dtype=torch.float64)
    # powers of ten through exp (the same bits under every kernel set; a float64 ``**`` is not)
    total = torch.exp((2 + 3 * uniform[0]) * math.log(10.0))
    manhattan = -total * (3 + uniform[1])
    held = manhattan - total * torch.exp((-6 + 6 * uniform[2]) * math.log(10.0))
    return manhattan, held, total


def test_fit_settings_are_checked_once_into_a_type():
    assert SearchConfig.from_config(fit="choose", horizon={"inlier_deg": 3}).horizon.inlier_deg == 3.0
    for bad in ({"fit": "lee"}, {"horizon": {"inlier_deg": 0}}, {"horizon": {"voters": 0}},
                {"horizon": {"unknown": 1}}, {"horizon": [1, 2]}):
        with pytest.raises(FRInputError):
            SearchConfig.from_config(**bad)
    assert HorizonFitConfig.parse(None) == HorizonFitConfig()


def test_the_cli_refuses_an_unknown_fit_in_one_line(capsys, tmp_path):
    from fr_torch.cli.main import main

    with pytest.raises(SystemExit) as stop:
        main(["calibrate", "--fit", "lee", str(tmp_path / "photo.jpg")])
    err = capsys.readouterr().err
    assert stop.value.code == 2 and "--fit" in err and "Traceback" not in err


def test_the_chooser_is_a_linear_rule_on_the_evidence_and_refuses_a_bad_file(tmp_path):
    chooser = HorizonChooser.load()  # the shipped rule
    assert len(chooser.coef) == len(CHOICE_FEATURES) and chooser.trained_on
    evidence = {name: torch.tensor([0.0, float("nan")], dtype=torch.float64) for name in CHOICE_FEATURES}
    score = chooser.score(evidence)
    assert torch.isfinite(score).all() and score[0] == score[1]  # NaN evidence counts as 0
    bad = tmp_path / "chooser.json"
    for text in ("not json", json.dumps({"features": ["x"], "mean": [0], "scale": [1], "coef": [1], "intercept": 0}),
                 json.dumps({"features": list(CHOICE_FEATURES), "mean": [0], "scale": [1], "coef": [1],
                             "intercept": 0})):
        bad.write_text(text)
        with pytest.raises(FRInputError):
            HorizonChooser.load(bad)


def test_the_horizon_fit_reports_its_evidence_as_cues():
    photo = _street(seed=7)
    [result] = FREstimator(mode="fast", search_config=SearchConfig.from_config(fit="horizon")).calibrate_segments(
        [photo[0]], [photo[1]])
    evidence = {name: result.cues[f"choice_{name}"] for name in CHOICE_FEATURES}
    assert all(np.isfinite(value) for value in evidence.values())
    assert evidence["horizon_shift"] < 0.05 and evidence["manhattan_tilt"] < 10
