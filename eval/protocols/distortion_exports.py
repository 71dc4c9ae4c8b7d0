"""How exactly COLMAP and OpenCV read fR's lens exports: each export against fR's own division model.

    python -m fr_eval.protocols.distortion_exports --out results/distortion/exports.md

For every image size and k, the exports of :mod:`fr_torch.core.geometry.lens` -- COLMAP's
``SIMPLE_DIVISION`` and ``RADIAL`` (:func:`~fr_torch.core.exports.colmap_camera`) and OpenCV's
``K`` + ``[k1, k2, p1, p2, k3]`` (:func:`~fr_torch.core.exports.opencv_camera`) -- are handed
to the tools themselves (pycolmap's ``Camera``, ``cv2``) over a grid of photo pixels that reaches
the image's corners (:func:`pixel_grid`), and their answers are compared with fR's
(:func:`~fr_torch.core.geometry.lens.undistort_points`, :func:`~fr_torch.core.geometry.lens.distort_points`)
in both directions (:func:`export_errors`).  ``tests/test_exports.py`` holds the exports to these
numbers; the table is ``results/distortion/exports.md``.
"""
from __future__ import annotations

import argparse
import math
import sys
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import pycolmap

from fr_torch.core.exports import colmap_camera, opencv_camera
from fr_torch.core.geometry.lens import normalising_radius, undistort_points
from fr_torch.output import write_text_atomic

#: The exports compared: COLMAP's two models of a division estimate (:class:`fr_torch.core.exports.ColmapModel`)
#: and OpenCV's.
EXPORTS = ("colmap-division", "colmap-radial", "opencv")
#: ``cv2.undistortPoints``' stopping rule here: enough iterations to converge (its default, 5, does not at strong k).
OPENCV_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12)


@dataclass(frozen=True)
class ExportErrors:
    """One export against fR's model over a pixel grid, pixels per grid point (M,) (inf where the
    tool gave no answer).  ``undistorting``: the tool's undistorted pixel of each photo pixel
    (pycolmap ``cam_from_img``, ``cv2.undistortPoints``) against :func:`undistort_points`';
    ``distorting``: the tool's photo pixel (``img_from_cam``, ``cv2.projectPoints``) of fR's
    undistorted pixel against the photo pixel.  ``model``: the exported model's name;
    ``stated_max_px``: the largest residual the export states (0 for an exact one)."""

    model: str
    undistorting: np.ndarray
    distorting: np.ndarray
    stated_max_px: float

    @property
    def max_px(self) -> float:
        """The largest disagreement in either direction (pixels)."""
        return float(max(self.undistorting.max(), self.distorting.max()))


def pixel_grid(width: int, height: int, per_side: int = 41) -> np.ndarray:
    """``per_side`` x ``per_side`` photo pixels (fR's convention: the first pixel's centre is (0, 0))
    spread evenly from the image's top-left corner (-0.5, -0.5) to its bottom-right corner
    (w - 0.5, h - 0.5), (M, 2) float64."""
    xs, ys = np.meshgrid(np.linspace(-0.5, width - 0.5, per_side), np.linspace(-0.5, height - 0.5, per_side))
    return np.stack([xs.ravel(), ys.ravel()], -1)


def _distance(theirs: np.ndarray, ours: np.ndarray) -> np.ndarray:
    distance = np.linalg.norm(np.asarray(theirs, np.float64).reshape(-1, 2) - ours, axis=-1)
    return np.where(np.isfinite(distance), distance, np.inf)


def export_errors(export: str, k: float, focal_px: float, centre, width: int, height: int,
                  per_side: int = 41) -> ExportErrors:
    """:class:`ExportErrors` of ``export`` (one of :data:`EXPORTS`) for the division model of ``k``
    with focal length ``focal_px`` and principal point ``centre`` (fR's pixels) over
    :func:`pixel_grid`."""
    centre = np.asarray(centre, np.float64)
    photo = pixel_grid(width, height, per_side)
    ours = undistort_points(photo, k, centre, normalising_radius(width, height))
    rays = np.concatenate([(ours - centre) / focal_px, np.ones((len(ours), 1))], 1)  # camera frame, z = 1
    if export == "opencv":
        camera = opencv_camera(k, focal_px, centre, width, height)
        matrix = np.array(camera["camera_matrix"]["data"]).reshape(3, 3)
        coefficients = np.array(camera["distortion_coefficients"]["data"])
        undistorted = cv2.undistortPoints(photo.reshape(-1, 1, 2), matrix, coefficients, None, None, matrix,
                                          OPENCV_CRITERIA)
        projected, _ = cv2.projectPoints(rays, np.zeros(3), np.zeros(3), matrix, coefficients)
        return ExportErrors("OpenCV k1 k2 p1 p2 k3", _distance(undistorted, ours), _distance(projected, photo),
                            camera["distortion_fit_residual_px"]["max"])
    if export not in EXPORTS:
        raise ValueError(f"export must be one of {', '.join(EXPORTS)}, got {export!r}")
    model, params, residual = colmap_camera(k, focal_px, centre, width, height, model=export.split("-")[1])
    camera = pycolmap.Camera.create_from_model_name(1, model, focal_px, width, height)
    camera.params = params
    # COLMAP's pixel origin is the image corner: its pixel = ours + 0.5
    undistorted = camera.cam_from_img(photo + 0.5) * focal_px + centre
    projected = camera.img_from_cam(rays) - 0.5
    return ExportErrors(model, _distance(undistorted, ours), _distance(projected, photo), residual["max_px"])


