"""Baselines behind the common interface: lee2009, simon2018, ctrlc, external, prior.

Accuracy tests use exact synthetic Manhattan segment sets (fr_torch.synthetic.synthetic_segments,
0.5 px endpoint noise, 30 % clutter).  Measured on 60 random cameras (hfov 50-110, pitch +-25,
roll +-10, pan +-45, 640 x 480): lee2009 0 failures, max roll / tilt error 0.21 / 0.24 deg, focal
error median 0.27 %, p90 0.75 %, max 2.95 %; simon2018 1 failure (pan near 0), max 0.23 / 0.35 deg,
focal median 0.36 %, p90 2.05 %, max 7.95 % (a horizontal VP near infinity); with 10 <= |pan| <= 35
its focal error is at most 2.9 %.  The tolerances below leave a margin over these numbers.
"""
from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
import torch

from fr_baselines import vp_geometry as vg
from fr_baselines.ctrlc import (
    CTRLC,
    camera_from_ctrlc,
    preprocess_image,
    preprocess_lines,
)
from fr_baselines.external import ExternalPredictions
from fr_baselines.lee2009 import Lee2009
from fr_baselines.prior import Prior
from fr_baselines.simon2018 import Simon2018, meaningful_modes
from fr_torch.core.geometry.conventions import focal_from_hfov, horizon_angles, image_centre, rotation_from_angles
from fr_torch.plugins.interface import (
    Calibrator,
    CameraEstimate,
    ImageMeta,
    available_methods,
    get_calibrator,
)
from fr_torch.synthetic import camera_matrix, render_manhattan_room, synthetic_segments

W, H = 640, 480

# (hfov, pitch, roll, pan) drawn once from hfov 50-110, pitch +-25, roll +-10; pans kept away from
# 0 / 45 where a horizontal VP is at infinity (simon2018 then has no focal by design).
CAMERAS = [
    (55.0, 18.0, -7.0, 28.0),
    (72.0, -22.0, 4.0, -35.0),
    (90.0, 8.0, 9.0, 17.0),
    (104.0, -12.0, -3.0, -22.0),
    (63.0, 2.5, 6.0, 38.0),
]
ROLL_TILT_TOL_DEG = 0.5
FOCAL_TOL_PCT = {"lee2009": 5.0, "simon2018": 6.0}


def _signed_permutations():
    for perm in itertools.permutations(range(3)):
        for signs in itertools.product((1.0, -1.0), repeat=3):
            p = np.zeros((3, 3))
            p[list(range(3)), list(perm)] = signs
            if np.linalg.det(p) > 0:
                yield p


def frame_error_deg(r_gt, r_est):
    """Rotation error up to relabelling of the Manhattan axes (min over the 24 proper signed perms)."""
    best = 180.0
    for p in _signed_permutations():
        rel = r_gt.T @ r_est @ p
        best = min(best, math.degrees(math.acos(np.clip((np.trace(rel) - 1) / 2, -1, 1))))
    return best


def _camera(hfov, pitch, roll, pan):
    rotation = rotation_from_angles(pan, pitch, roll).numpy()
    focal = focal_from_hfov(hfov, W)
    gt = {k: float(v) for k, v in horizon_angles(torch.as_tensor(rotation)).items()}
    return focal, rotation, gt


def _meta(segments, name="synthetic"):
    return ImageMeta(name=name, width=W, height=H, segments=segments)


# --------------------------------------------------------------------------- registry

def test_methods_registered_and_conform():
    names = available_methods()
    for name in ("lee2009", "simon2018", "ctrlc", "external", "prior"):
        assert name in names
    for name in ("lee2009", "simon2018", "ctrlc", "prior"):
        method = get_calibrator(name)
        assert isinstance(method, Calibrator) and method.name == name


# --------------------------------------------------------------------------- shared geometry

