"""The evaluation harness (``fr eval``) and the likelihood fit (``fr fit-likelihood``).

The harness runs on a small fake dataset (registered by import path) with dummy calibrators defined
here, and on two real YUD images with an oracle; the fit runs on the YUD training split.
"""
from __future__ import annotations

import argparse
import json
import math

import numpy as np
import pandas as pd
import pytest

from fr_eval.datasets.registry import CalibrationSample
from fr_eval.protocols import fit_likelihood, run_eval
from fr_torch.core.geometry.camera import Camera
from fr_torch.core.geometry.conventions import rotation_from_angles
from fr_torch.plugins.interface import CameraEstimate, ImageMeta
from fr_torch.registry import not_supplied, plugin
from fr_torch.resources import config_dir
from tests.conftest import require_dataset

# ----------------------------------------------------------------------------- fake data + methods

FAKE = {}


@plugin("dataset")
def load_fake(root=None, split="test", **_):
    """Six synthetic samples (no image files) with known cameras."""
    samples = []
    for i in range(6):
        s = CalibrationSample(name=f"fake_{i}", image_path=None, width=640, height=480,
                              camera=Camera(640, 480, 400.0 + 40 * i, (320.0, 240.0),
                                            rotation_from_angles(10.0 * i, -6.0 + 2 * i, 1.5 * i - 3).numpy()),
                              segments=np.array([[10.0, 10, 100, 12], [50, 20, 52, 200]]),
                              segment_labels=np.array([0, 1]), split=split)
        FAKE[s.name] = s
        samples.append(s)
    return samples


def _rot_z(deg):
    a = math.radians(deg)
    return np.array([[math.cos(a), -math.sin(a), 0], [math.sin(a), math.cos(a), 0], [0, 0, 1.0]])


PERM = np.array([[0, 0, -1.0], [0, -1, 0], [-1, 0, 0]])  # proper relabelling: swaps the horizontals, flips signs


class OracleCalibrator:
    """Returns the GT rotation turned by ``noise_deg`` about the optical axis, with permuted columns,
    and the GT focal length times ``focal_factor``; fails on ``fail_on`` images."""

    def __init__(self, noise_deg=2.0, focal_factor=1.05, fail_on=(), measure=None, device="cpu"):
        self.name = "oracle" + (f"[measure={measure}]" if measure else "")
        self.noise_deg = float(noise_deg) + (0.5 * "abcde".index(measure) if measure else 0.0)
        self.focal_factor = float(focal_factor)
        self.fail_on = set(fail_on)
        self.seen: list[ImageMeta] = []

    def estimate(self, image, meta: ImageMeta) -> CameraEstimate:
        self.seen.append(meta)
        if meta.name in self.fail_on:
            return CameraEstimate.failure(self.name, "no vanishing point")
        gt = FAKE[meta.name]
        camera = Camera(meta.width, meta.height, gt.focal_px * self.focal_factor,
                        rotation=_rot_z(self.noise_deg) @ gt.rotation @ PERM)
        return CameraEstimate(method=self.name, camera=camera, runtime_s=0.01)


class RotationOnly(OracleCalibrator):
    """Estimates the rotation only (focal / FOV must show n/a); crashes on fake_1."""

    def estimate(self, image, meta):
        if meta.name == "fake_1":
            raise RuntimeError("boom")
        est = super().estimate(image, meta)
        est.focal_px = None
        return est


@plugin("method")
def make_flaky(**kwargs):
    return OracleCalibrator(fail_on={"fake_2", "fake_4"}, **kwargs)


def parse(argv):
    parser = argparse.ArgumentParser()
    run_eval.add_arguments(parser)
    return parser.parse_args(argv)


# ----------------------------------------------------------------------------- harness

def test_split_and_expand_methods():
    assert run_eval.split_methods("fr, fast-fr,fr[measure=a,detector=lsd],m:C") == [
        "fr", "fast-fr", "fr[measure=a,detector=lsd]", "m:C"]
    assert run_eval.expand_methods(["fr", "x@labelled"], ["a", "b"]) == [
        "fr[measure=a]", "fr[measure=b]", "x[measure=a]@labelled", "x[measure=b]@labelled"]


