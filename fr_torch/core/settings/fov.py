"""The field-of-view search range, one value type from the command line to the search.

A :class:`FovRange` is the range of the field of view **across the image's long side**, in
degrees: for a landscape image that is the horizontal FOV; a portrait image gets the same focal
range in pixels as the same camera held in landscape.  Every method that searches the focal
length takes one, so one range means the same camera for all of them.  Results still report
``hfov_deg``, the horizontal FOV.

Example::

    >>> FovRange.parse("paper")
    FovRange(min_deg=50.0, max_deg=130.0)
    >>> FovRange.parse("40,90").focal_bounds(640)   # (f_min, f_max) in pixels for a 640 px long side
    (167.9..., 381.3...)
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import ClassVar

import torch

from fr_torch.core.geometry.conventions import focal_from_hfov, hfov_from_focal
from fr_torch.errors import FRInputError

#: A pinhole camera whose FOV across the long side lies outside these degrees cannot be estimated;
#: the bounds of every search range and of every focal length a user gives.
FOV_LIMITS_DEG = (1.0, 179.0)


@dataclass(frozen=True)
class FovRange:
    """Search range ``[min_deg, max_deg]`` of the FOV across the image's long side, degrees.

    Valid when finite and ``1 <= min_deg < max_deg <= 179`` (:data:`FOV_LIMITS_DEG`); anything else
    raises :class:`~fr_torch.errors.FRInputError` (one line).  Unpacks as a pair:
    ``low, high = fov_range``.
    """

    min_deg: float
    max_deg: float

    #: Named ranges: ``default`` covers the cameras users have (phones, action cameras, webcams,
    #: DSLR kit zooms); ``paper`` is Qian & Elder's [50, 130].
    NAMED: ClassVar[dict[str, tuple[float, float]]] = {"default": (30.0, 120.0), "paper": (50.0, 130.0)}

    def __post_init__(self) -> None:
        try:
            low, high = float(self.min_deg), float(self.max_deg)
        except (TypeError, ValueError):
            raise FRInputError(f"FOV range must be two numbers in degrees, got {self.min_deg!r}, "
                               f"{self.max_deg!r}") from None
        lo_lim, hi_lim = FOV_LIMITS_DEG
        if not (math.isfinite(low) and math.isfinite(high) and lo_lim <= low < high <= hi_lim):
            raise FRInputError(f"FOV range must be finite with {lo_lim:g} <= min < max <= {hi_lim:g} deg, "
                               f"got {low:g}, {high:g}")
        object.__setattr__(self, "min_deg", low)
        object.__setattr__(self, "max_deg", high)

    @classmethod
    def parse(cls, value=None) -> "FovRange":
        """A range from ``None`` (the library default), a :class:`FovRange`, a name
        (:attr:`NAMED`), ``"MIN,MAX"`` / ``"MIN:MAX"`` or a (min, max) pair, in degrees."""
        if value is None:
            return cls(*cls.NAMED["default"])
        if isinstance(value, FovRange):
            return value
        if isinstance(value, str):
            key = value.strip().lower()
            if key in cls.NAMED:
                return cls(*cls.NAMED[key])
            parts = key.replace(":", ",").split(",")
        else:
            try:
                parts = list(value)
            except TypeError:
                parts = [value]
        low, high = two_numbers(parts, f"FOV range must be MIN,MAX in degrees or one of "
                                       f"{', '.join(cls.NAMED)}, got {value!r}")
        return cls(low, high)

    def __iter__(self):
        return iter((self.min_deg, self.max_deg))

    def __str__(self) -> str:
        return f"[{self.min_deg:g}°, {self.max_deg:g}°]"

    def focal_bounds(self, long_side):
        """``(f_min, f_max)`` in pixels for a long side in pixels (a number or a tensor, float64
        out for tensors): f at ``max_deg`` and at ``min_deg``."""
        if torch.is_tensor(long_side):
            long_side = long_side.to(torch.float64)
            return (focal_from_hfov(torch.tensor(self.max_deg, dtype=torch.float64), long_side),
                    focal_from_hfov(torch.tensor(self.min_deg, dtype=torch.float64), long_side))
        return focal_from_hfov(self.max_deg, long_side), focal_from_hfov(self.min_deg, long_side)

    def at_edge(self, focal_px: float, long_side: float, tolerance_deg: float = 0.25) -> bool:
        """True when ``focal_px`` gives a long-side FOV within ``tolerance_deg`` of either end."""
        return self.fov_at_edge(hfov_from_focal(focal_px, long_side), tolerance_deg)

    def fov_at_edge(self, fov_deg: float, tolerance_deg: float = 0.25) -> bool:
        """True when the long-side FOV ``fov_deg`` lies within ``tolerance_deg`` of either end."""
        return fov_deg <= self.min_deg + tolerance_deg or fov_deg >= self.max_deg - tolerance_deg

    def log_focal_midpoint_deg(self) -> float:
        """The FOV (degrees) whose focal length is the geometric mean of the range's two ends."""
        middle = math.sqrt(focal_from_hfov(self.min_deg, 1.0) * focal_from_hfov(self.max_deg, 1.0))
        return hfov_from_focal(middle, 1.0)


def two_numbers(parts, message: str) -> tuple[float, float]:
    """``parts`` (two items) as floats; :class:`~fr_torch.errors.FRInputError` (``message``) when
    they are not two numbers."""
    try:
        low, high = (float(v) for v in parts)
    except (TypeError, ValueError):
        raise FRInputError(message) from None
    return low, high