def test_vp_geometry_recovers_camera_from_exact_vps():
    rng = np.random.default_rng(0)
    pp = np.array(image_centre(W, H))
    for hfov, pitch, roll, pan in CAMERAS:
        focal, rotation, gt = _camera(hfov, pitch, roll, pan)
        vps = camera_matrix(focal, W, H) @ rotation
        vps = vps * rng.choice([-1.0, 1.0], 3) * rng.uniform(0.5, 2.0, 3)  # VPs carry no sign / scale
        assert vg.focal_from_orthogonal_vps(vps[:, 0], vps[:, 2], pp) == pytest.approx(focal, rel=1e-9)
        r_est = vg.rotation_from_vps(vps[:, 1], vps[:, 0], focal, pp, vps[:, 2])
        assert np.linalg.det(r_est) == pytest.approx(1.0)
        assert r_est[1, 1] > 0  # vertical column points down
        assert frame_error_deg(rotation, r_est) < 1e-4  # acos resolution
        assert np.allclose(np.abs(r_est[:, 1]), np.abs(rotation[:, 1]))
        assert vg.roll_from_zenith(vps[:, 1], pp) == pytest.approx(gt["roll_deg"], abs=1e-9)
        est = vg.camera_estimate("x", vg.Camera(W, H, focal, pp, r_est))
        assert est.roll_deg == pytest.approx(gt["roll_deg"], abs=1e-6)
        assert est.tilt_deg == pytest.approx(gt["tilt_deg"], abs=1e-6)
        assert est.hfov_deg == pytest.approx(hfov, abs=1e-6)


def test_vp_least_squares_and_angle_error():
    focal, rotation, _ = _camera(70.0, 10.0, 5.0, 30.0)
    segments, labels = synthetic_segments(focal, rotation, noise_px=0.0, clutter_fraction=0.0, seed=1)
    true_vps = camera_matrix(focal, W, H) @ rotation
    for axis in range(3):
        vp = vg.vp_least_squares(segments[labels == axis])
        cos = abs(vp @ true_vps[:, axis]) / np.linalg.norm(true_vps[:, axis])
        assert cos > 1 - 1e-9
        assert vg.vp_angle_error(segments[labels == axis], true_vps[:, axis]).max() < 1e-6
    # Segments of another family are far from this VP.
    assert np.median(vg.vp_angle_error(segments[labels == 0], true_vps[:, 2])) > math.radians(5)


def test_vertical_vp_ignores_collinear_pairs():
    """Two segments on the same line (a duplicate, as detectors sometimes return) meet in no point:
    their zero 'intersection' has zero angle error to every segment, so it scored every segment
    as an inlier and won; it must never be a hypothesis."""
    focal, R, _ = _camera(70.0, 10.0, 3.0, 20.0)
    segments, labels = synthetic_segments(focal, R, W, H, n_per_family=30, seed=4)
    vertical = segments[labels == 1]
    longest = vertical[np.argmax(np.hypot(*(vertical[:, 2:] - vertical[:, :2]).T))]
    pieces = np.array([longest, longest[[2, 3, 0, 1]]])  # the same line twice (one reversed)
    with np.errstate(all="raise"):
        vp, inliers = vg.vertical_vp(np.vstack([pieces, segments]))
    true_vp = camera_matrix(focal, W, H) @ R[:, 1]
    true_vp = true_vp / np.linalg.norm(true_vp)
    assert np.isfinite(vp).all() and abs(vp @ true_vp) > 0.999
    assert inliers[2:][labels == 1].mean() > 0.8 and inliers[2:][labels == 3].mean() < 0.2


def test_meaningful_modes_finds_peak_not_noise():
    rng = np.random.default_rng(0)
    flat = np.bincount(rng.integers(0, 90, 300), minlength=90)
    assert meaningful_modes(flat, circular=True, max_width=10) == []
    peaked = flat.copy()
    peaked[40:43] += 25
    modes = meaningful_modes(peaked, circular=True, max_width=10)
    assert modes and modes[0][0] <= 41 < modes[0][0] + modes[0][1] and modes[0][2] < -5


# --------------------------------------------------------------------------- lee2009 / simon2018

@pytest.mark.parametrize("method_cls", [Lee2009, Simon2018], ids=["lee2009", "simon2018"])
@pytest.mark.parametrize("camera", CAMERAS, ids=[f"hfov{c[0]:.0f}_pitch{c[1]:.0f}" for c in CAMERAS])
def test_vp_baselines_recover_synthetic_camera(method_cls, camera):
    focal, rotation, gt = _camera(*camera)
    segments, _ = synthetic_segments(focal, rotation, W, H, noise_px=0.5, clutter_fraction=0.3,
                                     seed=int(camera[0]))
    method = method_cls()
    est = method.estimate(None, _meta(segments))
    assert est.ok, est.reason
    assert abs(est.roll_deg - gt["roll_deg"]) < ROLL_TILT_TOL_DEG
    assert abs(est.tilt_deg - gt["tilt_deg"]) < ROLL_TILT_TOL_DEG
    assert 100 * abs(est.focal_px - focal) / focal < FOCAL_TOL_PCT[method.name]
    assert est.hfov_deg == pytest.approx(math.degrees(2 * math.atan(W / 2 / est.focal_px)))
    assert np.linalg.det(est.rotation) == pytest.approx(1.0)
    assert frame_error_deg(rotation, est.rotation) < 1.0
    assert est.runtime_s > 0


