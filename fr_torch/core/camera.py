"""Camera model and angle conventions shared by the whole project.

Conventions (used everywhere: estimator, datasets, metrics, baselines)
---------------------------------------------------------------------
* Image coordinates: pixels, x right, y down, origin at the centre of the top-left pixel
  (OpenCV / LSD convention): pixel centres are at integer coordinates, the image spans
  ``[-0.5, w - 0.5] x [-0.5, h - 0.5]``.
* Camera frame: x right, y down, z forward (OpenCV).  K = [[f, 0, cx], [0, f, cy], [0, 0, 1]],
  square pixels, no skew; lens distortion, when estimated, is the division model of
  :mod:`fr_torch.core.distortion` (K and R then belong to the undistorted image).  The principal
  point defaults to the image centre ``((w - 1) / 2, (h - 1) / 2)`` (:func:`image_centre`).
* World (Manhattan) frame: x = first horizontal Manhattan direction, **y = vertical, pointing
  down (gravity)**, z = second horizontal Manhattan direction.  A level camera with pan = 0
  therefore has R = I.
* ``R`` maps world to camera (``X_cam = R @ X_world``).  Its columns are the three Manhattan
  directions expressed in the camera frame; **column 1 (0-based) is the vertical one**
  (``R[:, 1]`` points down, world-up is ``-R[:, 1]``).  Vanishing point i is ``K @ R[:, i]``
  (homogeneous).
* Angles: the camera-to-world rotation is ``R.T = Ry(pan) @ Rx(pitch) @ Rz(roll)`` (elementary
  active rotations about the world-down y axis, then the camera x axis, then the optical axis).
  Positive pan turns the camera to the right, positive pitch/tilt looks up, positive roll
  rotates the camera clockwise as seen from behind (the scene, and the horizon, appear rotated
  anticlockwise in the image).  All public angles are in **degrees**; internal tensors that end
  in ``_rad`` are radians.
* Reported roll and tilt follow the paper's horizon-based definitions, computed from the
  world-up direction ``c`` expressed in a y-up camera frame (``c = diag(1,-1,1) @ (-R[:, 1])``):
  ``roll = atan(-c_x / c_y)``, ``tilt = atan(c_z / c_y)``.  ``pitch = asin(c_z)`` is the
  elevation of the optical axis.  With the parametrisation above ``roll`` equals the roll
  angle exactly and ``pitch`` equals the pitch angle exactly, while
  ``tan(tilt) = tan(pitch) / cos(roll)`` (tilt 30.38 deg for pitch 30, roll 10).
* Field of view is horizontal: ``hfov = 2 atan(w / (2 f))``.
"""
from __future__ import annotations

import itertools
import math
from dataclasses import dataclass, replace
from functools import cached_property

import numpy as np
import torch

from fr_torch.core.exact import atan2

VERTICAL_AXIS = 1  # column of R holding the (downward) vertical Manhattan direction
Y_UP = (1.0, -1.0, 1.0)  # diag flipping the camera y axis (y-down <-> y-up frames)


def _scalar(value) -> float:
    """A number (or one-element array) as a Python float."""
    return value if isinstance(value, float) else float(np.asarray(value, np.float64).reshape(()))


def focal_from_hfov(hfov_deg, width):
    """Focal length in pixels from the horizontal field of view (degrees) and width (pixels):
    ``(w / 2) / tan(hfov / 2)``.  Tensors in (either argument), tensor out; numbers in, float out."""
    if not (torch.is_tensor(hfov_deg) or torch.is_tensor(width)):
        hfov, w = _scalar(hfov_deg), _scalar(width)
        try:
            return w / 2.0 / math.tan(math.radians(hfov) / 2.0)
        except (ValueError, ZeroDivisionError):  # 0 or inf: the tensor path's inf / NaN
            with np.errstate(all="ignore"):
                return float(np.float64(w) / 2.0 / np.tan(np.radians(np.float64(hfov)) / 2.0))
    hfov = torch.as_tensor(hfov_deg, dtype=torch.float64) if not torch.is_tensor(hfov_deg) else hfov_deg
    return (width / 2.0) / torch.tan(torch.deg2rad(hfov) / 2.0)