def test_build_meta_passes_no_ground_truth_camera():
    s = load_fake()[0]
    meta = run_eval.build_meta(s, "centre", labelled=False, known_focal=False, dataset="fake", device="cpu")
    assert meta.principal_point is None and meta.focal_px is None and meta.segments is None
    assert meta.extra["labelled_segments"].shape == (2, 4)
    assert not {"rotation", "roll_deg", "tilt_deg", "hfov_deg"} & set(meta.extra)
    meta = run_eval.build_meta(s, "calibrated", labelled=True, known_focal=True, dataset="fake", device="cpu")
    assert meta.principal_point == (320.0, 240.0) and meta.focal_px == s.focal_px
    assert np.array_equal(meta.segments, s.segments)


def test_eval_end_to_end_on_fake_dataset(tmp_path):
    methods = "tests.test_eval:OracleCalibrator,tests.test_eval:make_flaky,tests.test_eval:RotationOnly@labelled"
    args = parse(["--dataset", "tests.test_eval:load_fake", "--methods", methods, "--out", str(tmp_path)])
    assert run_eval.run(args) == 0
    pred = pd.read_csv(tmp_path / "predictions.csv")
    assert len(pred) == 18
    summary = pd.read_csv(tmp_path / "summary.csv").set_index("method")
    oracle = summary.loc["tests.test_eval:OracleCalibrator"]
    assert oracle["failures"] == 0 and oracle["n"] == 6
    assert oracle["frame_err_deg_mean"] == pytest.approx(2.0, abs=1e-6)
    assert oracle["focal_err_pct_mean"] == pytest.approx(5.0, abs=1e-6)
    assert oracle["focal_err_pct_se"] == pytest.approx(0.0, abs=1e-9)
    assert 0 < oracle["roll_err_deg_mean"] < 2.5
    flaky = summary.loc["tests.test_eval:make_flaky"]
    assert flaky["failures"] == 2 and flaky["failure_pct"] == pytest.approx(100 / 3)
    assert flaky["n_valid"] == 4 and flaky["valid_pct"] == pytest.approx(200 / 3)  # valid-result share
    assert oracle["valid_pct"] == 100.0
    assert flaky["frame_err_deg_n"] == 4 and flaky["runtime_s_n"] == 6
    rot = summary.loc["tests.test_eval:RotationOnly@labelled"]
    assert rot["failures"] == 1 and rot["focal_err_pct_n"] == 0 and rot["fov_err_pct_n"] == 0
    crashed = pred[(pred.method == "tests.test_eval:RotationOnly@labelled") & (pred.image == "fake_1")]
    assert crashed["failed"].item() and "boom" in crashed["reason"].item()
    md = (tmp_path / "summary.md").read_text()
    assert "n/a" in md and "2 (33.3%)" in md and "±" in md and "valid (%)" in md and "| 66.7 |" in md
    failed = pred[pred.method == "tests.test_eval:make_flaky"].set_index("image")
    assert failed.loc["fake_2", "failed"] and failed.loc["fake_2", "reason"] == "no vanishing point"
    assert r"\pm" in (tmp_path / "summary.tex").read_text()
    for spec in ("tests.test_eval:OracleCalibrator", "tests.test_eval:make_flaky"):
        assert (tmp_path / f"hist_{run_eval.safe_name(spec)}.png").stat().st_size > 1000
    assert not (tmp_path / "deviation_measures.md").exists()
    info = json.loads((tmp_path / "run_info.json").read_text())
    assert info["n_images"] == 6 and len(info["methods"]) == 3
    assert info["machine"]["cpu"] and info["machine"]["threads"] >= 1  # fR's figures depend on the CPU a little


def test_labelled_segments_reach_oracle_methods():
    calib = OracleCalibrator()
    samples = load_fake()[:2]
    run_eval.evaluate_method("x@labelled", samples, calibrator=calib, progress=False)
    assert all(m.segments is not None for m in calib.seen)
    calib = OracleCalibrator()
    run_eval.evaluate_method("x", samples, calibrator=calib, progress=False)
    assert all(m.segments is None for m in calib.seen)


