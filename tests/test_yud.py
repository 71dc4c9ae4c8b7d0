"""YorkUrbanDB loader against checkable facts (needs the data: skipped locally, fails in CI)."""
from __future__ import annotations

import csv
import math
from dataclasses import replace

import numpy as np
import pytest
import torch

from fr_eval.datasets.registry import get_dataset_loader, load_dataset
from fr_eval.datasets.yud import load_yud, rotation_from_vp_orthogonal
from fr_torch.core.geometry.conventions import vanishing_points
from tests.conftest import require_dataset


@pytest.fixture(scope="module")
def yud_dir(data_root):
    return require_dataset(data_root, "yorkurbandb")


@pytest.fixture(scope="module")
def samples(data_root, yud_dir):
    return load_yud(data_root, split="all")


def deviation_b_deg(sample, segments=None, labels=None, pp=None) -> np.ndarray:
    """Angle between each labelled segment and the line from its midpoint to its GT VP (degrees)."""
    segments = sample.segments if segments is None else segments
    labels = sample.segment_labels if labels is None else labels
    pp = sample.principal_point if pp is None else pp
    vps = vanishing_points(torch.tensor(sample.focal_px, dtype=torch.float64), torch.tensor(pp, dtype=torch.float64),
                           torch.as_tensor(sample.rotation)).numpy()
    mid = (segments[:, :2] + segments[:, 2:]) / 2
    d = segments[:, 2:] - segments[:, :2]
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    v = vps[:, labels].T
    w = v[:, :2] - mid * v[:, 2:3]  # homogeneous: finite for VPs at infinity
    w /= np.linalg.norm(w, axis=1, keepdims=True)
    return np.degrees(np.arccos(np.clip(np.abs((d * w).sum(1)), 0, 1)))


def test_registry_and_split(data_root, samples):
    assert get_dataset_loader("yud") is load_yud
    train, test = load_dataset("yud", data_root, "train"), load_dataset("yud", data_root, "test")
    assert len(samples) == 102 and len(train) == 51 and len(test) == 51
    assert not {s.name for s in train} & {s.name for s in test}
    assert {s.split for s in train} == {"train"} and {s.split for s in test} == {"test"}
    # the ECCV split starts with test = 1, 3, 4 ... (1-based .mat order), train = 2, 8, ...
    assert [s.extra["index_1based"] for s in test[:3]] == [1, 3, 4]
    assert [s.extra["index_1based"] for s in train[:2]] == [2, 8]
    assert all("\\" not in s.name and s.image_path.is_file() for s in samples)
    with pytest.raises(ValueError):
        load_yud(data_root, split="val")


def test_split_matches_index_csv(yud_dir, samples):
    with open(yud_dir / "yud_index.csv", newline="") as fh:
        rows = {r["name"]: r for r in csv.DictReader(fh)}
    for s in samples:
        assert rows[s.name]["eccv2008_split"] == s.split
        assert int(rows[s.name]["n_lines"]) == len(s.segments)
        for k in range(3):  # YUD VP k+1 -> our column k
            assert int(rows[s.name][f"n_lines_vp{k + 1}"]) == int((s.segment_labels == k).sum())


def test_camera(samples):
    s = samples[0]
    assert s.focal_px == pytest.approx(674.918, abs=1e-3)
    assert s.principal_point == pytest.approx((306.551, 250.454), abs=1e-3)  # 1-based (307.55, 251.45) - 1
    assert (s.width, s.height) == (640, 480)
    assert s.hfov_deg == pytest.approx(50.734, abs=1e-3)
    assert all(x.focal_px == s.focal_px for x in samples)


def test_rotations_follow_project_conventions(samples):
    for s in samples:
        r = s.rotation
        assert np.allclose(r.T @ r, np.eye(3), atol=1e-6)
        assert np.linalg.det(r) == pytest.approx(1.0, abs=1e-6)
        assert r[1, 1] > 0.9  # vertical column points down in the camera (y down)
        assert abs(s.roll_deg) < 6 and abs(s.tilt_deg) < 25
        assert -20 < s.tilt_deg < 14
    # the y-up -> y-down conversion: the vertical column is vp_orthogonal(:, 2) with y negated, up to sign
    vp = np.array([[0.6, 0.05, 0.8], [0.0, 0.99, -0.06], [-0.8, 0.05, 0.6]])
    vp, _ = np.linalg.qr(vp)
    vp = vp * np.sign(np.diag(vp))
    if np.linalg.det(vp) < 0:
        vp[:, 0] *= -1
    r = rotation_from_vp_orthogonal(vp)
    assert np.allclose(np.abs(r), np.abs(np.diag([1, -1, 1]) @ vp))
    assert np.linalg.det(r) == pytest.approx(1.0) and r[1, 1] > 0 and r[2, 2] >= 0


def test_tilt_sign_matches_vertical_vp(samples):
    """Positive tilt (looking up) <=> the vertical VP lies above the image (verticals converge upward)."""
    for s in samples:
        if abs(s.tilt_deg) < 1:
            continue
        v = s.focal_px * s.rotation[:, 1]  # K R[:, 1] relative to pp
        y = v[1] / v[2]  # image y (down) of the vertical VP relative to the principal point
        assert (y < 0) == (s.tilt_deg > 0), s.name


