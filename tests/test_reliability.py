"""Reliability model: storage without pickle, K by cross-validation, predictions, annotate."""
from __future__ import annotations

import json
import zipfile

import numpy as np
import pytest
from scipy.stats import spearmanr

from fr_torch.core.geometry.camera import Camera
from fr_torch.core.reliability.model import (
    CUE_NAMES,
    FR_MODEL_CUE_NAMES,
    MODEL_CUE_NAMES,
    PAPER_CUE_NAMES,
    TARGETS,
    ReliabilityModel,
    ReliabilitySet,
    cue_features,
    cues_array,
    load_thresholds,
    model_cue_names,
)
from fr_torch.core.result import CalibrationResult
from fr_torch.resources import config_dir


def make_training(n=400, noise=0.3, seed=0, informative=True):
    """Cues (n, 5) in MODEL_CUE_NAMES order like fR's: fewer family segments / larger entropy / lower
    likelihood / a larger focal prior share / a wider focal spread -> larger errors (n, 3)."""
    rng = np.random.default_rng(seed)
    m = np.round(np.exp(rng.uniform(np.log(2), np.log(80), n)))
    h = np.exp(rng.uniform(np.log(1e-7), np.log(3.0), n))
    ll = rng.normal(0.0, 0.5, n)
    share = np.exp(rng.uniform(np.log(3e-3), 0.0, n))
    spread = np.exp(rng.uniform(np.log(0.05), np.log(2.0), n))
    difficulty = (-np.log1p(m) + 0.3 * np.log(h + 1e-6) - 0.5 * ll + 0.3 * np.log(share + 1e-2)
                  + 0.3 * np.log(spread) if informative else rng.normal(size=n))
    scale = np.exp(difficulty - difficulty.mean())
    errors = np.stack([0.5 * scale, 1.0 * scale, 5.0 * scale], 1) * np.exp(noise * rng.normal(size=(n, 3)))
    return np.stack([m, h, ll, share, spread], 1), errors


def test_cue_features_documented_transform():
    x = cue_features([[9.0, 0.0, -0.25, 0.0, 0.0, 0.0, 0.0],
                      [0.0, 1.0, 2.0, 0.5, 0.5, -250.0, 0.3]])  # FR_MODEL_CUE_NAMES order (the default)
    np.testing.assert_allclose(x[0], [np.log(10.0), np.log(1e-6), -0.25, np.log(1e-3), np.log(1e-2), 0.0,
                                      np.log(1e-4)])
    np.testing.assert_allclose(x[1], [0.0, np.log(1.0 + 1e-6), 2.0, np.log(0.5 + 1e-3), np.log(0.5 + 1e-2),
                                      np.arcsinh(-2.5), np.log(0.3 + 1e-4)])
    np.testing.assert_allclose(cue_features([[9.0, 0.0, -0.25, 0.0, 0.0]], MODEL_CUE_NAMES), x[:1, [0, 1, 2, 4, 6]])
    # the paper's three cues alone, and a cue set in another order: one transform per name
    np.testing.assert_allclose(cue_features([[9.0, 0.0, -0.25]], PAPER_CUE_NAMES), x[:1, :3])
    np.testing.assert_allclose(cue_features([[0.5, 2.0]], ("focal_conditioning", "mean_log_likelihood")),
                               [[np.log(0.5 + 1e-3), 2.0]])
    for bad in (("min_family_segments", "nonsense"), ("grid_entropy", "grid_entropy"), ()):
        with pytest.raises(ValueError):
            cue_features(np.zeros((1, len(bad))), bad)
    with pytest.raises(ValueError):  # column count must match the names
        cue_features([[1.0, 2.0, 3.0]])