def test_deviation_measure_table(tmp_path):
    args = parse(["--dataset", "tests.test_eval:load_fake", "--methods", "tests.test_eval:OracleCalibrator",
                  "--measures", "a,b,c", "--out", str(tmp_path), "--limit", "3", "--no-plots"])
    assert run_eval.run(args) == 0
    table = pd.read_csv(tmp_path / "deviation_measures.csv")
    assert table["deviation measure"].str[0].tolist() == ["a", "b", "c"]
    assert table["frame_err_deg_mean"].to_numpy() == pytest.approx([2.0, 2.5, 3.0], abs=1e-6)
    assert (table["n"] == 3).all()
    assert "deviation measure" in (tmp_path / "deviation_measures.md").read_text()
    assert not list(tmp_path.glob("*.png"))


def test_bad_method_or_dataset_fails_cleanly(tmp_path):
    assert run_eval.run(parse(["--dataset", "tests.test_eval:load_fake", "--methods", "no-such-method",
                               "--out", str(tmp_path)])) == 2
    assert run_eval.run(parse(["--dataset", "no-such-dataset", "--methods", "fr", "--out", str(tmp_path)])) == 2


class YUDOracle:
    """GT camera of YUD images looked up by name (to check the harness on real files)."""

    def __init__(self, device="cpu"):
        from fr_eval.datasets.yud import load_yud

        self.name = "yud-oracle"
        self.gt = {s.name: s for s in load_yud(split="all")}

    def estimate(self, image, meta):
        assert image is not None and image.shape == (meta.height, meta.width, 3)
        s = self.gt[meta.name]
        return CameraEstimate(method=self.name, camera=Camera(meta.width, meta.height, s.focal_px,
                                                              rotation=s.rotation @ PERM))


def test_eval_on_two_yud_images(data_root, tmp_path):
    require_dataset(data_root, "yorkurbandb")
    args = parse(["--dataset", "yud", "--split", "test", "--methods", "tests.test_eval:YUDOracle",
                  "--data-root", str(data_root), "--limit", "2", "--out", str(tmp_path), "--pp", "calibrated"])
    assert run_eval.run(args) == 0
    row = pd.read_csv(tmp_path / "summary.csv").iloc[0]
    assert row["n"] == 2 and row["failures"] == 0
    for m in ("roll_err_deg", "tilt_err_deg", "fov_err_pct", "focal_err_pct", "frame_err_deg"):
        assert row[f"{m}_mean"] == pytest.approx(0.0, abs=1e-4)


# ----------------------------------------------------------------------------- --methods all, n/a rows, per-FOV

FOVS = (60.0, 90.0, 120.0)


@plugin("dataset")
def load_fake_fov(root=None, split="test", **_):
    """Nine samples with GT horizontal FOV 60 / 90 / 120 (no hand-labelled segments); image files are
    named but do not exist (the tests patch ``run_eval.load_image``)."""
    from pathlib import Path

    samples = []
    for i in range(9):
        hfov = FOVS[i % 3]
        s = CalibrationSample(name=f"fov_{i}", image_path=Path(f"/nonexistent/fov_{i}.png"), width=640, height=480,
                              camera=Camera.from_hfov(hfov, 640, 480, principal_point=(320.0, 240.0),
                                                      rotation=rotation_from_angles(5.0 * i, -10.0 + 2 * i, i - 4.0).numpy()),
                              split=split)
        FAKE[s.name] = s
        samples.append(s)
    return samples


class NotSupplied:
    """A method whose weights are absent: every estimate is an instant "n/a (...)" failure."""

    images_seen = 0

    def __init__(self, device="cpu"):
        self.name = "not-supplied"

    def estimate(self, image, meta):
        if image is not None:
            NotSupplied.images_seen += 1
        return CameraEstimate.failure(self.name, not_supplied("weights"))


class CueCalibrator(OracleCalibrator):
    """Oracle with fR-like predicted errors and reliability cues; fails on every third image."""

    def estimate(self, image, meta):
        if meta.name in ("fov_2", "fov_5", "fov_8"):  # all the 120-degree views
            return CameraEstimate.failure(self.name, "no orthogonal pair of finite horizontal VPs")
        est = super().estimate(image, meta)
        est.predicted_error = {"roll_deg": 0.5, "tilt_deg": 0.7, "focal_pct": 3.0}
        est.extra["cues"] = {"min_family_segments": 12.0, "grid_entropy": 1.5, "mean_log_likelihood": -2.0}
        return est


