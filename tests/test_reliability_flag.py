"""What `reliable` promises: conformal scales, bounds, limits, and the flag in a result's JSON."""
from __future__ import annotations

import json
import math

import numpy as np
import pytest

from fr_torch.core.geometry.camera import Camera
from fr_torch.core.reliability.bounds import (
    FOCAL_SIGMA_FLOOR_PCT,
    ReliabilityPromise,
    conformal_scale,
    focal_sigma_pct,
    tilt_sigma_deg,
    worst_group_scale,
)
from fr_torch.core.reliability.model import MODEL_CUE_NAMES, ReliabilityModel
from fr_torch.core.result import CalibrationResult


def test_conformal_scale_is_the_finite_sample_quantile():
    predicted = np.ones(9)
    actual = np.arange(1.0, 10.0)  # ratios 1..9
    assert conformal_scale(predicted, actual, 0.9) == 9.0  # ceil(10 * 0.9) = 9: the 9th smallest
    assert conformal_scale(np.ones(5), np.arange(1.0, 6.0), 0.9) == math.inf  # ceil(6 * 0.9) = 6 > 5
    assert conformal_scale(np.ones(19), np.arange(1.0, 20.0), 0.9) == 18.0  # ceil(20 * 0.9) = 18
    assert conformal_scale(predicted, actual, 0.5) == 5.0
    assert conformal_scale(np.array([1.0, np.nan, 1.0]), np.array([1.0, 2.0, np.inf]), 0.5) == 1.0  # finite pairs
    assert math.isnan(conformal_scale([], [], 0.9))
    # the floor keeps a near-zero prediction from making an infinite ratio
    assert conformal_scale([1e-9, 1.0], [1.0, 1.0], 0.4, floor=0.5) == 2.0  # ratios 1 and 1 / 0.5, not 1e9
    scale, per = worst_group_scale(np.ones(40), np.r_[np.full(20, 1.0), np.full(20, 3.0)], ["a"] * 20 + ["b"] * 20)
    assert per == {"a": 1.0, "b": 3.0} and scale == 3.0


def test_promise_bounds_violations_and_config(tmp_path):
    promise = ReliabilityPromise(limits={"focal_pct": 10.0, "tilt_deg": 3.0},
                                 scales={"fr": {"focal_pct": 2.0, "tilt_deg": 1.5}})
    cues = {"focal_profile_spread": 0.04, "focal_resample_spread": 0.01, "pitch_resample_spread": 1.2}
    # focal sigma = 100 sqrt(0.04 x 0.01) = 2 %, tilt sigma = hypot(1.2, 0.5) = 1.3 deg
    assert focal_sigma_pct(cues) == pytest.approx(2.0) and tilt_sigma_deg(cues) == pytest.approx(1.3)
    assert promise.bounds(cues, "fr") == pytest.approx({"focal_pct": 4.0, "tilt_deg": 1.95})
    assert promise.bounds(cues, "fr", focal_known=True)["focal_pct"] == 0.0  # a given focal length
    assert promise.bounds(cues, "fast") is None  # no scales for the mode
    # a near-zero spread is floored (a synthetic scene), a missing cue gives no bound
    assert focal_sigma_pct({**cues, "focal_resample_spread": 0.0}) == FOCAL_SIGMA_FLOOR_PCT
    assert math.isnan(promise.bounds({"pitch_resample_spread": 0.1}, "fr")["focal_pct"])
    # the same sigmas from a table's columns
    table = {name: np.array([value, value]) for name, value in cues.items()}
    np.testing.assert_allclose(focal_sigma_pct(table), [2.0, 2.0])
    assert promise.violations({"focal_pct": 8.0, "tilt_deg": 1.5}) == []
    [text] = promise.violations({"focal_pct": 12.0, "tilt_deg": 1.5})
    assert text == "90 % bound of focal 12.0 % > 10 % (2.0 % over)"
    [text] = promise.violations({"focal_pct": math.nan, "tilt_deg": 1.0})  # no bound = not reliable
    assert "no 90 % bound of focal" in text
    assert "focal error <= 10 %" in promise.describe() and "tilt error <= 3 deg" in promise.describe()
    for bad in (dict(coverage=1.5), dict(limits={"focal_pct": -1.0}), dict(limits={"nonsense": 1.0}),
                dict(scales={"fr": {"focal_pct": 0.0}}), dict(scales={"fr": {"roll_deg": 1.0}})):
        with pytest.raises(ValueError):
            ReliabilityPromise(**bad)
    path = tmp_path / "reliability.json"
    path.write_text(json.dumps({"thresholds": {}}))
    assert ReliabilityPromise.from_config(path) is None
    path.write_text(json.dumps({"promise": {"coverage": 0.8, "limits": {"focal_pct": 5},
                                            "scales": {"fast": {"focal_pct": 3}}}}))
    loaded = ReliabilityPromise.from_config(path)
    assert loaded.coverage == 0.8 and loaded.limits == {"focal_pct": 5.0} and loaded.scales["fast"]["focal_pct"] == 3.0
    assert loaded.enforce  # the promise is what `reliable` means unless the config says otherwise
    assert loaded.validated_detectors == ()  # a config that does not say: the models' own detector only
    path.write_text(json.dumps({"promise": {"scales": {"fr": {"focal_pct": 3}}, "validated_detectors": ["torch-lines"]}}))
    assert ReliabilityPromise.from_config(path).validated_detectors == ("torch-lines",)
    for bad in ("torch-lines", [""], [3], 3):
        path.write_text(json.dumps({"promise": {"validated_detectors": bad}}))
        with pytest.raises(ValueError, match="validated_detectors"):
            ReliabilityPromise.from_config(path)


