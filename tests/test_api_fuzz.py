"""Hostile and odd input to the Python API (issue 39), beside the CLI's (tests/test_fuzz.py): an
argument of the wrong form is one FRInputError naming it; a bad value fails only its image; no
record field is ever NaN / inf; a plug-in import path runs nothing that did not declare itself a
plug-in; options reach only the factories that take them; the reliability model predicts only for
the setting it was trained on."""
from __future__ import annotations

import math
import textwrap
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import pandas as pd
import pytest
import torch

from fr_torch import FREstimator, FRInputError
from fr_torch.cli.main import main
from fr_torch.core.geometry.camera import Camera
from fr_torch.core.geometry.conventions import rotation_from_angles
from fr_torch.core.likelihood.mixture import LikelihoodParams
from fr_torch.core.reliability.model import ReliabilityModel
from fr_torch.core.reliability.sanity import finite_record
from fr_torch.core.result import CalibrationResult
from fr_torch.detectors.lsd import LSDDetector
from fr_torch.detectors.registry import get_detector
from fr_torch.plugins.interface import get_calibrator
from fr_torch.registry import Registry
from fr_torch.synthetic import random_rotation, render_manhattan_room, synthetic_segments

SIZE = (640, 480)


def _scene(seed: int, focal: float = 500.0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    rotation = random_rotation(rng, pan=(-30, 30), pitch=(-20, 20), roll=(-8, 8))
    return synthetic_segments(focal, rotation, width=SIZE[0], height=SIZE[1], seed=seed)[0]


@pytest.fixture(scope="module")
def estimator() -> FREstimator:
    return FREstimator(mode="fast")


@pytest.fixture(scope="module")
def segments() -> np.ndarray:
    return _scene(0)


@pytest.fixture(scope="module")
def room() -> np.ndarray:
    return render_manhattan_room(260.0, rotation_from_angles(12.0, 6.0, 4.0).numpy(), 320, 240, seed=3)


def _non_finite(value, path="record") -> list[str]:
    """Paths of every NaN / inf number inside a JSON-like value."""
    if isinstance(value, dict):
        return [p for k, v in value.items() for p in _non_finite(v, f"{path}.{k}")]
    if isinstance(value, (list, tuple)):
        return [p for i, v in enumerate(value) for p in _non_finite(v, f"{path}[{i}]")]
    if isinstance(value, float) and not math.isfinite(value):
        return [path]
    return []


def _assert_finite(result: CalibrationResult) -> None:
    assert not _non_finite(result.to_json(include_segments=True)), _non_finite(result.to_json(True))


def _one_line_error(call, match: str) -> str:
    with pytest.raises(FRInputError, match=match) as info:
        call()
    message = str(info.value)
    assert "\n" not in message and message
    return message


# --------------------------------------------------------------------------- argument forms

@pytest.mark.parametrize("sizes, count, match", [
    ([640, 480], 1, r"image_sizes: expected one \(width, height\) pair .*flat"),
    ([640, 480], 2, r"image_sizes: .*flat"),
    ([("640", "480")], 1, r"image_sizes\[0\]: expected one \(width, height\) pair of numbers"),
    ([(640,)], 1, r"image_sizes\[0\]"),
    ([(640, 480, 3)], 1, r"image_sizes\[0\]"),
    ([None], 1, r"image_sizes\[0\]"),
    ([(True, 480)], 1, r"image_sizes\[0\]"),
    (None, 1, r"image_sizes: expected"),
    (640, 1, r"image_sizes: expected"),
    ("640x480", 1, r"image_sizes: expected"),
    ([(640, 480)] * 2, 1, r"image_sizes: expected one \(width, height\) pair per image \(1\), got 2"),
    (np.array([640, 480]), 1, r"image_sizes: .*flat"),
])
def test_image_sizes_of_the_wrong_form(estimator, segments, sizes, count, match):
    _one_line_error(lambda: estimator.calibrate_segments([segments] * count, sizes), match)


@pytest.mark.parametrize("make, match", [
    (lambda s: s, r"segments: .*one image's"),                              # one (N, 4) array, not wrapped
    (lambda s: torch.from_numpy(s), r"segments: .*one image's"),            # one (N, 4) tensor
    (lambda s: s.tolist(), r"segments: .*single segment"),                  # a list of 4-number rows
    (lambda s: "abc", r"segments: expected a sequence"),
    (lambda s: None, r"segments: expected a sequence"),
    (lambda s: 5, r"segments: expected a sequence"),
    (lambda s: {"a": s}, r"segments: expected a sequence"),
])
def test_segments_of_the_wrong_form(estimator, segments, make, match):
    _one_line_error(lambda: estimator.calibrate_segments(make(segments), [SIZE]), match)


@pytest.mark.parametrize("kwargs, match", [
    ({"names": "photo"}, r"names: expected a sequence of one name per image"),
    ({"names": ["a", "b"]}, r"names: expected one name per image \(1\), got 2"),
    ({"focal_px": "500"}, r"focal_px: expected None, a number"),
    ({"focal_px": True}, r"focal_px: expected"),
    ({"focal_px": [500.0, 400.0]}, r"focal_px: expected one value per image \(1\), got 2"),
    ({"focal_px": [[500.0]]}, r"focal_px\[0\]: expected"),
    ({"focal_px": ["500"]}, r"focal_px\[0\]: expected"),
    ({"principal_point": "320,240"}, r"principal_point: expected None, an \(x, y\) pair"),
    ({"principal_point": (320.0,)}, r"principal_point"),
    ({"principal_point": [(1, 2, 3)]}, r"principal_point\[0\]: expected"),
    ({"principal_point": [("320", "240")]}, r"principal_point\[0\]: expected"),
    ({"principal_point": [(320, 240), (320, 240)]}, r"principal_point: expected one value per image"),
])
def test_per_image_arguments_of_the_wrong_form(estimator, segments, kwargs, match):
    _one_line_error(lambda: estimator.calibrate_segments([segments], [SIZE], **kwargs), match)


def test_accepted_forms_agree(estimator):
    """Lists, tuples, arrays, tensors, nested lists, ragged counts and numpy / torch scalars all
    give the answer of the plain form."""
    a, b = _scene(1), _scene(2)[:300]
    reference = estimator.calibrate_segments([a, b], [SIZE, SIZE], focal_px=[None, 450.0],
                                             principal_point=[None, (330.0, 250.0)])
    results = estimator.calibrate_segments(
        (torch.from_numpy(a), b.astype(np.float32).tolist()), torch.tensor([SIZE, SIZE]), names=[Path("a.png"), "b"],
        focal_px=(None, torch.tensor(450.0)), principal_point=[None, np.array([330.0, 250.0])])
    for got, want in zip(results, reference):
        assert got.ok and want.ok and abs(got.focal_px - want.focal_px) < 1e-3 * want.focal_px
        _assert_finite(got)
    assert results[0].image == "a.png"
    one_focal = estimator.calibrate_segments(np.stack([a[:200], b[:200]]), np.array([SIZE, SIZE]),
                                             focal_px=np.float32(450.0), principal_point=np.array([330.0, 250.0]))
    assert [r.focal_px for r in one_focal] == pytest.approx([450.0, 450.0])


# --------------------------------------------------------------------------- absurd coordinates

_SOLO: dict = {}


@pytest.mark.parametrize("big", [1e20, 1e30, 1e300, -1e30, 1e5])
@pytest.mark.parametrize("apply_filter", [True, False])
def test_huge_coordinates_are_dropped_with_a_reason(estimator, segments, big, apply_filter):
    """One row far outside the image among ordinary ones is dropped (the count in the reason), the
    record stays finite, and the other image of the batch gets its solo answer."""
    other = _scene(5)
    if apply_filter not in _SOLO:
        [_SOLO[apply_filter]] = estimator.calibrate_segments([other], [SIZE], apply_filter=apply_filter)
    solo = _SOLO[apply_filter]
    hostile = segments.copy()
    hostile[3] = [big, 10.0, 20.0, big]
    bad, good = estimator.calibrate_segments([hostile, other], [SIZE, SIZE], apply_filter=apply_filter)
    assert bad.ok and not bad.reliable and "1 segment(s) with non-finite coordinates or beyond 10 image sizes" \
        in bad.reason
    _assert_finite(bad)
    assert good.focal_px == pytest.approx(solo.focal_px, rel=1e-5) and good.reason == solo.reason
    _assert_finite(good)


@pytest.mark.parametrize("big", [1e20, 1e30, 1e300])
@pytest.mark.parametrize("apply_filter", [True, False])
def test_all_rows_huge_fail_that_image_only(estimator, segments, big, apply_filter):
    hostile = np.full_like(segments, big)
    hostile[:, 2] = big * np.linspace(1.0, 2.0, len(hostile))  # distinct, long segments
    bad, good = estimator.calibrate_segments([hostile, segments], [SIZE, SIZE], apply_filter=apply_filter)
    assert not bad.ok and good.ok
    assert "all" in bad.reason and "beyond 10 image sizes" in bad.reason
    _assert_finite(bad)
    _assert_finite(good)


def test_final_guard_removes_every_non_finite_field():
    camera = Camera(640, 480, 500.0, rotation=np.eye(3))
    result = CalibrationResult("x", 640, 480, ok=True, reliable=True, camera=camera, log_likelihood=1.0,
                               manhattan_fraction=math.nan, cues={"grid_entropy": math.nan, "min_family_segments": 9.0},
                               predicted_error={"roll_deg": math.inf, "tilt_deg": 1.0, "focal_pct": 2.0},
                               runtime_s={"total": math.nan, "grid": 0.1})
    finite_record(result)
    assert result.ok and not result.reliable and "non-finite" in result.reason
    assert result.manhattan_fraction is None and result.cues == {"min_family_segments": 9.0}
    assert result.predicted_error is None and result.runtime_s == {"grid": 0.1}
    _assert_finite(result)
    broken = CalibrationResult("y", 640, 480, ok=True, reliable=True, camera=Camera(640, 480, math.nan),
                               log_likelihood=math.nan)
    finite_record(broken)
    assert not broken.ok and not broken.reliable and broken.camera is None and broken.log_likelihood is None
    _assert_finite(broken)


# --------------------------------------------------------------------------- plug-in import paths

HOSTILE_PATHS = ["subprocess:getoutput[cmd=touch {marker}]", "subprocess:Popen[args=touch {marker}]",
                 "os:system[command=touch {marker}]", "builtins:eval[source=__import__('os').system('touch {marker}')]",
                 "shutil:rmtree[path={marker}]"]


@pytest.mark.parametrize("spec", HOSTILE_PATHS)
def test_import_paths_call_nothing_undeclared(tmp_path, spec):
    """Methods, detectors and datasets by import path: anything not declared a plug-in is refused
    before it is called."""
    marker = tmp_path / "ran"
    spec = spec.format(marker=marker)
    with pytest.raises(ValueError, match="is not a method plug-in.*nothing was called"):
        get_calibrator(spec)
    with pytest.raises(FRInputError, match="is not a detector plug-in"):
        get_detector(spec)
    with pytest.raises(FRInputError, match="is not a detector plug-in"):
        FREstimator(mode="fast", detector=spec)
    from fr_eval.datasets.registry import get_dataset_loader

    with pytest.raises(ValueError, match="is not a dataset plug-in"):
        get_dataset_loader(spec.split("[")[0])
    assert not marker.exists()


@pytest.fixture()
def plugin_modules(tmp_path, monkeypatch):
    """A module of plug-ins written the simplest ways, and a one-image dataset, importable."""
    (tmp_path / "i39_plugins.py").write_text(textwrap.dedent('''
        from fr_torch.core.geometry.camera import Camera
        from fr_torch.core.geometry.conventions import focal_from_hfov
        from fr_torch.plugins.interface import CameraEstimate
        from fr_torch.registry import plugin

        CALLS = []

        class FixedFov:
            name = "fixed-fov"

            def estimate(self, image, meta):
                return CameraEstimate(self.name, camera=Camera(meta.width, meta.height,
                                                               focal_from_hfov(60.0, meta.width)))

        class WithDevice(FixedFov):
            def __init__(self, device="cpu", hfov="60"):
                CALLS.append(("WithDevice", device, hfov))

        @plugin("method")
        def make_any(**options):
            CALLS.append(("make_any", options))
            return FixedFov()

        def undeclared(**options):
            CALLS.append(("undeclared", options))
            return FixedFov()

        class Lines:
            name = "lines"

            def __call__(self, gray):
                import numpy as np
                return np.array([[10.0, 10.0, 100.0, 12.0]])
    '''))
    image = tmp_path / "room.png"
    cv2.imwrite(str(image), render_manhattan_room(500.0, rotation_from_angles(15.0, 0.0, 4.0).numpy(), seed=1))
    (tmp_path / "i39_data.py").write_text(textwrap.dedent(f'''
        from pathlib import Path
        from fr_eval.datasets.registry import CalibrationSample
        from fr_torch.core.geometry.camera import Camera
        from fr_torch.core.geometry.conventions import rotation_from_angles
        from fr_torch.registry import plugin

        @plugin("dataset")
        def load(root=None, split="test", **kwargs):
            return [CalibrationSample("room.png", Path({str(image)!r}), 640, 480,
                                      Camera(640, 480, 500.0, rotation=rotation_from_angles(15.0, 0.0, 4.0).numpy()))]

        def undeclared(root=None, split="test", **kwargs):
            raise AssertionError("called")
    '''))
    monkeypatch.syspath_prepend(str(tmp_path))
    import importlib

    importlib.invalidate_caches()
    module = importlib.import_module("i39_plugins")
    module.CALLS.clear()
    return module


def test_options_reach_only_factories_that_take_them(plugin_modules):
    from fr_eval.protocols.run_eval import make_calibrator

    assert make_calibrator("i39_plugins:FixedFov", "cpu").name == "fixed-fov"  # no constructor arguments
    make_calibrator("i39_plugins:WithDevice[hfov=70]", "cpu")
    make_calibrator("i39_plugins:make_any[x=1]", "cpu")
    assert plugin_modules.CALLS == [("WithDevice", "cpu", "70"), ("make_any", {"x": "1", "device": "cpu"})]
    with pytest.raises(ValueError, match="takes no option 'x'"):
        make_calibrator("i39_plugins:FixedFov[x=1]", "cpu")
    with pytest.raises(ValueError, match="is not a method plug-in"):
        make_calibrator("i39_plugins:undeclared", "cpu")
    assert [c[0] for c in plugin_modules.CALLS] == ["WithDevice", "make_any"]
    assert get_detector("i39_plugins:Lines").name == "lines"  # a detector class: name and __call__
    registry: Registry = Registry("method")
    assert registry.create("i39_plugins:make_any", offered={"device": "cuda"}).name == "fixed-fov"
    assert plugin_modules.CALLS[-1] == ("make_any", {"device": "cuda"})


def _cli(capsys, *args) -> tuple[int, str, str]:
    code = main([str(a) for a in args])
    captured = capsys.readouterr()
    return code, captured.out, captured.err


@pytest.mark.parametrize("methods, expected", [
    ("subprocess:getoutput[cmd=touch {marker}]", "is not a method plug-in"),
    ("os:system[command=touch {marker}]", "is not a method plug-in"),
    ("i39_plugins:undeclared", "is not a method plug-in"),
    ("i39_plugins:FixedFov[cmd=touch {marker}]", "takes no option 'cmd'"),
])
def test_fr_eval_refuses_undeclared_methods(capsys, tmp_path, plugin_modules, methods, expected):
    marker = tmp_path / "ran"
    code, out, err = _cli(capsys, "eval", "--dataset", "i39_data:load", "--methods", methods.format(marker=marker),
                          "--out", tmp_path / "out", "--no-plots", "--group-by", "none")
    assert code == 2 and expected in err and len(err.strip().splitlines()) == 1, err
    assert not marker.exists() and not plugin_modules.CALLS


def test_fr_eval_refuses_undeclared_dataset(capsys, tmp_path, plugin_modules):
    code, out, err = _cli(capsys, "eval", "--dataset", "i39_data:undeclared", "--methods", "prior",
                          "--out", tmp_path / "out", "--no-plots")
    assert code == 2 and "is not a dataset plug-in" in err, err


def test_fr_eval_runs_the_simplest_plugin(capsys, tmp_path, plugin_modules):
    out = tmp_path / "out"
    code, _, err = _cli(capsys, "eval", "--dataset", "i39_data:load", "--methods", "i39_plugins:FixedFov",
                        "--out", out, "--no-plots", "--group-by", "none")
    assert code == 0, err
    rows = pd.read_csv(out / "predictions.csv")
    assert len(rows) == 1 and not rows["failed"].astype(bool).any()


# --------------------------------------------------------------------------- reliability scope

@pytest.fixture(scope="module")
def scene_segments() -> list[np.ndarray]:
    return [_scene(7)]


@pytest.mark.parametrize("kwargs, gap", [
    ({"measure": "a"}, "measure a"), ({"measure": "c"}, "measure c"), ({"measure": "d"}, "measure d"),
    ({"measure": "e"}, "measure e"), ({"likelihood": "paper"}, "likelihood paper"),
    ({"likelihood_params": LikelihoodParams.from_config(mode="fast").__class__(measure="b", focal_prior_weight=0.0)},
     "likelihood custom parameters"),
])
def test_reliability_not_applicable_outside_its_training(scene_segments, kwargs, gap):
    results = FREstimator(mode="fast", **kwargs).calibrate_segments(scene_segments, [SIZE])
    for result in results:
        assert result.ok and result.predicted_error is None and not result.reliable
        assert f"reliability model not trained for {gap} (trained for measure b, detector lsd" in result.reason
        _assert_finite(result)


@pytest.mark.parametrize("kwargs", [{}, {"measure": "b"}, {"likelihood_params": LikelihoodParams.from_config(mode="fast")}])
def test_reliability_applies_to_its_training_setting(scene_segments, kwargs):
    for result in FREstimator(mode="fast", **kwargs).calibrate_segments(scene_segments, [SIZE]):
        assert result.predicted_error is not None and "not trained" not in result.reason


def test_reliability_scope_includes_the_detector(room):
    class Renamed(LSDDetector):
        name = "lsd-renamed"

    estimator = FREstimator(mode="fast", detector=Renamed())
    [result] = estimator.calibrate_images([room])
    assert result.ok and result.predicted_error is None and "not trained for detector lsd-renamed" in result.reason
    [own] = estimator.calibrate_segments([result.segments], [(320, 240)])  # the caller's segments: no detector
    assert own.predicted_error is not None


def test_reliability_scope_takes_the_detectors_its_promise_was_validated_on(room):
    shipped = ReliabilityModel.load_default("fast")
    params = LikelihoodParams.from_config(mode="fast")
    lsd_only = replace(shipped, promise=replace(shipped.promise, validated_detectors=()))
    assert lsd_only.detectors == ("lsd",)
    gap = lsd_only.scope_gap(params, "default", "torch-lines", "fast")
    assert "not trained for detector torch-lines" in gap and "detect with lsd (--detector)" in gap
    declared = replace(shipped, promise=replace(shipped.promise, validated_detectors=("torch-lines",)))
    assert declared.detectors == ("lsd", "torch-lines")
    for name in ("lsd", "torch-lines", None):  # None: the caller's segments
        assert declared.scope_gap(params, "default", name, "fast") is None
    for name in ("mcmlsd", "torch-lines[grad_threshold=3.0]"):  # unknown, or other settings than measured
        gap = declared.scope_gap(params, "default", name, "fast")
        assert f"not trained for detector {name}" in gap and "detect with lsd or torch-lines (--detector)" in gap
    [result] = FREstimator(mode="fast", detector="torch-lines", reliability=declared).calibrate_images([room])
    assert result.ok and result.predicted_error is not None and result.error_bound is not None
    assert "not trained" not in result.reason
    [result] = FREstimator(mode="fast", detector="torch-lines[grad_threshold=3]",
                           reliability=declared).calibrate_images([room])
    assert result.predicted_error is None and not result.reliable
    assert "not trained for detector torch-lines[grad_threshold=3.0]" in result.reason


def test_shipped_models_state_their_training_setting():
    for mode in ("fr", "fast"):
        model = ReliabilityModel.load_default(mode)
        assert model.meta["trained_for"] == {"measure": "b", "detector": "lsd", "likelihood": "default"}
        # the promise was measured on torch-lines' segments too (results/reliability/torch_lines.md)
        assert model.detectors == ("lsd", "torch-lines")
        legacy = ReliabilityModel(model.train_cues, model.train_errors, model.feature_mean, model.feature_components,
                                  model.feature_variance, model.k, {k: v for k, v in model.meta.items()
                                                                   if k != "trained_for"})
        assert legacy.trained_for == model.trained_for  # a file that does not say: the shipped setting
