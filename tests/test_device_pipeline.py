"""The GPU path from files to results (fr_torch.runtime.device_pipeline), checked on the CPU with a
stand-in for torchvision's device decoder; the CUDA tests run it for real."""
from __future__ import annotations

import cv2
import numpy as np
import pytest
import torch

from fr_torch.core.geometry.conventions import rotation_from_angles
from fr_torch.errors import FRInputError
from fr_torch.images.io import jpeg_header, working_image
from fr_torch.runtime import device_pipeline
from fr_torch.runtime.device_pipeline import (
    calibrate_on_device,
    decode_batch,
    device_path_gap,
    to_working_resolution,
)
from fr_torch.runtime.estimator import FREstimator
from fr_torch.runtime.pipeline import calibrate_paths
from fr_torch.synthetic import render_manhattan_room
from tests.conftest import gpu, with_exif_orientation

FOCAL, WIDTH, HEIGHT = 420.0, 320, 240


@pytest.fixture(scope="module")
def room() -> np.ndarray:
    rotation = rotation_from_angles(np.float64(15.0), np.float64(-6.0), np.float64(3.0)).numpy()
    return render_manhattan_room(FOCAL, rotation, WIDTH, HEIGHT, seed=5)


@pytest.fixture()
def files(room, tmp_path):
    ok, jpeg = cv2.imencode(".jpg", room, [cv2.IMWRITE_JPEG_QUALITY, 95])
    jpeg = jpeg.tobytes()
    paths = {"a.jpg": jpeg, "rotated.jpg": with_exif_orientation(jpeg, 6), "broken.jpg": jpeg[:300],
             "empty.jpg": b""}
    for name, data in paths.items():
        (tmp_path / name).write_bytes(data)
    cv2.imwrite(str(tmp_path / "b.png"), room[::-1].copy())
    big = cv2.resize(room, (WIDTH * 3, HEIGHT * 3), interpolation=cv2.INTER_LINEAR)
    cv2.imwrite(str(tmp_path / "big.jpg"), big)
    return tmp_path


@pytest.fixture()
def fake_device_decoder(monkeypatch):
    """torchvision's decode_jpeg stand-in: OpenCV's grey decode, None for a file it cannot read."""
    calls = []

    def decode(data, device):
        calls.append(len(data))
        out = []
        for b in data:
            image = cv2.imdecode(np.frombuffer(b, np.uint8), cv2.IMREAD_GRAYSCALE)
            out.append(None if image is None else torch.from_numpy(image).to(device))
        return out

    monkeypatch.setattr(device_pipeline, "_decode_jpegs", decode)
    return calls


def test_jpeg_header(room):
    jpeg = cv2.imencode(".jpg", room)[1].tobytes()
    assert jpeg_header(jpeg) == ((WIDTH, HEIGHT), False)
    assert jpeg_header(with_exif_orientation(jpeg, 1)) == ((WIDTH, HEIGHT), False)
    assert jpeg_header(with_exif_orientation(jpeg, 6)) == ((WIDTH, HEIGHT), True)  # decoded where EXIF is applied
    assert jpeg_header(jpeg[:2]) == (None, False)
    chunks = iter([jpeg[2:100], jpeg[100:]])  # read on demand, only up to the frame header
    assert jpeg_header(jpeg[:2], lambda n: next(chunks, b"")) == ((WIDTH, HEIGHT), False)


def test_decode_batch_routes_and_fails_per_file(files, fake_device_decoder):
    names = ["a.jpg", "b.png", "rotated.jpg", "broken.jpg", "missing.jpg", "empty.jpg", "big.jpg"]
    decoded = decode_batch([str(files / n) for n in names], names, torch.device("cpu"), 640)
    assert fake_device_decoder == [3]  # a.jpg, broken.jpg and big.jpg (1.5x the working side) tried on the device
    by_name = dict(zip(names, decoded))
    assert by_name["a.jpg"].error is None and tuple(by_name["a.jpg"].pixels.shape) == (HEIGHT, WIDTH)
    assert by_name["b.png"].error is None and by_name["b.png"].scale == 1.0
    rotated = by_name["rotated.jpg"]  # EXIF orientation 6: decoded upright on the host
    assert rotated.error is None and tuple(rotated.pixels.shape) == (WIDTH, HEIGHT)
    for name in ("broken.jpg", "missing.jpg", "empty.jpg"):
        error = by_name[name].error
        assert error and by_name[name].pixels is None and "\n" not in error and name in error, (name, error)
    big = by_name["big.jpg"]
    assert big.input_size == (3 * WIDTH, 3 * HEIGHT) and max(big.pixels.shape) == 640 and big.scale == pytest.approx(1.5)


