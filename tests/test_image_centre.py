"""The default principal point is the exact image centre ``((w - 1) / 2, (h - 1) / 2)`` (pixel centres at
integer coordinates), where OpenCV and COLMAP put a centred camera, in the input's pixels whatever the
working resolution; the working resolution maps points as ``cv2.resize`` moves pixels."""
import cv2
import numpy as np
import pytest

from fr_torch import FREstimator
from fr_torch.core.exports import colmap_camera
from fr_torch.core.geometry.camera import Camera
from fr_torch.core.geometry.conventions import image_centre, resize_homogeneous, resize_points, rotation_from_angles
from fr_torch.images.io import focal_and_pp_to_working, working_image, working_size
from fr_torch.synthetic import render_manhattan_room, synthetic_segments

ROTATION = rotation_from_angles(20.0, 8.0, -4.0).numpy()
# even and odd sides, landscape and portrait
SIZES = [(480, 360), (641, 481), (640, 480), (481, 641)]


@pytest.fixture(scope="module")
def estimator():
    return FREstimator(mode="fast")


@pytest.fixture(scope="module")
def centred(estimator):
    """{size: the result of synthetic segments of that size, principal point not given}."""
    out = {}
    for width, height in SIZES:
        segments, _ = synthetic_segments(0.9 * max(width, height), ROTATION, width, height, seed=5)
        [out[(width, height)]] = estimator.calibrate_segments([segments], [(width, height)])
    return out


def test_image_centre_is_the_mean_of_the_pixel_centres():
    for width, height in SIZES:
        ys, xs = np.mgrid[:height, :width]
        assert image_centre(width, height) == (xs.mean(), ys.mean())
    assert image_centre(480, 360) == (239.5, 179.5) and image_centre(641, 481) == (320.0, 240.0)
    assert Camera(480, 360, 500.0).principal_point == (239.5, 179.5)
    np.testing.assert_array_equal(image_centre(np.array([480, 641]), np.array([360, 481])), [[239.5, 320.0],
                                                                                               [179.5, 240.0]])


@pytest.mark.parametrize("size", SIZES)
def test_default_principal_point_of_segments_is_the_image_centre(centred, size):
    result = centred[size]
    assert result.ok and result.principal_point == image_centre(*size)
    assert tuple(result.to_json()["principal_point"]) == image_centre(*size)


@pytest.mark.parametrize("size", SIZES)
def test_opencv_centred_camera_is_the_default(centred, size):
    """``cv2.getDefaultNewCameraMatrix(..., centerPrincipalPoint=True)`` centres a camera at the default."""
    result = centred[size]
    K = np.asarray(result.camera.K, np.float64)
    centred_K = cv2.getDefaultNewCameraMatrix(K, size, centerPrincipalPoint=True)
    assert (centred_K[0, 2], centred_K[1, 2]) == result.principal_point
    exported = result.opencv()["camera_matrix"]["data"]
    assert (exported[2], exported[5]) == (centred_K[0, 2], centred_K[1, 2])


@pytest.mark.parametrize("size", SIZES)
def test_colmap_export_is_pycolmaps_centred_camera(centred, size):
    """COLMAP's pixels put the top-left pixel's centre at (0.5, 0.5); its centred camera (w / 2, h / 2)
    is fR's default principal point exported."""
    pycolmap = pytest.importorskip("pycolmap")
    result = centred[size]
    model, params, _ = result.colmap()
    own = pycolmap.Camera.create_from_model_name(1, model, result.focal_px, *size)
    assert model == "SIMPLE_PINHOLE" and (own.width, own.height) == size
    np.testing.assert_allclose(params, list(own.params), rtol=0, atol=1e-9)
    # a division-model estimate at the default centre: SIMPLE_DIVISION's f, cx, cy are COLMAP's centred ones
    model, params, _ = colmap_camera(-0.2, result.focal_px, result.principal_point, *size)
    own = pycolmap.Camera.create_from_model_name(1, model, result.focal_px, *size)
    assert model == "SIMPLE_DIVISION"
    np.testing.assert_allclose(params[:3], list(own.params)[:3], rtol=0, atol=1e-9)
    # the centre pixel is COLMAP's optical axis
    np.testing.assert_allclose(own.cam_from_img(np.array([[c + 0.5 for c in result.principal_point]]))[0], [0, 0],
                               atol=1e-12)


