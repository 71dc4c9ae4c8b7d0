"""Radial distortion (issue 46): the division model, its search, the exports and the sanity check."""
from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
import torch

from fr_torch import FREstimator
from fr_torch.cli.main import main as cli_main
from fr_torch.core.estimator import SegmentEstimator
from fr_torch.core.geometry.conventions import image_centre
from fr_torch.core.geometry.lens import (
    border_bow_percent,
    distort_points,
    k_for_bow,
    normalising_radius,
    undistort_points,
)
from fr_torch.core.geometry.params import DISTORTION, FOCAL, from_log_focal, rotations
from fr_torch.core.likelihood.measures import SegmentFeatures
from fr_torch.core.likelihood.mixture import LikelihoodParams, MixtureLikelihood
from fr_torch.core.search.lens import SegmentGeometry
from fr_torch.core.search.refine import objective_and_grad
from fr_torch.core.settings.config import SearchConfig
from fr_torch.core.settings.distortion import DistortionMode, DistortionSetting
from fr_torch.errors import FRInputError
from fr_torch.images.lens import distort_image, undistort_image
from fr_torch.synthetic import distorted_segments, random_rotation, synthetic_segments
from tests.conftest import gpu

WIDTH, HEIGHT = 640, 480
CENTRE = np.array(image_centre(WIDTH, HEIGHT))
RADIUS = normalising_radius(WIDTH, HEIGHT)


def test_round_trip_and_normalisation():
    rng = np.random.default_rng(0)
    points = rng.uniform([0, 0], [WIDTH, HEIGHT], (200, 2))
    for k in (-0.45, -0.2, 0.0, 0.15):
        back = distort_points(undistort_points(points, k, CENTRE, RADIUS), k, CENTRE, RADIUS)
        assert np.abs(back - points).max() < 1e-9
        torch_back = distort_points(undistort_points(torch.as_tensor(points), k, torch.as_tensor(CENTRE), RADIUS), k,
                                    torch.as_tensor(CENTRE), RADIUS)
        assert torch.allclose(torch_back, torch.as_tensor(points), atol=1e-9)
    # k means the same at every image size: halving the image halves every offset
    half = undistort_points(points / 2, -0.3, CENTRE / 2, RADIUS / 2)
    assert np.allclose(half * 2, undistort_points(points, -0.3, CENTRE, RADIUS))
    assert border_bow_percent(0.0, WIDTH, HEIGHT) == 0.0
    assert 3.0 < border_bow_percent(-0.2, WIDTH, HEIGHT) < 3.5 < border_bow_percent(-0.3, WIDTH, HEIGHT)
    assert border_bow_percent(0.1, WIDTH, HEIGHT) < 0
    assert border_bow_percent(k_for_bow(3.0, WIDTH, HEIGHT), WIDTH, HEIGHT) == pytest.approx(3.0, abs=1e-6)


def test_setting_parsing_is_one_line_errors():
    assert DistortionSetting.parse("auto").mode is DistortionMode.AUTO
    known = DistortionSetting(known_k=-0.2)
    assert known.mode is DistortionMode.DIVISION and known.k_box() == (-0.2, -0.2)
    assert SearchConfig.from_config(distortion={"mode": "division", "k_range": [-0.5, 0.1]}).distortion.k_range == (
        -0.5, 0.1)
    for bad in ({"mode": "fisheye"}, {"known_k": 1.5}, {"known_k": float("nan")}, {"k_range": (0.1, -0.1)},
                {"bend_min_gain": -1}):
        with pytest.raises(FRInputError):
            DistortionSetting.parse(bad)
    assert cli_main(["calibrate", "x.png", "--k", "2"]) == 2


