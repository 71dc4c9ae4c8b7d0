"""Plug-ins: the one registry, its method-spec grammar and marker, and a third-party package
(``examples/fr_plugin_example``) installed into a temporary folder, found through its entry points."""
from __future__ import annotations

import os
import shutil
import subprocess
import sys
import textwrap
from pathlib import Path

import cv2
import numpy as np
import pandas as pd
import pytest

from fr_torch.detectors.registry import available_detectors, get_detector
from fr_torch.errors import FRInputError
from fr_torch.plugins.interface import available_methods, get_calibrator
from fr_torch.registry import (
    NOT_SUPPLIED,
    Registry,
    entry_points,
    format_method_spec,
    is_not_supplied,
    not_supplied,
    parse_method_spec,
    split_method_list,
    with_option,
)

REPO = Path(__file__).resolve().parents[1]
EXAMPLE = REPO / "examples" / "fr_plugin_example"


def test_method_spec_grammar():
    assert parse_method_spec(" fr[measure=a, detector=mcmlsd] ") == ("fr", {"measure": "a", "detector": "mcmlsd"})
    assert parse_method_spec("pkg.mod:Cls[x=1]") == ("pkg.mod:Cls", {"x": "1"})
    assert parse_method_spec("lee2009") == ("lee2009", {})
    for bad in ("fr[measure]", "fr[measure=a", "fr]x["):
        with pytest.raises(ValueError):
            parse_method_spec(bad)
    assert parse_method_spec("fr[measure=a]@labelled", strict=False) == ("fr[measure=a]@labelled", {})
    assert format_method_spec("fr", {"measure": "a", "x": None}) == "fr[measure=a]"
    assert with_option("fr[detector=lsd]", "measure", "c") == "fr[detector=lsd,measure=c]"
    assert split_method_list("fr[measure=a,detector=lsd], lee2009,,") == ["fr[measure=a,detector=lsd]", "lee2009"]


def test_not_supplied_marker():
    assert not_supplied() == NOT_SUPPLIED == "n/a (not supplied)"
    assert not_supplied("set X") == "n/a (not supplied: set X)"
    assert is_not_supplied(not_supplied("x")) and not is_not_supplied("no segments")


def test_registry_lookup_order_and_errors():
    reg: Registry = Registry("thing", group="fr_torch.no-such-group")
    reg.register("a", lambda **kw: ("a", kw))
    assert reg.names() == ["a"] and "a" in reg
    assert reg.create("a[k=v]", extra=1) == ("a", {"k": "v", "extra": 1})
    with pytest.raises(ValueError, match="is not a thing plug-in"):  # an import path must declare itself
        reg.factory("os.path:join")
    with pytest.raises(ValueError, match="unknown thing 'b'; available: a"):
        reg.factory("b")
    with pytest.raises(ValueError, match="cannot import"):
        reg.factory("no_such_module_xyz:f")


def test_builtins_come_from_entry_points():
    # the checkout's own pyproject.toml declares the built-in methods (installed or not)
    declared = entry_points("fr_torch.calibrators")
    assert declared["lee2009"] == "fr_baselines.lee2009:Lee2009"
    assert {"fr", "fast-fr", "oracle-fr", "lee2009", "simon2018", "ctrlc", "ctrlc-retrained", "prior",
            "external", "hold-geoffroy2018"} <= set(available_methods())
    assert {"lsd", "mcmlsd", "onnx"} <= set(available_detectors())
    assert get_calibrator("prior").name == "prior"
    with pytest.raises(FRInputError, match="unknown detector"):
        get_detector("nope")


def test_registries_name_no_harness():
    """The core's registries never import or name eval/ or baselines/ (they read entry points)."""
    for name in ("registry.py", "plugins/interface.py", "core/likelihood/segments.py", "detectors/registry.py"):
        text = (REPO / "fr_torch" / name).read_text()
        assert "baselines" not in text and "eval." not in text, name


@pytest.fixture(scope="module")
def installed_plugin(tmp_path_factory) -> Path:
    """examples/fr_plugin_example pip-installed (no deps, no isolation) into a fresh target folder.
    Building it without isolation needs setuptools >= 70.1 (bdist_wheel built in) in this env."""
    target = tmp_path_factory.mktemp("site")
    build = tmp_path_factory.mktemp("build")
    source = shutil.copytree(EXAMPLE, build / EXAMPLE.name)  # setuptools writes build/ next to the source
    subprocess.run([sys.executable, "-m", "pip", "install", "-q", "--no-deps", "--no-build-isolation",
                    "--no-index", "--target", str(target), str(source)],
                   check=True, cwd=build, env={**os.environ, "PIP_NO_CACHE_DIR": "1"})
    assert list(target.glob("fr_plugin_example-*.dist-info/entry_points.txt"))
    return target


