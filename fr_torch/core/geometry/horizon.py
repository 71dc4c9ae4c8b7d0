"""The horizon: the vanishing line of the horizontal planes, where it crosses the image's borders, and
the :class:`Horizon` value fR reports and the horizon benchmark scores.

Conventions: :mod:`fr_torch.core.geometry.conventions` (pixels, y down; R world->camera with the
vertical in column 1).  Through a division-model lens (:mod:`fr_torch.core.geometry.lens`) the
horizon is a curve in the photo; its border crossings are found on the curve.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from fr_torch.core.geometry.camera import Camera
from fr_torch.core.geometry.conventions import VERTICAL_AXIS, principal_point_or_centre


def horizon_line(K, rotation, vertical_axis: int = VERTICAL_AXIS) -> np.ndarray | None:
    """The horizon of a pinhole camera: the vanishing line of the horizontal planes.

    ``l = K^-T R[:, vertical]`` (every horizontal direction d has ``R[:, vertical] . d = 0``, so its
    vanishing point ``K d`` lies on l), as ``(a, b, c)`` with ``a x + b y + c = 0`` in pixels of the
    (undistorted) image, scaled to ``a^2 + b^2 = 1`` and ``b >= 0``: ``a x + b y + c`` is then the
    signed distance in pixels, positive below the horizon (y grows downwards).  The line through
    any two horizontal vanishing points is the same line.

    Args:
        K: (3, 3) intrinsics, pixels.
        rotation: (3, 3) world->camera R; only its vertical column is used (a camera whose pan is
            unknown has the right one).
        vertical_axis: the column of R that is the vertical.

    Returns:
        (3,) float64, or None when the horizon is at infinity (the vertical along the optical
        axis: a camera looking straight up or down) or the inputs are not finite.
    """
    K, rotation = np.asarray(K, np.float64), np.asarray(rotation, np.float64)
    if not (np.isfinite(K).all() and np.isfinite(rotation).all()):
        return None
    v = rotation[:, vertical_axis]
    if K[1, 0] == 0 and K[2, 0] == 0 and K[2, 1] == 0 and np.all(np.diag(K) != 0):
        # K^T is lower triangular: forward substitution, one rounding per step (LAPACK's solver
        # picks its kernel by CPU)
        x0 = v[0] / K[0, 0]
        x1 = (v[1] - K[0, 1] * x0) / K[1, 1]
        line = np.array([x0, x1, ((v[2] - K[0, 2] * x0) - K[1, 2] * x1) / K[2, 2]])
    else:
        try:
            line = np.linalg.solve(K.T, v)
        except np.linalg.LinAlgError:
            return None
    return normalised_line(line, at_infinity=1e-12)


def normalised_line(line, at_infinity: float = 0.0) -> np.ndarray | None:
    """A line ``(a, b, c)`` (pixels) scaled to ``a^2 + b^2 = 1`` and ``b >= 0`` (``a > 0`` when b = 0),
    as :func:`horizon_line` reports it; None when it is not finite or is the line at infinity
    (``hypot(a, b) <= at_infinity |c|``)."""
    line = np.asarray(line, np.float64).reshape(3)
    norm = math.hypot(line[0], line[1])
    if not (np.isfinite(line).all() and norm > at_infinity * abs(line[2]) and norm > 0):
        return None
    line = line / norm
    return -line if line[1] < 0 or (line[1] == 0 and line[0] < 0) else line


def border_columns(width: float) -> tuple[float, float]:
    """The image columns at which a horizon is reported and scored: the centres of the first and
    last pixel columns, ``x = 0`` and ``x = w - 1`` (the horizon benchmark's: Lezama et al.'s
    evaluation code reads MATLAB columns 1 and W)."""
    return (0.0, float(width) - 1.0)


def horizon_border_y(line, width: float, height: float, k: float = 0.0,
                     centre=None) -> tuple[float | None, float | None]:
    """Where the horizon crosses the left and right borders (:func:`border_columns`) of the photo.

    Pinhole (``k = 0``): ``y = -(a x + c) / b`` on the line.  With a division-model lens
    (:mod:`fr_torch.core.geometry.lens`: photo pixel p, undistorted ``u = c0 + (p - c0) / (1 + k r^2)``,
    ``r = |p - c0| / s``, ``s`` half the image diagonal) the straight horizon of the undistorted
    image is a curve in the photo; its crossing with the column ``x_b`` is the photo point
    ``p = (x_b, y)`` whose undistorted point lies on ``l``.  With ``dx = x_b - c0_x``,
    ``dy = y - c0_y`` and ``L0 = l . (c0, 1)`` that is the quadratic
    ``(L0 k / s^2) dy^2 + b dy + (a dx + L0 (1 + k dx^2 / s^2)) = 0``, of which the root that tends to
    the pinhole one as ``k -> 0`` is taken (written so that it stays exact for small k).

    Args:
        line: (3,) ``(a, b, c)`` of the undistorted image (:func:`horizon_line`), pixels.
        width, height: photo size, pixels.
        k: the division model's k (normalised by half the image diagonal; 0 = pinhole).
        centre: the distortion centre (x, y) pixels (the principal point); None = image centre.

    Returns:
        (y at x = 0, y at x = w - 1) in photo pixels; None for a border the horizon does not cross
        (a vertical horizon, or a pincushion lens whose reach ends before it) or a non-finite one.
    """
    a, b, c = (float(v) for v in np.asarray(line, np.float64).reshape(3))
    cx, cy = principal_point_or_centre(centre, width, height)
    scale2 = (float(width) ** 2 + float(height) ** 2) / 4.0
    out = []
    for x in border_columns(width):
        if k == 0.0:
            y = -(a * x + c) / b if abs(b) > 1e-12 else None
        else:
            dx = x - cx
            at_centre = a * cx + b * cy + c
            quad, lin, const = at_centre * k / scale2, b, a * dx + at_centre * (1.0 + k * dx * dx / scale2)
            disc = lin * lin - 4.0 * quad * const
            denominator = lin + math.copysign(math.sqrt(disc), lin) if disc >= 0 else 0.0
            y = cy - 2.0 * const / denominator if abs(denominator) > 1e-12 else None
            if y is not None and not 1.0 + k * (dx * dx + (y - cy) ** 2) / scale2 > 0:
                y = None  # beyond the lens's reach
        out.append(y if y is not None and math.isfinite(y) else None)
    return out[0], out[1]


def line_through(p, q) -> np.ndarray | None:
    """The line ``(a, b, c)`` through two points (x, y) in pixels, scaled as :func:`horizon_line`
    (``a^2 + b^2 = 1``, ``b >= 0``); None when they coincide or are not finite."""
    return normalised_line(np.cross([p[0], p[1], 1.0], [q[0], q[1], 1.0]))


@dataclass(frozen=True)
class Horizon:
    """A horizon in the input image's pixels: what fR reports and what the horizon benchmark scores.

    ``line``: ``(a, b, c)``, ``a x + b y + c = 0`` in photo pixels (``a^2 + b^2 = 1``, ``b >= 0``).
    For a pinhole camera it is the horizon itself (:func:`horizon_line`).  Through a division-model
    lens the horizon is a curve in the photo; ``line`` is then the chord through its two border
    crossings (the straight line a benchmark label of that photo would be), and the curve itself
    follows from the undistorted line and the lens (the overlay draws it).
    ``left_y`` / ``right_y``: y (photo pixels) where the horizon crosses the borders ``x = 0`` and
    ``x = w - 1`` (:func:`border_columns`); None where it does not (a vertical horizon).
    ``bound_pct``: a 90 % bound of the larger of the two border errors, % of the image height
    (:func:`fr_torch.core.reliability.bounds.horizon_bound_pct`); None without one.
    """

    line: tuple[float, float, float]
    left_y: float | None
    right_y: float | None
    width: int
    height: int
    bound_pct: float | None = None

    @classmethod
    def from_line(cls, line, width: int, height: int, k: float = 0.0, centre=None,
                  bound_pct: float | None = None) -> "Horizon | None":
        """The horizon whose undistorted line is ``line`` (3,) at any scale, seen through a division lens
        ``k`` around ``centre`` (:func:`horizon_border_y`); None without a (finite) line."""
        line = None if line is None else normalised_line(line)
        if line is None:
            return None
        left, right = horizon_border_y(line, width, height, k, centre)
        if k != 0.0 and left is not None and right is not None:
            chord = line_through((border_columns(width)[0], left), (border_columns(width)[1], right))
            line = line if chord is None else chord
        return cls(tuple(float(v) for v in line), left, right, int(width), int(height), bound_pct)

    @classmethod
    def from_camera(cls, camera: "Camera", k: float = 0.0, bound_pct: float | None = None) -> "Horizon | None":
        """The horizon of ``camera`` (its K and vertical, :func:`horizon_line`) through a division
        lens ``k`` centred on its principal point; None without a focal length or a rotation."""
        if camera is None or camera.K is None or camera.rotation is None:
            return None
        return cls.from_line(horizon_line(camera.K, camera.rotation), camera.width, camera.height, k,
                             camera.principal_point, bound_pct)

    def error(self, truth: "Horizon") -> float:
        """The horizon benchmark's error of this horizon against ``truth`` (Barinova 2010, Lezama
        2014, Zhai 2016): the larger vertical distance between the two at the left and right
        borders, divided by the image height (a fraction; inf when either lacks a crossing)."""
        pairs = ((self.left_y, truth.left_y), (self.right_y, truth.right_y))
        if any(v is None for pair in pairs for v in pair):
            return math.inf
        return max(abs(y - t) for y, t in pairs) / float(truth.height)

    def to_json(self) -> dict:
        """``{"line": [a, b, c], "left_y", "right_y", "bound_pct"}`` (None where absent)."""
        return {"line": list(self.line), "left_y": self.left_y, "right_y": self.right_y, "bound_pct": self.bound_pct}