def _training(n=300, seed=0):
    rng = np.random.default_rng(seed)
    cues = np.stack([np.round(np.exp(rng.uniform(np.log(2), np.log(80), n))), np.exp(rng.uniform(-15, 1, n)),
                     rng.normal(0, 0.5, n), np.exp(rng.uniform(np.log(3e-3), 0, n)),
                     np.exp(rng.uniform(np.log(0.05), np.log(2.0), n))], 1)
    scale = np.exp(-np.log1p(cues[:, 0]) + 0.3 * np.log(cues[:, 3] + 1e-2) + 0.3 * np.log(cues[:, 4]))
    scale /= scale.mean()
    return cues, np.stack([0.5 * scale, 1.0 * scale, 5.0 * scale], 1)


EASY_SPREADS = {"focal_profile_spread": 0.01, "focal_resample_spread": 0.004, "pitch_resample_spread": 0.1}
HARD_SPREADS = {"focal_profile_spread": 0.5, "focal_resample_spread": 0.1, "pitch_resample_spread": 2.0}


def _result(cues, spreads):
    r = CalibrationResult(image="x", width=640, height=480, ok=True, reliable=True,
                          camera=Camera.from_angles(640, 480, 500.0, roll_deg=0.0, tilt_deg=0.0))
    r.cues = {**dict(zip(MODEL_CUE_NAMES, cues)), **spreads}
    return r