def test_labelled_segments_near_their_vanishing_points(samples):
    devs = np.concatenate([deviation_b_deg(s) for s in samples])
    assert len(devs) == 12122
    assert 0.5 < np.median(devs) < 0.65  # PROVENANCE: median 0.58 deg for vp_orthogonal
    assert devs.mean() < 1.2
    # the y flip matters: without it the labels do not fit (about 4.5 deg)
    s = samples[5]
    wrong = s.rotation.copy()
    wrong[1, :] *= -1
    bad = deviation_b_deg(replace(s, camera=replace(s.camera, rotation=wrong)))
    assert np.median(bad) > 2 * np.median(deviation_b_deg(s))
    # vertical-labelled segments are near-vertical in the image
    for s in samples[:20]:
        seg = s.segments[s.segment_labels == 1]
        if len(seg):
            assert np.median(np.abs(seg[:, 3] - seg[:, 1]) / (np.abs(seg[:, 2] - seg[:, 0]) + 1e-9)) > 3


def test_reproduces_authors_training_samples(data_root, samples):
    """Our train-split measure-b values equal the samples stored in the authors' pdfData.mat."""
    folder = require_dataset(data_root, "onlinefr") / "derived"
    train = [s for s in samples if s.split == "train"]
    devs = {"vertical": [], "horizontal": []}
    for s in train:
        d = np.radians(deviation_b_deg(s))
        devs["vertical"].append(d[s.segment_labels == 1])
        devs["horizontal"].append(d[s.segment_labels != 1])
    for family, tag in (("vertical", "pdfdv"), ("horizontal", "pdfdh")):
        theirs = np.sort(np.loadtxt(folder / f"pdfData_{family}_{tag}_deviation_samples_rad.csv", comments="#"))
        ours = np.sort(np.concatenate(devs[family]))
        assert ours.shape == theirs.shape
        assert np.abs(ours - theirs).max() < 1e-7
    assert math.degrees(np.concatenate(devs["vertical"]).mean()) == pytest.approx(0.5663, abs=1e-3)


def test_resolution_check_runs_on_upscaled_images(data_root, tmp_path):
    """`fr_eval.protocols.resolution_check` (results/resolution/): upscaled inputs give errors in input pixels."""
    from fr_eval.protocols.resolution_check import main

    assert main(["--scales", "1,2", "--mode", "fast", "--limit", "2", "--data-root", str(data_root),
                 "--out", str(tmp_path)]) == 0
    text = (tmp_path / "resolution_fast.md").read_text()
    assert "| 2x | 1280x960 | 2/2 |" in text and "nan" not in text and "Failed" not in text


def test_working_resolution_compares_caps(data_root, tmp_path, capsys):
    """`fr_eval.protocols.working_resolution` (results/resolution/working/): one row per cap, the
    upscaled photos scored in their own pixels; a bad cap is a one-line usage error."""
    from fr_eval.protocols.working_resolution import main

    assert main(["--dataset", "yud", "--split", "train", "--mode", "fast", "--caps", "320,input", "--upscale", "2",
                 "--limit", "2", "--data-root", str(data_root), "--out", str(tmp_path)]) == 0
    text = (tmp_path / "yud_train_fast_x2.md").read_text()
    assert "| 320 | " in text and "| input | " in text and "(2) |" in text and "nan" not in text
    with pytest.raises(SystemExit) as stop:
        main(["--caps", "12"])
    assert stop.value.code == 2 and "--caps: expected a whole number" in capsys.readouterr().err


@pytest.mark.parametrize("scales", ["0,2", "1,x", ""])
def test_resolution_check_rejects_bad_scales(scales, capsys):
    from fr_eval.protocols.resolution_check import main

    with pytest.raises(SystemExit) as stop:
        main(["--scales", scales])
    assert stop.value.code == 2 and "whole factors >= 1" in capsys.readouterr().err


def test_resolution_check_counts_failed_estimates(data_root, tmp_path, monkeypatch):
    """A failed estimate is counted in the `valid` column and named, not silently left out."""
    import fr_eval.protocols.resolution_check as check
    from fr_torch import FREstimator

    class FailsSecond(FREstimator):
        def calibrate_images(self, images, names=None, **kwargs):
            results = super().calibrate_images(images, names=names, **kwargs)
            if names and names[0] == self.fail_name:
                results[0].ok, results[0].reason = False, "too few segments"
            return results

    first_two = check.load_dataset("yud", root=str(data_root), split="test")[:2]
    FailsSecond.fail_name = first_two[1].name
    monkeypatch.setattr(check, "FREstimator", FailsSecond)
    assert check.main(["--scales", "1", "--mode", "fast", "--limit", "2", "--data-root", str(data_root),
                       "--out", str(tmp_path)]) == 0
    text = (tmp_path / "resolution_fast.md").read_text()
    assert "| 1x | 640x480 | 1/2 |" in text
    assert f"- 1x: {first_two[1].name} (too few segments)" in text and "nan" not in text