@pytest.fixture
def fake_images(monkeypatch):
    """Patch image decoding: counts the decoded images, returns a black frame."""
    calls = []

    def fake_load(path):
        calls.append(path)
        return np.zeros((480, 640, 3), np.uint8)

    monkeypatch.setattr(run_eval, "load_image", fake_load)
    NotSupplied.images_seen = 0
    return calls


def test_methods_all_expansion(monkeypatch):
    from fr_torch.plugins.interface import available_methods

    registered = available_methods()
    monkeypatch.delenv("FR_EXTERNAL_CSV", raising=False)
    methods, skipped = run_eval.resolve_methods(["all"], has_segments=True)
    assert skipped == ["external"] and sorted(methods) == sorted(set(registered) - {"external"})
    # The paper's rows first, in the paper's order.
    assert methods[:5] == ["fr", "fast-fr", "oracle-fr", "lee2009", "simon2018"]
    assert methods.index("hold-geoffroy2018") < methods.index("ctrlc") < methods.index("prior")
    monkeypatch.setenv("FR_EXTERNAL_CSV", "predictions.csv")
    methods, skipped = run_eval.resolve_methods(["fr", "all", "x:Y"], has_segments=False)
    assert skipped == [m for m in registered if m.startswith("oracle")] and "oracle-fr" in skipped
    assert methods[0] == "fr" and methods[-1] == "x:Y" and methods.count("fr") == 1
    assert set(methods) == set(registered) - set(skipped) | {"x:Y"}
    assert {"ctrlc", "ctrlc-retrained", "hold-geoffroy2018", "external", "simon2018"} <= set(methods)


def test_methods_all_run_with_na_row_and_by_fov(monkeypatch, fake_images, tmp_path):
    monkeypatch.setattr(run_eval, "available_methods", lambda: [
        "oracle-x", "tests.test_eval:NotSupplied", "tests.test_eval:CueCalibrator"])
    args = parse(["--dataset", "tests.test_eval:load_fake_fov", "--methods", "all", "--out", str(tmp_path)])
    assert run_eval.run(args) == 0
    info = json.loads((tmp_path / "run_info.json").read_text())
    assert info["skipped_methods"] == ["oracle-x"] and info["group_by"] == "hfov_deg"
    assert info["methods"] == ["tests.test_eval:NotSupplied", "tests.test_eval:CueCalibrator"]
    # the n/a method: decoded one image only, then answered without images; n/a in every cell
    assert NotSupplied.images_seen == 1 and len(fake_images) == 1 + 9
    md_rows = [line for line in (tmp_path / "summary.md").read_text().splitlines()
               if line.startswith("| tests.test_eval:NotSupplied")]
    cells = [c.strip() for c in md_rows[0].strip("|").split("|")]
    assert cells[1:] and all(c == "n/a (not supplied)" for c in cells[1:])
    summary = pd.read_csv(tmp_path / "summary.csv").set_index("method")
    na = summary.loc["tests.test_eval:NotSupplied"]
    assert na["status"] == "n/a (not supplied)" and na["n"] == 9
    assert all(math.isnan(na[f"{m}_mean"]) for m in ("runtime_s", "roll_err_deg", "fov_err_pct"))
    assert r"n/a (not supplied)" in (tmp_path / "summary.tex").read_text()
    assert not (tmp_path / "hist_tests.test_eval_NotSupplied.png").exists()
    # valid share: the 120-degree views failed
    cue = summary.loc["tests.test_eval:CueCalibrator"]
    assert cue["n_valid"] == 6 and cue["valid_pct"] == pytest.approx(200 / 3) and cue["failures"] == 3
    # per-FOV breakdown: method x FOV bin
    by_fov = pd.read_csv(tmp_path / "by_fov.csv")
    rows = by_fov[by_fov.method == "tests.test_eval:CueCalibrator"]
    assert rows["GT FOV (°)"].astype(str).tolist() == ["60", "90", "120"]
    assert rows["n"].tolist() == [3, 3, 3] and rows["valid_pct"].tolist() == [100.0, 100.0, 0.0]
    assert rows["focal_err_pct_mean"].iloc[:2].to_numpy() == pytest.approx([5.0, 5.0], abs=1e-6)
    assert rows["fov_err_pct_mean"].iloc[0] > rows["fov_err_pct_mean"].iloc[1] > 0  # focal +5% shrinks small FOVs more
    assert math.isnan(rows["roll_err_deg_mean"].iloc[2]) and rows["roll_err_deg_n"].iloc[2] == 0
    assert "frame_err_deg_mean" not in by_fov.columns and "runtime_s_mean" not in by_fov.columns
    na_rows = by_fov[by_fov.method == "tests.test_eval:NotSupplied"]
    assert len(na_rows) == 1 and na_rows["status"].item() == "n/a (not supplied)"
    md = (tmp_path / "by_fov.md").read_text()
    assert "GT FOV (°)" in md and "| 120 |" in md and "roll MAE (°)" in md and "±" in md
    # per-image predictions keep the predicted errors, cues and the FOV bin
    pred = pd.read_csv(tmp_path / "predictions.csv")
    ok = pred[(pred.method == "tests.test_eval:CueCalibrator") & ~pred.failed]
    assert (ok["pred_err_roll_deg"] == 0.5).all() and (ok["cue_min_family_segments"] == 12.0).all()
    assert (ok["cue_grid_entropy"] == 1.5).all() and (ok["cue_mean_log_likelihood"] == -2.0).all()
    assert sorted(pred["group"].unique().tolist()) == [60, 90, 120]
    assert (tmp_path / "distributions.png").stat().st_size > 5000