def test_save_load_round_trip_without_pickle(tmp_path):
    cues, errors = make_training(200)
    model = ReliabilityModel.fit(cues, errors, k_grid=[3, 10, 30], meta={"mode": "fr"})
    path = model.save(tmp_path / "reliability_fr.npz")
    # every member is a plain (non-object) array, loadable with allow_pickle=False
    with np.load(path, allow_pickle=False) as data:
        assert set(data.files) >= {"train_cues", "train_errors", "feature_mean", "feature_components",
                                   "feature_variance", "k", "meta_json"}
        assert all(data[key].dtype.kind != "O" for key in data.files)
    with zipfile.ZipFile(path) as zf:  # no pickle protocol header in any member
        assert all(b"\x80\x04\x95" not in zf.read(name)[:256] for name in zf.namelist())
    sidecar = json.loads(path.with_suffix(".json").read_text())
    assert sidecar["k"] == model.k and sidecar["mode"] == "fr"
    loaded = ReliabilityModel.load(path)
    probe = make_training(50, seed=1)[0]
    np.testing.assert_array_equal(loaded.predict(probe), model.predict(probe))
    assert loaded.k == model.k and loaded.meta["mode"] == "fr"
    # whitened training cues have identity covariance
    np.testing.assert_allclose(np.cov(loaded.whiten(loaded.train_cues).T), np.eye(5), atol=1e-8)
    assert loaded.cue_names == MODEL_CUE_NAMES and sidecar["cue_names"] == list(MODEL_CUE_NAMES)


def test_numpy_prediction_matches_sklearn():
    from sklearn.neighbors import KNeighborsRegressor

    cues, errors = make_training(300)
    model = ReliabilityModel.fit(cues, errors, k_grid=[7])
    probe = make_training(40, seed=3)[0]
    knn = KNeighborsRegressor(n_neighbors=7, algorithm="brute").fit(model.whiten(cues), errors)
    np.testing.assert_allclose(model.predict(probe), knn.predict(model.whiten(probe)), rtol=1e-10)


def test_cv_picks_sensible_k():
    # informative, moderately noisy cues: an intermediate K (neither 1 nor "everything")
    cues, errors = make_training(500, noise=0.5)
    k_mid = ReliabilityModel.fit(cues, errors).k
    assert 5 <= k_mid <= 120, k_mid
    # errors unrelated to the cues: the best predictor is the global mean -> the largest K
    cues, errors = make_training(500, noise=0.5, informative=False)
    k_noise = ReliabilityModel.fit(cues, errors).k
    assert k_noise >= 90 and k_noise > k_mid, (k_noise, k_mid)
    # nearly noise-free: few neighbours suffice
    cues, errors = make_training(500, noise=0.01)
    assert ReliabilityModel.fit(cues, errors).k <= 12


def test_grouped_cv_keeps_groups_together():
    cues, errors = make_training(200)
    groups = np.repeat(np.arange(40), 5)
    model = ReliabilityModel.fit(cues, errors, groups=groups, k_grid=[1, 5, 20])
    assert model.meta["cv"] == "GroupKFold" and model.k in (1, 5, 20)


def test_predictions_monotone_in_cues():
    cues, errors = make_training(600, noise=0.3)
    model = ReliabilityModel.fit(cues, errors)
    counts = np.array([2, 3, 5, 8, 13, 20, 30, 45, 70], float)
    probe = np.stack([counts, np.full_like(counts, 1e-3), np.zeros_like(counts), np.full_like(counts, 0.05),
                      np.full_like(counts, 0.3)], 1)
    predicted = model.predict(probe)
    for j in range(3):  # more segments in the weakest family -> smaller predicted error
        assert spearmanr(counts, predicted[:, j]).statistic < -0.8
        assert predicted[0, j] > 2 * predicted[-1, j]


def _result(cues):
    r = CalibrationResult(image="x", width=640, height=480, ok=True, reliable=True,
                          camera=Camera.from_angles(640, 480, 500.0, roll_deg=0.0, tilt_deg=0.0))
    r.cues = dict(zip(MODEL_CUE_NAMES, cues))
    return r


