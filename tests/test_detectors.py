"""Extra line-segment detectors: MCMLSD (fr_torch.detectors.mcmlsd) and the ONNX adapter."""
from __future__ import annotations

import math

import numpy as np
import pytest

from fr_torch.core.geometry.conventions import rotation_from_angles
from fr_torch.detectors.mcmlsd import (
    PARAMS_PATH,
    MCMLSDDetector,
    _posterior_on,
    _viterbi,
)
from fr_torch.detectors.onnx_detector import OnnxLineDetector
from fr_torch.detectors.registry import available_detectors, get_detector
from fr_torch.synthetic import camera_matrix, render_manhattan_room

FOCAL, WIDTH, HEIGHT = 500.0, 640, 480


@pytest.fixture(scope="module")
def room():
    rotation = rotation_from_angles(np.float64(20.0), np.float64(-8.0), np.float64(4.0)).numpy()
    image = render_manhattan_room(FOCAL, rotation, WIDTH, HEIGHT, seed=3)
    return image, camera_matrix(FOCAL, WIDTH, HEIGHT) @ rotation  # columns: the 3 true VPs


@pytest.fixture(scope="module")
def mcmlsd_result(room):
    image, _ = room
    return MCMLSDDetector().detect(image)


def vp_consistent_fraction(segments: np.ndarray, vps: np.ndarray, tol_deg: float = 2.0) -> float:
    """Length fraction of segments within tol of the line from their midpoint to some true VP."""
    p = np.c_[segments[:, :2], np.ones(len(segments))]
    q = np.c_[segments[:, 2:], np.ones(len(segments))]
    mid = (p + q) / 2
    seg_dir = (q - p)[:, :2]
    best = np.full(len(segments), np.inf)
    for i in range(3):
        line = np.cross(mid, vps[:, i])                  # homogeneous line through midpoint and VP
        line_dir = np.stack([line[:, 1], -line[:, 0]], 1)  # its direction
        cos = np.abs((seg_dir * line_dir).sum(1)) / (np.linalg.norm(seg_dir, axis=1) * np.linalg.norm(line_dir, axis=1) + 1e-12)
        best = np.minimum(best, np.degrees(np.arccos(np.clip(cos, 0, 1))))
    length = np.linalg.norm(seg_dir, axis=1)
    return float(length[best <= tol_deg].sum() / length.sum())


# ---------------------------------------------------------------------------- MCMLSD

def test_registered():
    names = available_detectors()
    assert "mcmlsd" in names and "onnx" in names
    assert isinstance(get_detector("mcmlsd"), MCMLSDDetector)


def test_params_shipped_and_small():
    assert PARAMS_PATH.is_file() and PARAMS_PATH.stat().st_size < 2_000_000


def test_mcmlsd_output_conventions(room, mcmlsd_result):
    image, _ = room
    segments, scores = mcmlsd_result
    assert segments.dtype == np.float64 and segments.ndim == 2 and segments.shape[1] == 4
    assert scores.shape == (len(segments),) and np.all(np.diff(scores) <= 1e-9)  # best first
    assert len(segments) >= 30
    assert np.isfinite(segments).all()
    # 0-based pixel centres inside the image
    assert segments[:, [0, 2]].min() >= -1.0 and segments[:, [0, 2]].max() <= WIDTH
    assert segments[:, [1, 3]].min() >= -1.0 and segments[:, [1, 3]].max() <= HEIGHT
    length = np.hypot(segments[:, 2] - segments[:, 0], segments[:, 3] - segments[:, 1])
    assert length.min() >= MCMLSDDetector().config.min_length - 1e-6
    assert length.max() > 150  # long straight segments, not fragments
    # __call__ == detect()[0]
    assert np.array_equal(MCMLSDDetector()(image), segments)


def test_mcmlsd_segments_point_at_true_vanishing_points(room, mcmlsd_result):
    _, vps = room
    segments, _ = mcmlsd_result
    fraction = vp_consistent_fraction(segments, vps)
    assert fraction >= 0.7, fraction


def test_vp_metric_can_fail(room, mcmlsd_result):
    """The consistency check rejects segments pointing elsewhere (guards against a vacuous test)."""
    _, vps = room
    segments, _ = mcmlsd_result
    rng = np.random.default_rng(0)
    centre = (segments[:, :2] + segments[:, 2:]) / 2
    half = np.linalg.norm(segments[:, 2:] - segments[:, :2], axis=1, keepdims=True) / 2
    angle = rng.uniform(0, math.pi, (len(segments), 1))
    offset = half * np.c_[np.cos(angle), np.sin(angle)]
    random_segments = np.c_[centre - offset, centre + offset]
    assert vp_consistent_fraction(random_segments, vps) < 0.3


def test_mcmlsd_localisation_matches_lsd(room, mcmlsd_result):
    """Long MCMLSD segments lie on image edges: LSD finds collinear segments nearby."""
    image, _ = room
    segments, _ = mcmlsd_result
    lsd = get_detector("lsd")(image)
    long = segments[np.hypot(*(segments[:, 2:] - segments[:, :2]).T) > 60]
    assert len(long) >= 10
    mids = (lsd[:, :2] + lsd[:, 2:]) / 2
    close = 0
    for s in long:
        d = s[2:] - s[:2]
        n = np.array([-d[1], d[0]]) / np.linalg.norm(d)
        dist = np.abs((mids - s[:2]) @ n)
        t = (mids - s[:2]) @ d / (d @ d)
        close += np.any((dist < 1.5) & (t > 0) & (t < 1))
    assert close / len(long) > 0.8


