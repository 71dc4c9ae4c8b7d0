"""The horizon: its geometry from K and R (pinhole and division lens), its bound, the benchmark's
metric and AUC, the ``ecd-tune`` dataset and ``fr eval --task horizon``."""
import math

import numpy as np
import pytest

from fr_eval.scoring.horizon_metric import FRAME, estimate_horizon, lezama_auc, truth_horizons
from fr_torch.core.geometry.camera import Camera
from fr_torch.core.geometry.horizon import Horizon, border_columns, horizon_border_y, horizon_line
from fr_torch.core.geometry.lens import distort_points, normalising_radius
from fr_torch.core.reliability.bounds import HORIZON_BOUND_CAP_PCT, horizon_bound_pct
from fr_torch.core.result import CalibrationResult
from fr_torch.plugins.interface import CameraEstimate

W, H, F = 640, 480, 500.0


def _camera(pan, pitch, roll, focal=F, pp=None):
    return Camera.from_angles(W, H, focal, roll_deg=roll, pitch_deg=pitch, pan_deg=pan, principal_point=pp)


@pytest.mark.parametrize("pan,pitch,roll,pp", [(0, 0, 0, None), (20, 12, 4, None), (-33, -18, -7, (330.0, 250.0))])
def test_horizon_follows_tilt_and_roll(pan, pitch, roll, pp):
    """y(x) = c_y + f tan(tilt) - (x - c_x) tan(roll) (module docstring of core/geometry/conventions.py), and every
    horizontal vanishing point lies on the line."""
    camera = _camera(pan, pitch, roll, pp=pp)
    horizon = Horizon.from_camera(camera)
    cx, cy = camera.principal_point
    tilt, roll_rad = math.radians(camera.angles["tilt_deg"]), math.radians(camera.angles["roll_deg"])
    for x, y in zip(border_columns(W), (horizon.left_y, horizon.right_y)):
        assert y == pytest.approx(cy + F * math.tan(tilt) - (x - cx) * math.tan(roll_rad), abs=1e-9)
    line = np.asarray(horizon.line)
    assert line[1] > 0 and np.hypot(line[0], line[1]) == pytest.approx(1.0)
    for column in (0, 2):  # the horizontal vanishing points
        vp = camera.K @ camera.rotation[:, column]
        assert abs(line @ vp) <= 1e-9 * np.linalg.norm(vp)
    assert horizon.error(horizon) == 0.0


def test_horizon_at_infinity_and_vertical_horizon():
    looking_down = _camera(0, -90, 0)
    assert horizon_line(looking_down.K, looking_down.rotation) is None
    assert Horizon.from_camera(looking_down) is None
    assert Horizon.from_camera(Camera(W, H, None, None, np.eye(3))) is None  # no focal length
    assert horizon_border_y((1.0, 0.0, -100.0), W, H) == (None, None)  # the line x = 100
    assert Horizon((1.0, 0.0, -100.0), None, None, W, H).error(Horizon.from_camera(_camera(0, 0, 0))) == math.inf


@pytest.mark.parametrize("k", [-0.3, -0.05, 0.15])
def test_border_crossings_through_a_division_lens(k):
    """The crossing solved in closed form equals the distorted straight horizon sampled densely."""
    camera = _camera(10, 8, 6)
    line = horizon_line(camera.K, camera.rotation)
    left, right = horizon_border_y(line, W, H, k, camera.principal_point)
    xs = np.linspace(-2 * W, 3 * W, 200001)
    photo = distort_points(np.c_[xs, -(line[0] * xs + line[2]) / line[1]], k, np.asarray(camera.principal_point),
                           normalising_radius(W, H))
    good = np.isfinite(photo).all(1)
    for x, y in zip(border_columns(W), (left, right)):
        i = np.argmin(np.abs(photo[good, 0] - x))
        assert y == pytest.approx(photo[good][i, 1], abs=0.05)
    straight = Horizon.from_camera(camera)
    bent = Horizon.from_camera(camera, k)
    assert bent.left_y == pytest.approx(left) and bent.line != straight.line
    assert Horizon.from_camera(camera, 1e-12).left_y == pytest.approx(straight.left_y, abs=1e-6)


def test_bound_from_the_tilt_and_focal_bounds():
    bounds = {"tilt_deg": 2.0, "focal_pct": 10.0}
    level = horizon_bound_pct(bounds, F, 0.0, H)  # tilt 0: the focal error does not move the horizon
    assert level == pytest.approx(100 * F * math.tan(math.radians(2.0)) / H)
    tilted = horizon_bound_pct(bounds, F, 20.0, H)
    t = math.radians(20.0)
    expected = F * (math.tan(t + math.radians(2.0)) - math.tan(t) + math.tan(t) * 0.10)
    assert tilted == pytest.approx(100 * expected / H)
    assert horizon_bound_pct({"tilt_deg": 2.0, "focal_pct": 0.0}, F, 20.0, H) < tilted  # a given focal length
    assert horizon_bound_pct(None, F, 0.0, H) is None
    assert horizon_bound_pct({"tilt_deg": None, "focal_pct": 1.0}, F, 0.0, H) is None
    assert horizon_bound_pct({"tilt_deg": 400.0, "focal_pct": 1e6}, F, 88.0, H) == HORIZON_BOUND_CAP_PCT


