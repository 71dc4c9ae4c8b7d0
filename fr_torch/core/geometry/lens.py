"""Radial lens distortion: the one-parameter division model and its conversions.

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
"""
from __future__ import annotations

import math
from typing import Any

import numpy as np
import torch
from fr_torch.core import exact_math

#: Open interval of k over which the division model is one-to-one on the image (module docstring).
K_LIMITS = (-1.0, 1.0)


def normalising_radius(width, height):
    """Half the image diagonal ``sqrt(w^2 + h^2) / 2`` (pixels): the unit of r in the division
    model.  Numbers in, float out; tensors in, tensor out."""
    if torch.is_tensor(width) or torch.is_tensor(height):
        return exact_math.sqrt(torch.as_tensor(width) ** 2 + torch.as_tensor(height) ** 2) / 2
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
        scale = 2 / (1 + exact_math.sqrt(disc))
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