def hfov_from_focal(focal_px, width):
    """Horizontal field of view in degrees from the focal length (pixels) and width (pixels):
    ``2 atan(w / (2 f))``.  Tensors in (either argument), tensor out; numbers in, float out."""
    if not (torch.is_tensor(focal_px) or torch.is_tensor(width)):
        focal, w = _scalar(focal_px), _scalar(width)
        try:
            return math.degrees(2.0 * math.atan(w / 2.0 / focal))
        except ZeroDivisionError:  # f = 0: the tensor path's +-180 (NaN for w = 0)
            with np.errstate(all="ignore"):
                return float(np.degrees(2.0 * np.arctan(np.float64(w) / 2.0 / np.float64(focal))))
    f = torch.as_tensor(focal_px, dtype=torch.float64) if not torch.is_tensor(focal_px) else focal_px
    return torch.rad2deg(2.0 * torch.atan((width / 2.0) / f))


def intrinsics(focal_px: torch.Tensor, principal_point: torch.Tensor) -> torch.Tensor:
    """K matrices, shape (..., 3, 3), from focal (...) and principal point (..., 2), pixels."""
    focal_px = torch.as_tensor(focal_px)
    pp = torch.as_tensor(principal_point, dtype=focal_px.dtype, device=focal_px.device)
    pp = pp.expand(focal_px.shape + (2,))
    zeros, ones = torch.zeros_like(focal_px), torch.ones_like(focal_px)
    rows = [
        torch.stack([focal_px, zeros, pp[..., 0]], -1),
        torch.stack([zeros, focal_px, pp[..., 1]], -1),
        torch.stack([zeros, zeros, ones], -1),
    ]
    return torch.stack(rows, -2)


def rotation_from_angles(pan_deg, pitch_deg, roll_deg) -> torch.Tensor:
    """World->camera rotation(s) R, shape (..., 3, 3), from pan / pitch / roll in degrees.

    ``R.T = Ry(pan) Rx(pitch) Rz(roll)``; see the module docstring for the meaning of each angle.
    Inputs broadcast and gradients flow; Python numbers and integer inputs give float64.  The one
    rotation builder of the project (:func:`rotation_from_cos_sin`).
    """
    tensors = [a for a in (pan_deg, pitch_deg, roll_deg) if torch.is_tensor(a) and a.is_floating_point()]
    dtype = tensors[0].dtype if tensors else torch.float64
    device = tensors[0].device if tensors else None
    angles = torch.stack(torch.broadcast_tensors(
        *(torch.as_tensor(a, dtype=dtype, device=device) for a in (pan_deg, pitch_deg, roll_deg))), -1)
    rad = torch.deg2rad(angles)
    return rotation_from_cos_sin(torch.cos(rad), torch.sin(rad))


def rotation_from_cos_sin(cos: torch.Tensor, sin: torch.Tensor) -> torch.Tensor:
    """World->camera R (..., 3, 3) from the cosines and sines of [pan, pitch, roll] (..., 3).

    Closed form of ``R.T = Ry(pan) Rx(pitch) Rz(roll)`` (each a right-handed rotation about the
    camera axis); differentiable.  The search calls it with the cosines it already has.
    """
    cp, ct, cr = cos.unbind(-1)
    sp, st, sr = sin.unbind(-1)
    spst, cpst = sp * st, cp * st
    # Row i of R = column i of R.T.
    rows = torch.stack([cp * cr + spst * sr, ct * sr, cpst * sr - sp * cr,
                        spst * cr - cp * sr, ct * cr, sp * sr + cpst * cr,
                        sp * ct, -st, cp * ct], -1)
    return rows.view(cos.shape[:-1] + (3, 3))


