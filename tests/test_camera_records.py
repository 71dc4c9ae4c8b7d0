"""One camera value type: every camera record (CalibrationResult, CameraEstimate, FrameEstimate,
FusedState, CalibrationSample) holds a :class:`fr_torch.core.geometry.camera.Camera` and reads K, hfov, angles,
rotation and vanishing points from it; the JSON schemas stay the same."""
from dataclasses import replace

import numpy as np
import pytest
import torch

from fr_eval.datasets.registry import CalibrationSample
from fr_torch.core.geometry.camera import Camera, pitch_from_tilt
from fr_torch.core.geometry.conventions import angles_from_rotation, hfov_from_focal, intrinsics, rotation_from_angles
from fr_torch.core.result import JSON_KEYS, CalibrationResult
from fr_torch.plugins.interface import CameraEstimate
from fr_torch.runtime.estimator import FREstimator
from fr_torch.synthetic import synthetic_segments
from fr_torch.video.fusion import (
    STATE_JSON_KEYS,
    FrameEstimate,
    FusedState,
    OnlineCalibrator,
)

ANGLES = ("pan_deg", "tilt_deg", "roll_deg", "pitch_deg")


def _camera() -> Camera:
    return Camera(640, 480, 512.5, (318.0, 243.5), rotation_from_angles(12.0, -7.0, 4.0).numpy())


def _records(camera):
    return [CalibrationResult(image="x", width=640, height=480, camera=camera),
            CameraEstimate(method="m", camera=camera),
            FrameEstimate(index=0, ok=True, reliable=True, camera=camera),
            FusedState(frame=0, status="started", epoch=0, n_fused=1, camera=camera),
            CalibrationSample(name="x", image_path=None, width=640, height=480, camera=camera)]


def test_each_record_reads_its_camera():
    camera = _camera()
    expected = {k: float(v) for k, v in angles_from_rotation(torch.as_tensor(camera.rotation)).items()}
    k = intrinsics(torch.tensor(512.5, dtype=torch.float64), torch.tensor([318.0, 243.5], dtype=torch.float64))
    assert np.array_equal(camera.K, k.numpy())
    assert camera.hfov_deg == hfov_from_focal(512.5, 640)
    assert camera.angles == expected
    vps = (camera.K @ camera.rotation).T
    assert np.allclose(camera.vanishing_points, vps * np.sign(vps[:, 2:]), atol=1e-12)
    for record in _records(camera):
        name = type(record).__name__
        assert record.focal_px == camera.focal_px and record.hfov_deg == camera.hfov_deg, name
        assert record.principal_point == (318.0, 243.5), name
        assert record.rotation is camera.rotation, name
        assert {key: getattr(record, key) for key in ANGLES} == expected, name
        assert np.array_equal(record.vanishing_points, camera.vanishing_points), name
        assert record.camera.K is camera.K  # computed once per camera value


def test_derived_fields_are_read_only_and_none_makes_that_part_unknown():
    record = CameraEstimate(method="m", camera=_camera())
    with pytest.raises(AttributeError, match="derived from .camera"):
        record.roll_deg = 1.0
    with pytest.raises(AttributeError):
        record.principal_point = None
    record.focal_px = None  # a rotation-only answer
    assert record.focal_px is None and record.hfov_deg is None and record.vanishing_points is None
    assert record.rotation is not None and record.roll_deg == pytest.approx(4.0)
    record.roll_deg = None  # clears the rotation, every angle with it
    assert record.rotation is None and all(getattr(record, key) is None for key in ANGLES)
    assert record.principal_point == (318.0, 243.5)
    empty = CameraEstimate.failure("m", "no VP")
    assert empty.camera is None and empty.focal_px is None and empty.roll_deg is None
    empty.focal_px = None  # no camera: nothing to clear


