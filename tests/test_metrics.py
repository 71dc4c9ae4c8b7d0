"""Evaluation metrics and tables on hand-made cases."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from fr_eval.datasets.registry import CalibrationSample
from fr_eval.scoring.metrics import (
    NOT_SUPPLIED,
    frame_error_deg,
    image_errors,
    mean_se,
    proper_signed_permutations,
    summarize,
    summarize_groups,
)
from fr_eval.scoring.tables import (
    deviation_measure_summaries,
    display_frame,
    format_mean_se,
    parse_method_spec,
    to_latex,
    to_markdown,
)
from fr_torch.core.geometry.camera import Camera
from fr_torch.core.geometry.conventions import hfov_from_focal, horizon_angles, rotation_from_angles
from fr_torch.plugins.interface import CameraEstimate
from fr_torch.registry import not_supplied, with_option


def rot_z(deg: float) -> np.ndarray:
    a = math.radians(deg)
    return np.array([[math.cos(a), -math.sin(a), 0], [math.sin(a), math.cos(a), 0], [0, 0, 1.0]])


def rot_axis(axis, deg: float) -> np.ndarray:
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    a = math.radians(deg)
    return np.eye(3) + math.sin(a) * k + (1 - math.cos(a)) * k @ k


R0 = rotation_from_angles(23.0, 7.0, -3.0).numpy()


def test_24_distinct_proper_signed_permutations():
    perms = proper_signed_permutations()
    assert perms.shape == (24, 3, 3)
    assert np.allclose(np.linalg.det(perms), 1.0)
    assert len({p.tobytes() for p in perms}) == 24
    assert all(np.allclose(p @ p.T, np.eye(3)) for p in perms)


def test_frame_error_zero_for_relabelled_axes():
    for p in proper_signed_permutations():
        assert frame_error_deg(R0, R0 @ p) == pytest.approx(0.0, abs=1e-5)


def test_frame_error_of_known_rotation():
    assert frame_error_deg(R0, R0 @ rot_z(5.0)) == pytest.approx(5.0, abs=1e-6)
    assert frame_error_deg(np.eye(3), rot_z(5.0)) == pytest.approx(5.0, abs=1e-6)
    # world-side perturbation about an oblique axis, plus a relabelling of the estimate's columns
    p = proper_signed_permutations()[7]
    assert frame_error_deg(R0, rot_axis([1, 2, 3], 3.0) @ R0 @ p) == pytest.approx(3.0, abs=1e-6)
    # 45 deg about a Manhattan axis is the farthest a frame can be along that axis
    assert frame_error_deg(np.eye(3), rot_z(45.0)) == pytest.approx(45.0, abs=1e-6)
    # a 60 deg turn is folded by the symmetry: 60 -> 30
    assert frame_error_deg(np.eye(3), rot_z(60.0)) == pytest.approx(30.0, abs=1e-6)


def test_frame_error_rejects_left_handed():
    with pytest.raises(ValueError):
        frame_error_deg(R0, R0 @ np.diag([1.0, -1.0, 1.0]))


def test_mean_se():
    mean, se, n = mean_se([1.0, 2.0, 3.0])
    assert (mean, n) == (2.0, 3)
    assert se == pytest.approx(1.0 / math.sqrt(3))
    mean, se, n = mean_se([4.0, None, float("nan")])
    assert (mean, n) == (4.0, 1) and math.isnan(se)
    mean, se, n = mean_se([])
    assert n == 0 and math.isnan(mean)


def sample(f=500.0, pan=10.0, pitch=5.0, roll=3.0, width=640):
    return CalibrationSample(name="s", image_path=None, width=width, height=480,
                             camera=Camera(width, 480, f, rotation=rotation_from_angles(pan, pitch, roll).numpy()))


def test_sample_fills_angles_and_fov():
    s = sample(pitch=30.0, roll=10.0)
    assert s.roll_deg == pytest.approx(10.0, abs=1e-9)
    assert s.pitch_deg == pytest.approx(30.0, abs=1e-9)
    assert s.tilt_deg == pytest.approx(30.38, abs=0.01)
    assert s.hfov_deg == pytest.approx(2 * math.degrees(math.atan(320 / 500)))


def test_image_errors_from_rotation_and_focal():
    gt = sample()
    r_est = rotation_from_angles(10.0 + 90.0, 7.0, 3.0).numpy()  # pan by 90: same Manhattan frame
    est = CameraEstimate(method="m", camera=Camera(640, 480, 550.0, rotation=r_est))
    err = image_errors(gt, est)
    angles = horizon_angles(torch.as_tensor(r_est))
    assert err["tilt_err_deg"] == pytest.approx(abs(float(angles["tilt_deg"]) - gt.tilt_deg))
    assert err["tilt_err_deg"] == pytest.approx(2.0, abs=0.05)
    assert err["roll_err_deg"] == pytest.approx(0.0, abs=1e-6)
    assert err["focal_err_pct"] == pytest.approx(10.0)
    expected_fov = 100 * abs(hfov_from_focal(550.0, 640) - gt.hfov_deg) / gt.hfov_deg
    assert err["fov_err_pct"] == pytest.approx(expected_fov)
    assert err["frame_err_deg"] == pytest.approx(2.0, abs=1e-6)


def test_image_errors_explicit_fields_and_missing_quantities():
    gt = sample()
    # a partial answer (roll and hfov only) as a dict: the metrics take any object with these keys
    est = {"method": "m", "ok": True, "roll_deg": gt.roll_deg + 1.5, "hfov_deg": gt.hfov_deg * 1.1}
    err = image_errors(gt, est)
    assert err["roll_err_deg"] == pytest.approx(1.5)
    assert err["fov_err_pct"] == pytest.approx(10.0)
    assert err["focal_err_pct"] is not None  # derived from hfov and the width
    assert err["tilt_err_deg"] is None and err["frame_err_deg"] is None


def test_left_handed_estimate_made_proper():
    gt = sample()
    est = CameraEstimate(method="m", camera=Camera(640, 480, rotation=gt.rotation @ np.diag([1.0, -1.0, 1.0])))
    assert image_errors(gt, est)["frame_err_deg"] == pytest.approx(0.0, abs=1e-5)


def test_failures_are_counted_not_dropped():
    gt = sample()
    assert all(v is None for v in image_errors(gt, None).values())
    assert all(v is None for v in image_errors(gt, CameraEstimate.failure("m", "no VP")).values())
    rows = [
        {"failed": False, "runtime_s": 1.0, "roll_err_deg": 1.0, "tilt_err_deg": 2.0},
        {"failed": False, "runtime_s": 3.0, "roll_err_deg": 3.0, "tilt_err_deg": 4.0},
        {"failed": True, "runtime_s": 5.0, "roll_err_deg": None},
    ]
    s = summarize("m", rows)
    assert s.n_images == 3 and s.failures == 1
    assert s.failure_pct == pytest.approx(100 / 3)
    assert s.mean["roll_err_deg"] == 2.0 and s.n["roll_err_deg"] == 2
    assert s.mean["runtime_s"] == 3.0 and s.n["runtime_s"] == 3  # run time counts the failed image
    assert s.n["focal_err_pct"] == 0
    table = display_frame([s])
    assert table.loc[0, "focal MAE (%)"] == "n/a"
    assert table.loc[0, "roll MAE (°)"] == "2.00 ± 1.00"
    assert table.loc[0, "failures"] == "1 (33.3%)"
    md, tex = to_markdown(table), to_latex(table, "caption 50%")
    assert "n/a" in md and "2.00 ± 1.00" in md
    assert r"$\pm$" in tex and r"50\%" in tex and r"\toprule" in tex


def test_format_and_specs():
    assert format_mean_se(1.234, 0.05, 10) == "1.23 ± 0.05"
    assert format_mean_se(float("nan"), float("nan"), 0) == "n/a"
    assert parse_method_spec("fr[measure=a, detector=lsd]") == ("fr", {"measure": "a", "detector": "lsd"})
    assert parse_method_spec("pkg.mod:Cls") == ("pkg.mod:Cls", {})
    assert with_option("fr", "measure", "c") == "fr[measure=c]"
    assert with_option("fr[detector=lsd]", "measure", "c") == "fr[detector=lsd,measure=c]"


def test_deviation_measure_rows():
    rows = [{"failed": False, "runtime_s": 1.0, "roll_err_deg": 1.0}]
    summaries = [summarize(m, rows) for m in ("fr", "fr[measure=c]", "fr[measure=a]", "fast-fr[measure=b]")]
    picked = deviation_measure_summaries(summaries)
    assert [s.method for s in picked] == ["b (fast-fr)", "a (fr)", "c (fr)"]


def test_valid_share_and_not_supplied_rows():
    rows = [{"failed": False, "runtime_s": 1.0, "roll_err_deg": 1.0, "group": "60"},
            {"failed": True, "reason": "no VP", "runtime_s": 1.0, "group": "90"},
            {"failed": False, "runtime_s": 1.0, "roll_err_deg": 3.0, "group": "60"},
            {"failed": True, "reason": not_supplied("weights"), "runtime_s": 1.0, "group": "90"}]
    s = summarize("m", rows)
    assert s.n_valid == 2 and s.valid_pct == 50.0 and not s.not_supplied  # partial n/a = ordinary failures
    table = display_frame([s])
    assert table.loc[0, "valid (%)"] == "50.0" and table.loc[0, "failures"] == "2 (50.0%)"
    na_rows = [{"failed": True, "reason": "n/a (not supplied)", "runtime_s": 0.001}] * 3
    na = summarize("ctrlc", na_rows)
    assert na.not_supplied and na.na_reason == NOT_SUPPLIED and na.n_images == 3
    assert math.isnan(na.mean["runtime_s"]) and na.n["runtime_s"] == 0  # no number at all
    row = display_frame([s, na]).iloc[1]
    assert row["method"] == "ctrlc" and all(v == NOT_SUPPLIED for v in row.drop("method"))
    assert na.as_row()["status"] == NOT_SUPPLIED and s.as_row()["status"] == ""
    groups = summarize_groups("m", rows)
    assert [(g.group, g.n_images, g.failures) for g in groups] == [("60", 2, 0), ("90", 2, 2)]
    assert groups[0].mean["roll_err_deg"] == 2.0
    assert [g.group for g in summarize_groups("ctrlc", na_rows)] == ["all"]
    numbers = [{"failed": False, "group": g} for g in ("120", "60", "90")]
    assert [g.group for g in summarize_groups("m", numbers)] == ["60", "90", "120"]
    grouped = display_frame(groups, metrics=("roll_err_deg",), group_label="FOV")
    assert list(grouped.columns) == ["method", "FOV", "n", "valid (%)", "failures", "roll MAE (°)"]
