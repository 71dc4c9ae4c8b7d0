"""Issue 13: non-finite estimates are failures; the FOV search range (validation, names, portrait
== landscape); the "no probabilistic model" ablation."""
from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
import torch

from fr_torch.core.geometry.camera import Camera
from fr_torch.core.reliability.sanity import check_result
from fr_torch.core.settings.config import SearchConfig
from fr_torch.core.settings.fov import FovRange
from fr_torch.errors import FRInputError
from fr_torch.plugins.interface import CameraEstimate
from fr_torch.runtime.estimator import FREstimator
from fr_torch.synthetic import random_rotation, synthetic_segments


def _scene(seed: int, focal: float, width: int = 640, height: int = 480):
    rng = np.random.default_rng(seed)
    rotation = random_rotation(rng, pan=(-30, 30), pitch=(-20, 20), roll=(-8, 8))
    segments, _ = synthetic_segments(focal, rotation, width=width, height=height, seed=seed)
    return segments, rotation


@pytest.mark.parametrize("mode", ["fast", "fr"])
def test_measure_e_float32_is_finite(mode):
    """Measure (e) in float32 used to make NaN parameters (asin' = inf where |s|/|n| rounds to 1)."""
    est = FREstimator(mode=mode, measure="e", dtype=torch.float32)
    scenes = [_scene(seed, focal) for seed, focal in ((0, 300.0), (1, 500.0), (2, 900.0))]
    results = est.calibrate_segments([s for s, _ in scenes], [(640, 480)] * 3)
    for (segments, rotation), result, focal in zip(scenes, results, (300.0, 500.0, 900.0)):
        assert result.ok, result.reason
        assert all(math.isfinite(v) for v in (result.focal_px, result.hfov_deg, result.roll_deg, result.tilt_deg,
                                               result.log_likelihood))
        assert np.isfinite(result.rotation).all() and np.isfinite(result.vanishing_points).all()
        assert abs(result.focal_px - focal) / focal < 0.1


def test_check_result_marks_non_finite_as_failure():
    [result] = FREstimator(mode="fast").calibrate_segments([_scene(3, 500.0)[0]], [(640, 480)])
    assert result.ok
    result.camera = replace(result.camera, focal_px=float("nan"))  # a NaN anywhere in the camera
    assert math.isnan(result.hfov_deg)
    check_result(result, SearchConfig.from_config())
    assert not result.ok and not result.reliable and "non-finite" in result.reason
    assert result.focal_px is None and result.rotation is None


def test_non_finite_refinement_fails_that_image_only(monkeypatch):
    """A NaN from the search (parameters or objective) makes that image's result ok=False with the
    reason, in a batch whose other images keep their estimates."""
    import fr_torch.core.search.refine as refine_module

    real_refine = refine_module.refine

    def refine_with_nan(*args, **kwargs):
        params, objective = real_refine(*args, **kwargs)
        params, objective = params.clone(), objective.clone()
        params[1, :, 3] = float("nan")  # image 1: NaN focal at every refined start ...
        objective[1] = float("inf")  # ... scored above everything, so it is the one chosen
        return params, objective

    monkeypatch.setattr(refine_module, "refine", refine_with_nan)
    scenes = [_scene(seed, 500.0)[0] for seed in (3, 4, 5)]
    results = FREstimator(mode="fast", reliability=None).calibrate_segments(scenes, [(640, 480)] * 3)
    assert [r.ok for r in results] == [True, False, True]
    assert "non-finite" in results[1].reason and results[1].focal_px is None and results[1].rotation is None
    assert all(abs(r.focal_px - 500.0) / 500.0 < 0.1 for r in (results[0], results[2]))