def world_up_in_camera_yup(rotation: torch.Tensor, vertical_axis: int = VERTICAL_AXIS) -> torch.Tensor:
    """World-up unit vector c in a y-up camera frame (x right, y up, z forward), shape (..., 3)."""
    down = rotation[..., :, vertical_axis]
    flip = torch.tensor(Y_UP, dtype=rotation.dtype, device=rotation.device)
    up = -down * flip
    # The vertical direction carries no sign in a vanishing-point model: take the one with c_y >= 0.
    sign = torch.where(up[..., 1:2] < 0, -1.0, 1.0).to(up.dtype)
    return up * sign


def horizon_angles(rotation: torch.Tensor, vertical_axis: int = VERTICAL_AXIS) -> dict[str, torch.Tensor]:
    """Paper definitions of roll, tilt and the optical-axis pitch, degrees, from R (..., 3, 3).

    roll = atan(-c_x / c_y), tilt = atan(c_z / c_y), pitch = asin(c_z) with c the world-up
    direction in a y-up camera frame.  ``atan`` (not atan2) as in the paper: range (-90, 90).
    """
    c = world_up_in_camera_yup(rotation, vertical_axis)
    cy = c[..., 1].clamp_min(1e-12)
    return {
        "roll_deg": torch.rad2deg(torch.atan(-c[..., 0] / cy)),
        "tilt_deg": torch.rad2deg(torch.atan(c[..., 2] / cy)),
        "pitch_deg": torch.rad2deg(torch.asin(c[..., 2].clamp(-1.0, 1.0))),
    }


def pan_from_rotation(rotation: torch.Tensor, vertical_axis: int = VERTICAL_AXIS) -> torch.Tensor:
    """Pan in degrees, folded into [-45, 45) (a Manhattan frame is symmetric under 90 deg turns).

    Pan is the heading of the optical axis measured from the nearest horizontal Manhattan
    direction, about the vertical; positive to the right.
    """
    horizontal = [i for i in range(3) if i != vertical_axis]
    # Optical axis (camera z) in world coordinates is row 2 of R.
    axis_world = rotation[..., 2, :]
    heading = atan2(axis_world[..., horizontal[0]], axis_world[..., horizontal[1]])
    deg = torch.rad2deg(heading)
    return torch.remainder(deg + 45.0, 90.0) - 45.0


def angles_from_rotation(rotation: torch.Tensor, vertical_axis: int = VERTICAL_AXIS) -> dict[str, torch.Tensor]:
    """pan (folded to [-45, 45)), roll, tilt and pitch in degrees from world->camera R (..., 3, 3)."""
    out = horizon_angles(rotation, vertical_axis)
    out["pan_deg"] = pan_from_rotation(rotation, vertical_axis)
    return out


def vanishing_points(focal_px: torch.Tensor, principal_point: torch.Tensor, rotation: torch.Tensor) -> torch.Tensor:
    """Homogeneous vanishing points K @ R, shape (..., 3, 3): column i is VP i (never dehomogenised).

    ``focal_px`` (...), ``principal_point`` (..., 2) pixels, broadcastable with ``rotation``'s
    batch shape.  Written out (rows ``f R_0 + c_x R_2``, ``f R_1 + c_y R_2``, ``R_2``, each product
    and sum rounded once), not as a matrix product: the same bits in any batch and on any kernel
    set (:mod:`fr_torch.core.exact`).
    """
    focal_px = torch.as_tensor(focal_px, dtype=rotation.dtype, device=rotation.device)[..., None]
    pp = torch.as_tensor(principal_point, dtype=rotation.dtype, device=rotation.device)
    last = rotation[..., 2, :]
    return torch.stack([focal_px * rotation[..., 0, :] + pp[..., 0:1] * last,
                        focal_px * rotation[..., 1, :] + pp[..., 1:2] * last,
                        last.expand(torch.broadcast_shapes(last.shape, focal_px.shape))], -2)


def vanishing_point_rows(focal_px: torch.Tensor, principal_point: torch.Tensor,
                         rotation: torch.Tensor) -> torch.Tensor:
    """Vanishing points as rows, (..., 3, 3): row i = ``K @ R[:, i]`` (x, y, w) signed so that
    ``w >= 0`` (the record layout of :attr:`Camera.vanishing_points`)."""
    return signed_rows(vanishing_points(focal_px, principal_point, rotation).transpose(-1, -2))


