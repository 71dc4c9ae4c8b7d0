"""Hostile and odd inputs (issue 17): a one-line error or a flagged result, never a crash, a hang,
unbounded memory, NaN in the JSON, or a lost result of another image of the same call.

Fast cases run in CI; ``@pytest.mark.slow`` ones (huge PNG, 500 images) run with ``FR_SLOW=1`` or
``-m slow``.
"""
from __future__ import annotations

import json
import math
import os
import struct
import subprocess
import sys
import threading
import zlib
from pathlib import Path

import cv2
import numpy as np
import pytest

from fr_torch import FREstimator, FRInputError
from fr_torch.cli.main import main
from fr_torch.core.geometry.conventions import rotation_from_angles
from fr_torch.core.likelihood.mixture import LikelihoodParams
from fr_torch.images.io import WORKING_LONG_SIDE, load_image, parse_working_long_side, probe_image_size, read_image
from fr_torch.plugins.methods import FRCalibrator
from fr_torch.output import dumps, json_safe
from fr_torch.synthetic import render_manhattan_room
from tests.conftest import checkout_env, with_exif_orientation

# --------------------------------------------------------------------------- hostile files

def _png_chunk(kind: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)


def forged_png(width: int, height: int) -> bytes:
    """A PNG whose IHDR declares width x height (valid CRC) but holds one tiny IDAT."""
    ihdr = struct.pack(">IIBBBBB", width, height, 8, 0, 0, 0, 0)
    return (b"\x89PNG\r\n\x1a\n" + _png_chunk(b"IHDR", ihdr) + _png_chunk(b"IDAT", zlib.compress(b"\0" * 64))
            + _png_chunk(b"IEND", b""))


def compressible_png(path: Path, width: int, height: int) -> None:
    """A real, valid, all-black grey PNG, streamed (never holds the pixels in memory)."""
    compressor = zlib.compressobj(9)
    row = b"\0" * (width + 1)
    parts = [compressor.compress(row) for _ in range(height)]
    data = b"".join(parts) + compressor.flush()
    ihdr = struct.pack(">IIBBBBB", width, height, 8, 0, 0, 0, 0)
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + _png_chunk(b"IHDR", ihdr) + _png_chunk(b"IDAT", data)
                     + _png_chunk(b"IEND", b""))


def forged_jpeg(image: np.ndarray, width: int, height: int) -> bytes:
    """A real JPEG whose SOF0 marker is patched to declare width x height."""
    data = bytearray(cv2.imencode(".jpg", image)[1].tobytes())
    sof = data.index(b"\xff\xc0")
    data[sof + 5:sof + 9] = struct.pack(">HH", height, width)
    return bytes(data)


def exif_orientation_jpeg(image: np.ndarray, orientation: int) -> bytes:
    """A JPEG of ``image`` with an EXIF APP1 segment (big-endian) holding only the Orientation tag."""
    data = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, 95])[1].tobytes()
    return with_exif_orientation(data, orientation, big_endian=True)


@pytest.fixture(scope="module")
def scene():
    """A 320 x 240 grey Manhattan room (the good image of every mixed call)."""
    return render_manhattan_room(260.0, rotation_from_angles(12.0, 6.0, 4.0).numpy(), 320, 240, seed=3)


@pytest.fixture(scope="module")
def estimator():
    return FREstimator(mode="fast")


