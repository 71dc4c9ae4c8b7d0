"""The fast paths are exact: float32 vs an independent float64 reference, batch == one by one,
chunking invariance, analytic gradient == autograd; plus a smoke run of ``fr bench --quick``."""
import json
import math
from dataclasses import replace

import numpy as np
import pytest
import torch

import fr_torch.core.geometry.params as param_rows
import fr_torch.core.search.grid as search_grid
import fr_torch.core.search.passes as search_passes
import fr_torch.core.search.refine as search_refine
from fr_torch import FREstimator
from fr_torch.core.geometry.conventions import focal_from_hfov, rotation_from_angles
from fr_torch.core.geometry.params import rotations as fast_rotations
from fr_torch.core.likelihood.measures import SegmentFeatures
from fr_torch.core.likelihood.mixture import LikelihoodParams, MixtureLikelihood
from fr_torch.core.likelihood.segments import SegmentBatch
from fr_torch.core.search.grid import grid_hypotheses, score_grid
from fr_torch.core.search.refine import refine
from fr_torch.core.settings.config import SearchConfig
from fr_torch.synthetic import synthetic_segments
from tests.conftest import gpu

PP = (320.0, 240.0)


def _rotation_np(pan, pitch, roll):
    """World->camera R with R.T = Ry(pan) Rx(pitch) Rz(roll), degrees (written independently)."""
    p, t, r = np.radians([pan, pitch, roll])
    ry = np.array([[np.cos(p), 0, np.sin(p)], [0, 1, 0], [-np.sin(p), 0, np.cos(p)]])
    rx = np.array([[1, 0, 0], [0, np.cos(t), -np.sin(t)], [0, np.sin(t), np.cos(t)]])
    rz = np.array([[np.cos(r), -np.sin(r), 0], [np.sin(r), np.cos(r), 0], [0, 0, 1]])
    return (ry @ rx @ rz).T


def _data_only() -> LikelihoodParams:
    """Default params without the focal prior: these tests compare the data term's code paths (the
    focal prior is one added term, checked in test_likelihood.py)."""
    from dataclasses import replace
    return replace(LikelihoodParams.from_config("b"), focal_prior_weight=0.0)


def _reference_objective(segments, pan, pitch, roll, focal, params: LikelihoodParams, pp=PP):
    """Measure-b mixture objective, float64 numpy, straight from the definitions (no shared code).

    Angle between the segment and the line from its midpoint to each VP; exponential densities
    with the vertical parameters on column 1; uniform background on [0, pi/2]; sum len * log p.
    """
    K = np.array([[focal, 0, pp[0]], [0, focal, pp[1]], [0, 0, 1.0]])
    V = K @ _rotation_np(pan, pitch, roll)  # column k = homogeneous VP k
    p1, p2 = segments[:, :2], segments[:, 2:]
    d = p2 - p1
    length = np.linalg.norm(d, axis=1)
    m = (p1 + p2) / 2
    total = np.full(len(segments), params.prior_background / (np.pi / 2))
    for k in range(3):
        v = V[:, k]
        to_vp = v[None, :2] - m * v[2]  # direction from the midpoint towards the VP (times v3)
        cross = d[:, 0] * to_vp[:, 1] - d[:, 1] * to_vp[:, 0]
        dot = (d * to_vp).sum(1)
        angle = np.arctan2(np.abs(cross), np.abs(dot))
        lam = params.scale_vertical if k == 1 else params.scale_horizontal
        prior = params.prior_vertical if k == 1 else params.prior_horizontal
        total += prior / lam * np.exp(-angle / lam)
    return float((length * np.log(total)).sum())


def _features(segment_list, dtype, device="cpu"):
    batch = SegmentBatch.from_list(segment_list, [(640, 480)] * len(segment_list), device, dtype)
    pp = torch.tensor([PP] * len(segment_list), dtype=dtype, device=device)
    return SegmentFeatures.from_batch(batch, pp)


def _scene(seed, hfov=70.0, pan=15.0, pitch=10.0, roll=5.0, n_per_family=60):
    focal = focal_from_hfov(hfov, 640)
    R = _rotation_np(pan, pitch, roll)
    seg, _ = synthetic_segments(focal, R, 640, 480, n_per_family=n_per_family, noise_px=0.5,
                                clutter_fraction=0.3, seed=seed)
    return seg