def test_features_and_analytic_gradient_of_k():
    """The refinement's closed-form gradient in k (through d line / dk) equals autograd's."""
    torch.manual_seed(0)
    likelihood = MixtureLikelihood(LikelihoodParams.from_config())
    batch, count, starts = 2, 60, 3
    endpoints = torch.rand(batch, count, 4, dtype=torch.float64) * torch.tensor([640.0, 480.0, 640.0, 480.0])
    mask = torch.ones(batch, count, dtype=torch.bool)
    mask[1, 50:] = False
    pp = torch.tensor([[320.0, 240.0], [300.0, 250.0]], dtype=torch.float64)
    long_side = torch.tensor([640.0, 640.0], dtype=torch.float64)
    features = SegmentFeatures.from_endpoints(endpoints, mask, pp, long_side)
    geometry = SegmentGeometry(endpoints, mask, pp, torch.tensor([400.0, 400.0], dtype=torch.float64), long_side,
                               k_prior_weight=2.0)
    at_zero = geometry.features(torch.zeros(batch, 1, dtype=torch.float64))
    assert torch.allclose(at_zero.line_along, features.line_along, atol=1e-9)
    assert torch.equal(at_zero.weight, features.weight)
    lower = torch.tensor([-45.0, -35.0, -15.0, 5.5, -0.6], dtype=torch.float64).expand(batch, 1, 5)
    span = torch.tensor([90.0, 70.0, 30.0, 1.5, 0.8], dtype=torch.float64).expand(batch, 1, 5)
    u = torch.rand(batch, starts, 5, dtype=torch.float64)
    grad_out = torch.tensor([[-1e-3], [-2e-3]], dtype=torch.float64)
    objective, grad = objective_and_grad(likelihood, features, lower, span, u, grad_out, geometry)
    u_auto = u.clone().requires_grad_(True)
    params = from_log_focal(lower + u_auto * span)
    virtual = geometry.features(params[..., DISTORTION])
    rows = params[..., :DISTORTION].reshape(batch * starts, 1, DISTORTION)
    value = likelihood.objective(virtual, rotations(rows), rows[..., FOCAL]).view(batch, starts)
    value = value + geometry.k_log_prior(params[..., DISTORTION])[0]
    (grad_out * value).sum().backward()
    assert torch.allclose(value, objective, atol=1e-9)
    assert torch.allclose(u_auto.grad, grad, atol=1e-8)


def scene(k: float, seed: int = 3, focal: float = 380.0):
    rotation = random_rotation(np.random.default_rng(seed))
    segments, labels = synthetic_segments(focal, rotation, WIDTH, HEIGHT, n_per_family=50, noise_px=0.3,
                                          clutter_fraction=0.1, seed=seed, max_length_px=220.0)
    pieces, _ = distorted_segments(segments, labels, k, WIDTH, HEIGHT, piece_px=30.0)
    return pieces, rotation, focal


def test_division_search_recovers_k_and_focal_and_pinhole_is_flagged():
    pieces, _, focal = scene(-0.25)
    config = SearchConfig.from_config(grid_points_per_dim=6, focal_sweep_points=8)
    division = SegmentEstimator(mode="fast", reliability=None, search_config=config, distortion="division")
    [result] = division.calibrate_segments([pieces], [(WIDTH, HEIGHT)])
    assert abs(result.distortion_k + 0.25) < 0.03 and abs(result.focal_px / focal - 1) < 0.05
    assert result.distortion["model"] == "division" and result.to_json()["distortion"]["k"] == result.distortion_k
    # the round trip: bend straight lines with the estimate, straighten them again -> straight
    line = np.stack([np.linspace(20, 620, 50), np.linspace(30, 200, 50)], -1)
    back = result.undistort_points(result.distort_points(line))
    assert np.abs(back - line).max() < 1e-6
    pinhole = SegmentEstimator(mode="fast", reliability=None, search_config=config)
    [flagged] = pinhole.calibrate_segments([pieces], [(WIDTH, HEIGHT)])
    assert not flagged.reliable and "lines bend" in flagged.reason and "--distortion division" in flagged.reason
    straight, _, _ = scene(0.0)
    [clean] = pinhole.calibrate_segments([straight], [(WIDTH, HEIGHT)])
    assert "lines bend" not in clean.reason


