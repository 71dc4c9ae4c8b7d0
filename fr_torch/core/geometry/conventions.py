"""Camera model and angle conventions shared by the whole project.

Conventions (used everywhere: estimator, datasets, metrics, baselines)
---------------------------------------------------------------------
* Image coordinates: pixels, x right, y down, origin at the centre of the top-left pixel
  (OpenCV / LSD convention): pixel centres are at integer coordinates, the image spans
  ``[-0.5, w - 0.5] x [-0.5, h - 0.5]``.
* Camera frame: x right, y down, z forward (OpenCV).  K = [[f, 0, cx], [0, f, cy], [0, 0, 1]],
  square pixels, no skew; lens distortion, when estimated, is the division model of
  :mod:`fr_torch.core.geometry.lens` (K and R then belong to the undistorted image).  The principal
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

import numpy as np
import torch

from fr_torch.core.exact import atan2
from fr_torch.core import exact_math

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
            return w / 2.0 / exact_math.of(exact_math.tan, math.radians(hfov) / 2.0)
        except (ValueError, ZeroDivisionError):  # 0 or inf: the tensor path's inf / NaN
            with np.errstate(all="ignore"):
                return float(np.float64(w) / 2.0 / np.tan(np.radians(np.float64(hfov)) / 2.0))
    hfov = torch.as_tensor(hfov_deg, dtype=torch.float64) if not torch.is_tensor(hfov_deg) else hfov_deg
    return (width / 2.0) / exact_math.tan(torch.deg2rad(hfov) / 2.0)


def hfov_from_focal(focal_px, width):
    """Horizontal field of view in degrees from the focal length (pixels) and width (pixels):
    ``2 atan(w / (2 f))``.  Tensors in (either argument), tensor out; numbers in, float out."""
    if not (torch.is_tensor(focal_px) or torch.is_tensor(width)):
        focal, w = _scalar(focal_px), _scalar(width)
        try:
            return math.degrees(2.0 * exact_math.of(exact_math.atan, w / 2.0 / focal))
        except ZeroDivisionError:  # f = 0: the tensor path's +-180 (NaN for w = 0)
            with np.errstate(all="ignore"):
                return float(np.degrees(2.0 * np.arctan(np.float64(w) / 2.0 / np.float64(focal))))
    f = torch.as_tensor(focal_px, dtype=torch.float64) if not torch.is_tensor(focal_px) else focal_px
    return torch.rad2deg(2.0 * exact_math.atan((width / 2.0) / f))


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
    sin, cos = exact_math.sin_cos(rad)
    return rotation_from_cos_sin(cos, sin)


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
        "roll_deg": torch.rad2deg(exact_math.atan(-c[..., 0] / cy)),
        "tilt_deg": torch.rad2deg(exact_math.atan(c[..., 2] / cy)),
        "pitch_deg": torch.rad2deg(exact_math.asin(c[..., 2].clamp(-1.0, 1.0))),
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
    first = focal_px * rotation[..., 0, :] + pp[..., 0:1] * last
    # the third row as a view of the first two's shape (torch.broadcast_shapes would import sympy, a
    # third of a second on a process's first search)
    return torch.stack([first, focal_px * rotation[..., 1, :] + pp[..., 1:2] * last, last.expand(first.shape)], -2)


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
        return torch.rad2deg(exact_math.acos(cos))
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


DEG = math.pi / 180.0