def test_mcmlsd_blank_and_tiny_images():
    detector = MCMLSDDetector()
    for image in (np.zeros((480, 640), np.uint8), np.full((100, 80), 200, np.uint8), np.zeros((4, 4), np.uint8)):
        out = detector(image)
        assert out.shape == (0, 4) and out.dtype == np.float64


def test_mcmlsd_single_line_endpoints():
    image = np.full((120, 160), 40, np.uint8)
    image[60:, 30:131] = 200  # horizontal step edge between rows 59 and 60, x in [30, 130]
    segments, _ = MCMLSDDetector().detect(image)
    assert len(segments) >= 1
    best = segments[0]
    xs, ys = sorted([best[0], best[2]]), [best[1], best[3]]
    assert abs(ys[0] - 59.5) < 0.75 and abs(ys[1] - 59.5) < 0.75
    assert abs(xs[0] - 30) < 4 and abs(xs[1] - 130) < 4


def test_hmm_decoders_agree_with_brute_force():
    rng = np.random.default_rng(1)
    steps, lengths = 7, np.array([7, 5, 2])
    log_e = rng.normal(size=(steps, 3, 2))
    a = np.array([[0.8, 0.2], [0.3, 0.7]])
    pi = np.array([0.6, 0.4])
    path = _viterbi(log_e.copy(), lengths, np.log(a), np.log(pi))
    post = _posterior_on(log_e.copy(), lengths, a, pi)
    import itertools
    for j, n in enumerate(lengths):
        scores = {}
        for states in itertools.product((0, 1), repeat=int(n)):
            lp = math.log(pi[states[0]]) + log_e[0, j, states[0]]
            for k in range(1, n):
                lp += math.log(a[states[k - 1], states[k]]) + log_e[k, j, states[k]]
            scores[states] = lp
        best = max(scores, key=scores.get)
        assert tuple(path[:n, j].astype(int)) == best
        assert not path[n:, j].any()
        z = np.logaddexp.reduce(list(scores.values()))
        for k in range(n):
            marg = np.exp(np.logaddexp.reduce([v for s, v in scores.items() if s[k] == 1]) - z)
            assert abs(post[k, j] - marg) < 1e-9


# ---------------------------------------------------------------------------- ONNX adapter

def _tiny_line_model(path, w_in=64, h_in=48, channels=1):
    """ONNX model: fixed segments (input pixels) + scores scaled by 2 * mean(input)."""
    onnx = pytest.importorskip("onnx")
    from onnx import TensorProto, helper, numpy_helper

    segs = np.array([[[0, 0, w_in - 1, 0], [10, 5, 10, 40], [1, 2, 3, 4]]], np.float32)
    base = np.array([[0.9, 0.2, 0.7]], np.float32)
    graph = helper.make_graph(
        [helper.make_node("Identity", ["seg_const"], ["segments"]),
         helper.make_node("ReduceMean", ["image"], ["m"], keepdims=0),
         helper.make_node("Mul", ["m", "two"], ["m2"]),
         helper.make_node("Mul", ["base", "m2"], ["scores"])],
        "tiny_lines",
        [helper.make_tensor_value_info("image", TensorProto.FLOAT, [1, channels, h_in, w_in])],
        [helper.make_tensor_value_info("segments", TensorProto.FLOAT, [1, 3, 4]),
         helper.make_tensor_value_info("scores", TensorProto.FLOAT, [1, 3])],
        [numpy_helper.from_array(segs, "seg_const"), numpy_helper.from_array(base, "base"),
         numpy_helper.from_array(np.array(2.0, np.float32), "two")])
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 13)])
    model.ir_version = 8
    onnx.checker.check_model(model)
    onnx.save(model, str(path))
    return segs[0].astype(np.float64), base[0].astype(np.float64)


def test_onnx_adapter_end_to_end(tmp_path):
    pytest.importorskip("onnxruntime")
    model_path = tmp_path / "tiny.onnx"
    segs, base = _tiny_line_model(model_path)
    detector = get_detector("onnx", model_path=model_path, score_threshold=0.5)
    assert isinstance(detector, OnnxLineDetector) and detector.input_size == (64, 48)
    image = np.full((96, 128), 255 // 2, np.uint8)  # 2x the model input; mean ~0.5 -> scores ~ base
    segments, scores = detector.detect(image)
    assert segments.shape == (2, 4) and segments.dtype == np.float64
    np.testing.assert_allclose(scores, base[[0, 2]] * 2 * (127 / 255), rtol=1e-5)
    expected = (segs[[0, 2]] + 0.5) * 2 - 0.5  # pixel-centre rescaling to the original image
    np.testing.assert_allclose(segments, expected, atol=1e-5)
    # threshold applies to the model's scores (the image mean drives them)
    assert len(detector(np.zeros((96, 128), np.uint8))) == 0
    assert len(OnnxLineDetector(model_path)(image)) == 3  # no threshold, sorted by score
    # BGR colour input is accepted for a grey model
    assert OnnxLineDetector(model_path, score_threshold=0.5)(np.full((96, 128, 3), 127, np.uint8)).shape == (2, 4)


def test_onnx_adapter_rgb_model_and_errors(tmp_path):
    pytest.importorskip("onnxruntime")
    model_path = tmp_path / "tiny_rgb.onnx"
    _tiny_line_model(model_path, w_in=32, h_in=32, channels=3)
    detector = OnnxLineDetector(model_path, mean=0.5, std=0.5)  # input in [-1, 1]
    assert detector.channels == 3
    x = detector.preprocess(np.full((64, 64, 3), 255, np.uint8))
    assert x.shape == (1, 3, 32, 32) and np.allclose(x, 1.0)
    with pytest.raises(FileNotFoundError):
        OnnxLineDetector(tmp_path / "missing.onnx")
    with pytest.raises(ValueError):
        OnnxLineDetector()