def test_group_by_options(fake_images, tmp_path):
    samples = load_fake_fov()
    assert run_eval.resolve_group_by("auto", samples) == "hfov_deg"
    assert run_eval.resolve_group_by("none", samples) is None
    assert run_eval.resolve_group_by("hfov", samples[:1]) == "hfov_deg"
    assert run_eval.resolve_group_by("auto", samples[:3:3]) is None  # a single FOV: no breakdown
    assert run_eval.group_value(samples[0], "hfov_deg") == "60"
    args = parse(["--dataset", "tests.test_eval:load_fake_fov", "--methods", "tests.test_eval:OracleCalibrator",
                  "--out", str(tmp_path), "--group-by", "none", "--no-plots"])
    assert run_eval.run(args) == 0
    assert not (tmp_path / "by_fov.csv").exists() and not (tmp_path / "distributions.png").exists()


def test_oracle_needs_labelled_segments(fake_images, tmp_path):
    args = parse(["--dataset", "tests.test_eval:load_fake_fov",
                  "--methods", "tests.test_eval:OracleCalibrator@labelled", "--out", str(tmp_path)])
    assert run_eval.run(args) == 2


def test_distributions_figure_handles_missing_estimates(tmp_path):
    from fr_eval.scoring.plots import distributions_figure

    frame = pd.DataFrame({"method": ["a", "a", "b", "b"], "image": ["x", "y", "x", "y"], "failed": [0, 0, 1, 1],
                          "gt_roll_deg": [1.0, 2.0, 1.0, 2.0], "est_roll_deg": [1.5, 2.5, np.nan, np.nan],
                          "gt_tilt_deg": [3.0, 4.0, 3.0, 4.0], "est_tilt_deg": [3.0, 4.0, np.nan, np.nan]})
    path = distributions_figure(frame, tmp_path / "d.png")  # no FOV columns at all
    assert path.stat().st_size > 5000


# ----------------------------------------------------------------------------- likelihood fit

def test_em_recovers_mixing_weights():
    rng = np.random.default_rng(0)
    lam_v, lam_h = math.radians(0.6), math.radians(1.5)
    n = 20000
    comp = rng.choice(4, size=n, p=[0.25, 0.4, 0.25, 0.10])
    x = np.empty((n, 3))
    x[:] = rng.uniform(0, math.pi / 2, size=(n, 3))  # far from the VPs a segment does not belong to
    for k, lam in ((0, lam_h), (1, lam_v), (2, lam_h)):
        x[comp == k, k] = rng.exponential(lam, size=(comp == k).sum())
    em = fit_likelihood.em_mixing_weights([x], [np.ones(n)], lam_v, lam_h)
    assert em["vertical"] == pytest.approx(0.4, abs=0.02)
    assert em["horizontal"] == pytest.approx(0.25, abs=0.02)
    assert em["background"] == pytest.approx(0.10, abs=0.02)