def test_metrics_count_non_finite_estimate_as_failure():
    from fr_eval.protocols.run_eval import prediction_row
    from fr_eval.scoring.metrics import failure_reason, is_failure, summarize

    class Sample:
        name, width, height, split = "img", 640, 480, "test"
        roll_deg, tilt_deg, pitch_deg, hfov_deg, focal_px = 1.0, 2.0, 2.0, 60.0, 554.26
        rotation = np.eye(3)

    good = CameraEstimate(method="m", camera=Camera(640, 480, 554.26, rotation=np.eye(3)))
    nan = CameraEstimate(method="m", camera=Camera(640, 480, float("nan"), rotation=np.eye(3)))
    bad_rotation = CameraEstimate(method="m", camera=Camera(640, 480, 500.0, rotation=np.full((3, 3), np.nan)))
    assert not is_failure(good) and is_failure(nan) and is_failure(bad_rotation)
    assert "non-finite" in failure_reason(nan)
    rows = [prediction_row("m", Sample(), est, 0.1) for est in (good, nan, bad_rotation)]
    assert [r["failed"] for r in rows] == [False, True, True]
    summary = summarize("m", rows)
    assert summary.failures == 2 and summary.valid_pct == pytest.approx(100 / 3)
    assert summary.n["focal_err_pct"] == 1


def test_fov_range_validation_and_names():
    assert tuple(FovRange.parse("paper")) == (50.0, 130.0) == FovRange.NAMED["paper"]
    assert FovRange.parse("30:120") == FovRange(30.0, 120.0) == FovRange.parse("30,120") == FovRange.parse(None)
    assert FovRange.parse((40, 90)) == FovRange.parse(FovRange(40, 90)) and str(FovRange(40, 90)) == "[40°, 90°]"
    lo, hi = SearchConfig.from_config().fov_range
    assert lo <= 30.0 and hi >= 120.0  # the library default covers the cameras users have
    for bad in ((60.0, 20.0), (0.5, 90.0), (30.0, 180.0), (float("nan"), 90.0), (30.0, math.inf), (40.0, 40.0)):
        with pytest.raises(FRInputError, match="min < max"):
            SearchConfig.from_config(fov_range=bad)
    with pytest.raises(FRInputError, match="FOV range"):
        FovRange.parse("wide")


def test_cli_hfov_range_errors_are_one_line(capsys, tmp_path):
    from fr_torch.cli.main import main

    assert main(["calibrate", str(tmp_path / "x.png"), "--hfov-range", "120,30"]) == 2
    err = capsys.readouterr().err.strip()
    assert "min < max" in err and len(err.splitlines()) == 1


def test_portrait_sees_the_same_focal_range_as_landscape():
    """The range is on the long side: a portrait image (480 x 640) gets the same focal bounds as the
    same camera held in landscape (640 x 480), and both recover the same focal length."""
    config = SearchConfig.from_config()
    landscape = config.fov_range.focal_bounds(torch.tensor([640.0]))
    portrait = config.fov_range.focal_bounds(torch.tensor([max(480.0, 640.0)]))
    assert torch.equal(landscape[0], portrait[0]) and torch.equal(landscape[1], portrait[1])
    focal = 520.0
    seg_l, _ = _scene(5, focal, 640, 480)
    seg_p, _ = _scene(5, focal, 480, 640)
    est = FREstimator(mode="fr")
    [r_l] = est.calibrate_segments([seg_l], [(640, 480)])
    [r_p] = est.calibrate_segments([seg_p], [(480, 640)])
    assert abs(r_l.focal_px - focal) / focal < 0.03 and abs(r_p.focal_px - focal) / focal < 0.03
    # hfov_deg stays the horizontal FOV of each image
    assert r_p.hfov_deg == pytest.approx(math.degrees(2 * math.atan(240 / r_p.focal_px)), rel=1e-6)


def test_nomixture_ablation_runs():
    from fr_torch.plugins.interface import get_calibrator

    method = get_calibrator("fr[model=nomixture,range=paper]")
    assert method.name == "fr[range=paper,model=nomixture]"
    assert method.estimator.likelihood.params.model == "nomixture"
    segments, _ = _scene(8, 400.0)
    [result] = method.estimator.calibrate_segments([segments], [(640, 480)])
    assert result.ok and abs(result.focal_px - 400.0) / 400.0 < 0.1