@pytest.mark.parametrize("method_cls", [Lee2009, Simon2018], ids=["lee2009", "simon2018"])
def test_vp_baselines_on_rendered_image_with_lsd(method_cls):
    focal, rotation, gt = _camera(70.0, 10.0, 5.0, 25.0)
    image = render_manhattan_room(focal, rotation, W, H)
    est = method_cls().estimate(image, ImageMeta(name="room"))  # no segments: runs LSD
    assert est.ok, est.reason
    assert abs(est.roll_deg - gt["roll_deg"]) < ROLL_TILT_TOL_DEG
    assert abs(est.tilt_deg - gt["tilt_deg"]) < ROLL_TILT_TOL_DEG
    assert 100 * abs(est.focal_px - focal) / focal < 3.0


def test_simon2018_without_finite_pair_is_flagged_with_roll():
    # pan = 0: one horizontal VP exactly at infinity, so no orthogonal pair of finite hVPs.
    focal, rotation, gt = _camera(70.0, 12.0, 6.0, 0.0)
    segments, _ = synthetic_segments(focal, rotation, W, H, noise_px=0.5, clutter_fraction=0.3, seed=3)
    est = Simon2018().estimate(None, _meta(segments))
    assert not est.ok and "orthogonal pair" in est.reason
    assert est.focal_px is None and est.tilt_deg is None
    assert abs(est.extra["roll_deg"] - gt["roll_deg"]) < ROLL_TILT_TOL_DEG
    # lee2009 still answers for the same scene (the vertical VP constrains the focal length).
    lee = Lee2009().estimate(None, _meta(segments))
    assert lee.ok and abs(lee.tilt_deg - gt["tilt_deg"]) < ROLL_TILT_TOL_DEG


@pytest.mark.parametrize("method_cls", [Lee2009, Simon2018], ids=["lee2009", "simon2018"])
def test_vp_baselines_flag_failures(method_cls):
    method = method_cls()
    blank = np.zeros((H, W, 3), np.uint8)
    cases = [
        (blank, ImageMeta(name="blank")),  # LSD finds nothing
        (None, _meta(np.zeros((0, 4)))),  # no segments
        (None, ImageMeta(name="nothing")),  # neither image nor segments
        (None, _meta(np.array([[0.0, 0.0, np.nan, 1.0]]))),  # malformed segments
        (None, _meta(np.array([[10.0, 10.0, 200.0, 12.0]] * 3))),  # too few segments
        (None, _meta(np.tile([[10.0, 100.0, 300.0, 100.0]], (30, 1)) + np.arange(30)[:, None] * [0, 5, 0, 5])),
    ]
    for image, meta in cases:
        est = method.estimate(image, meta)
        assert isinstance(est, CameraEstimate)
        assert not est.ok and est.reason, meta.name
        assert est.focal_px is None


# --------------------------------------------------------------------------- ctrlc

class TinyCTRLC(torch.nn.Module):
    """Stand-in with CTRL-C's ONNX signature (random weights)."""

    def __init__(self):
        super().__init__()
        self.conv = torch.nn.Conv2d(3, 8, 16, stride=16)
        self.line = torch.nn.Linear(3, 8)
        self.zvp = torch.nn.Linear(16, 3)
        self.fovy = torch.nn.Linear(16, 1)
        self.hl = torch.nn.Linear(16, 3)

    def forward(self, image, lines, line_mask):
        a = self.conv(image).mean(dim=(2, 3))
        b = (self.line(lines) * line_mask).sum(1) / line_mask.sum(1).clamp_min(1.0)
        h = torch.cat([a, b], -1)
        zvp = torch.nn.functional.normalize(self.zvp(h), dim=-1)
        fovy = torch.sigmoid(self.fovy(h)) * math.pi
        hl = torch.nn.functional.normalize(self.hl(h), dim=-1)
        return zvp, fovy, hl