def test_fast_rotations_equal_camera_convention():
    rng = np.random.default_rng(0)
    angles = torch.tensor(rng.uniform(-60, 60, (20, 3)), dtype=torch.float64)
    expected = rotation_from_angles(angles[:, 0], angles[:, 1], angles[:, 2])
    assert torch.allclose(fast_rotations(angles), expected, atol=1e-13)
    assert np.allclose(fast_rotations(angles[:1])[0].numpy(), _rotation_np(*angles[0].tolist()), atol=1e-13)


def test_float32_objective_matches_independent_float64_reference():
    rng = np.random.default_rng(3)
    model = MixtureLikelihood(_data_only())
    segs = [rng.uniform(0, 640, (80, 4)), _scene(1)]
    hyp = np.stack([rng.uniform(-45, 45, 6), rng.uniform(-35, 35, 6), rng.uniform(-15, 15, 6),
                    rng.uniform(150, 700, 6)], 1)
    hyp_t = torch.tensor(hyp, dtype=torch.float32)
    R = rotation_from_angles(hyp_t[:, 0], hyp_t[:, 1], hyp_t[:, 2])
    for b, seg in enumerate(segs):
        features = _features([seg], torch.float32)
        got = model.objective(features, R[None], hyp_t[None, :, 3])[0].double().numpy()
        with torch.no_grad():
            got_nograd = model.objective(features, R[None], hyp_t[None, :, 3])[0].double().numpy()
        expected = np.array([_reference_objective(seg, *h, model.params) for h in hyp.astype(np.float32).astype(float)])
        assert np.allclose(got, expected, rtol=1e-4), (got, expected)
        assert np.allclose(got_nograd, expected, rtol=1e-4)


def test_grid_maximum_float32_matches_float64_and_reference():
    config = SearchConfig.from_config()
    segs = [_scene(0), _scene(2, 95.0, -30.0, -15.0, -7.0)]
    width = torch.tensor([640.0, 640.0], dtype=torch.float64)
    hyp = grid_hypotheses(config, width)
    model = MixtureLikelihood(_data_only())
    s32 = score_grid(model, _features(segs, torch.float32), hyp, config.max_chunk_elements).double()
    s64 = score_grid(model, _features(segs, torch.float64), hyp, config.max_chunk_elements)
    best32, best64 = s32.max(1), s64.max(1)
    assert torch.allclose(best32.values, best64.values, rtol=1e-4)
    assert torch.allclose(s32, s64, rtol=1e-4, atol=1e-3 * s64.abs().max())
    for b, seg in enumerate(segs):
        h = hyp[b, best64.indices[b]].tolist()
        assert best64.values[b].item() == pytest.approx(_reference_objective(seg, *h, model.params), rel=1e-9)


@pytest.mark.parametrize("mode", ["fast", "fr"])
def test_estimator_float32_matches_float64(mode):
    segs = [_scene(4, 80.0, 20.0, 12.0, 4.0)]
    a = FREstimator(mode=mode, dtype=torch.float32).calibrate_segments(segs, [(640, 480)])[0]
    b = FREstimator(mode=mode, dtype=torch.float64).calibrate_segments(segs, [(640, 480)])[0]
    # 100 Adam steps on a flat optimum need not land on the same point in both precisions; the two
    # must agree far below the estimator's accuracy (0.1 % focal, 0.01 deg) and in objective value
    # (measured: 0.003 deg / 0.003 px apart, objective 1.9e-4 apart -- the objective is sharp in the
    # parameters because long segments weigh thousands of pixels).
    assert a.log_likelihood == pytest.approx(b.log_likelihood, rel=5e-4)
    assert a.focal_px == pytest.approx(b.focal_px, rel=1e-3)
    for key in ("pan_deg", "pitch_deg", "roll_deg"):
        # float32 and float64 refinements stop at slightly different points of a flat optimum
        # (measured up to 0.013 deg of pan with the focal prior on)
        assert abs(getattr(a, key) - getattr(b, key)) < 0.02, key