def test_horizon_only_and_focal_only_cameras():
    horizon = Camera.from_angles(640, 480, 500.0, roll_deg=5.0, tilt_deg=-12.0)
    assert not horizon.pan_known and horizon.known_rotation is None and "pan_deg" not in horizon.angles
    assert horizon.angles["roll_deg"] == pytest.approx(5.0, abs=1e-9)
    assert horizon.angles["tilt_deg"] == pytest.approx(-12.0, abs=1e-9)
    assert horizon.angles["pitch_deg"] == pytest.approx(pitch_from_tilt(-12.0, 5.0), abs=1e-9)
    estimate = CameraEstimate(method="m", camera=horizon)
    assert estimate.rotation is None and estimate.pan_deg is None and estimate.vanishing_points is None
    assert estimate.hfov_deg == pytest.approx(hfov_from_focal(500.0, 640))
    full = Camera.from_angles(640, 480, 500.0, roll_deg=5.0, pitch_deg=3.0, pan_deg=20.0)
    assert full.pan_known and full.angles["pan_deg"] == pytest.approx(20.0)
    focal_only = Camera(640, 480, 500.0)
    assert focal_only.angles == {} and focal_only.vanishing_points is None and focal_only.K[0, 2] == 319.5
    no_focal = Camera(640, 480, None, rotation=np.eye(3))
    assert no_focal.K is None and no_focal.hfov_deg is None and no_focal.angles["roll_deg"] == 0.0
    assert Camera(0, 0, 500.0).hfov_deg is None  # width unknown
    resized = _camera().resized(1280, 960)
    assert resized.focal_px == 1025.0 and resized.principal_point == (636.5, 487.5)  # (x + 0.5) * 2 - 0.5
    assert set(_camera().to_torch()) == {"focal_px", "principal_point", "K", "rotation"}
    assert set(Camera(640, 480).to_torch()) == {"principal_point"}


def test_json_schemas_unchanged():
    assert JSON_KEYS == ("image", "width", "height", "ok", "reliable", "reason", "horizon_reliable", "horizon_reason",
                         "model", "focal_px",
                         "hfov_deg", "principal_point", "rotation", "vertical_axis", "pan_deg", "tilt_deg", "roll_deg",
                         "pitch_deg", "vanishing_points", "ranked_vanishing_points", "horizon", "distortion",
                         "log_likelihood",
                         "num_segments",
                         "manhattan_fraction", "cues", "predicted_error", "error_bound", "runtime_s")
    assert STATE_JSON_KEYS == ("frame", "status", "epoch", "n_fused", "focal_px", "rotation", "roll_deg", "tilt_deg",
                               "pitch_deg", "pan_deg", "sigma", "restarted", "disagreement")
    failed = CalibrationResult(image="y", width=1, height=1, ok=False, reason="boom").to_json()
    assert list(failed) == list(JSON_KEYS) and failed["focal_px"] is None and failed["principal_point"] is None
    out = CalibrationResult(image="x", width=640, height=480, camera=_camera()).to_json()
    assert out["principal_point"] == (318.0, 243.5) and isinstance(out["rotation"], list)
    assert np.allclose(out["vanishing_points"], _camera().vanishing_points)


def test_estimator_and_fusion_build_cameras():
    rotation = rotation_from_angles(15.0, -5.0, 3.0).numpy()
    segments, _ = synthetic_segments(450.0, rotation, seed=3)
    [result] = FREstimator(mode="fast").calibrate_segments([segments], [(640, 480)])
    assert result.ok and result.camera.width == 640 and result.principal_point == (319.5, 239.5)
    assert np.array_equal(result.camera.K, intrinsics(torch.tensor(result.focal_px, dtype=torch.float64),
                                                      torch.tensor([319.5, 239.5], dtype=torch.float64)).numpy())
    assert result.roll_deg == result.camera.angles["roll_deg"]
    tracker = OnlineCalibrator()
    state = tracker.update(result)
    assert state.camera.width == 640 and state.focal_px == pytest.approx(result.focal_px)  # exp(log f)
    assert state.hfov_deg == pytest.approx(result.hfov_deg)
    assert state.to_json()["rotation"] == np.asarray(state.rotation).tolist()
    # the non-finite check clears focal and rotation, keeps the principal point (as before)
    from fr_torch.core.reliability.sanity import check_result
    from fr_torch.core.settings.config import SearchConfig

    result.camera = replace(result.camera, rotation=np.full((3, 3), np.nan))
    check_result(result, SearchConfig.from_config())
    assert not result.ok and result.focal_px is None and result.rotation is None and result.roll_deg is None
    assert result.to_json()["principal_point"] == (319.5, 239.5)