def signed_rows(points: torch.Tensor) -> torch.Tensor:
    """Homogeneous points as rows (..., 3) (x, y, w), each negated where ``w < 0`` so that ``w >= 0``."""
    return points * torch.where(points[..., 2:] < 0, -1.0, 1.0).to(points.dtype)


def rotation_angle_deg(r_a, r_b):
    """Geodesic angle (degrees) between rotations r_a and r_b, shape (..., 3, 3) -> (...).

    Tensors in, tensor out (differentiable); arrays in, array out (a float for single matrices).
    """
    if torch.is_tensor(r_a) and torch.is_tensor(r_b):
        rel = r_a.transpose(-1, -2) @ r_b
        cos = ((rel.diagonal(dim1=-2, dim2=-1).sum(-1) - 1.0) / 2.0).clamp(-1.0, 1.0)
        return torch.rad2deg(torch.acos(cos))
    rel = np.swapaxes(np.asarray(r_a, np.float64), -1, -2) @ np.asarray(r_b, np.float64)
    angle = np.degrees(np.arccos(np.clip((np.trace(rel, axis1=-2, axis2=-1) - 1.0) / 2.0, -1.0, 1.0)))
    return float(angle) if np.ndim(angle) == 0 else angle


def image_centre(width, height):
    """Default principal point (pixels): the exact centre of a ``width`` x ``height`` image,
    ``((w - 1) / 2, (h - 1) / 2)`` with pixel centres at integer coordinates -- where OpenCV
    (``cv2.getDefaultNewCameraMatrix(..., centerPrincipalPoint=True)``) and COLMAP (``(w / 2, h / 2)``
    in its pixels, whose origin is the top-left pixel's corner) put a centred camera.

    Numbers, arrays or tensors in (broadcast), the same kind out: ``(cx, cy)``.
    """
    return ((width - 1) / 2.0, (height - 1) / 2.0)


def resize_points(points, size, new_size) -> np.ndarray:
    """Where points of an image of ``size`` lie once the image is resized to ``new_size``.

    The geometry of ``cv2.resize`` (every interpolation) and of ``torch`` resampling with
    ``align_corners=False``: pixel centres at integer coordinates, the image's edges ``-0.5`` and
    ``w - 0.5`` map to the new edges, so ``x' = (x + 0.5) w' / w - 0.5`` and ``y' = (y + 0.5) h' / h
    - 0.5`` (each axis by its own ratio) and :func:`image_centre` maps to :func:`image_centre`
    exactly.  Lengths (a focal length) scale by the ratio alone.

    Args:
        points: (..., 2) ``(x, y)`` pixels of the ``size`` image; (..., 4) segment rows ``[x1, y1,
            x2, y2]`` are taken as two points each.
        size, new_size: ``(width, height)`` in pixels, before and after (positive).

    Returns:
        float64 numpy array of ``points``' shape, pixels of the ``new_size`` image.
    """
    points = np.asarray(points, np.float64)
    old, new = np.asarray(size, np.float64), np.asarray(new_size, np.float64)
    if points.shape[-1] == 4:
        old, new = np.tile(old, 2), np.tile(new, 2)
    return (points + 0.5) * new / old - 0.5


def resize_homogeneous(points, size, new_size) -> np.ndarray:
    """:func:`resize_points` for homogeneous points (..., 3) rows ``(x, y, w)`` (vanishing points,
    ``w = 0`` at infinity): ``x' = x r + w (r - 1) / 2`` with ``r = w' / w`` per axis; float64 numpy."""
    points = np.asarray(points, np.float64)
    ratio = np.asarray(new_size, np.float64) / np.asarray(size, np.float64)
    out = points.copy()
    out[..., :2] = points[..., :2] * ratio + points[..., 2:3] * (ratio - 1.0) / 2.0
    return out