def test_batch_equals_one_by_one(monkeypatch):
    segs = [_scene(5), _scene(6, 100.0, -20.0, 5.0, -3.0, n_per_family=30), _scene(7, 60.0, 30.0, -20.0, 8.0, 90)]
    est = FREstimator(mode="fast")
    batch = est.calibrate_segments(segs, [(640, 480)] * 3)
    monkeypatch.setattr("fr_torch.core.estimator.SEARCH_CHUNK_IMAGES", 2)  # searched as 2 + 1 images
    chunked = est.calibrate_segments(segs, [(640, 480)] * 3)
    for i, seg in enumerate(segs):
        [single] = est.calibrate_segments([seg], [(640, 480)])
        for other in (single, chunked[i]):
            assert batch[i].focal_px == pytest.approx(other.focal_px, rel=1e-5)
            assert batch[i].log_likelihood == pytest.approx(other.log_likelihood, rel=1e-5)
            assert np.allclose(batch[i].rotation, other.rotation, atol=1e-5)
            assert np.array_equal(batch[i].labels, other.labels)
            assert batch[i].reliable == other.reliable and batch[i].predicted_error == other.predicted_error


def test_chunking_does_not_change_scores_or_refinement(monkeypatch):
    config = SearchConfig.from_config(grid_points_per_dim=3)
    segs = [_scene(8, n_per_family=25), _scene(9, 90.0, -10.0, 20.0, 2.0, 15)]
    features = _features(segs, torch.float64)
    width = torch.tensor([640.0, 640.0], dtype=torch.float64)
    hyp = grid_hypotheses(config, width)
    model = MixtureLikelihood(_data_only())
    whole = score_grid(model, features, hyp, 1 << 30)
    monkeypatch.setattr(search_grid, "CPU_CHUNK_ELEMENTS", 1000)  # many tiny chunks, also split over images
    assert torch.allclose(score_grid(model, features, hyp, 1 << 30), whole, rtol=1e-12)
    assert torch.allclose(score_grid(model, features, hyp, 7), whole, rtol=1e-12)  # one hypothesis, one image
    starts = hyp[:, :2]
    lower, upper = search_grid.parameter_box(config, width, None)
    p1, o1 = refine(model, features, starts, lower, upper, 5, fast=True)
    p2, o2 = refine(model, features, starts, lower, upper, 5, fast=True, max_chunk_elements=10)  # image by image
    assert torch.allclose(p1, p2, rtol=1e-12) and torch.allclose(o1, o2, rtol=1e-12)


def test_analytic_gradient_matches_autograd_of_generic_path():
    rng = np.random.default_rng(11)
    features = _features([rng.uniform(0, 640, (40, 4)), rng.uniform(0, 640, (25, 4))], torch.float64)
    model = MixtureLikelihood(_data_only())
    angles = torch.tensor(rng.uniform(-30, 30, (2, 3, 3)), requires_grad=True)
    focal = torch.tensor(rng.uniform(200, 800, (2, 3)), requires_grad=True)
    R = fast_rotations(angles)
    fast = model.objective(features, R, focal)
    generic = torch.einsum("bnh,bn->bh", model.segment_log_likelihood(features, R, focal), features.weight)
    assert torch.allclose(fast, generic, rtol=1e-12)
    g_fast = torch.autograd.grad(fast.sum(), [angles, focal], retain_graph=True)
    g_generic = torch.autograd.grad(generic.sum(), [angles, focal])
    for a, b in zip(g_fast, g_generic):
        assert torch.allclose(a, b, rtol=1e-9, atol=1e-9 * b.abs().max())
    # Padding rows (s = t = 0) give finite gradients.
    assert all(torch.isfinite(g).all() for g in g_fast)


def test_posteriors_chunked_equal_whole():
    segs = [_scene(12), _scene(13, n_per_family=20)]
    features = _features(segs, torch.float64)
    model = MixtureLikelihood(_data_only())
    R = rotation_from_angles(torch.tensor([[10.0], [-5.0]], dtype=torch.float64), 3.0, 1.0)
    f = torch.tensor([[400.0], [500.0]], dtype=torch.float64)
    q1, l1 = model.posteriors(features, R, f)
    q2, l2 = model.posteriors(features, R, f, max_chunk_elements=1)
    assert torch.allclose(q1, q2, rtol=1e-12, atol=1e-300) and torch.allclose(l1, l2, rtol=1e-12)