def test_annotate_with_a_promise_sets_bounds_and_reliable(tmp_path):
    """The promise's bounds come from a result's spread cues (not the KNN's prediction); the reason
    says which bound failed and by how much."""
    cues, errors = _training()
    model = ReliabilityModel.fit(cues, errors, meta={"mode": "fast"}, thresholds={"focal_pct": 1e-9})
    model.save(tmp_path / "reliability_fast.npz")
    (tmp_path / "reliability.json").write_text(json.dumps({
        "thresholds": {"focal_pct": 1e-9},  # replaced by the promise
        "promise": {"coverage": 0.9, "limits": {"focal_pct": 10.0, "tilt_deg": 3.0},
                    "scales": {"fast": {"focal_pct": 2.0, "tilt_deg": 2.0}}}}))
    loaded = ReliabilityModel.load_default("fast", config_dir=tmp_path)
    assert loaded.needs_spreads and not model.needs_spreads
    easy, hard = _result([70.0, 1e-6, 0.5, 0.01, 0.1], EASY_SPREADS), _result([2.0, 2.0, -1.0, 1.0, 2.0], HARD_SPREADS)
    loaded.annotate_many([easy, hard], mode="fast")
    assert easy.reliable and easy.reason == ""
    assert easy.error_bound["focal_pct"] == pytest.approx(2.0 * 100 * math.sqrt(0.01 * 0.004))
    assert easy.error_bound["tilt_deg"] == pytest.approx(2.0 * math.hypot(0.1, 0.5))
    assert easy.error_bound["coverage"] == 0.9 and easy.error_bound["limits"] == {"focal_pct": 10.0, "tilt_deg": 3.0}
    assert easy.predicted_error is not None  # the KNN still predicts (fr track weighs frames by it)
    assert not hard.reliable and "outside the promise: 90 % bound of focal 44.7 % > 10 % (34.7 % over)" in hard.reason
    assert "90 % bound of tilt 4.1 deg > 3 deg (1.1 deg over)" in hard.reason and "focal prior set" in hard.reason
    assert json.loads(json.dumps(hard.to_json()))["error_bound"]["focal_pct"] > 10.0
    # a given focal length: no focal bound to exceed
    given = _result([2.0, 2.0, -1.0, 1.0, 2.0], {**HARD_SPREADS, "pitch_resample_spread": 0.1})
    loaded.annotate_many([given], mode="fast", focal_known=[True])
    assert given.error_bound["focal_pct"] == 0.0 and given.reliable and "focal" not in given.reason
    # a model without a promise keeps the thresholds and writes no bound
    plain = _result([70.0, 1e-6, 0.5, 0.01, 0.1], EASY_SPREADS)
    model.annotate(plain, mode="fast")
    assert plain.error_bound is None and not plain.reliable and "above threshold" in plain.reason
    # "enforce": false -> the bounds are reported, `reliable` keeps the thresholds
    (tmp_path / "reliability.json").write_text(json.dumps({
        "thresholds": {"roll_deg": 100.0, "tilt_deg": 100.0, "focal_pct": 100.0},
        "promise": {"limits": {"focal_pct": 10.0, "tilt_deg": 3.0}, "enforce": False,
                    "scales": {"fast": {"focal_pct": 2.0, "tilt_deg": 2.0}}}}))
    reported = ReliabilityModel.load_default("fast", config_dir=tmp_path)
    hard = _result([2.0, 2.0, -1.0, 1.0, 2.0], HARD_SPREADS)
    reported.annotate_many([hard], mode="fast")
    assert hard.reliable and hard.error_bound["focal_pct"] > 10.0 and hard.error_bound["enforced"] is False
    # missing spread cues: no bound (None in the JSON, never NaN) and not reliable
    (tmp_path / "reliability.json").write_text(json.dumps({"promise": {"limits": {"focal_pct": 10.0},
                                                                       "scales": {"fast": {"focal_pct": 2.0}}}}))
    strict = ReliabilityModel.load_default("fast", config_dir=tmp_path)
    blind = _result([70.0, 1e-6, 0.5, 0.01, 0.1], EASY_SPREADS)
    blind.cues.pop("focal_resample_spread")
    strict.annotate_many([blind], mode="fast")
    assert blind.error_bound["focal_pct"] is None and not blind.reliable and "no 90 % bound of focal" in blind.reason
    assert "NaN" not in json.dumps(blind.to_json()["error_bound"])
    # an unreadable promise is a warning, not a crash
    (tmp_path / "reliability.json").write_text(json.dumps({"promise": {"coverage": 7}}))
    assert ReliabilityModel.load_default("fast", config_dir=tmp_path).promise is None
