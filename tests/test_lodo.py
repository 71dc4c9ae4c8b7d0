"""The LODO protocol's pieces: NYU-VP's loader on a self-made photo, zenith error, families, given segments."""
from __future__ import annotations

import numpy as np
import pytest
from fr_eval.datasets import nyu_vp
from fr_eval.protocols.lodo import (
    FAMILIES,
    REPORTED,
    family_of,
    jobs,
    setting_name,
    zenith_error_deg,
)
from fr_eval.protocols.run_eval import build_meta, given_segments

from fr_torch.core.camera import rotation_from_angles


def _write_photo(folder, index, rotation, extra_vp=None):
    """NYU-VP's three files for one photo whose labelled VPs are those of ``rotation`` (+ one more)."""
    K = nyu_vp.calibration_matrix()
    vps = [(K @ rotation[:, k]) for k in (1, 0, 2)]  # vertical first, as a labeller might
    if extra_vp is not None:
        vps.append(K @ extra_vp)
    tag = f"{index:04d}"
    (folder / f"vps_{tag}.csv").write_text("idx X Y\n" + "".join(
        f"{i} {v[0] / v[2]:.6f} {v[1] / v[2]:.6f}\n" for i, v in enumerate(vps)))
    lines = "idx " + " ".join(f"line{k}_x1 line{k}_y1 line{k}_x2 line{k}_y2" for k in range(1, 9)) + "\n"
    for i in range(len(vps)):
        lines += f"{i} 10 20 30 40 50 60 70 80" + " " * 24 + "\n"
    (folder / f"labelled_lines_{tag}.csv").write_text(lines)
    header = ("line_hom_a line_hom_b line_hom_c centroid_x centroid_y centroid_z point1_x point1_y point1_z "
              "point2_x point2_y point2_z\n")
    (folder / f"lsd_lines_{tag}.csv").write_text(header + "0 1 -5 2 5 1 1.5 5.5 1 100.25 7.75 1\n"
                                                  "0 1 -5 2 5 1 10 20 1 30 40 1\n")


def test_nyu_vp_loader_on_a_made_photo(tmp_path):
    rotation = rotation_from_angles(20.0, -12.0, 4.0).numpy()
    _write_photo(tmp_path, 7, rotation, extra_vp=rotation @ np.array([np.cos(0.5), 0.0, np.sin(0.5)]))
    sample = nyu_vp.load_sample(tmp_path, 7, "train")
    assert sample.name == "nyu_0007" and sample.image_path is None and sample.width == 640
    assert sample.focal_px == pytest.approx(518.8579) and sample.principal_point == pytest.approx((325.5824, 253.7362))
    # the vertical and the horizontal frame are the labelled ones (up to relabelling of the horizontals)
    np.testing.assert_allclose(sample.camera.rotation[:, 1], rotation[:, 1], atol=1e-6)
    assert sample.camera.pan_known
    assert abs(sample.camera.rotation[:, 0] @ rotation[:, 0]) == pytest.approx(1.0, abs=1e-6) or \
        abs(sample.camera.rotation[:, 0] @ rotation[:, 2]) == pytest.approx(1.0, abs=1e-6)
    assert sample.tilt_deg == pytest.approx(-12.0 / np.cos(np.radians(4.0)), abs=0.3)
    # hand-labelled lines of the three Manhattan VPs, the fourth (non-Manhattan) one's left out
    assert sample.extra["num_labelled_vps"] == 4 and sample.extra["num_manhattan_vps"] == 3
    assert sample.segments.shape == (6, 4) and sorted(set(sample.segment_labels.tolist())) == [0, 1, 2]
    np.testing.assert_allclose(sample.extra["detected_segments"], [[1.5, 5.5, 100.25, 7.75], [10, 20, 30, 40]])
    # fr eval hands the given segments to every method; an oracle run still gets the labelled ones
    np.testing.assert_allclose(given_segments(sample), sample.extra["detected_segments"])
    assert build_meta(sample, "centre", False, False, "nyu-vp", "cpu").segments.shape == (2, 4)
    assert build_meta(sample, "centre", True, False, "nyu-vp", "cpu").segments.shape == (6, 4)
    assert build_meta(sample, "calibrated", False, False, "nyu-vp", "cpu").principal_point == pytest.approx(
        (325.5824, 253.7362))


