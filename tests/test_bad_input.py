"""Bad input gives a clear error or a flagged result, never a deep crash or a silent wrong answer."""
import cv2
import numpy as np
import pytest

from fr_torch import FREstimator, FRInputError
from fr_torch.core.geometry.conventions import rotation_from_angles
from fr_torch.images.convert import to_bgr8
from fr_torch.images.io import load_image
from fr_torch.synthetic import render_manhattan_room


@pytest.fixture(scope="module")
def estimator():
    return FREstimator(mode="fast")


@pytest.fixture(scope="module")
def room():
    return render_manhattan_room(450.0, rotation_from_angles(10.0, 5.0, 3.0).numpy(), 320, 240, seed=1)


def test_unreadable_files(tmp_path, estimator):
    text = tmp_path / "notes.png"
    text.write_text("this is not an image")
    empty = tmp_path / "empty.jpg"
    empty.write_bytes(b"")
    for path, message in [(tmp_path / "missing.jpg", "no such file"), (text, "not a readable image"),
                          (empty, "empty file"), (tmp_path, "is a directory")]:
        with pytest.raises(FRInputError, match=message):
            load_image(path)
        [result] = estimator.calibrate_images([path])
        assert not result.ok and message in result.reason and result.focal_px is None


def test_thin_strips_are_a_clear_result(tmp_path, estimator):
    # A 5000 x 1 PNG: a reduced decode (1/8, done by resizing for non-JPEG formats) would have a
    # 0-pixel side, and OpenCV's resize assertion was the reason the user got.
    paths = []
    for name, shape in (("strip.png", (1, 5000, 3)), ("strip.jpg", (2, 5000, 3)), ("column.tif", (6000, 3))):
        paths.append(tmp_path / name)
        cv2.imwrite(str(paths[-1]), np.zeros(shape, np.uint8))
    for path, result in zip(paths, estimator.calibrate_images(paths)):
        assert not result.ok and result.reason == "no line segments found: cannot calibrate", (path.name, result.reason)
        assert max(result.width, result.height) >= 5000


def test_zero_size_and_wrong_shapes():
    for bad in (np.zeros((0, 0, 3), np.uint8), np.zeros((10, 0), np.uint8), np.zeros((4, 4, 5), np.uint8),
                np.zeros((2, 2, 2, 2), np.uint8)):
        with pytest.raises(FRInputError):
            to_bgr8(bad)
    with pytest.raises(FRInputError, match="NaN"):
        to_bgr8(np.full((8, 8), np.nan, np.float32))


def test_image_formats_are_accepted(tmp_path, estimator, room):
    variants = {
        "gray": room,
        "bgr": cv2.cvtColor(room, cv2.COLOR_GRAY2BGR),
        "bgra": cv2.cvtColor(room, cv2.COLOR_GRAY2BGRA),
        "gray16": room.astype(np.uint16) * 257,
        "float": room.astype(np.float32) / 255.0,
    }
    paths = []
    for name, image in variants.items():
        if name != "float":
            paths.append(tmp_path / f"{name}.png")
            cv2.imwrite(str(paths[-1]), image)
    results = estimator.calibrate_images(list(variants.values()) + paths)
    focal = [r.focal_px for r in results]
    assert all(r.ok for r in results)
    assert max(focal) - min(focal) < 0.02 * np.mean(focal)  # same picture, same answer


def test_blank_noise_and_nature_like_images(estimator):
    rng = np.random.default_rng(0)
    blank = np.full((240, 320), 128, np.uint8)
    noise = rng.integers(0, 256, (240, 320)).astype(np.uint8)
    blobs = cv2.GaussianBlur(rng.integers(0, 256, (240, 320)).astype(np.uint8), (0, 0), 6)  # no straight lines
    results = estimator.calibrate_images([blank, noise, blobs], names=["blank", "noise", "blobs"])
    assert not results[0].ok and "no line segments" in results[0].reason
    for result in results[1:]:
        assert not (result.ok and result.reliable), f"{result.image} should be flagged: {result.reason}"
        assert result.reason


def test_bad_segments(estimator):
    good = np.array([[10, 10, 100, 12], [50, 20, 52, 200]] * 10, float)
    nan = good.copy()
    nan[3, 1] = np.nan
    cases = [nan, np.zeros((5, 3)), "abc", good.copy() * np.inf]
    results = estimator.calibrate_segments(cases + [good], [(640, 480)] * 5)
    for result in results[:4]:
        assert not result.ok and result.reason
    assert "NaN or infinite" in results[0].reason and "(N, 4)" in results[1].reason
    assert results[4].ok  # one bad input never loses the others' results
    with pytest.raises(FRInputError):
        estimator.calibrate_segments([good], [(640, 480)] * 2)
    [bad_size] = estimator.calibrate_segments([good], [(0, 480)])
    assert not bad_size.ok and "image size" in bad_size.reason
    [bad_focal] = estimator.calibrate_segments([good], [(640, 480)], focal_px=-3)
    assert not bad_focal.ok and "focal" in bad_focal.reason


def test_too_few_segments_is_flagged(estimator):
    few = np.array([[10, 10, 100, 12], [50, 20, 52, 200], [300, 300, 400, 330]], float)
    [result] = estimator.calibrate_segments([few], [(640, 480)])
    assert result.ok and not result.reliable and "only 3 segments" in result.reason


def test_unknown_options():
    with pytest.raises(ValueError, match="mode"):
        FREstimator(mode="slow")
    with pytest.raises(ValueError, match="measure"):
        FREstimator(measure="z")
    with pytest.raises(FRInputError, match="detector"):
        FREstimator(detector="nope")