@gpu
def test_cuda_grid_and_estimate_equal_cpu():
    config = SearchConfig.from_config()
    segs = [_scene(0), _scene(2, 95.0, -30.0, -15.0, -7.0)]
    hyp = grid_hypotheses(config, torch.tensor([640.0, 640.0], dtype=torch.float64))
    model = MixtureLikelihood(_data_only())
    cpu = score_grid(model, _features(segs, torch.float32), hyp, config.max_chunk_elements)
    cuda = score_grid(model, _features(segs, torch.float32, "cuda"), hyp, config.max_chunk_elements).cpu()
    assert torch.allclose(cpu, cuda, rtol=1e-4, atol=1e-3 * cpu.abs().max())
    a = FREstimator(mode="fast").calibrate_segments(segs, [(640, 480)] * 2)
    b = FREstimator(mode="fast", device="cuda").calibrate_segments(segs, [(640, 480)] * 2)
    for x, y in zip(a, b):
        assert x.focal_px == pytest.approx(y.focal_px, rel=1e-4)


def test_bench_quick_smoke(tmp_path):
    from fr_eval.bench import command as bench

    assert bench.main(["--quick", "--out", str(tmp_path), "--device", "cpu"]) == 0
    report = json.loads((tmp_path / "bench.json").read_text())
    assert {"machine", "end_to_end", "throughput", "memory", "scaling"} <= set(report)
    assert report["machine"]["threads"] >= 1 and report["machine"]["torch"]
    stages = report["end_to_end"][0]
    assert all(math.isfinite(stages[f"{k}_ms"]) for k in ("detect", "grid", "refine", "cues", "total"))
    assert report["throughput"][0]["images_per_s"] > 0
    assert report["memory"] and report["memory"][0]["ok"]
    assert (tmp_path / "bench.md").read_text().startswith("# fR speed benchmark")
    assert (tmp_path / "scaling.png").stat().st_size > 0
    lines = [json.loads(x) for x in (tmp_path / "bench.jsonl").read_text().splitlines()]
    assert {"end_to_end", "throughput", "parallel", "profile", "outside_search"} <= {x["section"] for x in lines}
    outside = report["outside_search"][0]  # work outside the search, per image
    assert outside["device"] == "cpu" and outside["ms_per_image"] > 0 and "outside the search" in \
        (tmp_path / "bench.md").read_text()
    assert {(r["kind"], r["count"]) for r in report["parallel"]} == {("threads", 1), ("threads", 2),
                                                                     ("workers", 1), ("workers", 2)}
    assert report["profiles"] and (tmp_path / report["profiles"][0]["file"]).read_text()
    assert (tmp_path / "throughput.png").stat().st_size > 0
    assert {(r["mode"], r["distortion"]) for r in report["distortion"]} == {("fast", "pinhole"), ("fast", "division")}
    # A run cut short leaves its rows: --from-jsonl rebuilds the report from them (same tables).
    rebuilt = tmp_path / "rebuilt"
    assert bench.main(["--from-jsonl", str(tmp_path / "bench.jsonl"), "--out", str(rebuilt)]) == 0
    again = json.loads((rebuilt / "bench.json").read_text())
    assert again["throughput"] == report["throughput"] and again["parallel"] == report["parallel"]
    assert again["machine"]["cpu"] == report["machine"]["cpu"] and again["command"] == report["command"]
    table = [line for line in (tmp_path / "bench.md").read_text().splitlines() if line.startswith("| cpu | fast")]
    assert table and all(line in (rebuilt / "bench.md").read_text() for line in table)
    # --sections: only what is asked for
    only = tmp_path / "only"
    assert bench.main(["--quick", "--out", str(only), "--device", "cpu", "--sections", "scaling",
                       "--no-progress"]) == 0
    part = json.loads((only / "bench.json").read_text())
    assert part["scaling"] and not part["throughput"] and not part["end_to_end"] and not part["parallel"]
    # The accelerator section's code path, run on a second CPU device name (CI has no GPU)
    device = tmp_path / "device"
    assert bench.main(["--quick", "--out", str(device), "--device", "cpu:0", "--sections", "device",
                       "--no-progress"]) == 0
    part = json.loads((device / "bench.json").read_text())
    assert {r["device"] for r in part["throughput"]} == {"cpu:0"} and part["grid_kernel"][0]["deviations_per_s"] > 0
    assert part["outside_search"] and part["profiles"] and "Grid kernel alone" in (device / "bench.md").read_text()
    with pytest.raises(ValueError, match="--sections"):
        bench.main(["--quick", "--out", str(only), "--device", "cpu", "--sections", "everything"])