@pytest.fixture(scope="module")
def tiny_ctrlc(tmp_path_factory):
    torch.manual_seed(0)
    model = TinyCTRLC().eval()
    path = tmp_path_factory.mktemp("ctrlc") / "tiny_ctrlc.onnx"
    args = (torch.randn(1, 3, 512, 512), torch.randn(1, 512, 3), torch.ones(1, 512, 1))
    torch.onnx.export(model, args, str(path), dynamo=True, input_names=["image", "lines", "line_mask"],
                      output_names=["pred_zvp", "pred_fovy", "pred_hl"])
    return model, path


def test_ctrlc_without_weights_is_not_supplied(monkeypatch):
    monkeypatch.delenv("FR_CTRLC_ONNX", raising=False)
    method = CTRLC()
    assert method.available is False
    est = method.estimate(np.zeros((H, W, 3), np.uint8), ImageMeta(name="x"))
    assert not est.ok and est.reason == "n/a (not supplied: weights: set FR_CTRLC_ONNX)"
    missing = CTRLC(onnx_path="/nonexistent/ctrlc.onnx")
    assert not missing.available
    assert "not supplied" in missing.estimate(None, ImageMeta(name="x")).reason


def test_named_rows_read_their_own_weights_and_predictions(monkeypatch, tmp_path):
    from fr_torch.plugins.interface import get_calibrator as get_method

    monkeypatch.setenv("FR_CTRLC_ONNX", str(tmp_path / "gsv.onnx"))
    monkeypatch.delenv("FR_CTRLC_RETRAINED_ONNX", raising=False)
    retrained = get_method("ctrlc-retrained")
    assert retrained.name == "ctrlc-retrained" and retrained.onnx_path is None  # not the other checkpoint
    assert get_method("ctrlc").onnx_path == tmp_path / "gsv.onnx"
    monkeypatch.setenv("FR_CTRLC_RETRAINED_ONNX", str(tmp_path / "retrained.onnx"))
    assert get_method("ctrlc-retrained").onnx_path == tmp_path / "retrained.onnx"

    monkeypatch.delenv("FR_HOLD_GEOFFROY_CSV", raising=False)
    est = get_method("hold-geoffroy2018").estimate(None, ImageMeta(name="a.jpg", width=W, height=H))
    assert not est.ok and est.method == "hold-geoffroy2018" and "not supplied" in est.reason
    csv_path = tmp_path / "hg.csv"
    csv_path.write_text("image,hfov_deg,roll_deg,tilt_deg\na.jpg,70,1.5,-2\n")
    monkeypatch.setenv("FR_HOLD_GEOFFROY_CSV", str(csv_path))
    est = get_method("hold-geoffroy2018").estimate(None, ImageMeta(name="a.jpg", width=W, height=H))
    assert est.ok and est.hfov_deg == pytest.approx(70.0, abs=1e-9)
    assert est.roll_deg == pytest.approx(1.5, abs=1e-9) and est.tilt_deg == pytest.approx(-2.0, abs=1e-9)


def test_ctrlc_conversion_recovers_known_camera():
    for hfov, pitch, roll, pan in CAMERAS:
        focal, rotation, gt = _camera(hfov, pitch, roll, pan)
        short = min(W, H)
        fovy = 2 * math.atan((short / 2) / focal)
        # Zenith VP in CTRL-C's normalised coordinates 2 / min(w, h) * (x - centre), either sign.
        k_norm = np.diag([2 / short, 2 / short, 1.0]) @ camera_matrix(focal, W, H)
        k_norm[:2, 2] = 0.0
        zvp = k_norm @ rotation[:, 1]
        for sign in (1.0, -1.0):
            cam = camera_from_ctrlc(sign * zvp / np.linalg.norm(zvp), fovy, W, H)
            assert cam["focal_px"] == pytest.approx(focal, rel=1e-9)
            assert cam["roll_deg"] == pytest.approx(gt["roll_deg"], abs=1e-6)
            assert cam["tilt_deg"] == pytest.approx(gt["tilt_deg"], abs=1e-6)
            assert cam["up"][1] < 0  # pointing up (camera y is down)