@pytest.fixture()
def files(tmp_path, scene):
    """Hostile files, by case name -> (path, expected substring of the reason)."""
    good = tmp_path / "good.png"
    cv2.imwrite(str(good), scene)
    out = {"good": (good, None)}
    (tmp_path / "forged_ihdr.png").write_bytes(forged_png(50000, 50000))
    out["png_50000x50000"] = (tmp_path / "forged_ihdr.png", "limit")
    (tmp_path / "forged_sof.jpg").write_bytes(forged_jpeg(scene, 30000, 30000))
    out["jpeg_sof_30000x30000"] = (tmp_path / "forged_sof.jpg", "limit")
    (tmp_path / "zero.png").write_bytes(forged_png(0, 10))
    out["png_zero_width"] = (tmp_path / "zero.png", "zero-size")
    data = good.read_bytes()
    (tmp_path / "truncated.png").write_bytes(data[: len(data) // 2])
    out["png_truncated"] = (tmp_path / "truncated.png", "")
    (tmp_path / "garbage.jpg").write_bytes(b"\xff\xd8\xff" + os.urandom(2000))
    out["jpeg_garbage"] = (tmp_path / "garbage.jpg", "")
    fifo = tmp_path / "pipe.png"
    os.mkfifo(fifo)
    out["fifo"] = (fifo, "named pipe")
    out["directory"] = (tmp_path, "directory")
    out["missing"] = (tmp_path / "missing.jpg", "no such file")
    out["device"] = (Path("/dev/zero"), "device")
    return out


HOSTILE = ["png_50000x50000", "jpeg_sof_30000x30000", "png_zero_width", "png_truncated", "jpeg_garbage", "fifo",
           "directory", "missing", "device"]


def _no_hang(function, *args, seconds: float = 60.0):
    box = {}

    def target():
        try:
            box["value"] = function(*args)
        except BaseException as exc:  # noqa: BLE001 - the test inspects it
            box["error"] = exc

    thread = threading.Thread(target=target, daemon=True)
    thread.start()
    thread.join(seconds)
    assert not thread.is_alive(), "hung (a FIFO opened for reading?)"
    return box


@pytest.mark.parametrize("case", HOSTILE)
def test_hostile_file_is_a_clean_failure(files, case):
    path, reason = files[case]
    box = _no_hang(load_image, path)
    assert isinstance(box.get("error"), FRInputError), box
    assert "\n" not in str(box["error"]) and reason in str(box["error"])


def test_declared_size_is_read_from_the_header(files, scene):
    assert probe_image_size(files["png_50000x50000"][0]) == (50000, 50000)
    assert probe_image_size(files["jpeg_sof_30000x30000"][0]) == (30000, 30000)
    assert probe_image_size(files["good"][0]) == (320, 240)


def test_bad_images_do_not_cost_the_good_ones(files, estimator):
    order = ["good"] + HOSTILE + ["good"]
    results = _no_hang(estimator.calibrate_images, [files[c][0] for c in order])["value"]
    assert [r.ok for r in results] == [True] + [False] * len(HOSTILE) + [True]
    assert results[0].focal_px == pytest.approx(results[-1].focal_px)
    for r in results[1:-1]:
        assert r.reason and r.focal_px is None and "\n" not in r.reason


def test_exif_orientation_is_applied(tmp_path, scene):
    path = tmp_path / "rotated.jpg"
    path.write_bytes(exif_orientation_jpeg(scene, 6))
    image, size = read_image(path)
    assert image.shape[:2] == (320, 240) and size == (240, 320)  # displayed upright: portrait
    upright = cv2.rotate(cv2.cvtColor(scene, cv2.COLOR_GRAY2BGR), cv2.ROTATE_90_CLOCKWISE)
    assert np.abs(image.astype(int) - upright).mean() < 4  # orientation 6 = rotate 90 deg clockwise
    [result] = FREstimator(mode="fast").calibrate_images([path])
    assert (result.width, result.height) == (240, 320)


# --------------------------------------------------------------------------- CLI boundaries

def _cli(capsys, *argv):
    code = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    assert "Traceback" not in err
    return code, out, err


@pytest.mark.parametrize("options, message", [
    (["--device", "bogus"], "unknown device"),
    (["--device", "meta"], "cannot run"),
    (["--pp", "nan,240"], "finite"),
    (["--pp", "inf,inf"], "finite"),
    (["--focal", "nan"], "finite"),
    (["--focal", "-5"], "> 0"),
    (["--batch-size", "0"], "batch-size"),
    (["--fov-range", "x"], "fov-range"),
])
def test_calibrate_bad_options_are_one_line(capsys, files, options, message):
    code, out, err = _cli(capsys, "calibrate", files["good"][0], *options)
    assert code == 2 and message in err and len(err.strip().splitlines()) == 1


@pytest.mark.parametrize("focal", ["1e12", "0.001"])
def test_absurd_focal_is_rejected_per_image(capsys, files, focal):
    code, out, err = _cli(capsys, "calibrate", files["good"][0], "--focal", focal)
    record = json.loads(out)
    assert code == 1 and not record["ok"] and "field of view" in record["reason"]


LIKELIHOODS = {
    "empty_object": {},
    "list": [1, 2],
    "string_value": {"measures": {"b": {"unit": "deg", "lambda_vertical": "x", "lambda_horizontal": 1}},
                     "priors": {"vertical": 1, "horizontal": 1, "background": 1}},
    "huge_int": {"measures": {"b": {"unit": "deg", "lambda_vertical": 10 ** 400, "lambda_horizontal": 1}},
                 "priors": {"vertical": 1, "horizontal": 1, "background": 1}},
    "zero_lambda": {"measures": {"b": {"unit": "deg", "lambda_vertical": 0, "lambda_horizontal": 1}},
                    "priors": {"vertical": 1, "horizontal": 1, "background": 1}},
    "negative_lambda": {"measures": {"b": {"unit": "deg", "lambda_vertical": -1, "lambda_horizontal": 1}},
                        "priors": {"vertical": 1, "horizontal": 1, "background": 1}},
    "nan_lambda": {"measures": {"b": {"unit": "deg", "lambda_vertical": float("nan"), "lambda_horizontal": 1}},
                   "priors": {"vertical": 1, "horizontal": 1, "background": 1}},
    "zero_priors": {"measures": {"b": {"unit": "deg", "lambda_vertical": 1, "lambda_horizontal": 1}},
                    "priors": {"vertical": 0, "horizontal": 0, "background": 0}},
    "missing_priors": {"measures": {"b": {"unit": "deg", "lambda_vertical": 1, "lambda_horizontal": 1}}},
}


@pytest.mark.parametrize("case", sorted(LIKELIHOODS))
def test_bad_likelihood_config(capsys, tmp_path, files, case):
    path = tmp_path / "likelihood.json"
    path.write_text(json.dumps(LIKELIHOODS[case]))  # NaN is written as the JSON extension NaN
    with pytest.raises(ValueError):
        LikelihoodParams.from_config(None, path)
    code, out, err = _cli(capsys, "calibrate", files["good"][0], "--likelihood", path)
    assert code == 2 and out == "" and len(err.strip().splitlines()) == 1


def test_likelihood_params_reject_bad_values():
    for bad in ({"scale_vertical": 0.0}, {"scale_horizontal": float("nan")}, {"prior_background": 0.0},
                {"prior_vertical": -0.1}):
        with pytest.raises(ValueError):
            LikelihoodParams(**bad)


def test_overlay_to_existing_file_or_readonly_folder(capsys, tmp_path, files):
    existing = tmp_path / "taken"
    existing.write_text("x")
    code, out, err = _cli(capsys, "calibrate", files["good"][0], "--overlay", existing)
    assert code == 2 and "not a folder" in err
    if os.geteuid() != 0:  # root writes anywhere
        readonly = tmp_path / "ro"
        readonly.mkdir()
        readonly.chmod(0o500)
        code, out, err = _cli(capsys, "calibrate", files["good"][0], "--overlay", readonly)
        assert code == 2 and "not writable" in err


def test_non_utf8_file_name_with_overlay(capsys, tmp_path, scene):
    raw = os.path.join(os.fsencode(tmp_path), b"caf\xe9_\xff.png")
    with open(raw, "wb") as handle:
        handle.write(cv2.imencode(".png", scene)[1].tobytes())
    out_dir = tmp_path / "overlays"
    code, out, err = _cli(capsys, "calibrate", os.fsdecode(raw), "--overlay", out_dir, "--fast")
    assert code == 0 and json.loads(out)["ok"]
    assert os.listdir(os.fsencode(out_dir)) == [b"caf\xe9_\xff_fr.png"]


def test_mixed_call_json_complete_and_finite(capsys, tmp_path, files):
    target = tmp_path / "out" / "all.json"
    paths = [files[c][0] for c in ("good", "png_50000x50000", "fifo", "png_truncated", "good")]
    code, out, err = _cli(capsys, "calibrate", *paths, "--fast", "--json", target)
    assert code == 1
    lines = [json.loads(line) for line in out.splitlines()]
    written = json.loads(target.read_text())
    assert [r["ok"] for r in written] == [r["ok"] for r in lines] == [True, False, False, False, True]
    assert "NaN" not in target.read_text() and "Infinity" not in target.read_text()
    assert len(err.strip().splitlines()) == 3  # one line per failed image
    assert not list(target.parent.glob(".*.tmp"))  # atomic write leaves no temporary file


def test_json_never_holds_nan():
    record = {"a": float("nan"), "b": [np.float32(np.inf), 1.5], "c": np.array([1.0, -np.inf]), "d": np.int64(3)}
    assert json_safe(record) == {"a": None, "b": [None, 1.5], "c": [1.0, None], "d": 3}
    assert json.loads(dumps(record))["a"] is None


@pytest.mark.parametrize("options, message", [
    (["--memory", "0"], "--memory"),
    (["--change-k", "0"], "--change-k"),
    (["--device", "bogus"], "unknown device"),
])
def test_track_bad_options(capsys, tmp_path, files, options, message):
    folder = tmp_path / "frames"
    folder.mkdir()
    (folder / "f0.png").write_bytes(files["good"][0].read_bytes())
    code, out, err = _cli(capsys, "track", folder, "--out", tmp_path / "t", *options)
    assert code == 2 and message in err


def test_track_only_bad_frames(capsys, tmp_path):
    folder = tmp_path / "frames"
    folder.mkdir()
    (folder / "a.png").write_text("not an image")
    (folder / "b.jpg").write_bytes(b"\xff\xd8\xff\x00")
    code, out, err = _cli(capsys, "track", folder, "--out", tmp_path / "t")
    assert code == 2 and "no frame could be read" in err


def test_eval_bad_input(capsys, tmp_path, data_root):
    code, out, err = _cli(capsys, "eval", "--dataset", "yud", "--limit", "1", "--out", tmp_path / "e",
                          "--data-root", tmp_path / "nonexistent")
    assert code == 2 and "not found" in err
    code, out, err = _cli(capsys, "eval", "--dataset", "yud", "--limit", "1", "--out", tmp_path / "e",
                          "--data-root", data_root, "--methods", "fr[bogus=1]", "--no-plots")
    assert code == 2 and "bogus" in err and len(err.strip().splitlines()) == 1


# --------------------------------------------------------------------------- resolution independence

def test_same_scene_at_two_resolutions_gives_the_same_camera():
    """A room rendered at 640 x 480 and at 2560 x 1920 (focal scaled) gives the same angles and FOV,
    and the focal length in each input's own pixels."""
    rotation = rotation_from_angles(15.0, 8.0, -5.0).numpy()
    small = render_manhattan_room(500.0, rotation, 640, 480, seed=5)
    large = cv2.resize(small, (2560, 1920), interpolation=cv2.INTER_CUBIC)
    a, b = FREstimator(mode="fast").calibrate_images([small, large])
    assert (b.width, b.height) == (2560, 1920) and b.principal_point == (1279.5, 959.5)  # the exact centre
    assert abs(a.roll_deg - b.roll_deg) < 0.3 and abs(a.tilt_deg - b.tilt_deg) < 0.5
    assert abs(a.hfov_deg - b.hfov_deg) < 0.02 * a.hfov_deg
    assert b.focal_px == pytest.approx(4 * a.focal_px, rel=0.02)
    assert b.segments.max() > 1100  # segments reported in the input's pixels


@pytest.mark.parametrize("value, expected", [(640, 640), ("1280", 1280), (2048.0, 2048), ("input", None),
                                             (" Input ", None), (None, None)])
def test_working_long_side_is_parsed_once(value, expected):
    assert parse_working_long_side(value) == expected
    assert FREstimator(mode="fast", reliability=None, working_long_side=value).working_long_side == expected


@pytest.mark.parametrize("value", [0, 63, -640, 640.5, "640px", "nan", True, [640]])
def test_a_bad_working_long_side_is_one_line(value, capsys):
    with pytest.raises(FRInputError, match="working_long_side: expected a whole number") as caught:
        FREstimator(mode="fast", reliability=None, working_long_side=value)
    assert "\n" not in str(caught.value)
    code = main(["calibrate", "--fast", "missing.png", "--working-long-side", str(value)])
    err = capsys.readouterr().err
    assert code == 2 and "--working-long-side: expected" in err and len(err.strip().splitlines()) == 1


def test_working_long_side_caps_the_detection_not_the_answer_s_pixels():
    """A 1600 x 1200 room: the default detects it at WORKING_LONG_SIDE, 640 at 640 and ``input`` at
    1600, and every answer is in the input's pixels (focal within 3 % of each other)."""
    rotation = rotation_from_angles(-10.0, 6.0, 3.0).numpy()
    image = render_manhattan_room(1000.0, rotation, 1600, 1200, seed=11)
    results = {}
    for side in (640, None, "input"):
        estimator = FREstimator(mode="fast", reliability=None, **({} if side is None else {"working_long_side": side}))
        [results[side]] = estimator.calibrate_images([image])
    assert estimator.working_long_side is None and WORKING_LONG_SIDE < 1600
    for result in results.values():
        assert result.ok and (result.width, result.height) == (1600, 1200)
        assert result.focal_px == pytest.approx(1000.0, rel=0.03)
    assert FRCalibrator(mode="fr", working_long_side="640").name == "fr[working_long_side=640]"


# --------------------------------------------------------------------------- slow: memory and many images

def _peak_rss_mb(code: str, cwd: Path) -> tuple[int, float, str]:
    script = code + "\nimport resource, sys\nprint('PEAK_MB', resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024)\n"
    proc = subprocess.run([sys.executable, "-c", script], cwd=cwd, capture_output=True, text=True, timeout=600,
                          env=checkout_env())
    peak = [float(line.split()[1]) for line in proc.stdout.splitlines() if line.startswith("PEAK_MB")]
    return proc.returncode, peak[0] if peak else math.nan, proc.stdout + proc.stderr


@pytest.mark.slow
def test_huge_compressible_png_is_bounded(tmp_path):
    path = tmp_path / "huge.png"
    compressible_png(path, 20000, 20000)
    code, peak, text = _peak_rss_mb(
        f"from fr_torch import FREstimator\n[r] = FREstimator(mode='fast').calibrate_images([{str(path)!r}])\n"
        "print('RESULT', r.ok, r.width, r.height, r.reason)", tmp_path)
    assert code == 0, text
    assert "RESULT False 20000 20000" in text or "RESULT True 20000 20000" in text, text
    assert peak < 1500, f"peak RSS {peak:.0f} MB"  # torch + OpenCV themselves take ~400 MB


@pytest.mark.slow
def test_500_images_in_one_call(tmp_path, scene):
    small = cv2.resize(scene, (160, 120), interpolation=cv2.INTER_AREA)
    paths = []
    for i in range(500):
        paths.append(tmp_path / f"im{i:03d}.png")
        cv2.imwrite(str(paths[-1]), small if i % 50 else np.zeros((4, 4), np.uint8))
    target = tmp_path / "all.json"
    code, peak, text = _peak_rss_mb(
        "from fr_torch.cli import main\n"
        f"code = main(['calibrate', '--fast', '--json', {str(target)!r}] + {[str(p) for p in paths]!r})\n"
        "print('CODE', code)", tmp_path)
    assert "CODE 1" in text, text[-2000:]
    records = json.loads(target.read_text())
    assert len(records) == 500 and sum(r["ok"] for r in records) >= 480
    assert peak < 1500, f"peak RSS {peak:.0f} MB"
