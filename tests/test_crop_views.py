"""fr_eval.datasets.crop_views: crops centred on the principal point keep focal and rotation; the panoviews
loader reads them back."""
import cv2
import numpy as np
import pytest

from fr_eval.datasets.crop_views import crop_dataset, crop_origin, main
from fr_eval.datasets.panoviews import PanoViews
from fr_eval.datasets.registry import CalibrationSample
from fr_torch.core.geometry.camera import Camera
from fr_torch.core.geometry.conventions import hfov_from_focal, image_centre, rotation_from_angles
from fr_torch.synthetic import render_manhattan_room


def _sample(tmp_path, name, size=(320, 240), pp=(153.3, 125.2), focal=300.0):
    rotation = rotation_from_angles(10.0, 5.0, 3.0).numpy()
    path = tmp_path / f"{name}.png"
    cv2.imwrite(str(path), render_manhattan_room(focal, rotation, *size, seed=1))
    return CalibrationSample(name=name, image_path=path, width=size[0], height=size[1],
                             camera=Camera(size[0], size[1], focal, pp, rotation), split="test")


def test_crop_keeps_the_camera_and_centres_the_principal_point(tmp_path):
    samples = [_sample(tmp_path, "a"), _sample(tmp_path, "small", size=(100, 80), pp=(50.0, 40.0))]
    summary = crop_dataset(samples, (200, 150), tmp_path / "out")
    assert summary["images"] == 1 and "small" in summary["skipped"][0]
    [view] = list(PanoViews(tmp_path / "out", "test"))
    assert (view.width, view.height) == (200, 150)
    assert view.focal_px == pytest.approx(300.0)
    assert view.hfov_deg == pytest.approx(hfov_from_focal(300.0, 200))
    np.testing.assert_allclose(view.rotation, samples[0].camera.rotation, atol=1e-9)
    x0, y0 = crop_origin((153.3, 125.2), (200, 150))
    assert abs(153.3 - x0 - 99.5) <= 0.5 and abs(125.2 - y0 - 74.5) <= 0.5  # the crop's centre (99.5, 74.5)
    assert view.principal_point == image_centre(200, 150)
    source = cv2.imread(str(samples[0].image_path), cv2.IMREAD_GRAYSCALE)
    crop = cv2.imread(str(view.image_path), cv2.IMREAD_GRAYSCALE)
    np.testing.assert_array_equal(crop, source[y0:y0 + 150, x0:x0 + 200])
    assert view.roll_deg == pytest.approx(samples[0].roll_deg) and view.tilt_deg == pytest.approx(samples[0].tilt_deg)


@pytest.mark.parametrize("size", ["400", "0x300", "axb", "8x8"])
def test_bad_crop_size_is_a_usage_error(size, capsys):
    with pytest.raises(SystemExit) as stop:
        main(["--size", size, "--out", "unused"])
    assert stop.value.code == 2 and "WIDTHxHEIGHT" in capsys.readouterr().err