def test_ctrlc_preprocessing_contract():
    image = render_manhattan_room(400.0, rotation_from_angles(20.0, 5.0, 3.0).numpy(), W, H)
    x = preprocess_image(image)
    assert x.shape == (1, 3, 512, 512) and x.dtype == np.float32
    assert -2.2 < x.min() and x.max() < 2.7  # ImageNet-normalised
    segments = np.array([[0, 0, 5, 0], [100, 100, 300, 100], [320, 0, 320, 480]], float)
    lines, mask = preprocess_lines(segments, W, H)
    assert lines.shape == (1, 512, 3) and mask.shape == (1, 512, 1)
    assert mask.sum() == 2 and not lines[0, 2:].any()  # the 5 px segment is dropped, rest padded
    assert np.allclose(np.linalg.norm(lines[0, :2], axis=1), 1.0)
    # Normalised coordinates: the line y = 100 px is y_n = 2/480 * (100 - 240); the vertical x = 320 is x_n = 0.
    y_n = 2 / 480 * (100 - 240)
    assert abs(lines[0, 0] @ [0.0, y_n, 1.0]) < 1e-6 and abs(lines[0, 1] @ [0.0, 0.7, 1.0]) < 1e-6
    many = np.random.default_rng(0).uniform(0, 400, (900, 4))
    a, ma = preprocess_lines(many, W, H, seed=0)
    b, _ = preprocess_lines(many, W, H, seed=0)
    assert ma.sum() == 512 and np.array_equal(a, b)  # length-weighted sampling, fixed seed


def test_ctrlc_end_to_end_with_tiny_onnx(tiny_ctrlc):
    model, path = tiny_ctrlc
    focal, rotation, _ = _camera(70.0, 10.0, 5.0, 25.0)
    image = render_manhattan_room(focal, rotation, W, H)
    segments, _ = synthetic_segments(focal, rotation, W, H, seed=0)
    method = get_calibrator("ctrlc", onnx_path=str(path))
    assert method.available
    est = method.estimate(image, ImageMeta(name="room", segments=segments))
    assert est.ok, est.reason
    # Same answer as the PyTorch module on the adapter's own inputs, converted independently.
    lines, mask = preprocess_lines(segments, W, H)
    with torch.no_grad():
        zvp, fovy, hl = model(torch.from_numpy(preprocess_image(image)), torch.from_numpy(lines),
                              torch.from_numpy(mask))
    f_expected = (min(W, H) / 2) / math.tan(float(fovy) / 2)
    assert est.focal_px == pytest.approx(f_expected, rel=1e-4)
    up = np.array([zvp[0, 0], zvp[0, 1], zvp[0, 2] / math.tan(float(fovy) / 2)], dtype=np.float64)
    up = up * (-1 if up[1] > 0 else 1) / np.linalg.norm(up)
    c = up * [1, -1, 1]  # y-up frame
    assert est.roll_deg == pytest.approx(math.degrees(math.atan(-c[0] / c[1])), abs=1e-3)
    assert est.tilt_deg == pytest.approx(math.degrees(math.atan(c[2] / c[1])), abs=1e-3)
    assert est.rotation is None and est.pan_deg is None
    assert np.allclose(est.extra["pred_hl"], hl[0].numpy(), atol=1e-5)
    # Without meta.segments it runs LSD on the image; a missing image is a flagged failure.
    assert method.estimate(image, ImageMeta(name="room")).ok
    assert not method.estimate(None, ImageMeta(name="room", segments=segments)).ok
    # Same settings as every other row: a known focal replaces the predicted FOV; CTRL-C's principal
    # point is the image centre, so an off-centre one is refused rather than ignored.
    known = method.estimate(image, ImageMeta(name="room", segments=segments, focal_px=321.0))
    assert known.ok and known.focal_px == 321.0
    centred = ImageMeta(name="room", segments=segments, principal_point=image_centre(W, H))
    assert method.estimate(image, centred).ok
    off = method.estimate(image, ImageMeta(name="room", segments=segments, principal_point=(W / 2 + 20, H / 2)))
    assert not off.ok and "principal point at the image centre" in off.reason


# --------------------------------------------------------------------------- external / prior