def _px(value: float) -> str:
    if not math.isfinite(value):
        return "none"
    if value == 0:
        return "0"
    return f"{value:.1e}" if value < 1e-3 else f"{value:.3f}" if value < 10 else f"{value:.1f}"


def table(sizes, ks, hfov_deg: float, per_side: int) -> str:
    """A Markdown table: per image size, k and export, the median and largest disagreement (pixels)
    in each direction and the residual the export states; the focal length gives ``hfov_deg``
    across the width, the principal point is the image centre."""
    lines = ["| image | k | export | undistorting: median | max | distorting: median | max | stated max |",
             "|---|---|---|---|---|---|---|---|"]
    for width, height in sizes:
        focal = width / 2 / math.tan(math.radians(hfov_deg) / 2)
        centre = ((width - 1) / 2, (height - 1) / 2)
        for k in ks:
            for export in EXPORTS:
                errors = export_errors(export, k, focal, centre, width, height, per_side)
                lines.append(f"| {width}x{height} | {k:g} | {errors.model} | {_px(np.median(errors.undistorting))} "
                             f"| {_px(errors.undistorting.max())} | {_px(np.median(errors.distorting))} "
                             f"| {_px(errors.distorting.max())} | {_px(errors.stated_max_px)} |")
    return "\n".join(lines) + "\n"


def report(sizes, ks, hfov_deg: float, per_side: int, command: str) -> str:
    """``exports.md``: what was compared, the ``command`` that wrote it and :func:`table`."""
    return (f"# Lens exports read by COLMAP and OpenCV against fR's division model\n\n"
            f"Written by `{command}` (pycolmap {pycolmap.__version__}, OpenCV {cv2.__version__}).\n\n"
            f"Each export of a division-model estimate -- COLMAP `SIMPLE_DIVISION` (exact) and `RADIAL` "
            f"(k1 k2 fitted), OpenCV k1 k2 (k3) (fitted) -- handed to the tool itself, on a {per_side} x {per_side} "
            f"grid of photo pixels from corner to corner of the image; {hfov_deg:g}° across the width, principal "
            f"point at the image centre. *Undistorting*: the tool's undistorted pixel of each photo pixel "
            f"(pycolmap `Camera.cam_from_img`, `cv2.undistortPoints` with 100 iterations) against fR's "
            f"`undistort_points`; *distorting*: the tool's photo pixel (`Camera.img_from_cam`, `cv2.projectPoints`) "
            f"of fR's undistorted pixel against the photo pixel. Pixels of the image at its size; *stated max*: "
            f"the residual the export states beside its numbers (`cameras.txt` comment, "
            f"`distortion_fit_residual_px`). The fitted residuals in pixels do not depend on the focal length "
            f"and grow with the image's size (k is normalised by half the diagonal). Commentary: "
            f"[README.md](README.md#lens-exports).\n\n" + table(sizes, ks, hfov_deg, per_side))


def _pairs(text: str) -> list[tuple[int, int]]:
    try:
        return [tuple(int(v) for v in item.split("x")) for item in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected sizes such as 640x480,4000x3000, got {text!r}") from None


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", type=_pairs, default=[(640, 480), (4000, 3000)], help="WxH,WxH...")
    parser.add_argument("--k", type=lambda text: [float(v) for v in text.split(",")], default=[-0.4, -0.2, -0.05])
    parser.add_argument("--hfov", type=float, default=60.0, help="horizontal field of view, degrees")
    parser.add_argument("--grid", type=int, default=201, help="grid points per side")
    parser.add_argument("--out", type=Path, default=None, help="write the table to this Markdown file")
    args = parser.parse_args(argv)
    command = "python -m fr_eval.protocols.distortion_exports " + " ".join(sys.argv[1:] if argv is None else argv)
    text = report(args.sizes, args.k, args.hfov, args.grid, command.strip())
    if args.out:
        write_text_atomic(args.out, text)
    print(text, end="")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