def test_nyu_vp_gravity_only_photo_and_missing_folder(tmp_path):
    rotation = rotation_from_angles(0.0, -30.0, 2.0).numpy()
    K = nyu_vp.calibration_matrix()
    v = K @ rotation[:, 1]
    (tmp_path / "vps_0000.csv").write_text(f"idx X Y\n0 {v[0] / v[2]} {v[1] / v[2]}\n")
    (tmp_path / "labelled_lines_0000.csv").write_text("idx line1_x1 line1_y1 line1_x2 line1_y2\n0 1 2 3 4\n")
    (tmp_path / "lsd_lines_0000.csv").write_text("header\n")
    sample = nyu_vp.load_sample(tmp_path, 0, "val")
    assert not sample.camera.pan_known and sample.extra["detected_segments"].shape == (0, 4)
    np.testing.assert_allclose(sample.camera.rotation[:, 1], rotation[:, 1], atol=1e-9)
    assert np.linalg.det(sample.camera.rotation) == pytest.approx(1.0)
    with pytest.raises(FileNotFoundError):
        nyu_vp.nyu_root(tmp_path / "nothing")
    with pytest.raises(ValueError):
        nyu_vp.load_nyu_vp(tmp_path, split="nonsense")


def test_zenith_error_and_families():
    assert zenith_error_deg([0.0], [10.0], [0.0], [10.0])[0] == pytest.approx(0.0, abs=1e-6)
    assert zenith_error_deg([0.0], [10.0], [0.0], [15.0])[0] == pytest.approx(5.0)
    assert zenith_error_deg([3.0], [0.0], [0.0], [0.0])[0] == pytest.approx(3.0)
    assert np.isnan(zenith_error_deg([0.0], [0.0], [np.nan], [0.0])[0])
    assert family_of("yud-crop-400x300") == "yud" and family_of("nyu-vp") == "nyu-vp"
    with pytest.raises(ValueError):
        family_of("kitti")
    assert {family_of(d) for d, _ in REPORTED} == set(FAMILIES)
    assert setting_name(None) == "all" and setting_name("zind-fr") == "without-zind-fr"
    # every reported dataset has a held-out run of both tuned methods
    planned = jobs()
    for dataset, split in REPORTED:
        for method in ("fr", "fast-fr"):
            assert (dataset, split, method, setting_name(family_of(dataset)), "centre") in planned


def test_lodo_reliability_scales_and_judgement():
    """Out-of-family conformal scales and the held-out judgement on self-made records."""
    import pandas as pd
    from fr_eval.protocols.lodo_reliability import evaluate, family_scales

    from fr_torch.core.reliability import ERROR_COLUMNS, MODEL_CUE_NAMES
    from fr_torch.core.reliability_bounds import ReliabilityPromise

    rng = np.random.default_rng(0)
    n = 120
    segments = np.round(np.exp(rng.uniform(np.log(3), np.log(80), n)))
    difficulty = 30.0 / segments * np.exp(0.2 * rng.normal(size=n))
    table = pd.DataFrame({"min_family_segments": segments, "grid_entropy": np.exp(rng.uniform(-10, 0, n)),
                          "mean_log_likelihood": rng.normal(0, 0.3, n), "focal_prior_share": rng.uniform(0.01, 0.5, n),
                          "focal_spread": rng.uniform(0.05, 2.0, n), "roll_err_deg": 0.2 * difficulty, "tilt_err_deg": 0.5 * difficulty,
                          "focal_err_pct": 3.0 * difficulty})
    table["dataset"] = np.where(np.arange(n) < 60, "yud", "nyu-vp")
    table["group"] = [f"g{i}" for i in range(n)]
    scales = family_scales(table, "fast", 0.9)
    assert set(scales) == {"roll_deg", "tilt_deg", "focal_pct"}
    worst, per = scales["focal_pct"]
    assert set(per) == {"yud", "nyu-vp"} and worst == max(per.values()) and 0 < worst < 10
    pooled = family_scales(table, "fast", 0.9, rule="pooled")["focal_pct"][0]
    assert pooled <= worst + 1e-12
    predicted = table[list(ERROR_COLUMNS)].to_numpy() * 1.0  # a perfect predictor
    predicted[0, 1] = np.nan  # a missing prediction is never reliable
    table.loc[1, "tilt_err_deg"] = np.nan  # no known vertical: focal only
    promise = ReliabilityPromise(limits={"focal_pct": 10.0, "tilt_deg": 3.0},
                                 scales={"fast": {"focal_pct": 1.0, "tilt_deg": 1.0}})
    out = evaluate(table, predicted, promise, "fast")
    assert out["rho_focal"] == pytest.approx(1.0) and out["coverage_both"] == 100.0
    assert out["top_quarter_ratio"] < 0.5 and 0 < out["reliable_n"] < n
    assert MODEL_CUE_NAMES == ("min_family_segments", "grid_entropy", "mean_log_likelihood", "focal_prior_share",
                               "focal_spread")