def test_annotate_sets_fields_and_thresholds(tmp_path):
    cues, errors = make_training(400, noise=0.2)
    model = ReliabilityModel.fit(cues, errors, meta={"mode": "fast"},
                                 thresholds={"roll_deg": 2.0, "tilt_deg": 3.0, "focal_pct": 15.0})
    easy, hard = _result([70.0, 1e-6, 0.5, 0.01, 0.1]), _result([2.0, 2.0, -1.0, 1.0, 2.0])
    model.annotate(easy, mode="fast")
    model.annotate(hard, mode="fast")
    assert set(easy.predicted_error) == set(TARGETS) and set(hard.predicted_error) == set(TARGETS)
    assert easy.reliable and easy.reason == ""
    assert hard.predicted_error["focal_pct"] > 15.0
    assert not hard.reliable and "predicted error above threshold" in hard.reason and "focal" in hard.reason
    # its focal length is the prior's (focal_prior_share 1): the reason says so and what helps
    assert "focal prior set most of the focal length" in hard.reason
    lines_set = _result([2.0, 2.0, -1.0, 0.2, 2.0])  # as hard but the lines carry most of f: no hint
    model.annotate(lines_set, mode="fast")
    assert not lines_set.reliable and "focal prior" not in lines_set.reason
    # an existing reason is kept, a failed result is left alone
    prior = _result([2.0, 2.0, -1.0, 0.002, 2.0])
    prior.reliable, prior.reason = False, "only 5 segments (< 10)"
    model.annotate(prior, mode="fast")
    assert prior.reason.startswith("only 5 segments (< 10); predicted error")
    failed = CalibrationResult(image="y", width=1, height=1, ok=False, reason="boom")
    assert model.annotate(failed).predicted_error is None
    with pytest.raises(ValueError):
        model.annotate(_result([10.0, 1e-3, 0.0, 0.3, 0.3]), mode="fr")
    # load_default from a folder: a set keyed by mode, thresholds from reliability.json
    model.save(tmp_path / "reliability_fast.npz")
    (tmp_path / "reliability.json").write_text(json.dumps({"thresholds": {"focal_pct": 1000.0}}))
    models = ReliabilityModel.load_default(config_dir=tmp_path)
    assert isinstance(models, ReliabilitySet) and set(models.models) == {"fast"}
    r = models.annotate(_result([2.0, 2.0, -1.0, 1.0, 2.0]), mode="fast")
    assert r.predicted_error is not None and "focal" not in r.reason
    assert models.annotate(_result([2.0, 2.0, -1.0, 1.0, 2.0]), mode="fr").predicted_error is None
    assert ReliabilityModel.load_default(config_dir=tmp_path / "nothing") is None


def test_shipped_models_and_thresholds():
    thresholds = load_thresholds()
    assert set(thresholds) == set(TARGETS)
    shipped = [m for m in ("fr", "fast") if (config_dir() / f"reliability_{m}.npz").is_file()]
    if not shipped:
        pytest.skip("no trained default models in configs/")
    models = ReliabilityModel.load_default()
    for mode in shipped:
        model = models.models[mode]
        assert model.meta["mode"] == mode and len(model.train_cues) >= 100
        assert model.cue_names == model_cue_names(mode)
        assert model.cue_names == (FR_MODEL_CUE_NAMES if mode == "fr" else MODEL_CUE_NAMES)
        # a clean scene; fR's cues: the estimate's focal length wins by 2,000 nats
        clean = dict(min_family_segments=60.0, grid_entropy=1e-6, mean_log_likelihood=0.3, focal_conditioning=0.3,
                     focal_prior_share=0.02, focal_profile_gap=2000.0, focal_spread=0.15)
        good, bad = model.predict([clean, dict(clean, min_family_segments=2.0, grid_entropy=1.0,
                                                mean_log_likelihood=-1.0)])
        assert good[2] < bad[2]  # a clean scene is predicted better than a near-empty family
        pinned, prior_set = model.predict([clean, dict(clean, focal_prior_share=1.0, focal_spread=1.0)])
        assert pinned[2] < prior_set[2]  # segments that pin f down beat a focal length the prior sets
        if mode == "fr":
            clear, tied = model.predict([dict(clean, focal_profile_gap=3000.0), dict(clean, focal_profile_gap=10.0)])
            assert clear[2] < tied[2]  # a second basin nearly as good: a larger predicted focal error


