"""Vanishing points as a result: CONSAC's metric, fR's ranked and Atlanta VPs, CONSAC with its weights.

The metric is checked on hand-made cases whose errors and AUC are computed by hand; fR's Atlanta
families on a synthetic scene with a fourth horizontal family; CONSAC's network against the
authors' formulation (conv, instance norm, batch norm with batch statistics) and, with the real
weights (``models_root``: fails in CI when missing, like the data), its state dict and output shape.
"""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from fr_baselines import consac as consac_module
from fr_baselines import vp_geometry as vg
from fr_eval.scoring.vp_metric import (
    MISSING_VP_DEG,
    angle_cost_deg,
    auc_table,
    consac_auc,
    directions_from_vps,
    match_errors,
)
from fr_torch.core.geometry.conventions import image_centre, rotation_from_angles
from fr_torch.core.geometry.vanishing import AtlantaConfig
from fr_torch.errors import FRInputError
from fr_torch.plugins.interface import ImageMeta
from fr_torch.runtime.estimator import FREstimator
from fr_torch.synthetic import camera_matrix, synthetic_segments


def _rotated(direction, axis, degrees):
    """``direction`` rotated by ``degrees`` about unit ``axis`` (Rodrigues)."""
    a = np.radians(degrees)
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    d = np.asarray(direction, float)
    return d * np.cos(a) + np.cross(axis, d) * np.sin(a) + axis * (axis @ d) * (1 - np.cos(a))


# --------------------------------------------------------------------------- the metric


def test_match_errors_hand_made():
    truth = np.eye(3)
    # Estimates permuted, one sign flipped, off by 1, 2 and 3 degrees.
    est = np.stack([_rotated(truth[2], [1, 0, 0], 3.0), -_rotated(truth[0], [0, 0, 1], 1.0),
                    _rotated(truth[1], [1, 0, 0], 2.0)])
    np.testing.assert_allclose(match_errors(truth, est), [1.0, 2.0, 3.0], atol=1e-9)
    # Only the first len(truth) estimates count: a perfect 4th estimate is ignored.
    two = match_errors(truth[:2], np.stack([truth[2], _rotated(truth[0], [0, 1, 0], 4.0), truth[1]]))
    np.testing.assert_allclose(np.sort(two), [4.0, 90.0], atol=1e-9)
    # Fewer estimates than labels: the unmatched labelled VPs get 90 degrees.
    np.testing.assert_allclose(match_errors(truth, truth[:1]), [0.0, MISSING_VP_DEG, MISSING_VP_DEG])
    np.testing.assert_allclose(match_errors(truth, None), [MISSING_VP_DEG] * 3)


def test_directions_from_pixels_with_calibration():
    K = camera_matrix(500.0, 640, 480, (330.0, 250.0))
    d = np.array([0.3, -0.2, 1.0])
    d /= np.linalg.norm(d)
    vp = K @ d * 7.0  # any homogeneous scale
    np.testing.assert_allclose(np.abs(directions_from_vps(vp[None], K)[0] @ d), 1.0, atol=1e-12)
    at_infinity = directions_from_vps(np.array([[1.0, 1.0, 0.0]]), K)[0]
    np.testing.assert_allclose(at_infinity, [math.sqrt(0.5), math.sqrt(0.5), 0.0], atol=1e-12)


def test_consac_auc_hand_computed():
    # Sorted errors 2, 4, 6, 12 (recall 1/4 ... 1); the cutoff 10 lies between 6 and 12, so the
    # curve's value there is CONSAC's (6 * 0.75 + 12 * 1) / (6 + 12) = 0.91667.  Trapezoids from
    # the first error: 2 * 0.375 + 2 * 0.625 + 4 * (0.75 + 0.91667) / 2.
    auc, points = consac_auc([12.0, 2.0, 6.0, 4.0], 10.0)
    assert points[-2, 0] == pytest.approx(10.0) and points[-2, 1] == pytest.approx(16.5 / 18)
    assert auc == pytest.approx((0.75 + 1.25 + 2.0 * (0.75 + 16.5 / 18)) / 10.0)
    # Every error below the cutoff: the curve ends at (cutoff, 1).
    assert consac_auc([1.0, 3.0], 10.0)[0] == pytest.approx((2 * 0.75 + 7 * 1.0) / 10.0)
    # Every error above the cutoff: no area.
    assert consac_auc([15.0, 90.0], 10.0)[0] == 0.0
    # CONSAC's value at the cutoff weighs the two errors around it by their size: nine errors of
    # 0.5 and one of 90 give (0.5 * 0.9 + 90 * 1) / 90.5 there, not 0.9.
    table = auc_table([0.5] * 9 + [90.0])
    assert table["auc10"] == pytest.approx(100 * 9.5 * (0.9 + 90.45 / 90.5) / 2 / 10)