def test_working_resolution_matches_the_host(room):
    big = cv2.resize(room, (1000, 750), interpolation=cv2.INTER_LINEAR)
    ours, scale = to_working_resolution(torch.from_numpy(big), 640)
    host, host_scale = working_image(big, None, 640)
    assert scale == pytest.approx(host_scale) and ours.shape == host.shape
    assert np.abs(ours.numpy().astype(int) - host.astype(int)).mean() < 1.0
    same, one = to_working_resolution(torch.from_numpy(room), 640)
    assert one == 1.0 and torch.equal(same, torch.from_numpy(room))


def test_device_path_is_for_gpus():
    cpu = FREstimator(mode="fast", reliability=None)
    assert cpu.detector.name == "lsd" and "CPU" in device_path_gap(cpu)
    with pytest.raises(FRInputError, match="--decode device"):
        device_path_gap(FREstimator(mode="fast", reliability=None, decode="device"))
    with pytest.raises(FRInputError, match="--decode"):
        FREstimator(mode="fast", decode="gpu")


def test_calibrate_on_device_equals_the_host_path(files, fake_device_decoder):
    """The orchestration (reader thread, grouping by size, segment filter, input pixels) on the CPU:
    the same results as the host pipeline with the same detector, the failures in place."""
    estimator = FREstimator(mode="fast", detector="torch-lines", reliability=None)
    names = ["a.jpg", "broken.jpg", "b.png", "big.jpg", "a.jpg"]
    paths = [str(files / n) for n in names]
    count = len(paths)
    host = [r for _, batch in calibrate_paths(estimator, paths, 2) for r in batch]
    assert [r.ok for r in host] == [True, False, True, True, True]
    for batch_size, searchers in ((2, 1), (1, 2), (2, 3)):  # results in input order, whatever the overlap
        pairs = list(calibrate_on_device(estimator, paths, paths, [None] * count, [None] * count, batch_size,
                                         searchers))
        assert [p for chunk, _ in pairs for p in chunk] == paths
        ours = [r for _, batch in pairs for r in batch]
        assert [r.ok for r in ours] == [r.ok for r in host] and [r.image for r in ours] == paths
        for a, b in zip(ours, host):
            if a.ok:
                assert abs(a.focal_px - b.focal_px) / b.focal_px < 0.02 and a.width == b.width
        assert abs(ours[0].focal_px - FOCAL) / FOCAL < 0.1 and ours[3].width == 3 * WIDTH
        assert "broken.jpg" in ours[1].reason


@gpu
def test_cuda_images_decode_and_detect_on_the_device(files):
    estimator = FREstimator(mode="fast", device="cuda", reliability=None)
    assert estimator.detector.name == "torch-lines" and device_path_gap(estimator) is None
    names = ["a.jpg", "broken.jpg", "b.png", "rotated.jpg"]
    results = estimator.calibrate_images([str(files / n) for n in names])
    assert [r.ok for r in results] == [True, False, True, True]
    assert abs(results[0].focal_px - FOCAL) / FOCAL < 0.1 and (results[3].width, results[3].height) == (HEIGHT, WIDTH)
    cpu = FREstimator(mode="fast", detector="torch-lines", reliability=None).calibrate_images([str(files / "a.jpg")])
    assert abs(results[0].focal_px - cpu[0].focal_px) / cpu[0].focal_px < 0.02


def test_the_lens_setting_travels_the_device_path(room, tmp_path, fake_device_decoder):
    """``distortion='auto'`` on a photo through a barrel lens: the device path finds the division
    model and the same k and focal length as the host path."""
    from fr_torch.images.lens import distort_image

    path = tmp_path / "bent.jpg"
    cv2.imwrite(str(path), distort_image(room, -0.25, (WIDTH, HEIGHT)), [cv2.IMWRITE_JPEG_QUALITY, 95])
    estimator = FREstimator(mode="fast", detector="torch-lines", distortion="auto", reliability=None)
    [host] = [r for _, batch in calibrate_paths(estimator, [str(path)], 1) for r in batch]
    [ours] = [r for _, batch in calibrate_on_device(estimator, [str(path)], [str(path)], [None], [None], 1, 1)
              for r in batch]
    assert ours.distortion_model == host.distortion_model == "division"
    assert ours.distortion_k == pytest.approx(host.distortion_k, abs=0.01)
    assert ours.focal_px == pytest.approx(host.focal_px, rel=0.02)
