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
from fr_torch.core.geometry.conventions import rotation_from_angles


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
    """Per-family conformal scales of the spreads' sigmas and the held-out judgement on self-made records."""
    import pandas as pd

    from fr_eval.protocols.lodo_reliability import evaluate, family_scales, sigmas
    from fr_eval.scoring.metrics import aurc, risk_coverage
    from fr_torch.core.reliability.model import MODEL_CUE_NAMES

    rng = np.random.default_rng(0)
    n = 120
    spread = np.tile(np.exp(rng.uniform(np.log(0.005), np.log(0.1), n // 2)), 2)  # log f; the same in both families
    table = pd.DataFrame({"focal_profile_spread": spread, "focal_resample_spread": spread,
                          "pitch_resample_spread": rng.uniform(0.05, 1.0, n)})
    table["dataset"] = np.where(np.arange(n) < 60, "yud", "nyu-vp")
    noise = np.tile(np.abs(rng.normal(size=n // 2)), 2)
    table["focal_err_pct"] = 100 * spread * noise * np.where(table["dataset"] == "yud", 1.0, 2.0)
    table["tilt_err_deg"] = np.hypot(table["pitch_resample_spread"], 0.5) * noise
    table["roll_err_deg"] = 0.1
    scales = family_scales(table, "fast", 0.9)
    assert set(scales) == {"focal_pct", "tilt_deg"}
    worst, per = scales["focal_pct"]
    assert set(per) == {"yud", "nyu-vp"} and worst == max(per.values()) and per["nyu-vp"] == pytest.approx(2 * per["yud"])
    assert family_scales(table, "fast", 0.9, rule="pooled")["focal_pct"][0] <= worst + 1e-12
    sigma = sigmas(table)
    np.testing.assert_allclose(sigma["focal_pct"], np.maximum(100 * spread, 0.3))
    bounds = {t: scales[t][0] * sigma[t] for t in sigma}
    table.loc[1, "tilt_err_deg"] = np.nan  # no known vertical: judged on its focal error alone
    out = evaluate(table, bounds, {"focal_pct": 10.0, "tilt_deg": 3.0})
    assert out["bound_holds_focal"] >= 90.0 and 0 < out["reliable_n"] < n
    assert out["precision_pct"] > out["good_pct"] and 0 < out["recall_pct"] <= 100
    assert out["aurc_ratio"] >= 1.0 and out["aurc_oracle"] == pytest.approx(aurc(table["focal_err_pct"],
                                                                                table["focal_err_pct"]))
    given = evaluate(table, bounds, {"focal_pct": 10.0, "tilt_deg": 3.0}, flagged=np.arange(n) < 10)
    assert given["reliable_n"] == 10 and given["aurc"] == out["aurc"]  # the flag given, the ranking by the bounds
    # the risk-coverage curve: the mean error of the k photos ranked first, NaN scores last
    kept, risk = risk_coverage([3.0, np.nan, 1.0, 2.0], [30.0, 40.0, 10.0, 20.0])
    np.testing.assert_allclose(kept, [0.25, 0.5, 0.75, 1.0])
    np.testing.assert_allclose(risk, [10, 15, 20, 25])
    assert aurc([3.0, np.nan, 1.0, 2.0], [30.0, 40.0, 10.0, 20.0]) == pytest.approx(17.5)
    assert MODEL_CUE_NAMES == ("min_family_segments", "grid_entropy", "mean_log_likelihood", "focal_prior_share",
                               "focal_spread")


def test_detector_reliability_verdict():
    """The rule of results/decisions/45.md: >= 90 % where LSD is, and within LSD's per-family spread."""
    import pandas as pd

    from fr_eval.protocols.detector_reliability import verdict

    def table(other: dict[str, float]) -> pd.DataFrame:
        lsd = {"YUD family train": 95.0, "ZInD-fR train": 98.0}
        return pd.DataFrame([{"mode": mode, "rows": family, "split": "train pooled", "detector": detector,
                              "precision_pct": value}
                             for mode in ("fr", "fast") for detector, values in (("lsd", lsd), ("torch-lines", other))
                             for family, value in values.items()])

    holds, lines = verdict(table({"YUD family train": 96.0, "ZInD-fR train": 95.5}))
    assert holds and len(lines) == 4  # below LSD's 98 % on ZInD-fR, but within LSD's spread (95-98 %)
    holds, lines = verdict(table({"YUD family train": 94.0, "ZInD-fR train": 99.0}))
    assert not holds and "FAILS" in lines[0]  # below LSD's lowest family
