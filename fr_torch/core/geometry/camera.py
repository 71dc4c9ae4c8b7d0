"""The :class:`Camera` value type: image size, focal length, principal point and orientation, with
every derived quantity (K, hfov, angles, vanishing points, the horizon) read from it; and
:func:`camera_record`, which gives a record holding a ``camera`` those quantities as read-only
attributes (:class:`CameraField`).

Conventions: :mod:`fr_torch.core.geometry.conventions`.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace
from functools import cached_property

import numpy as np
import torch

from fr_torch.core import exact_math
from fr_torch.core.geometry.conventions import (
    angles_from_rotation,
    focal_from_hfov,
    hfov_from_focal,
    intrinsics,
    principal_point_or_centre,
    resize_points,
    rotation_angles,
    rotation_from_angles,
    vanishing_point_rows,
)


def pitch_from_tilt(tilt_deg: float, roll_deg: float) -> float:
    """Optical-axis pitch (degrees) from the paper's tilt and roll: ``tan(pitch) = tan(tilt) cos(roll)``."""
    tan, cos = (exact_math.of(f, math.radians(a)) for f, a in ((exact_math.tan, tilt_deg), (exact_math.cos, roll_deg)))
    return math.degrees(exact_math.of(exact_math.atan, tan * cos))


@dataclass(frozen=True)
class Camera:
    """A pinhole camera: image size, focal length, principal point and orientation.

    The one camera value of the project: :class:`~fr_torch.core.result.CalibrationResult`,
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
            raise AttributeError(f"{self.name} is derived from .camera (a fr_torch.core.geometry.camera.Camera); set .camera")
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