def test_refinement_closed_form_gradient_matches_autograd():
    from fr_torch.core.search.refine import objective_and_grad
    features = _features([_scene(0), _scene(1, hfov=90.0, n_per_family=40)], torch.float64)
    model = MixtureLikelihood()
    batch = features.weight.shape[0]
    lower = torch.tensor([-45.0, -35.0, -15.0, math.log(150.0)], dtype=torch.float64).expand(batch, 1, 4)
    span = torch.tensor([90.0, 70.0, 30.0, math.log(950.0 / 150.0)], dtype=torch.float64).expand(batch, 1, 4)
    u = torch.rand(batch, 4, 4, dtype=torch.float64, generator=torch.Generator().manual_seed(0)).requires_grad_(True)
    weight = torch.rand(batch, 1, dtype=torch.float64, generator=torch.Generator().manual_seed(1))
    params = lower + u * span  # the refinement's coordinates: [pan, pitch, roll, log f]
    objective = model.objective(features, fast_rotations(params), params[..., 3].exp())
    (objective * weight).sum().backward()
    value, grad = objective_and_grad(model, features, lower, span, u.detach(), weight)
    assert torch.allclose(value, objective.detach(), rtol=1e-12)
    assert torch.allclose(grad, u.grad, rtol=1e-9, atol=1e-9 * u.grad.abs().max())


def test_closed_form_refinement_gradient_matches_autograd_with_focal_prior():
    """search_refine.objective_and_grad (the refinement's gradient, no autograd) = autograd of the full
    objective, focal prior included."""
    from fr_torch.core.search.refine import objective_and_grad

    rng = np.random.default_rng(5)
    features = _features([_scene(3), _scene(4, n_per_family=20)], torch.float64)
    params = replace(LikelihoodParams.from_config("b"), focal_prior_weight=0.3)
    model = MixtureLikelihood(params)
    lower = torch.tensor([[[-45.0, -40.0, -30.0, math.log(200.0)]]] * 2, dtype=torch.float64)
    span = torch.tensor([[[90.0, 80.0, 60.0, math.log(1100.0 / 200.0)]]] * 2, dtype=torch.float64)
    u = torch.tensor(rng.uniform(0.2, 0.8, (2, 3, 4)), requires_grad=True)
    grad_out = torch.tensor(rng.uniform(-1, 1, (2, 3)), dtype=torch.float64)
    p = lower + u * span
    objective = model.objective(features, fast_rotations(p), p[..., 3].exp())
    (expected,) = torch.autograd.grad((grad_out * objective).sum(), [u])
    value, grad = objective_and_grad(model, features, lower, span, u.detach(), grad_out)
    assert torch.allclose(value, objective.detach(), rtol=1e-12)
    assert torch.allclose(grad, expected, rtol=1e-8, atol=1e-8 * expected.abs().max())


