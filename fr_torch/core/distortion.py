"""Radial lens distortion: the one-parameter division model, its setting, and conversions.

Division model (Fitzgibbon 2001)
--------------------------------
A pixel ``p`` of the photo (distorted) is the image of the undistorted (pinhole) pixel

    ``u = c + (p - c) / (1 + k r^2)``,    ``r = |p - c| / s``,

with ``c`` the distortion centre (= the principal point) and ``s`` the **normalising radius**,
half the image diagonal ``sqrt(w^2 + h^2) / 2`` (:func:`normalising_radius`), so that ``r = 1`` at
the corners of an image centred on its principal point.  Resizing an image scales ``p - c`` and
``s`` alike, so **k means the same at every image size** (a result's k needs no conversion
between the working resolution and the input's pixels).  ``k < 0`` is barrel distortion (wide
angle, CCTV, action cameras), ``k > 0`` pincushion, ``k = 0`` a pinhole camera.  The focal length,
the rotation, the vanishing points and the horizon are those of the undistorted image: ``u = K R X``
up to scale.  The model stays one-to-one over the image while ``1 + k r^2 > 0`` and
``k r^2 < 1`` for ``r <= 1``, i.e. ``-1 < k < 1`` (:data:`K_LIMITS`).

How strong is k?  :func:`border_bow_percent` gives the bow of a straight line at the image border:
in a 4:3 image, k = -0.1 bends the straight vertical line through the middle of the left border
by about 1.6 % of the width, k = -0.2 by 3.2 %, k = -0.35 by 5.6 %.

Exports (:func:`colmap_camera`, :func:`opencv_coefficients`)
--------------------------------------------------------------
COLMAP (>= 4.0) has the division model itself, ``SIMPLE_DIVISION`` (f, cx, cy, k'): it lifts a
pixel to ``x = (p - c) / f`` and undistorts it to ``x / (1 + k' |x|^2)``, i.e. its radius is
normalised by the **focal length**, ours by ``s``.  Since ``|p - c|^2 / s^2 = |x|^2 f^2 / s^2``,
the two are the same model exactly when

    ``k' = k (f / s)^2``        (and back: ``k = k' (s / f)^2``)

(:func:`colmap_division_k`; checked against pycolmap's ``cam_from_img`` / ``img_from_cam`` in
``tests/test_exports.py``).  COLMAP's ``DIVISION`` (fx, fy, cx, cy, k') is the same with two
focal lengths; fR has one.  COLMAP's pixel origin is the image's top-left corner, so its cx, cy
are ours + 0.5 (the offsets ``p - c``, and with them k', are unchanged).

OpenCV (any version) and COLMAP before 4.0 have no division model: their radial models are
polynomials in the undistorted radius, ``x_d = x_u (1 + k1 R^2 + k2 R^4 ...)``, whose
coefficients are fitted to the division model by least squares over the image
(:func:`fit_radial_polynomial`), and the fit's residual (pixels) is stated with them.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, fields
from enum import StrEnum
from typing import Any

import numpy as np
import torch

from fr_torch.core.checks import enum_member, finite_number
from fr_torch.errors import FRInputError

#: Open interval of k over which the division model is one-to-one on the image (module docstring).
K_LIMITS = (-1.0, 1.0)


class DistortionMode(StrEnum):
    """``pinhole`` (no distortion: the paper's model, the default), ``division`` (estimate k of the
    division model jointly with f and R) or ``auto`` (the pinhole search, then the division search
    for the images whose lines bend: :attr:`DistortionSetting.bend_min_gain`)."""

    PINHOLE = "pinhole"
    DIVISION = "division"
    AUTO = "auto"

    @classmethod
    def parse(cls, value) -> "DistortionMode":
        """A mode from its name (or a :class:`DistortionMode`); FRInputError (one line) otherwise."""
        return enum_member(cls, value, "distortion")


@dataclass(frozen=True)
class DistortionSetting:
    """What the search assumes about the lens, parsed once (``--distortion``, ``--k``).

    ``mode``: a :class:`DistortionMode`.  ``known_k``: a given k (normalised, module docstring);
    the search then holds it fixed (``mode`` becomes ``division``); None = estimate it.
    ``k_range``: the search box of k (default [-0.6, 0.2]: from no distortion to a fisheye-like
    barrel whose border lines bow by ~10 % of the width, and a mild pincushion), within
    :data:`K_LIMITS`.  ``k_prior_weight`` (gamma >= 0): a prior on k, ``log p(k) = -(gamma / 2) W k^2``
    per image (W its total segment length, pixels; nats), which holds k near 0 where the lines say
    little about it (:meth:`fr_torch.core.search_distortion.SegmentGeometry.k_log_prior`).
    ``bend_min_gain``, ``bend_min_share``, ``bend_min_pairs``,
    ``bend_min_bow_pct``: when the lines of a pinhole estimate bend
    (:func:`fr_torch.core.cues.lines_bend_reason`; the estimate is then not reliable, and ``auto``
    searches that image with the division model instead).  ``results/decisions/46.md`` says how they
    were chosen (train splits; 2-3 % of undistorted photos flagged).
    """

    mode: DistortionMode = DistortionMode.PINHOLE
    known_k: float | None = None
    k_range: tuple[float, float] = (-0.6, 0.2)
    k_prior_weight: float = 3.0
    bend_min_gain: float = 60.0
    bend_min_share: float = 0.15
    bend_min_pairs: int = 8
    bend_min_bow_pct: float = 1.0

    def __post_init__(self) -> None:
        object.__setattr__(self, "mode", DistortionMode.parse(self.mode))
        low, high = (float(v) for v in self.k_range)
        if not (math.isfinite(low) and math.isfinite(high) and K_LIMITS[0] < low < high < K_LIMITS[1]):
            raise FRInputError(f"k range must be finite MIN,MAX with {K_LIMITS[0]:g} < MIN < MAX < {K_LIMITS[1]:g}, "
                               f"got {self.k_range}")
        object.__setattr__(self, "k_range", (low, high))
        if self.known_k is not None:
            k = finite_number(self.known_k, "k")
            if not K_LIMITS[0] < k < K_LIMITS[1]:
                raise FRInputError(f"k must lie in ({K_LIMITS[0]:g}, {K_LIMITS[1]:g}) (division model, normalised by "
                                   f"half the image diagonal), got {self.known_k!r}")
            object.__setattr__(self, "known_k", k)
            if self.mode is DistortionMode.PINHOLE:
                object.__setattr__(self, "mode", DistortionMode.DIVISION)
        for name in ("k_prior_weight", "bend_min_gain", "bend_min_share", "bend_min_pairs", "bend_min_bow_pct"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value >= 0):
                raise FRInputError(f"{name} must be a finite number >= 0, got {value!r}")

    @classmethod
    def parse(cls, value=None) -> "DistortionSetting":
        """A setting from a :class:`DistortionSetting`, a mode name (``"division"``), a dict of the
        fields (``configs/search.json``) or None (the default, pinhole); FRInputError otherwise."""
        if value is None:
            return cls()
        if isinstance(value, cls):
            return value
        if isinstance(value, (str, DistortionMode)):
            return cls(mode=value)
        if isinstance(value, dict):
            unknown = sorted(set(value) - {f.name for f in fields(cls)})
            if unknown:
                raise FRInputError(f"distortion setting: unknown field(s) {', '.join(unknown)}")
            return cls(**{key: tuple(v) if isinstance(v, list) else v for key, v in value.items()})
        raise FRInputError(f"distortion must be a mode name or a setting, got {value!r}")

    @property
    def estimates_k(self) -> bool:
        """True when the search has a k parameter (``division`` or ``auto``, known k included)."""
        return self.mode is not DistortionMode.PINHOLE

    def k_box(self) -> tuple[float, float]:
        """The search box of k: ``k_range``, or (k, k) for a known k."""
        return (self.known_k, self.known_k) if self.known_k is not None else self.k_range


# --------------------------------------------------------------------------- the model

def normalising_radius(width, height):
    """Half the image diagonal ``sqrt(w^2 + h^2) / 2`` (pixels): the unit of r in the division
    model.  Numbers in, float out; tensors in, tensor out."""
    if torch.is_tensor(width) or torch.is_tensor(height):
        return torch.sqrt(torch.as_tensor(width) ** 2 + torch.as_tensor(height) ** 2) / 2
    return math.hypot(float(width), float(height)) / 2


def undistort_points(points, k, centre, radius):
    """Undistorted pixels ``c + (p - c) / (1 + k r^2)`` of photo pixels ``points`` (..., 2).

    ``k``, ``radius`` broadcast against ``points[..., 0]``; ``centre`` against ``points``.  NumPy
    arrays or tensors (the type of ``points``)."""
    offset = points - centre
    r2 = (offset ** 2).sum(-1) / radius ** 2
    return centre + offset / (1 + k * r2)[..., None]


def distort_points(points, k, centre, radius):
    """Photo pixels of undistorted pixels ``points`` (..., 2): the inverse of :func:`undistort_points`.

    With ``R = |u - c| / s``, the photo radius is ``r = 2 R / (1 + sqrt(1 - 4 k R^2))`` (the root of
    ``k R r^2 - r + R = 0`` that tends to R as k -> 0).  Where ``1 - 4 k R^2 < 0`` (a pincushion
    model's reach ends) the result is NaN.  NumPy arrays or tensors.
    """
    if torch.is_tensor(points):
        offset = points - centre
        big_r2 = (offset ** 2).sum(-1) / radius ** 2
        disc = 1 - 4 * k * big_r2
        scale = 2 / (1 + torch.sqrt(disc))
        return centre + offset * torch.where(disc >= 0, scale, torch.full_like(scale, math.nan)).unsqueeze(-1)
    offset = np.asarray(points, np.float64) - centre
    big_r2 = (offset ** 2).sum(-1) / np.asarray(radius, np.float64) ** 2
    disc = 1 - 4 * np.asarray(k, np.float64) * big_r2
    with np.errstate(invalid="ignore"):
        scale = np.where(disc >= 0, 2 / (1 + np.sqrt(np.maximum(disc, 0))), np.nan)
    return centre + offset * scale[..., None]


def border_bow_percent(k: float, width: float, height: float) -> float:
    """How far the straight line through the middle of the photo's left border bends, % of the width.

    The vertical line of the undistorted image that passes through the middle of the photo's left
    edge (``w / 2`` left of the principal point, taken at the image centre) is drawn in the photo;
    its horizontal distance from that point where it meets the top edge (``h / 2`` above the centre;
    the sagitta of the bowed line) is the bow.  Positive for barrel (k < 0: the line bows
    outwards), negative for pincushion; 0 for k = 0; NaN where the model does not reach the top
    edge.
    """
    if k == 0:
        return 0.0
    width, height = float(width), float(height)
    radius = normalising_radius(width, height)
    centre = np.zeros(2)
    line_x = undistort_points(np.array([-width / 2, 0.0]), k, centre, radius)[0]  # relative to the centre
    # the undistorted point (line_x, y) whose photo point lies on the top edge: bisection over y <= 0
    low, high = -10.0 * height, 0.0
    for _ in range(100):
        mid = (low + high) / 2
        y_photo = distort_points(np.array([line_x, mid]), k, centre, radius)[1]
        if np.isfinite(y_photo) and y_photo >= -height / 2:
            high = mid
        else:
            low = mid
    photo = distort_points(np.array([line_x, high]), k, centre, radius)
    if not np.isfinite(photo).all():
        return math.nan
    return 100.0 * (photo[0] + width / 2) / width


def k_for_bow(bow_percent: float, width: float, height: float) -> float:
    """The k whose :func:`border_bow_percent` is ``bow_percent`` (bisection over (-1, 1))."""
    low, high = K_LIMITS[0] + 1e-6, K_LIMITS[1] - 1e-6
    for _ in range(80):  # the bow falls as k grows
        mid = (low + high) / 2
        if not border_bow_percent(mid, width, height) <= bow_percent:
            low = mid
        else:
            high = mid
    return (low + high) / 2


def distortion_record(k: float, centre, width: int, height: int) -> dict[str, Any]:
    """The ``distortion`` field of a result: ``{"model": "division", "k", "centre": [x, y],
    "radius_px", "bow_pct"}`` (k normalised by ``radius_px``, half the diagonal of the
    ``width`` x ``height`` image; ``bow_pct``: :func:`border_bow_percent`)."""
    return {"model": "division", "k": float(k), "centre": [float(centre[0]), float(centre[1])],
            "radius_px": normalising_radius(width, height), "bow_pct": border_bow_percent(float(k), width, height)}


# --------------------------------------------------------------------------- exports

#: Points per side of the grid over the image on which the exported polynomial models are fitted.
FIT_GRID = 41
#: Reweighting rounds of :func:`fit_radial_polynomial` (the first is the plain least-squares fit).
FIT_REWEIGHTS = 4


def _fit_points(k: float, centre, width: float, height: float):
    """Photo pixels on a grid over the image (``FIT_GRID`` per side, corners included), and their
    undistorted pixels, (M, 2) each, float64."""
    xs, ys = np.meshgrid(np.linspace(-0.5, width - 0.5, FIT_GRID), np.linspace(-0.5, height - 0.5, FIT_GRID))
    photo = np.stack([xs.ravel(), ys.ravel()], -1)
    centre = np.asarray(centre, np.float64)
    return photo, undistort_points(photo, k, centre, normalising_radius(width, height))


def _polynomial_distort(normalised: np.ndarray, coefficients) -> np.ndarray:
    """OpenCV / COLMAP radial model: ``x (1 + k1 R^2 + k2 R^4 + ...)`` of undistorted normalised
    coordinates (M, 2)."""
    r2 = (normalised ** 2).sum(-1, keepdims=True)
    factor = 1.0 + sum(c * r2 ** (i + 1) for i, c in enumerate(coefficients))
    return normalised * factor


def _polynomial_undistort(normalised: np.ndarray, coefficients, iterations: int = 200) -> np.ndarray:
    """Inverse of :func:`_polynomial_distort` by fixed-point iteration (as OpenCV's
    ``undistortPoints`` does), (M, 2)."""
    x = normalised.copy()
    for _ in range(iterations):
        r2 = (x ** 2).sum(-1, keepdims=True)
        x = normalised / (1.0 + sum(c * r2 ** (i + 1) for i, c in enumerate(coefficients)))
    return x


def fit_radial_polynomial(k: float, focal_px: float, centre, width: float, height: float, terms: int = 2):
    """Least-squares coefficients ``k1 .. k_terms`` of the radial polynomial ``x_d = x_u (1 + k1 R^2 +
    k2 R^4 ...)`` (``x = (p - c) / f``, OpenCV's and COLMAP's convention) that best match the division
    model of ``k`` over the photo, and the fit's residual.

    The fit is linear in the coefficients: ``x_d - x_u = x_u (k1 R^2 + ...)`` at the
    :data:`FIT_GRID`^2 grid of photo pixels (corners included).  Residual, pixels, in both
    directions at every grid pixel: undistorting (the distance between its undistorted pixel under
    the division model and under the fitted polynomial, inverted as OpenCV's ``undistortPoints``
    and COLMAP's ``cam_from_img`` do) and distorting (the distance between the grid pixel and the
    polynomial's image of its division-model undistorted pixel, as ``cv2.projectPoints`` and
    COLMAP's ``img_from_cam`` compute it); ``rms_px`` and ``max_px`` over both.  The residual in
    pixels does not depend on ``focal_px`` (the coefficients absorb it).  Returns
    (coefficients (terms,), {"rms_px", "max_px"}).
    """
    if k == 0:
        return np.zeros(terms), {"rms_px": 0.0, "max_px": 0.0}
    centre = np.asarray(centre, np.float64)
    photo, undistorted = _fit_points(k, centre, width, height)
    x_d, x_u = (photo - centre) / focal_px, (undistorted - centre) / focal_px
    r2 = (x_u ** 2).sum(-1)
    design = np.concatenate([(x_u * (r2 ** (i + 1))[:, None]).reshape(-1, 1) for i in range(terms)], 1)
    target = (x_d - x_u).reshape(-1)
    # A photo-side error e becomes e / J on the undistorted side, J = d r_d / d r_u of the polynomial:
    # reweighted least squares (weights 1 / J of the previous fit) minimises the undistorted-side error.
    weight = np.ones(len(x_u))
    for _ in range(FIT_REWEIGHTS):
        coefficients = np.linalg.lstsq(design * np.repeat(weight, 2)[:, None], target * np.repeat(weight, 2),
                                       rcond=None)[0]
        slope = 1.0 + sum((2 * i + 3) * c * r2 ** (i + 1) for i, c in enumerate(coefficients))
        weight = 1.0 / np.maximum(np.abs(slope), 1e-3)
    undistorting = np.linalg.norm(_polynomial_undistort(x_d, coefficients) * focal_px + centre - undistorted, axis=-1)
    distorting = np.linalg.norm(_polynomial_distort(x_u, coefficients) * focal_px + centre - photo, axis=-1)
    error = np.concatenate([undistorting, distorting])
    error = np.where(np.isfinite(error), error, np.inf)
    return coefficients, {"rms_px": float(np.sqrt(np.mean(error ** 2))), "max_px": float(error.max())}


#: Largest residual (pixels, over the image) of an export with fewer terms before one more is fitted.
EXPORT_TOLERANCE_PX = 1.0


def opencv_coefficients(k: float, focal_px: float, centre, width: float, height: float):
    """OpenCV's distortion coefficients ``[k1, k2, p1, p2, k3]`` for the division model of ``k``
    (:func:`fit_radial_polynomial`): k1, k2 fitted (k3 = 0), or k1, k2, k3 where two terms leave more
    than :data:`EXPORT_TOLERANCE_PX` somewhere in the image (strong barrel); p1 = p2 = 0.  Returns
    (coefficients, the fit's residual in pixels ``{"rms_px", "max_px"}``): over the image,
    ``cv2.undistortPoints`` with them agrees with :func:`undistort_points` and ``cv2.projectPoints``
    with :func:`distort_points` to within ``max_px`` (``undistortPoints`` given enough iterations:
    its default 5 add up to ~0.1 px at strong distortion)."""
    coefficients, residual = fit_radial_polynomial(k, focal_px, centre, width, height, terms=2)
    if residual["max_px"] > EXPORT_TOLERANCE_PX:
        three, residual3 = fit_radial_polynomial(k, focal_px, centre, width, height, terms=3)
        if residual3["max_px"] < residual["max_px"]:
            return [float(three[0]), float(three[1]), 0.0, 0.0, float(three[2])], residual3
    return [float(coefficients[0]), float(coefficients[1]), 0.0, 0.0, 0.0], residual


def opencv_camera(k: float, focal_px: float, centre, width: int, height: int) -> dict[str, Any]:
    """One image's camera in a form ``cv2.FileStorage`` reads (JSON): ``image_width``,
    ``image_height``, ``camera_matrix`` (3 x 3) and ``distortion_coefficients`` (1 x 5,
    :func:`opencv_coefficients`) as ``opencv-matrix`` nodes, and ``distortion_fit_residual_px``
    {rms, max} (pixels)."""
    coefficients, residual = opencv_coefficients(k, focal_px, centre, width, height)
    camera_matrix = [float(focal_px), 0.0, float(centre[0]), 0.0, float(focal_px), float(centre[1]), 0.0, 0.0, 1.0]
    return {"image_width": int(width), "image_height": int(height),
            "camera_matrix": {"type_id": "opencv-matrix", "rows": 3, "cols": 3, "dt": "d", "data": camera_matrix},
            "distortion_coefficients": {"type_id": "opencv-matrix", "rows": 1, "cols": 5, "dt": "d",
                                        "data": coefficients},
            "distortion_fit_residual_px": {"rms": residual["rms_px"], "max": residual["max_px"]}}


class ColmapModel(StrEnum):
    """The COLMAP camera model a division estimate is written as: ``division`` (``SIMPLE_DIVISION``,
    the same model exactly; COLMAP >= 4.0) or ``radial`` (``RADIAL``, k1 k2 fitted to it, with the
    fit's residual; every COLMAP version).  A pinhole estimate is ``SIMPLE_PINHOLE`` either way."""

    DIVISION = "division"
    RADIAL = "radial"

    @classmethod
    def parse(cls, value) -> "ColmapModel":
        """A model from its name (or a :class:`ColmapModel`); FRInputError (one line) otherwise."""
        return enum_member(cls, value, "COLMAP model")


def colmap_division_k(k: float, focal_px: float, width: float, height: float) -> float:
    """COLMAP's division parameter (``SIMPLE_DIVISION`` / ``DIVISION``, radius in units of the focal
    length) of fR's ``k`` (radius in units of :func:`normalising_radius`): ``k (f / s)^2``
    (module docstring).  Dimensionless, like k."""
    return float(k) * (float(focal_px) / normalising_radius(width, height)) ** 2


def colmap_camera(k: float, focal_px: float, centre, width: int, height: int,
                  model: ColmapModel | str = ColmapModel.DIVISION) -> tuple[str, list[float], dict]:
    """COLMAP's camera model and parameters for the division model of ``k``.

    ``SIMPLE_PINHOLE`` (f, cx, cy) for k = 0; else, by ``model`` (:class:`ColmapModel`),
    ``SIMPLE_DIVISION`` (f, cx, cy, :func:`colmap_division_k`): the same model, residual 0 -- or
    ``RADIAL`` (f, cx, cy, k1, k2) fitted by :func:`fit_radial_polynomial`.  COLMAP puts the image
    origin at the top-left *corner* (the first pixel's centre is (0.5, 0.5)), so the principal point
    moves by half a pixel.  Returns (model name, params, residual {"rms_px", "max_px"}, pixels).
    """
    model = ColmapModel.parse(model)
    cx, cy = float(centre[0]) + 0.5, float(centre[1]) + 0.5
    if k == 0:
        return "SIMPLE_PINHOLE", [float(focal_px), cx, cy], {"rms_px": 0.0, "max_px": 0.0}
    if model is ColmapModel.DIVISION:
        return ("SIMPLE_DIVISION", [float(focal_px), cx, cy, colmap_division_k(k, focal_px, width, height)],
                {"rms_px": 0.0, "max_px": 0.0})
    (k1, k2), residual = fit_radial_polynomial(k, focal_px, centre, width, height, terms=2)
    return "RADIAL", [float(focal_px), cx, cy, float(k1), float(k2)], residual


def colmap_cameras_txt(cameras: list[tuple[str, int, int, str, list[float], dict] | tuple[str, str]]) -> str:
    """COLMAP's ``cameras.txt``: the header, then per ``(image, width, height, model, params,
    residual)`` (:func:`colmap_camera`; ids from 1 in order) a comment line with the image (and,
    for a fitted model, its residual in pixels) and the line ``CAMERA_ID MODEL WIDTH HEIGHT
    PARAMS...`` (each number written so that it reads back to the same float); an ``(image,
    reason)`` pair (no estimate) becomes a comment line and takes no id."""
    lines = ["# Camera list with one line of data per camera:",
             "#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]",
             f"# Number of cameras: {sum(len(c) == 6 for c in cameras)}"]
    camera_id = 0
    for camera in cameras:
        if len(camera) == 2:
            lines.append(f"# {camera[0]}: no camera ({camera[1]})")
            continue
        camera_id += 1
        image, width, height, model, params, residual = camera
        fitted = (f" ({model} fitted to fR's division model: residual rms {residual['rms_px']:.3g} px, "
                  f"max {residual['max_px']:.3g} px)" if residual["max_px"] > 0 else "")
        lines.append(f"# {image}{fitted}")
        lines.append(f"{camera_id} {model} {width} {height} " + " ".join(repr(float(p)) for p in params))
    return "\n".join(lines) + "\n"