def _run(code_or_args, target: Path, cwd: Path) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(target), str(cwd), str(REPO)])}
    args = ["-c", code_or_args] if isinstance(code_or_args, str) else code_or_args
    return subprocess.run([sys.executable, *args], env=env, cwd=cwd, capture_output=True, text=True, timeout=300)


@pytest.fixture(scope="module")
def plugin_process(installed_plugin, tmp_path_factory) -> tuple[subprocess.CompletedProcess, Path]:
    """One process with the plug-in installed: the checks of :func:`test_installed_plugin_is_found_and_runs`
    (it prints OK), then ``fr eval --methods horizon-lines,prior`` (``fr_torch.cli.main``) on a
    two-image synthetic dataset given by import path; returns it and the eval's output folder."""
    from fr_torch.core.geometry.conventions import rotation_from_angles
    from fr_torch.synthetic import render_manhattan_room

    work = tmp_path_factory.mktemp("plugin_run")
    for i, roll in enumerate((4.0, -7.0)):
        cv2.imwrite(str(work / f"room{i}.png"),
                    render_manhattan_room(500.0, rotation_from_angles(15.0, 0.0, roll).numpy(), seed=i))
    (work / "rooms_ds.py").write_text(textwrap.dedent(f"""
        from pathlib import Path
        from fr_eval.datasets.registry import CalibrationSample
        from fr_torch.core.geometry.camera import Camera
        from fr_torch.core.geometry.conventions import rotation_from_angles
        from fr_torch.registry import plugin

        @plugin("dataset")
        def load(root=None, split="test", **kwargs):
            return [CalibrationSample(name=f"room{{i}}.png", image_path=Path({str(work)!r}) / f"room{{i}}.png",
                                      width=640, height=480,
                                      camera=Camera(640, 480, 500.0, rotation=rotation_from_angles(15.0, 0.0, roll).numpy()))
                    for i, roll in enumerate((4.0, -7.0))]
    """))
    out = work / "out"
    code = textwrap.dedent(f"""
        from fr_torch.core.geometry.conventions import rotation_from_angles
        from fr_torch.plugins.interface import ImageMeta, available_methods, get_calibrator
        from fr_torch.registry import load_object  # finds fr_eval also in a checkout that is not installed
        from fr_torch.detectors.registry import available_detectors, get_detector
        from fr_torch.synthetic import render_manhattan_room
        assert "horizon-lines" in available_methods() and "long-lsd" in available_detectors()
        methods, _ = load_object("fr_eval.protocols.run_eval:resolve_methods")(["all"], has_segments=False)
        assert "horizon-lines" in methods and "fr" in methods, methods
        method = get_calibrator("horizon-lines[hfov_deg=70]")
        image = render_manhattan_room(500.0, rotation_from_angles(20.0, 0.0, 6.0).numpy())
        est = method.estimate(image, ImageMeta(name="room", width=640, height=480))
        assert est.ok and abs(est.hfov_deg - 70.0) < 1e-9 and abs(est.roll_deg - 6.0) < 1.0, est
        assert len(get_detector("long-lsd[min_length=40]")(image)) > 10
        print("OK", flush=True)
        from fr_torch.cli.main import main
        raise SystemExit(main(["eval", "--dataset", "rooms_ds:load", "--methods", "horizon-lines,prior",
                               "--out", {str(out)!r}, "--no-plots", "--group-by", "none"]))
    """)
    return _run(code, installed_plugin, work), out


def test_installed_plugin_is_found_and_runs(plugin_process):
    """After installation (and only then) ``horizon-lines`` is a method and ``long-lsd`` a detector:
    in ``fr eval --methods all``, by name, with options, and estimating a synthetic room's roll."""
    result, _ = plugin_process
    assert "OK" in result.stdout.splitlines(), result.stderr[-3000:]
    # without the installation the name is unknown
    assert "horizon-lines" not in available_methods()


def test_installed_plugin_in_fr_eval(plugin_process):
    """``fr eval --methods horizon-lines,prior`` on a two-image synthetic dataset given by import path."""
    result, out = plugin_process
    assert result.returncode == 0, result.stderr[-3000:]
    rows = pd.read_csv(out / "predictions.csv")
    mine = rows[rows["method"] == "horizon-lines"]
    assert len(mine) == 2 and not mine["failed"].astype(bool).any()
    assert np.all(np.abs(mine["roll_err_deg"].to_numpy()) < 1.0)