def principal_point_or_centre(principal_point, width: float, height: float) -> tuple[float, float]:
    """``principal_point`` as an (x, y) float pair, or the image centre when it is None."""
    if principal_point is None:
        return image_centre(width, height)
    x, y = (float(v) for v in np.asarray(principal_point, np.float64).reshape(2))
    return (x, y)


# ---------------------------------------------------------------------------------- Manhattan frames

def manhattan_symmetries() -> np.ndarray:
    """The 24 proper signed permutation matrices P (det +1), shape (24, 3, 3): the rotation group of
    the cube.  ``R @ P`` describes the same Manhattan frame as R with its axes relabelled."""
    out = []
    for perm in itertools.permutations(range(3)):
        for signs in itertools.product((1.0, -1.0), repeat=3):
            p = np.zeros((3, 3))
            for row, col in enumerate(perm):
                p[row, col] = signs[row]
            if np.linalg.det(p) > 0:
                out.append(p)
    return np.stack(out)


MANHATTAN_SYMMETRIES = manhattan_symmetries()


def align_to(rotation: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """The relabelling ``rotation @ P`` of a Manhattan frame closest (chordal) to ``reference``."""
    candidates = np.asarray(rotation, np.float64)[None] @ MANHATTAN_SYMMETRIES  # (24, 3, 3)
    return candidates[int(np.argmax(np.einsum("kij,ij->k", candidates, reference)))]


def manhattan_frame_error_deg(r_ref: np.ndarray, r_est: np.ndarray) -> float:
    """``min_P angle(r_ref, r_est P)`` over the 24 symmetries: rotation error up to relabelling (deg)."""
    return float(np.min(rotation_angle_deg(np.asarray(r_ref, np.float64)[None],
                                           np.asarray(r_est, np.float64)[None] @ MANHATTAN_SYMMETRIES)))


def nearest_rotation(matrix: np.ndarray) -> np.ndarray:
    """Closest proper rotation (Frobenius norm) to a 3 x 3 matrix (orthogonal Procrustes, SVD).

    With ``matrix = sum_i w_i R_i`` this is the weighted chordal L2 mean of the rotations.
    """
    u, _, vt = np.linalg.svd(np.asarray(matrix, np.float64))
    d = np.sign(np.linalg.det(u @ vt)) or 1.0
    return u @ np.diag([1.0, 1.0, d]) @ vt


def rotation_angles(rotation) -> dict[str, float]:
    """pan (folded), roll, tilt, pitch in degrees (floats) of one world->camera R (array or tensor)."""
    angles = angles_from_rotation(torch.as_tensor(np.asarray(rotation, np.float64)))
    return {k: float(v) for k, v in angles.items()}


# ---------------------------------------------------------------------------------- the horizon

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
    try:
        line = np.linalg.solve(K.T, rotation[:, vertical_axis])
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
    (:mod:`fr_torch.core.distortion`: photo pixel p, undistorted ``u = c0 + (p - c0) / (1 + k r^2)``,
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
    (:func:`fr_torch.core.reliability_bounds.horizon_bound_pct`); None without one.
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


# ---------------------------------------------------------------------------------- value type

def pitch_from_tilt(tilt_deg: float, roll_deg: float) -> float:
    """Optical-axis pitch (degrees) from the paper's tilt and roll: ``tan(pitch) = tan(tilt) cos(roll)``."""
    return math.degrees(math.atan(math.tan(math.radians(tilt_deg)) * math.cos(math.radians(roll_deg))))


@dataclass(frozen=True)
class Camera:
    """A pinhole camera: image size, focal length, principal point and orientation.

    The one camera value of the project: :class:`~fr_torch.core.estimator.CalibrationResult`,
    :class:`~fr_torch.plugins.interface.CameraEstimate`, :class:`~fr_torch.video.fusion.FrameEstimate`,
    :class:`~fr_torch.video.fusion.FusedState` and the harness's ``CalibrationSample`` hold one and read
    every derived quantity (K, hfov, angles, vanishing points) from it through :class:`CameraField`.

    Args:
        width, height: image size in pixels (0 where a method was not told the height).
        focal_px: focal length in pixels (square pixels, no skew); None when unknown (a method
            that estimates only the orientation): ``K``, ``hfov_deg`` and the vanishing points are
            then None.
        principal_point: (x, y) in pixels; None -> the image centre ``((w - 1) / 2, (h - 1) / 2)``
            (:func:`image_centre`).
        rotation: (3, 3) world->camera R (stored as float64 numpy), or None when unknown.
        pan_known: False when only the direction of gravity is known, not the horizontal Manhattan
            directions (a horizon-only method, a view whose Manhattan frame is unknown): ``rotation``
            is then any rotation with the right roll and pitch (e.g. ``rotation_from_angles(0,
            pitch, roll)``); roll / tilt / pitch are reported, pan, ``known_rotation`` and the
            vanishing points are not.

    Convention:
        Pixels: x right, y down.  Camera frame x right, y down, z forward.  World frame: the
        Manhattan frame, y = vertical pointing down; ``R[:, 1]`` is the vertical direction in the
        camera frame.  ``K = [[f, 0, cx], [0, f, cy], [0, 0, 1]]``.  Angles in degrees with the
        definitions of this module's docstring (roll / tilt from the horizon, pan folded into
        [-45, 45)).  Vanishing points are rows ``(x, y, w)`` of ``(K R).T`` with ``w >= 0``.

    No validation: a NaN focal length or rotation is kept (the estimator and the harness turn it
    into a failure).  ``to_torch`` returns the tensors the estimator works with; every other
    accessor gives numpy arrays / floats, computed once per value.
    """

    width: int
    height: int
    focal_px: float | None = None
    principal_point: tuple[float, float] | None = None
    rotation: np.ndarray | None = None
    pan_known: bool = True

    def __post_init__(self) -> None:
        object.__setattr__(self, "principal_point",
                           principal_point_or_centre(self.principal_point, self.width, self.height))
        if self.focal_px is not None:
            object.__setattr__(self, "focal_px", float(self.focal_px))
        if self.rotation is not None:
            object.__setattr__(self, "rotation", np.asarray(self.rotation, np.float64).reshape(3, 3))

    @classmethod
    def from_hfov(cls, hfov_deg: float, width: int, height: int, **kwargs) -> "Camera":
        """A camera from its horizontal field of view.

        Args:
            hfov_deg: horizontal field of view, degrees, in (0, 180).
            width, height: image size, pixels.
            **kwargs: ``principal_point``, ``rotation``, ``pan_known`` as for the constructor.

        Returns:
            Camera with ``focal_px = (w / 2) / tan(hfov / 2)``.
        """
        return cls(width, height, focal_from_hfov(hfov_deg, width), **kwargs)

    @classmethod
    def from_angles(cls, width: int, height: int, focal_px: float | None = None, *, roll_deg: float,
                    pitch_deg: float | None = None, tilt_deg: float | None = None, pan_deg: float | None = None,
                    principal_point=None) -> "Camera":
        """A camera from roll and pitch (or the paper's tilt) in degrees, and pan when known.

        Args:
            width, height, focal_px, principal_point: as for the constructor.
            roll_deg: roll (degrees).
            pitch_deg, tilt_deg: pitch of the optical axis, or the paper's tilt (one of them;
                ``tan(tilt) = tan(pitch) / cos(roll)``).
            pan_deg: pan (degrees); None -> ``pan_known = False`` (R built with pan 0).

        Returns:
            Camera with ``rotation = rotation_from_angles(pan or 0, pitch, roll)`` (3, 3).
        """
        if pitch_deg is None:
            if tilt_deg is None:
                raise ValueError("Camera.from_angles needs pitch_deg or tilt_deg")
            pitch_deg = pitch_from_tilt(tilt_deg, roll_deg)
        rotation = rotation_from_angles(0.0 if pan_deg is None else pan_deg, pitch_deg, roll_deg).numpy()
        return cls(width, height, focal_px, principal_point, rotation, pan_known=pan_deg is not None)

    @cached_property
    def K(self) -> np.ndarray | None:
        """Intrinsic matrix ``[[f, 0, cx], [0, f, cy], [0, 0, 1]]``, (3, 3) float64 numpy (built by
        :func:`intrinsics`); None when the focal length is unknown."""
        if self.focal_px is None:
            return None
        return intrinsics(torch.tensor(self.focal_px, dtype=torch.float64),
                          torch.tensor(self.principal_point, dtype=torch.float64)).numpy()

    @cached_property
    def hfov_deg(self) -> float | None:
        """Horizontal field of view in degrees, ``2 atan(w / (2 f))``; None when the focal length or
        the width is unknown."""
        return None if self.focal_px is None or self.width <= 0 else hfov_from_focal(self.focal_px, self.width)

    @property
    def known_rotation(self) -> np.ndarray | None:
        """(3, 3) world->camera R when the whole orientation is known (None when ``pan_known`` is False)."""
        return self.rotation if self.pan_known else None

    @cached_property
    def angles(self) -> dict[str, float]:
        """``pan_deg``, ``roll_deg``, ``tilt_deg``, ``pitch_deg`` (floats, degrees) of the rotation.

        Empty when the rotation is unknown; without ``pan_deg`` when ``pan_known`` is False.
        """
        if self.rotation is None:
            return {}
        angles = rotation_angles(self.rotation)
        if not self.pan_known:
            del angles["pan_deg"]
        return angles

    @cached_property
    def vanishing_points(self) -> np.ndarray | None:
        """Vanishing points, (3, 3) float64: row i = homogeneous VP ``(x, y, w)`` (pixels, ``w >= 0``,
        never dehomogenised) of Manhattan direction i, i.e. ``K @ R[:, i]`` (:func:`vanishing_points`);
        None unless K and the whole rotation are known."""
        if self.K is None or self.known_rotation is None:
            return None
        return vanishing_point_rows(torch.tensor(self.focal_px, dtype=torch.float64),
                                    torch.tensor(self.principal_point, dtype=torch.float64),
                                    torch.as_tensor(self.rotation)).numpy()

    @classmethod
    def many(cls, width: np.ndarray, height: np.ndarray, focal_px: np.ndarray, principal_point: np.ndarray,
             rotation: np.ndarray) -> list["Camera"]:
        """B cameras with a known focal length and whole rotation, their derived values (K, hfov,
        angles, vanishing points) computed for the batch at once by the same functions the single
        accessors call (values equal to computing them camera by camera; no per-camera torch work).

        Args:
            width, height: (B,) image sizes, pixels.
            focal_px: (B,) focal lengths, pixels.
            principal_point: (B, 2) (x, y), pixels.
            rotation: (B, 3, 3) world->camera R.

        Returns:
            list of B :class:`Camera`.
        """
        width, height = np.asarray(width).reshape(-1), np.asarray(height).reshape(-1)
        focal = torch.as_tensor(np.asarray(focal_px, np.float64).reshape(-1))
        pp = torch.as_tensor(np.asarray(principal_point, np.float64).reshape(-1, 2))
        rot = torch.as_tensor(np.asarray(rotation, np.float64).reshape(-1, 3, 3))
        K = intrinsics(focal, pp).numpy()
        hfov = hfov_from_focal(focal, torch.as_tensor(width, dtype=torch.float64)).numpy()
        angles = {key: value.numpy() for key, value in angles_from_rotation(rot).items()}
        vps = vanishing_point_rows(focal, pp, rot).numpy()
        rot_np, pp_np, focal_np = rot.numpy(), pp.numpy(), focal.numpy()
        cameras = []
        for j in range(len(focal_np)):
            camera = cls(int(width[j]), int(height[j]), focal_np[j], (pp_np[j, 0], pp_np[j, 1]), rot_np[j])
            # Fill the cached properties with the batch's values (cached_property keeps them here).
            camera.__dict__.update(K=K[j], hfov_deg=float(hfov[j]) if width[j] > 0 else None,
                                   angles={key: float(value[j]) for key, value in angles.items()},
                                   vanishing_points=vps[j])
            cameras.append(camera)
        return cameras

    def resized(self, width: int, height: int, factor: float | None = None) -> "Camera":
        """The same camera for the image resized to ``width`` x ``height`` pixels: the focal length
        scales by ``factor`` (default ``width / self.width``), the principal point moves as the
        resize moves a pixel (:func:`resize_points`, pixel centres at integers: the image centre
        stays the image centre).  A zero side of this camera's size is taken as ``new / factor``."""
        factor = width / max(self.width, 1) if factor is None else float(factor)
        size = (self.width if self.width > 0 else width / factor, self.height if self.height > 0 else height / factor)
        x, y = resize_points(self.principal_point, size, (width, height))
        return replace(self, width=width, height=height,
                       focal_px=None if self.focal_px is None else self.focal_px * factor,
                       principal_point=(float(x), float(y)))

    def to_torch(self, dtype: torch.dtype = torch.float64, device=None) -> dict[str, torch.Tensor]:
        """The camera as tensors for the torch code (the estimator's layout).

        Args:
            dtype, device: of the returned tensors.

        Returns:
            ``{"principal_point": (2,), "focal_px": (), "K": (3, 3), "rotation": (3, 3)}``; the
            focal / K keys only when the focal length is known, ``rotation`` only when a rotation is.
        """
        out = {"principal_point": torch.tensor(self.principal_point, dtype=dtype, device=device)}
        if self.focal_px is not None:
            out["focal_px"] = torch.tensor(self.focal_px, dtype=dtype, device=device)
            out["K"] = torch.as_tensor(self.K, dtype=dtype, device=device)
        if self.rotation is not None:
            out["rotation"] = torch.as_tensor(self.rotation, dtype=dtype, device=device)
        return out


class CameraField:
    """A record attribute derived from the record's ``camera`` (a :class:`Camera` or None).

    Reading gives ``getter(camera)`` (None without a camera).  The attribute is read-only, except
    that assigning None makes the part of the camera it comes from unknown (``part``: the Camera
    field set to None, e.g. ``focal_px`` for ``hfov_deg``, ``rotation`` for ``roll_deg``), which is
    how a check that finds a NaN clears an estimate.
    """

    def __init__(self, getter, part: str | None):
        self.getter, self.part = getter, part

    def __set_name__(self, owner, name: str) -> None:
        self.name = name

    def __get__(self, obj, objtype=None):
        if obj is None:
            return self
        camera = obj.camera
        return None if camera is None else self.getter(camera)

    def __set__(self, obj, value) -> None:
        if value is not None or self.part is None:
            raise AttributeError(f"{self.name} is derived from .camera (a fr_torch.core.camera.Camera); set .camera")
        if obj.camera is not None:
            obj.camera = replace(obj.camera, **{self.part: None})


# attribute -> (getter, the Camera field that assigning None clears)
CAMERA_FIELDS = {
    "focal_px": (lambda c: c.focal_px, "focal_px"),
    "hfov_deg": (lambda c: c.hfov_deg, "focal_px"),
    "principal_point": (lambda c: c.principal_point, None),
    "rotation": (lambda c: c.known_rotation, "rotation"),
    "vanishing_points": (lambda c: c.vanishing_points, "rotation"),
    **{key: ((lambda c, key=key: c.angles.get(key)), "rotation")
       for key in ("pan_deg", "tilt_deg", "roll_deg", "pitch_deg")},
}


def camera_record(cls):
    """Class decorator: give a record with a ``camera`` attribute the derived, read-only attributes
    ``focal_px``, ``hfov_deg``, ``principal_point``, ``rotation`` (None unless the whole orientation
    is known), ``pan_deg``, ``tilt_deg``, ``roll_deg``, ``pitch_deg`` and ``vanishing_points``
    (:class:`CameraField`; None where the camera, or that part of it, is unknown; assigning None
    makes that part unknown)."""
    for name, (getter, part) in CAMERA_FIELDS.items():
        attribute = CameraField(getter, part)
        attribute.__set_name__(cls, name)
        setattr(cls, name, attribute)
    return cls


DEG = math.pi / 180.0
