"""The lens exports read back by the tools themselves: COLMAP's cameras through pycolmap, OpenCV's
coefficients through cv2, against fR's own division model (fr_eval.protocols.distortion_exports)."""
from __future__ import annotations

import numpy as np
import pycolmap
import pytest

from fr_eval.protocols.distortion_exports import export_errors
from fr_torch.core.exports import ColmapModel, colmap_camera, colmap_cameras_txt, colmap_division_k
from fr_torch.core.geometry.lens import normalising_radius
from fr_torch.errors import FRInputError

# (width, height, focal_px, principal point off the centre): landscape and portrait, small and large
CAMERAS = [(640, 480, 450.0, (331.0, 228.5)), (480, 640, 700.0, (233.2, 331.0)), (4000, 3000, 2300.0, (1930.7, 1560.2))]


@pytest.mark.parametrize("width, height, focal, centre", CAMERAS)
@pytest.mark.parametrize("k", [-0.4, -0.2, -0.05, 0.1])
def test_simple_division_is_the_division_model_in_pycolmap(width, height, focal, centre, k):
    errors = export_errors("colmap-division", k, focal, centre, width, height, per_side=21)
    assert errors.model == "SIMPLE_DIVISION" and errors.stated_max_px == 0.0
    assert errors.undistorting.max() < 1e-6 and errors.distorting.max() < 1e-6


def test_colmap_division_k_is_normalised_by_the_focal_length():
    width, height, focal = 4000, 3000, 3100.0
    radius = normalising_radius(width, height)
    assert colmap_division_k(-0.2, focal, width, height) == pytest.approx(-0.2 * (focal / radius) ** 2)
    assert colmap_division_k(-0.2, radius, width, height) == pytest.approx(-0.2)  # f = s: the same number
    model, params, residual = colmap_camera(-0.2, focal, (1999.5, 1499.5), width, height)
    assert model == "SIMPLE_DIVISION" and params == [focal, 2000.0, 1500.0, colmap_division_k(-0.2, focal, width, height)]
    assert colmap_camera(0.0, focal, (1999.5, 1499.5), width, height, "radial")[0] == "SIMPLE_PINHOLE"
    with pytest.raises(FRInputError, match="COLMAP model"):
        colmap_camera(-0.2, focal, (1999.5, 1499.5), width, height, "opencv")


@pytest.mark.parametrize("width, height, focal, centre", CAMERAS[:2])
@pytest.mark.parametrize("k", [-0.2, -0.05, 0.1])
@pytest.mark.parametrize("export", ["colmap-radial", "opencv"])
def test_fitted_exports_agree_within_their_stated_residual(width, height, focal, centre, k, export):
    """RADIAL through pycolmap, k1 k2 (k3) through cv2.undistortPoints / projectPoints: within the
    residual the export states, in both directions, over a denser grid than the fit's."""
    errors = export_errors(export, k, focal, centre, width, height, per_side=63)
    assert 0 < errors.stated_max_px < 10.0
    assert errors.max_px <= errors.stated_max_px * 1.02 + 1e-6
    assert errors.model == ("RADIAL" if export == "colmap-radial" else "OpenCV k1 k2 p1 p2 k3")


def test_cameras_txt_reads_back_through_pycolmap(tmp_path):
    cameras = [("a.jpg", 640, 480, *colmap_camera(-0.2, 450.0, (331.0, 228.5), 640, 480)),
               ("b.jpg", "no segments"),
               ("c.jpg", 480, 640, *colmap_camera(-0.2, 700.0, (233.2, 331.0), 480, 640, ColmapModel.RADIAL)),
               ("d.jpg", 640, 480, *colmap_camera(0.0, 500.0, (319.5, 239.5), 640, 480))]
    text = colmap_cameras_txt(cameras)
    assert "# b.jpg: no camera (no segments)" in text and "# Number of cameras: 3" in text
    assert "# c.jpg (RADIAL fitted to fR's division model: residual rms" in text
    (tmp_path / "cameras.txt").write_text(text)
    (tmp_path / "images.txt").write_text("")
    (tmp_path / "points3D.txt").write_text("")
    reconstruction = pycolmap.Reconstruction()
    reconstruction.read_text(str(tmp_path))
    read = {camera_id: (camera.model.name, camera.width, camera.height, list(camera.params))
            for camera_id, camera in reconstruction.cameras.items()}
    expected = [camera for camera in cameras if len(camera) == 6]
    assert read == {i + 1: (model, width, height, params)  # every number reads back to the same float
                    for i, (_, width, height, model, params, _) in enumerate(expected)}