def test_subdivision_passes_improve_starts_stay_in_box_and_batch_equals_single():
    """Coarse-to-fine passes never lower a start's score, keep points in the box (a known focal
    fixed), move each start on its own, and with 0 passes return the starts unchanged."""
    config = SearchConfig.from_config(grid_points_per_dim=4, top_l=2, grid_passes=3)
    segs = [_scene(11, n_per_family=25), _scene(12, 95.0, -10.0, 20.0, 2.0, 20)]
    features = _features(segs, torch.float64)
    long_side = torch.tensor([640.0, 640.0], dtype=torch.float64)
    model = MixtureLikelihood(_data_only())
    hyp = grid_hypotheses(config, long_side)
    starts, scores = search_grid.select_starts(config, score_grid(model, features, hyp, 1 << 30), hyp)
    lower, upper = search_grid.parameter_box(config, long_side, None)
    moved, moved_scores = search_passes.subdivide_starts(model, features, starts, scores, config, lower, upper)
    assert moved.shape == starts.shape and (moved_scores >= scores).all() and (moved_scores > scores).any()
    assert (moved >= lower[:, None] - 1e-9).all() and (moved <= upper[:, None] + 1e-9).all()
    rescored = score_grid(model, features, moved, 1 << 30)
    assert torch.allclose(rescored, moved_scores, rtol=1e-12)  # the scores are those of the returned points
    one, one_scores = search_passes.subdivide_starts(model, _features(segs[1:], torch.float64), starts[1:], scores[1:],
                                              config, lower[1:], upper[1:])
    assert torch.allclose(one, moved[1:], rtol=1e-12) and torch.allclose(one_scores, moved_scores[1:], rtol=1e-12)
    same, same_scores = search_passes.subdivide_starts(model, features, starts, scores, replace(config, grid_passes=0),
                                                lower, upper)
    assert same is starts and same_scores is scores
    known = torch.tensor([500.0, 300.0], dtype=torch.float64)
    k_lower, k_upper = search_grid.parameter_box(config, long_side, known)
    k_hyp = grid_hypotheses(config, long_side, known)
    k_starts, k_scores = search_grid.select_starts(config, score_grid(model, features, k_hyp, 1 << 30), k_hyp)
    fixed, _ = search_passes.subdivide_starts(model, features, k_starts, k_scores, config, k_lower, k_upper)
    assert torch.allclose(fixed[..., 3], known[:, None].expand(-1, 2), rtol=1e-12)


def test_search_angles_invert_fast_rotations():
    """angles_from_search_rotation is the inverse of fast_rotations (pan folded to [-45, 45))."""
    rng = np.random.default_rng(3)
    angles = torch.tensor(np.c_[rng.uniform(-44, 44, 30), rng.uniform(-60, 60, 30), rng.uniform(-80, 80, 30)])
    assert torch.allclose(param_rows.angles_from_search_rotation(fast_rotations(angles)), angles, atol=1e-10)


def test_focal_ridge_rotations_keep_the_vertical_vp_and_stay_rotations():
    """Along the ridge the vertical VP keeps its image position at every focal length, the result
    is a proper rotation, and a ratio of 1 returns the input rotation."""
    angles = torch.tensor([[20.0, 12.0, 4.0], [-30.0, -25.0, -8.0], [5.0, 0.0, 0.0]], dtype=torch.float64)
    rotation = fast_rotations(angles)
    ratio = torch.tensor([[0.5, 1.0, 2.0]] * 3, dtype=torch.float64)
    ridge = search_passes._focal_ridge_rotations(rotation, ratio)  # (3, 3 ratios, 3, 3)
    eye = torch.eye(3, dtype=torch.float64)
    assert torch.allclose(ridge @ ridge.transpose(-1, -2), eye.expand_as(ridge), atol=1e-12)
    assert torch.allclose(torch.linalg.det(ridge), torch.ones(3, 3, dtype=torch.float64), atol=1e-12)
    assert torch.allclose(ridge[:, 1], rotation, atol=1e-12)
    focal = 400.0
    for j in range(3):
        for i in range(2):  # images 0, 1: finite vertical VP at f * (x, y) / z
            before = focal * rotation[i, :2, 1] / rotation[i, 2, 1]
            after = focal * ratio[i, j] * ridge[i, j, :2, 1] / ridge[i, j, 2, 1]
            assert torch.allclose(after, before, rtol=1e-10)
        assert torch.allclose(ridge[2, j, :, 1], rotation[2, :, 1], atol=1e-12)  # VP at infinity stays


