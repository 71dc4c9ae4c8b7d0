"""The search's camera parameters: batched ``[pan, pitch, roll, focal]`` rows with named fields.

The search works on tensors of shape (..., 4) holding, per hypothesis, pan, pitch and roll in
degrees (the angles of :func:`fr_torch.core.geometry.conventions.rotation_from_angles`) and the focal length in
pixels; with a distortion parameter (:mod:`fr_torch.core.geometry.lens`) rows have a fifth field,
:data:`DISTORTION`, the division model's normalised k.  :class:`CameraParams` names those fields and holds the conversions; the hot loops index
the raw tensors with :data:`PAN`, :data:`PITCH`, :data:`ROLL`, :data:`FOCAL` and :data:`ANGLES`.
The refinement optimises the focal length in log space (:func:`to_log_focal`).

Example::

    params = CameraParams.from_fields(pan_deg=10.0, pitch_deg=5.0, roll_deg=-2.0, focal_px=500.0)
    params.rotation()          # (3, 3) world->camera
    params.focal_px            # tensor(500., dtype=torch.float64)
"""
from __future__ import annotations

import torch

from fr_torch.core.exact import atan2
from fr_torch.core.geometry.conventions import pan_from_rotation, rotation_from_cos_sin
from fr_torch.core import exact_math

#: Positions of the fields in the last dimension.
PAN, PITCH, ROLL, FOCAL = 0, 1, 2, 3
#: Position of the division model's k in rows of 5 (the search with a distortion parameter).
DISTORTION = 4
#: The three angles (degrees), in the order of :func:`fr_torch.core.geometry.conventions.rotation_from_angles`.
ANGLES = slice(PAN, ROLL + 1)
#: Field names, in order (the columns of a parameter table).
NAMES = ("pan_deg", "pitch_deg", "roll_deg", "focal_px")


def rotations(params: torch.Tensor) -> torch.Tensor:
    """World->camera R (..., 3, 3) of parameter rows (..., 4) (or (..., 3) angles alone)."""
    rad = torch.deg2rad(params[..., ANGLES])
    sin, cos = exact_math.sin_cos(rad)
    return rotation_from_cos_sin(cos, sin)


def to_log_focal(params: torch.Tensor) -> torch.Tensor:
    """Rows (..., 4) or (..., 5) with the focal length replaced by its natural log (the refinement's
    space); a fifth field (k) is kept as it is."""
    return torch.cat([params[..., ANGLES], exact_math.log(params[..., FOCAL:FOCAL + 1]), params[..., FOCAL + 1:]], -1)


def from_log_focal(params: torch.Tensor) -> torch.Tensor:
    """Inverse of :func:`to_log_focal`."""
    return torch.cat([params[..., ANGLES], exact_math.exp(params[..., FOCAL:FOCAL + 1]), params[..., FOCAL + 1:]], -1)


class CameraParams:
    """Batched camera parameters: a tensor ``data`` of shape (..., 4), fields pan, pitch, roll
    (degrees) and focal length (pixels)."""

    __slots__ = ("data",)

    def __init__(self, data: torch.Tensor):
        if data.shape[-1] != 4:
            raise ValueError(f"camera parameters need a last dimension of 4, got shape {tuple(data.shape)}")
        self.data = data

    @classmethod
    def from_fields(cls, pan_deg, pitch_deg, roll_deg, focal_px) -> "CameraParams":
        """Parameters from the four fields (numbers or broadcastable tensors; float64 for numbers)."""
        values = [torch.as_tensor(v, dtype=torch.float64) if not torch.is_tensor(v) else v
                  for v in (pan_deg, pitch_deg, roll_deg, focal_px)]
        return cls(torch.stack(torch.broadcast_tensors(*values), -1))

    @property
    def pan_deg(self) -> torch.Tensor:
        return self.data[..., PAN]

    @property
    def pitch_deg(self) -> torch.Tensor:
        return self.data[..., PITCH]

    @property
    def roll_deg(self) -> torch.Tensor:
        return self.data[..., ROLL]

    @property
    def focal_px(self) -> torch.Tensor:
        return self.data[..., FOCAL]

    @property
    def angles_deg(self) -> torch.Tensor:
        """(..., 3) pan, pitch, roll."""
        return self.data[..., ANGLES]

    @property
    def shape(self) -> torch.Size:
        """The batch shape (without the field dimension)."""
        return self.data.shape[:-1]

    def rotation(self) -> torch.Tensor:
        """World->camera R (..., 3, 3)."""
        return rotations(self.data)

    def to(self, *args, **kwargs) -> "CameraParams":
        return CameraParams(self.data.to(*args, **kwargs))

    def __getitem__(self, index) -> "CameraParams":
        return CameraParams(self.data[index])

    def __repr__(self) -> str:
        return f"CameraParams(shape={tuple(self.shape)}, dtype={self.data.dtype})"


def angles_from_search_rotation(rotation: torch.Tensor) -> torch.Tensor:
    """[pan, pitch, roll] in degrees, (..., 3), from world->camera R (..., 3, 3): the inverse of
    :func:`fr_torch.core.geometry.params.rotations` (``R.T = Ry(pan) Rx(pitch) Rz(roll)``) for |pitch| < 90 deg, pan folded
    into [-45, 45) (:func:`fr_torch.core.geometry.conventions.pan_from_rotation`; the Manhattan frame is symmetric
    under quarter turns about the vertical)."""
    pitch = torch.rad2deg(exact_math.asin((-rotation[..., 2, 1]).clamp(-1.0, 1.0)))
    roll = torch.rad2deg(atan2(rotation[..., 0, 1], rotation[..., 1, 1]))
    return torch.stack([pan_from_rotation(rotation), pitch, roll], -1)