def test_image_warps_invert_each_other():
    image = np.zeros((HEIGHT, WIDTH), np.uint8)
    for x in range(40, WIDTH, 60):
        cv2.line(image, (x, 0), (x, HEIGHT - 1), 255, 3)
    bent = distort_image(image, -0.2, (WIDTH, HEIGHT))
    assert np.abs(bent.astype(int) - image).mean() > 5  # visibly bent
    straight = undistort_image(bent, -0.2, CENTRE)
    middle = (slice(120, 360), slice(160, 480))
    assert np.abs(straight[middle].astype(int) - image[middle]).mean() < 6


def test_cli_formats_and_undistort(tmp_path, capsys):
    pieces, _, _ = scene(-0.2)
    image = np.full((HEIGHT, WIDTH), 90, np.uint8)
    for x1, y1, x2, y2 in pieces:
        cv2.line(image, (int(round(x1)), int(round(y1))), (int(round(x2)), int(round(y2))), 230, 2, cv2.LINE_AA)
    path = tmp_path / "bent.png"
    cv2.imwrite(str(path), image)
    estimator = FREstimator(mode="fast", reliability=None, distortion="division")
    [result] = estimator.calibrate_images([str(path)])
    assert result.ok and result.distortion_k < -0.05
    camera = result.to_kornia()
    assert torch.allclose(camera.intrinsics[0, :3, :3], torch.as_tensor(result.camera.K))
    record = result.opencv()
    target = tmp_path / "camera.json"
    target.write_text(json.dumps(record))
    storage = cv2.FileStorage(str(target), cv2.FILE_STORAGE_READ)
    assert np.allclose(storage.getNode("camera_matrix").mat(), result.camera.K)
    assert storage.getNode("distortion_coefficients").mat().shape == (1, 5)
    for option, model in ((), "SIMPLE_DIVISION"), (("--colmap-model", "radial"), "RADIAL"):
        assert cli_main(["calibrate", str(path), "--distortion", "division", "--fast", "--no-reliability",
                         "--format", "colmap", *option]) == 0
        line = capsys.readouterr().out.strip().splitlines()[-1].split()
        assert line[1:4] == [model, str(WIDTH), str(HEIGHT)]
        expected = result.colmap(model=option[1] if option else "division")[1]
        assert [float(v) for v in line[4:]] == pytest.approx(expected, rel=1e-3, abs=1e-6)
    assert cli_main(["calibrate", str(path), "--colmap-model", "radial"]) == 2  # without --format colmap
    assert "--colmap-model applies to --format colmap" in capsys.readouterr().err
    out = tmp_path / "out"
    assert cli_main(["undistort", str(path), "--out", str(out), "--fast", "--no-reliability"]) == 0
    assert (out / "bent_undistorted.png").is_file() and (out / "bent_undistorted.json").is_file()


@gpu
@pytest.mark.parametrize("lens", ["pinhole", "division", "auto"])
def test_cuda_lens_settings_equal_cpu(lens):
    """Every lens setting (the pinhole estimate's lines-bend check included) runs on a CUDA device
    and gives the CPU's estimate."""
    pieces, _, _ = scene(-0.25)
    config = SearchConfig.from_config(grid_points_per_dim=6, focal_sweep_points=8)
    results = [SegmentEstimator(mode="fast", reliability=None, search_config=config, distortion=lens,
                                device=device).calibrate_segments([pieces], [(WIDTH, HEIGHT)])[0]
               for device in ("cpu", "cuda")]
    cpu, cuda = results
    assert cuda.ok and cuda.distortion_model == cpu.distortion_model and cuda.reason == cpu.reason
    assert cuda.focal_px == pytest.approx(cpu.focal_px, rel=1e-3)
    assert cuda.distortion_k == pytest.approx(cpu.distortion_k, abs=1e-3)
