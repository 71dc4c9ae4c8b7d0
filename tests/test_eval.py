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

from eval import fit_likelihood, run_eval
from eval.datasets.registry import CalibrationSample
from fr_torch.camera import rotation_from_angles
from fr_torch.interface import CameraEstimate, ImageMeta
from tests.conftest import require_dataset

# ----------------------------------------------------------------------------- fake data + methods

FAKE = {}


def load_fake(root=None, split="test", **_):
    """Six synthetic samples (no image files) with known cameras."""
    samples = []
    for i in range(6):
        s = CalibrationSample(name=f"fake_{i}", image_path=None, width=640, height=480, focal_px=400.0 + 40 * i,
                              principal_point=(320.0, 240.0),
                              rotation=rotation_from_angles(10.0 * i, -6.0 + 2 * i, 1.5 * i - 3).numpy(),
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
        return CameraEstimate(method=self.name, rotation=_rot_z(self.noise_deg) @ gt.rotation @ PERM,
                              focal_px=gt.focal_px * self.focal_factor, runtime_s=0.01)


class RotationOnly(OracleCalibrator):
    """Estimates the rotation only (focal / FOV must show n/a); crashes on fake_1."""

    def estimate(self, image, meta):
        if meta.name == "fake_1":
            raise RuntimeError("boom")
        est = super().estimate(image, meta)
        est.focal_px = None
        return est


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
    assert flaky["frame_err_deg_n"] == 4 and flaky["runtime_s_n"] == 6
    rot = summary.loc["tests.test_eval:RotationOnly@labelled"]
    assert rot["failures"] == 1 and rot["focal_err_pct_n"] == 0 and rot["fov_err_pct_n"] == 0
    crashed = pred[(pred.method == "tests.test_eval:RotationOnly@labelled") & (pred.image == "fake_1")]
    assert crashed["failed"].item() and "boom" in crashed["reason"].item()
    md = (tmp_path / "summary.md").read_text()
    assert "n/a" in md and "2 (33.3%)" in md and "±" in md
    assert r"\pm" in (tmp_path / "summary.tex").read_text()
    for spec in ("tests.test_eval:OracleCalibrator", "tests.test_eval:make_flaky"):
        assert (tmp_path / f"hist_{run_eval.safe_name(spec)}.png").stat().st_size > 1000
    assert not (tmp_path / "deviation_measures.md").exists()
    info = json.loads((tmp_path / "run_info.json").read_text())
    assert info["n_images"] == 6 and len(info["methods"]) == 3


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
        from eval.datasets.yud import load_yud

        self.name = "yud-oracle"
        self.gt = {s.name: s for s in load_yud(split="all")}

    def estimate(self, image, meta):
        assert image is not None and image.shape == (meta.height, meta.width, 3)
        s = self.gt[meta.name]
        return CameraEstimate(method=self.name, rotation=s.rotation @ PERM, focal_px=s.focal_px)


def test_eval_on_two_yud_images(data_root, tmp_path):
    require_dataset(data_root, "yorkurbandb")
    args = parse(["--dataset", "yud", "--split", "test", "--methods", "tests.test_eval:YUDOracle",
                  "--data-root", str(data_root), "--limit", "2", "--out", str(tmp_path), "--pp", "calibrated"])
    assert run_eval.run(args) == 0
    row = pd.read_csv(tmp_path / "summary.csv").iloc[0]
    assert row["n"] == 2 and row["failures"] == 0
    for m in ("roll_err_deg", "tilt_err_deg", "fov_err_pct", "focal_err_pct", "frame_err_deg"):
        assert row[f"{m}_mean"] == pytest.approx(0.0, abs=1e-4)


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
    pytest.importorskip("fr_torch.likelihood")
    from fr_torch.likelihood import LikelihoodParams

    out, report = tmp_path / "fitted.json", tmp_path / "fit.md"
    parser = argparse.ArgumentParser()
    fit_likelihood.add_arguments(parser)
    args = parser.parse_args(["--data-root", str(data_root), "--out", str(out), "--report", str(report), "--no-em"])
    assert fit_likelihood.run(args) == 0
    config = json.loads(out.read_text())
    assert set(config) == {"default_measure", "measures", "priors", "source"}
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