def test_focal_sweep_finds_the_focal_the_grid_traded_for_pitch():
    """A start on the wrong part of the focal-pitch ridge (same vertical VP, wrong f and pitch)
    gains a second start near the true focal; the inputs come back first, unchanged; a start the
    sweep cannot improve is copied; a batch equals images one by one; a known focal and
    focal_sweep_points = 0 return the inputs."""
    config = SearchConfig.from_config(top_l=1)
    true_focal = focal_from_hfov(110.0, 640)
    segs = [_scene(21, 110.0, 10.0, -15.0, 3.0), _scene(22, 60.0, -20.0, 8.0, -2.0)]
    features = _features(segs, torch.float64)
    long_side = torch.tensor([640.0, 640.0], dtype=torch.float64)
    lower, upper = search_grid.parameter_box(config, long_side, None)
    # Image 0's start: f 1.6x too long, pitch moved so that the vertical VP stays where it is.
    wrong = search_passes._focal_ridge_rotations(fast_rotations(torch.tensor([[10.0, -15.0, 3.0]], dtype=torch.float64)),
                                          torch.tensor([[1.6]], dtype=torch.float64))[0, 0]
    start0 = torch.cat([param_rows.angles_from_search_rotation(wrong), torch.tensor([1.6 * true_focal])])
    start1 = torch.tensor([-20.0, 8.0, -2.0, focal_from_hfov(60.0, 640)], dtype=torch.float64)
    starts = torch.stack([start0, start1])[:, None]
    model = MixtureLikelihood(_data_only())
    scores = score_grid(model, features, starts, 1 << 30)
    out, out_scores = search_passes.sweep_focal(model, features, starts, scores, config, lower, upper)
    assert out.shape == (2, 2, 4) and out_scores.shape == (2, 2)
    assert torch.equal(out[:, :1], starts) and torch.equal(out_scores[:, :1], scores)
    assert (out_scores[:, 1] >= scores[:, 0]).all() and out_scores[0, 1] > scores[0, 0]
    assert abs(out[0, 1, 3].item() / true_focal - 1) < 0.1  # within the sweep's spacing (12 % in f)
    assert torch.allclose(score_grid(model, features, out, 1 << 30), out_scores, rtol=1e-12)
    assert (out >= lower[:, None] - 1e-9).all() and (out <= upper[:, None] + 1e-9).all()
    if not out_scores[1, 1] > scores[1, 0]:  # the true camera: nothing better on the ridge, a copy
        assert torch.equal(out[1, 1], starts[1, 0])
    one, one_scores = search_passes.sweep_focal(model, _features(segs[1:], torch.float64), starts[1:], scores[1:],
                                         config, lower[1:], upper[1:])
    assert torch.allclose(one, out[1:], rtol=1e-12) and torch.allclose(one_scores, out_scores[1:], rtol=1e-12)
    k_lower, k_upper = search_grid.parameter_box(config, long_side, starts[:, 0, 3])
    assert search_passes.sweep_focal(model, features, starts, scores, config, k_lower, k_upper)[0] is starts
    off = replace(config, focal_sweep_points=0)
    assert search_passes.sweep_focal(model, features, starts, scores, off, lower, upper)[0] is starts


@pytest.mark.parametrize("dtype,rtol", [(torch.float64, 1e-12), (torch.float32, 1e-5)])
def test_grid_shared_vertical_vp_equals_full_scoring(dtype, rtol, monkeypatch):
    """The grid's runs of k pan values share the vertical VP: scoring it once per run gives the
    scores of scoring every hypothesis in full, whatever the chunking."""
    config = SearchConfig.from_config(grid_points_per_dim=4)
    segs = [_scene(13, n_per_family=25), _scene(14, 95.0, -10.0, 20.0, 2.0, 20)]
    features = _features(segs, dtype)
    hyp = grid_hypotheses(config, torch.tensor([640.0, 640.0], dtype=torch.float64))
    assert torch.equal(hyp[:, :4, 1:], hyp[:, :1, 1:].expand(-1, 4, -1))  # pan varies fastest
    model = MixtureLikelihood(LikelihoodParams.from_config("b"))
    full = score_grid(model, features, hyp, 1 << 30)
    assert torch.allclose(score_grid(model, features, hyp, 1 << 30, vertical_block=4), full, rtol=rtol)
    monkeypatch.setattr(search_grid, "CPU_CHUNK_ELEMENTS", 500)  # chunks of whole runs, images one by one
    assert torch.allclose(score_grid(model, features, hyp, 1 << 30, vertical_block=4), full, rtol=rtol)
    odd = hyp[:, :6]  # 6 is not a multiple of 4: scored in full
    assert torch.allclose(score_grid(model, features, odd, 1 << 30, vertical_block=4), full[:, :6], rtol=rtol)