def test_external_csv_round_trip(tmp_path, monkeypatch):
    r = rotation_from_angles(20.0, 10.0, -4.0).numpy()
    gt = {k: float(v) for k, v in horizon_angles(torch.as_tensor(r)).items()}
    header = ["image", "focal_px", "hfov_deg", "roll_deg", "tilt_deg", "pan_deg"] + [f"r{i}{j}" for i in range(3) for j in range(3)]
    rows = [
        ["a.jpg", "500", "", "2.5", "-3.0", ""] + [""] * 9,
        ["sub/b.png", "", "70", "", "", ""] + [f"{v:.12f}" for v in r.ravel()],
        ["c", "", "", "", "", ""] + [""] * 9,
    ]
    path = tmp_path / "preds.csv"
    path.write_text("\n".join(",".join(row) for row in [header] + rows) + "\n")
    method = ExternalPredictions(csv_path=path, method="hold-geoffroy2018")
    assert method.name == "hold-geoffroy2018" and method.available

    a = method.estimate(None, ImageMeta(name="a", width=W, height=H))  # matched by stem
    assert a.ok and a.focal_px == 500  # roll, tilt: through the camera (R with pan 0), exact to rounding
    assert a.roll_deg == pytest.approx(2.5, abs=1e-9) and a.tilt_deg == pytest.approx(-3.0, abs=1e-9)
    assert a.hfov_deg == pytest.approx(math.degrees(2 * math.atan(W / 2 / 500)))
    assert a.pitch_deg == pytest.approx(math.degrees(math.atan(math.tan(math.radians(-3)) * math.cos(math.radians(2.5)))))
    assert a.rotation is None and a.pan_deg is None and not a.camera.pan_known  # horizon only

    b = method.estimate(None, ImageMeta(name="/data/sub/b.png", width=W, height=H))
    assert b.ok and b.hfov_deg == pytest.approx(70.0, abs=1e-9) and b.focal_px == pytest.approx(focal_from_hfov(70.0, W))
    assert np.allclose(b.rotation, r, atol=1e-9)
    assert b.roll_deg == pytest.approx(gt["roll_deg"]) and b.tilt_deg == pytest.approx(gt["tilt_deg"])
    assert b.pan_deg == pytest.approx(20.0)

    c = method.estimate(None, ImageMeta(name="c.jpg", width=W, height=H))
    assert not c.ok and c.reason.startswith("n/a")
    missing = method.estimate(None, ImageMeta(name="zzz.jpg", width=W, height=H))
    assert not missing.ok and missing.reason == "n/a (not supplied)"

    monkeypatch.setenv("FR_EXTERNAL_CSV", str(path))
    assert get_calibrator("external").estimate(None, ImageMeta(name="a.jpg", width=W)).focal_px == 500
    monkeypatch.delenv("FR_EXTERNAL_CSV")
    nothing = get_calibrator("external")
    assert not nothing.available
    assert nothing.estimate(None, ImageMeta(name="a.jpg")).reason == "n/a (not supplied)"


def test_prior():
    est = get_calibrator("prior").estimate(None, ImageMeta(name="x", width=W, height=H))
    assert est.ok and est.hfov_deg == pytest.approx(60.0, abs=1e-9)
    assert est.focal_px == pytest.approx((W / 2) / math.tan(math.radians(30)))
    assert est.roll_deg == 0.0 and est.tilt_deg == 0.0 and est.pan_deg == 0.0  # R = I
    assert np.array_equal(est.rotation, np.eye(3))
    from_image = Prior().estimate(np.zeros((100, 200, 3), np.uint8), ImageMeta(name="y"))
    assert from_image.focal_px == pytest.approx(100 / math.tan(math.radians(30)))
    assert not Prior().estimate(None, ImageMeta(name="z")).ok


def test_learned_rows_name_their_weights_in_captions(tmp_path, tiny_ctrlc, monkeypatch):
    """Table captions name each learned row's weights / predictions: file name + sha256."""
    import hashlib

    from fr_eval.protocols.run_eval import weights_note

    _, onnx_path = tiny_ctrlc
    csv = tmp_path / "hg.csv"
    csv.write_text("image,hfov_deg\na.jpg,60\n")
    monkeypatch.delenv("FR_CTRLC_ONNX", raising=False)
    note = weights_note({"ctrlc": CTRLC(onnx_path=onnx_path), "prior": Prior(),
                         "hold-geoffroy2018": ExternalPredictions(csv_path=csv, method="hold-geoffroy2018"),
                         "ctrlc-retrained": CTRLC(name="ctrlc-retrained", env_var="NO_SUCH_VAR")})
    digest = hashlib.sha256(onnx_path.read_bytes()).hexdigest()
    assert f"ctrlc = {onnx_path.name} (sha256 {digest})" in note
    assert f"hold-geoffroy2018 = predictions hg.csv (sha256 {hashlib.sha256(csv.read_bytes()).hexdigest()})" in note
    assert "prior" not in note and "ctrlc-retrained" not in note