# --------------------------------------------------------------------------- fR: ranking, Atlanta

W, H, F_PX = 640, 480, 500.0


def _scene_with_fourth_family(turn: np.ndarray, seed: int = 3):
    """Manhattan segments of a camera plus the world-x family of the frame turned by ``turn``
    (world -> world rotation): (segments, the fourth direction in the camera)."""
    rotation = rotation_from_angles(12.0, 8.0, 3.0).numpy()
    segments, _ = synthetic_segments(F_PX, rotation, W, H, n_per_family=60, clutter_fraction=0.2, seed=seed)
    turned = rotation @ turn
    extra, labels = synthetic_segments(F_PX, turned, W, H, n_per_family=50, clutter_fraction=0.0, seed=seed + 1)
    return np.concatenate([segments, extra[labels == 0]]), turned[:, 0]


ABOUT_VERTICAL_30 = rotation_from_angles(30.0, 0.0, 0.0).numpy().T  # about world y: still horizontal
ABOUT_Z_60 = rotation_from_angles(0.0, 0.0, 60.0).numpy().T  # about world z: 60 deg off the horizon


@pytest.mark.parametrize("turn, horizontal", [(ABOUT_VERTICAL_30, True), (ABOUT_Z_60, False)])
def test_atlanta_finds_a_fourth_family_without_moving_f_or_r(turn, horizontal):
    segments, fourth = _scene_with_fourth_family(turn)
    plain = FREstimator(mode="fast", reliability=None)
    atlanta = FREstimator(mode="fast", reliability=None, atlanta="on")
    [r0] = plain.calibrate_segments([segments], [(W, H)])
    [r1] = atlanta.calibrate_segments([segments], [(W, H)])
    assert r0.ok and r1.ok
    assert r1.focal_px == r0.focal_px and np.array_equal(r1.rotation, r0.rotation)
    assert len(r0.ranked_vanishing_points) == 3 and sorted(r0.vanishing_point_families) == [0, 1, 2]
    manhattan = r1.vanishing_point_families < 3
    np.testing.assert_allclose(r1.ranked_vanishing_points[manhattan][np.argsort(r1.vanishing_point_families[manhattan])],
                               r0.ranked_vanishing_points[np.argsort(r0.vanishing_point_families)])
    assert np.all(np.diff(r1.vanishing_point_support) <= 0)  # ranked by support
    extra = r1.ranked_vanishing_points[~manhattan]
    assert len(extra) >= 1
    K = camera_matrix(r1.focal_px, W, H)
    found = directions_from_vps(extra, K)
    errors = angle_cost_deg(fourth[None], found)[0]
    best = int(np.argmin(errors))
    assert errors[best] < 1.0
    off_horizon = np.degrees(np.arcsin(min(1.0, abs(found[best] @ r1.rotation[:, 1]))))
    assert (off_horizon < 1e-6) == horizontal
    record = r1.to_json()["ranked_vanishing_points"]
    assert [item["family"] for item in record] == r1.vanishing_point_families.tolist()


def test_atlanta_config_parsing():
    assert AtlantaConfig.parse(None) is None and AtlantaConfig.parse("off") is None
    assert AtlantaConfig.parse("on") == AtlantaConfig()
    assert AtlantaConfig.parse("max_extra=2:prior=0.05") == AtlantaConfig(max_extra=2, prior=0.05)
    for bad in ("maybe", "max_extra=x", "prior=0.9", "unknown=1"):
        with pytest.raises(FRInputError):
            AtlantaConfig.parse(bad)


def test_zenith_and_orthogonal_pair_from_ranked_points():
    rotation = rotation_from_angles(20.0, 10.0, 2.0).numpy()
    K = camera_matrix(F_PX, W, H)
    points = (K @ rotation).T
    pp = np.array(image_centre(W, H))
    ranked = vg.rank_by_support(points, [5.0, 9.0, 7.0])  # vertical (column 1) first
    zenith = vg.pick_zenith(ranked, pp, 30.0, H / 2)
    assert zenith == 0
    others = [{"vp": ranked[i], "significance": 1.0} for i in (1, 2)]
    focal, _, _ = vg.orthogonal_pair(others, ranked[zenith], pp, math.hypot(W, H), (100.0, 2000.0), 20.0, 5.0)
    assert focal == pytest.approx(F_PX, rel=1e-6)


# --------------------------------------------------------------------------- CONSAC