def test_fit_on_yud_train(data_root, tmp_path):
    require_dataset(data_root, "yorkurbandb")
    pytest.importorskip("fr_torch.core.likelihood.mixture")
    from fr_torch.core.likelihood.mixture import LikelihoodParams

    out, report = tmp_path / "fitted.json", tmp_path / "fit.md"
    parser = argparse.ArgumentParser()
    fit_likelihood.add_arguments(parser)
    args = parser.parse_args(["--data-root", str(data_root), "--out", str(out), "--report", str(report), "--no-em"])
    assert fit_likelihood.run(args) == 0
    config = json.loads(out.read_text())
    assert set(config) == {"default_measure", "measures", "priors", "source", "focal_prior"}
    shipped = json.loads((config_dir() / "likelihood.json").read_text())
    assert config["focal_prior"] == shipped["focal_prior"]  # not fitted: carried over from the shipped config
    b = config["measures"]["b"]
    assert b["unit"] == "deg"
    assert b["lambda_vertical"] == pytest.approx(0.5663, abs=1e-3)  # = the authors' pdfData means
    assert b["lambda_horizontal"] == pytest.approx(1.4601, abs=1e-3)
    assert config["measures"]["e"]["lambda_horizontal"] == pytest.approx(0.80, abs=0.1)
    assert config["measures"]["d"]["sigma"] == 1.0
    assert config["priors"]["background"] == pytest.approx(0.03)
    assert config["priors"]["vertical"] + 2 * config["priors"]["horizontal"] + 0.03 == pytest.approx(1.0, abs=1e-3)
    for measure in "abcde":  # the estimator reads the file
        params = LikelihoodParams.from_config(measure, path=out)
        assert params.scale_vertical > 0 and params.scale_horizontal > 0
    text = report.read_text()
    assert "| b | deg | 0.57 | 0.57 | 1.46 | 1.46 |" in text
    assert "max |sorted difference|" in text or "onlinefr" not in text


def test_common_subset_table_compares_methods_on_shared_images():
    def row(method, image, err, failed=False):
        values = {m: (None if failed else err) for m in ("roll_err_deg", "tilt_err_deg", "fov_err_pct",
                                                         "focal_err_pct", "frame_err_deg")}
        return {"method": method, "image": image, "failed": failed, "runtime_s": 0.1, **values}

    rows = [row("a", "x", 1.0), row("a", "y", 3.0), row("a", "z", 5.0),
            row("b", "x", 2.0), row("b", "y", 0.0, failed=True), row("b", "z", 4.0)]
    summaries = [run_eval.summarize(m, [r for r in rows if r["method"] == m]) for m in ("a", "b")]
    common, n = run_eval.common_subset_summaries(rows, summaries)
    assert n == 2
    assert common[0].mean["roll_err_deg"] == pytest.approx(3.0)  # (1 + 5) / 2, image y left out
    assert common[1].mean["roll_err_deg"] == pytest.approx(3.0) and common[1].failures == 0
    assert summaries[0].mean["roll_err_deg"] == pytest.approx(3.0) and summaries[0].n["roll_err_deg"] == 3
    no_failures = [r for r in rows if not r["failed"] or r["method"] == "a"]
    no_failures = [r for r in no_failures if r["image"] != "y"]
    assert run_eval.common_subset_summaries(no_failures, summaries) is None


def test_fr_uses_segments_given_in_meta():
    """fR / Fast-fR calibrate from ``meta.segments`` when given (what ``fr@labelled`` means), not
    from the image; the oracle requires them."""
    from fr_torch.plugins.interface import ImageMeta, get_calibrator
    from fr_torch.synthetic import random_rotation, synthetic_segments

    segments, _ = synthetic_segments(420.0, random_rotation(np.random.default_rng(4)), 640, 480, seed=4)
    blank = np.zeros((480, 640, 3), np.uint8)  # no segments at all on the image itself
    meta = ImageMeta(name="x", width=640, height=480, segments=segments)
    given = get_calibrator("fast-fr").estimate(blank, meta)
    assert given.ok and given.extra["num_segments"] > 0.9 * len(segments)  # (the filter drops a few tiny ones)
    assert not get_calibrator("fast-fr").estimate(blank, ImageMeta(name="x", width=640, height=480)).ok
    oracle = get_calibrator("oracle-fr").estimate(None, ImageMeta(name="x", width=640, height=480))
    assert not oracle.ok and oracle.reason.startswith("n/a")