def test_reliability_is_a_stage_of_the_estimator():
    from fr_torch.plugins.interface import ImageMeta
    from fr_torch.plugins.methods import FRCalibrator
    from fr_torch.runtime.estimator import FREstimator
    from fr_torch.synthetic import random_rotation, synthetic_segments

    segments, _ = synthetic_segments(420.0, random_rotation(np.random.default_rng(3)), 640, 480, seed=3)
    if not (config_dir() / "reliability_fast.npz").is_file():
        pytest.skip("no shipped fast model")
    [on] = FREstimator(mode="fast").calibrate_segments([segments], [(640, 480)])
    assert on.ok and set(on.predicted_error) == set(TARGETS)
    [off] = FREstimator(mode="fast", reliability=None).calibrate_segments([segments], [(640, 480)])
    assert off.ok and off.predicted_error is None
    # the Calibrator interface carries the predicted errors too (eval's predictions.csv columns)
    calibrator = FRCalibrator(mode="fast", use_meta_segments=True)
    estimate = calibrator.estimate(None, ImageMeta(name="x", width=640, height=480, segments=segments))
    assert estimate.predicted_error == on.predicted_error


def test_paper_cue_model_and_older_files(tmp_path):
    """A model trained on the paper's three cues keeps predicting from them (also a file written
    before the fourth cue existed, whose metadata has no cue names); dicts may carry more cues."""
    cues, errors = make_training(300)
    paper = ReliabilityModel.fit(cues[:, :3], errors, meta={"mode": "fr"}, cue_names=PAPER_CUE_NAMES, k_grid=[9])
    assert paper.cue_names == PAPER_CUE_NAMES and paper.meta["cue_names"] == list(PAPER_CUE_NAMES)
    probe = make_training(20, seed=5)[0]
    dicts = [dict(zip(MODEL_CUE_NAMES, row)) for row in probe]
    np.testing.assert_array_equal(paper.predict(dicts), paper.predict(probe[:, :3]))
    path = paper.save(tmp_path / "old.npz")
    with np.load(path, allow_pickle=False) as data:  # rewrite it as an older version did: no cue names
        arrays = {key: data[key] for key in data.files}
    meta = json.loads(str(arrays["meta_json"]))
    meta.pop("cue_names")
    arrays["meta_json"] = np.array(json.dumps(meta))
    np.savez(tmp_path / "older.npz", **arrays)
    older = ReliabilityModel.load(tmp_path / "older.npz")
    assert older.cue_names == PAPER_CUE_NAMES
    np.testing.assert_array_equal(older.predict(dicts), paper.predict(dicts))
    # a four-cue model asked about a result without the fourth cue: NaN, not a guess
    full = ReliabilityModel.fit(cues, errors, k_grid=[9])
    assert np.isnan(full.predict([dict(zip(PAPER_CUE_NAMES, probe[0, :3]))])).all()
    assert cues_array({"grid_entropy": 1.0}).shape == (1, len(FR_MODEL_CUE_NAMES))
    with pytest.raises(ValueError):  # cue names that do not match the stored columns
        ReliabilityModel(cues, errors, paper.feature_mean, paper.feature_components, paper.feature_variance, 5,
                         {"cue_names": list(PAPER_CUE_NAMES)})


def test_given_focal_length_has_no_predicted_focal_error():
    """With focal_px given, the predicted focal error is 0 and the focal threshold never fires
    (the models predict the error of an *estimated* focal length)."""
    from fr_torch.runtime.estimator import FREstimator
    from fr_torch.synthetic import random_rotation, synthetic_segments

    path = config_dir() / "reliability_fast.npz"
    if not path.is_file():
        pytest.skip("no shipped fast model")
    strict = ReliabilityModel.load(path, thresholds={"roll_deg": 100.0, "tilt_deg": 100.0, "focal_pct": 1e-6})
    segments, _ = synthetic_segments(420.0, random_rotation(np.random.default_rng(5)), 640, 480, seed=5)
    est = FREstimator(mode="fast", reliability=strict)
    [estimated] = est.calibrate_segments([segments], [(640, 480)])
    [given] = est.calibrate_segments([segments], [(640, 480)], focal_px=420.0)
    assert estimated.predicted_error["focal_pct"] > 0 and not estimated.reliable and "focal" in estimated.reason
    assert given.ok and given.predicted_error["focal_pct"] == 0.0 and given.reliable, given.reason
    assert given.predicted_error["roll_deg"] > 0  # the angles are still predicted
    with pytest.raises(ValueError):
        strict.annotate_many([estimated], focal_known=[True, False])