@pytest.mark.parametrize("size", [(1280, 960), (1281, 961), (961, 1281)])
def test_default_principal_point_of_an_image_calibrated_smaller(size, tmp_path):
    """Calibrated at a working resolution of long side 640, reported in the input's pixels: the
    default principal point is the input's centre exactly."""
    estimator = FREstimator(mode="fast", working_long_side=640)
    width, height = size
    assert working_size(size, 640) != size
    path = tmp_path / "room.png"
    cv2.imwrite(str(path), render_manhattan_room(0.8 * max(size), ROTATION, width, height, seed=2))
    [result] = estimator.calibrate_images([str(path)])
    assert result.ok and (result.width, result.height) == size
    assert result.principal_point == image_centre(width, height)
    # a given principal point comes back as it was given
    given = (0.47 * width, 0.55 * height)
    [result] = estimator.calibrate_images([str(path)], principal_point=given)
    assert result.ok
    np.testing.assert_allclose(result.principal_point, given, rtol=0, atol=1e-9)


@pytest.mark.parametrize("size", [(1280, 960), (1281, 961), (961, 1281), (4000, 3000), (3001, 4001), (641, 481)])
def test_working_resolution_maps_the_centre_onto_the_centre(size):
    working = working_size(size, 640)
    scale = size[0] / working[0]
    assert tuple(resize_points(image_centre(*size), size, working)) == image_centre(*working)
    assert tuple(resize_points(image_centre(*working), working, size)) == image_centre(*size)
    focal, pp = focal_and_pp_to_working(1000.0, image_centre(*size), scale, size, working)
    assert pp == image_centre(*working) and focal == 1000.0 / scale
    # the image's edges map to the edges; a point goes there and back
    np.testing.assert_allclose(resize_points([[-0.5, -0.5], [size[0] - 0.5, size[1] - 0.5]], size, working),
                               [[-0.5, -0.5], [working[0] - 0.5, working[1] - 0.5]], atol=1e-12)
    point = np.array([[123.25, 77.5], [10.0, 300.75]])
    np.testing.assert_allclose(resize_points(resize_points(point, size, working), working, size), point, atol=1e-9)
    segment = np.concatenate(point)[None]
    np.testing.assert_allclose(resize_points(segment, size, working).reshape(-1, 2),
                               resize_points(point, size, working))
    # homogeneous points: the same map for finite ones, directions scale per axis at infinity
    homogeneous = np.array([[2 * 123.25, 2 * 77.5, 2.0], [3.0, -4.0, 0.0]])
    moved = resize_homogeneous(homogeneous, size, working)
    np.testing.assert_allclose(moved[0, :2] / moved[0, 2], resize_points(point[0], size, working), atol=1e-9)
    np.testing.assert_allclose(moved[1], [3.0 * working[0] / size[0], -4.0 * working[1] / size[1], 0.0])


@pytest.mark.parametrize("size", [(1280, 960), (1281, 961), (1000, 750)])
def test_working_image_moves_a_point_as_resize_points_says(size):
    """The resize of the working image (INTER_AREA) follows the pixel-centre convention: a blob's centroid
    lands where :func:`resize_points` puts it, not at ``x / scale`` (the corner convention)."""
    width, height = size
    image = np.zeros((height, width), np.uint8)
    image[401:409, 600:608] = 255  # centroid (603.5, 404.5)
    small, scale = working_image(image, None, 640)
    ys, xs = np.mgrid[:small.shape[0], :small.shape[1]]
    weight = small.astype(np.float64)
    centroid = np.array([(weight * xs).sum(), (weight * ys).sum()]) / weight.sum()
    expected = resize_points([603.5, 404.5], size, (small.shape[1], small.shape[0]))
    np.testing.assert_allclose(centroid, expected, atol=0.03)  # uint8 rounding
    corner = np.array([603.5, 404.5]) / scale  # the corner convention: 0.5 (1 - 1 / scale) px off
    assert np.abs(centroid - corner).min() > 0.15