@pytest.mark.parametrize("bad", [float("nan"), float("inf"), 1e30])
def test_refinement_stays_finite_and_in_the_box_under_a_bad_gradient(monkeypatch, bad):
    """A NaN, infinite or absurdly large gradient (e.g. measure e's asin' where |s|/|n| rounds to 1)
    never makes a refined parameter non-finite or moves it out of the box: the refinement makes the
    gradient finite and bounded before Adam sees it."""
    config = SearchConfig.from_config(grid_points_per_dim=3)
    features = _features([_scene(21, n_per_family=20)], torch.float32)
    width = torch.tensor([640.0], dtype=torch.float64)
    hyp = grid_hypotheses(config, width)
    lower, upper = search_grid.parameter_box(config, width, None)
    real = search_refine.objective_and_grad

    def spoiled(*args, **kwargs):
        objective, grad = real(*args, **kwargs)
        grad = grad.clone()
        grad[..., 0] = bad  # pan: always the bad value
        grad[..., 3] *= 1e30 if bad == 1e30 else 1.0  # focal: huge too, but of the right sign
        return objective, grad

    monkeypatch.setattr(search_refine, "objective_and_grad", spoiled)
    params, objective = refine(MixtureLikelihood(), features, hyp[:, :3], lower, upper, 20, fast=False)
    assert torch.isfinite(params).all() and torch.isfinite(objective).all()
    assert (params >= lower[:, None].to(params) - 1e-4).all() and (params <= upper[:, None].to(params) + 1e-3).all()


def test_refinement_adam_is_torch_adam_and_the_same_bits_in_any_layout():
    """search_refine.Adam = torch.optim.Adam stepped by ExponentialLR (to float rounding), and an entry's
    update does not depend on where it sits (torch's fused kernel rounds body and tail differently)."""
    torch.manual_seed(0)
    grads = [torch.randn(3, 8, 4) * 10 ** torch.randint(-3, 3, ()).item() for _ in range(30)]
    ours = torch.rand(3, 8, 4)
    shifted = torch.cat([torch.rand(1, 8, 4), ours.clone()])  # the same entries one image further on
    theirs = ours.clone().requires_grad_(True)
    steps = search_refine.adam_schedule(0.03, 0.03 * 0.8 ** (len(grads) - 1), len(grads), (0.5, 0.9))  # x0.8 a step
    adam = search_refine.Adam(ours, steps, betas=(0.5, 0.9))
    adam_shifted = search_refine.Adam(shifted, steps, betas=(0.5, 0.9))
    reference = torch.optim.Adam([theirs], lr=0.03, betas=(0.5, 0.9), foreach=False)
    schedule = torch.optim.lr_scheduler.ExponentialLR(reference, 0.8)
    for grad in grads:
        adam.step(grad)
        adam_shifted.step(torch.cat([torch.randn(1, 8, 4), grad]))
        theirs.grad = grad.clone()
        reference.step()
        schedule.step()
        assert torch.allclose(ours, theirs.detach(), rtol=1e-5, atol=1e-6)
        assert torch.equal(ours, shifted[1:])


def test_calibrating_does_not_import_the_compiler():
    """torch.optim's first optimiser imports torch._dynamo (1-2 s); the refinement must not pay it.
    A fresh process (:func:`tests.conftest.fresh_process_records`: Fast-fR on photos, extra families
    and fR on a scene) never imported it."""
    from tests.conftest import fresh_process_records

    fresh = fresh_process_records("default")
    assert fresh["fr_ok"][0], fresh["fr_ok"][1]
    assert fresh["dynamo_imported"] is False


def test_compile_was_removed_with_a_one_line_reason(capsys):
    """``--compile`` / ``compile_search`` are gone (the fused CPU kernels replaced them, with the
    default search's bits): both fail with one line that says so, for a release's time."""
    from fr_torch.cli.main import main
    from fr_torch.errors import FRInputError

    with pytest.raises(FRInputError, match="fused CPU kernels"):
        SearchConfig.from_config(compile_search=True)
    assert main(["calibrate", "--compile", "examples/room.png"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--compile" in err[0] and "fused CPU kernels" in err[0], err