def _reference_forward(network, inputs):
    """The authors' formulation: conv2d on (B, C, N, 1), instance norm, batch norm in training mode."""
    x = F.relu(network.p_in(inputs.transpose(1, 2).unsqueeze(-1)))
    for i in range(network.blocks):
        residual = x
        for conv, norm in ((f"{i}s0", f"{i}s1"), (f"{i}s2", f"{i}s3")):
            bn = getattr(network, norm)
            x = F.batch_norm(F.instance_norm(getattr(network, conv)(x)), None, None, bn.weight, bn.bias, True, 0.1,
                             bn.eps)
            x = F.relu(x)
        x = x + residual
    log_probs = F.logsigmoid(network.p_out(x)).view(x.shape[0], -1)
    return log_probs - torch.logsumexp(log_probs, 1, keepdim=True)


def test_consac_network_matches_the_authors_formulation():
    torch.manual_seed(0)
    network = consac_module.ConsacNetwork()
    for name, module in network.named_modules():
        if isinstance(module, torch.nn.BatchNorm2d):
            module.weight.data.uniform_(0.5, 1.5)
            module.bias.data.uniform_(-0.5, 0.5)
    inputs = torch.randn(1, 120, 9)
    with torch.no_grad():
        torch.testing.assert_close(network(inputs), _reference_forward(network, inputs), atol=1e-4, rtol=1e-4)


def test_consac_without_weights_is_not_supplied(tmp_path):
    method = consac_module.Consac(weights=str(tmp_path / "absent.net"))
    estimate = method.estimate(None, ImageMeta(name="x", width=W, height=H, segments=np.zeros((5, 4))))
    assert not estimate.ok and estimate.reason.startswith("n/a (")


@pytest.mark.data
@pytest.mark.parametrize("variant", ["consac", "consac-s"])
def test_consac_weights_load_and_run(models_root, variant):
    path = consac_module.weights_path(variant, models_root / "consac")
    network = consac_module.load_network(path)
    with torch.no_grad():
        out = network(torch.randn(2, 150, 9))
    assert out.shape == (2, 150) and torch.isfinite(out).all()
    torch.testing.assert_close(torch.logsumexp(out, 1), torch.zeros(2), atol=1e-5, rtol=0)
    # A synthetic scene, few hypotheses (speed): the three Manhattan VPs are among the six found.
    rotation = rotation_from_angles(25.0, 10.0, 4.0).numpy()
    segments, _ = synthetic_segments(F_PX, rotation, W, H, n_per_family=40, clutter_fraction=0.1, seed=5)
    method = consac_module.Consac(variant=variant, weights=str(models_root / "consac"), hypotheses=16,
                                  outer_hypotheses=4)
    estimate = method.estimate(None, ImageMeta(name="synthetic", width=W, height=H, segments=segments))
    points = estimate.ranked_vanishing_points
    assert points.shape == (6, 3) and "no EM" in estimate.extra["vp_variants"]
    K = camera_matrix(F_PX, W, H)
    found = directions_from_vps(points, K)
    worst = angle_cost_deg(rotation.T, found).min(1).max()
    assert worst < 2.0


# --------------------------------------------------------------------------- datasets and the VP task


@pytest.mark.data
def test_vp_labels_of_the_datasets(data_root):
    from fr_eval.protocols.vp_eval import load_vp_samples

    plus_test = load_vp_samples("yud+", data_root, "test")
    plus_train = load_vp_samples("yud+", data_root, "train")
    assert len(plus_train) == 25 and len(plus_test) == 77  # CONSAC's split, names sorted
    assert plus_train[-1].name < plus_test[0].name
    assert sum(len(s.extra["vp_directions"]) for s in plus_test) > 3 * 77
    yud = load_vp_samples("yud", data_root, "test")  # the same photos, the three Manhattan VPs
    assert [s.name for s in yud] == [s.name for s in plus_test]
    assert all(len(s.extra["vp_directions"]) == 3 for s in yud)
    for sample in yud[:5]:  # YUD's first three labels are its Manhattan frame
        np.testing.assert_allclose(np.abs(sample.extra["vp_directions"] @ sample.rotation).max(0), 1.0, atol=0.02)
    nyu = load_vp_samples("nyu-vp", data_root, "val")
    assert len(nyu) == 224 and nyu[0].name == "nyu_1000"
    np.testing.assert_allclose(np.linalg.norm(nyu[0].extra["vp_directions"], axis=1), 1.0)


@pytest.mark.data
def test_vp_task_end_to_end(data_root, tmp_path):
    from fr_eval.protocols.eval_command import main

    out = tmp_path / "vp"
    assert main(["--task", "vp", "--dataset", "nyu-vp", "--split", "val", "--limit", "2", "--methods", "fast-fr",
                 "--data-root", str(data_root), "--out", str(out)]) == 0
    for name in ("vp_errors.csv", "vp_summary.md", "vp_summary.csv", "vp_recall.png", "run_info.json"):
        assert (out / name).is_file()
    text = (out / "vp_summary.md").read_text()
    assert "| fast-fr |" in text and "AUC@10° (f unknown)" in text and "AUC@10° (K known)" in text