def test_result_reports_the_horizon_in_json():
    camera = _camera(20, 12, 4)
    result = CalibrationResult(image="x", width=W, height=H, camera=camera,
                               error_bound={"tilt_deg": 1.5, "focal_pct": 5.0})
    record = result.to_json()["horizon"]
    expected = Horizon.from_camera(camera)
    assert record["line"] == list(expected.line) and record["left_y"] == expected.left_y
    assert record["bound_pct"] == pytest.approx(horizon_bound_pct(result.error_bound, F, camera.angles["tilt_deg"], H))
    assert CalibrationResult(image="y", width=W, height=H, ok=False).to_json()["horizon"] is None


def test_lezama_auc_hand_computed():
    # calc_auc.m: sort, clip at 0.25, points (e_i, i/n) then (0.25, 1), trapezoids / 0.25
    auc, points = lezama_auc([0.1, 0.0, 0.3, 0.05])
    expected = (0.05 * (0.25 + 0.5) / 2 + 0.05 * (0.5 + 0.75) / 2 + 0.15 * (0.75 + 1.0) / 2) / 0.25
    assert auc == pytest.approx(expected)
    assert points[-1].tolist() == [0.25, 1.0]
    assert lezama_auc([0.0, 0.0])[0] == pytest.approx(1.0)
    assert lezama_auc([math.inf, math.nan, 1.0])[0] == 0.0  # failures count beyond the cutoff
    assert math.isnan(lezama_auc([])[0])


def test_truth_and_estimate_horizons():
    camera = _camera(5, 3, 1)

    class Sample:
        width, height = W, H
        extra = {"horizons": {"labelled": np.asarray(Horizon.from_camera(camera).line) * -3.0}}

    sample = Sample()
    sample.camera = camera
    truths = truth_horizons(sample)
    assert set(truths) == {"labelled", FRAME} and truths["labelled"].error(truths[FRAME]) < 1e-12
    assert np.allclose(truths["labelled"].line, truths[FRAME].line)  # scaled as horizon_line reports it
    estimate = CameraEstimate(method="m", camera=_camera(5, 4, 1), extra={"horizon_bound_pct": 2.5})
    horizon = estimate_horizon(estimate)
    assert horizon.bound_pct == 2.5 and horizon.error(truths[FRAME]) > 0
    assert estimate_horizon(CameraEstimate.failure("m", "no")) is None


@pytest.mark.data
def test_ecd_tune_and_the_horizon_task(data_root, tmp_path):
    from fr_eval.datasets.registry import load_dataset
    from fr_eval.protocols.eval_command import main

    samples = load_dataset("ecd-tune", root=data_root, split="all")
    assert len(samples) == 25 and samples[0].name == "000" and samples[0].camera is None
    assert set(truth_horizons(samples[0])) == {"labelled"}
    with pytest.raises(ValueError, match="held out"):
        load_dataset("ecd-tune", root=data_root, split="test")
    yud = load_dataset("yud", root=data_root, split="test")[0]
    truths = truth_horizons(yud)
    assert set(truths) == {"labelled", "lezama-code", FRAME}
    assert truths["labelled"].error(truths[FRAME]) < 0.05  # the labelled VPs and the orthogonal frame agree roughly
    out = tmp_path / "horizon"
    assert main(["--task", "horizon", "--dataset", "ecd-tune", "--split", "all", "--limit", "2", "--methods",
                 "fast-fr", "--data-root", str(data_root), "--out", str(out), "--no-plots"]) == 0
    for name in ("horizon_errors.csv", "horizon_summary.md", "horizon_summary.csv", "run_info.json"):
        assert (out / name).is_file()
    text = (out / "horizon_summary.md").read_text()
    assert "| fast-fr |" in text and "AUC (labelled)" in text and "calc_auc.m" in text


def test_analysis_attribution_and_free_vanishing_points():
    """The Shapley shares and the definition gap add up to the error; a family's VP fitted alone from
    exact segments is its direction."""
    from fr_eval.protocols.horizon_analysis import attribution, family_directions
    from fr_torch.synthetic import synthetic_segments

    truth = _camera(10, 6, 2, pp=(330.0, 250.0))
    estimate = _camera(11, 7.5, 2.6, focal=470.0)
    target = Horizon.from_camera(_camera(10, 6.3, 2.1, pp=(330.0, 250.0)))
    shares = attribution(estimate, truth, target)
    assert sum(shares[k] for k in ("tilt", "roll", "f", "pp", "definition")) == pytest.approx(shares["total"])
    assert shares["total"] == pytest.approx(100 * Horizon.from_camera(estimate).error(target))
    assert shares["definition"] == pytest.approx(100 * Horizon.from_camera(truth).error(target))
    segments, labels = synthetic_segments(F, truth.rotation, W, H, n_per_family=30, noise_px=0.0, clutter_fraction=0.0,
                                          seed=1, principal_point=truth.principal_point)
    record = {"segments": segments.tolist(), "labels": labels.tolist()}
    for family, (direction, support) in family_directions(record, truth.K).items():
        assert abs(direction @ truth.rotation[:, family]) == pytest.approx(1.0, abs=1e-9) and support > 0
