"""Validation at the boundaries (CLI options, API arguments, JSON output): one-line errors.

Everything here raises :class:`~fr_torch.errors.FRInputError` (a ``ValueError``) with a message
that names the offending value; the CLI prints it as one line (no traceback).
"""
from __future__ import annotations

import math

import numpy as np
import torch

from fr_torch.core.camera import focal_from_hfov
from fr_torch.errors import FRInputError

# A pinhole camera whose field of view (on the image's long side) is outside [MIN, MAX] degrees
# means nothing we can estimate: a user focal length outside that range is refused.
MIN_FOV_DEG, MAX_FOV_DEG = 1.0, 179.0


def finite_number(value, name: str) -> float:
    """``value`` as a finite float, else FRInputError naming it."""
    try:
        number = float(value)
    except (TypeError, ValueError, OverflowError):
        raise FRInputError(f"{name} must be a number, got {value!r}") from None
    if not math.isfinite(number):
        raise FRInputError(f"{name} must be finite, got {value!r}")
    return number


def check_focal(focal, width: float, height: float, name: str = "focal length") -> float:
    """A user focal length (pixels) that a pinhole camera of this size can have: finite, > 0 and a
    field of view on the long side within [1, 179] degrees."""
    f = finite_number(focal, name)
    long_side = max(width, height)
    low, high = focal_from_hfov(MAX_FOV_DEG, long_side), focal_from_hfov(MIN_FOV_DEG, long_side)
    if not f > 0:
        raise FRInputError(f"{name} must be a positive number of pixels, got {focal}")
    if not low <= f <= high:
        raise FRInputError(f"{name} {f:g} px is outside [{low:.3g}, {high:.4g}] px, a field of view of "
                           f"{MIN_FOV_DEG:g}-{MAX_FOV_DEG:g} deg on this {width} x {height} image")
    return f


def check_principal_point(pp, width: float, height: float, name: str = "principal point") -> tuple[float, float]:
    """A finite (x, y) in pixels no further than 10 image sizes from the image centre."""
    try:
        x, y = pp
    except (TypeError, ValueError):
        raise FRInputError(f"{name} must be (x, y) in pixels, got {pp!r}") from None
    x, y = finite_number(x, f"{name} x"), finite_number(y, f"{name} y")
    reach = 10 * max(width, height)
    if abs(x - width / 2) > reach or abs(y - height / 2) > reach:
        raise FRInputError(f"{name} ({x:g}, {y:g}) is absurdly far from the {width} x {height} image")
    return x, y


def check_camera(focal, pp, size: tuple[int, int], name: str) -> None:
    """Per-image check of the user's focal / principal point (None = unknown / image centre)."""
    width, height = size
    if focal is not None:
        check_focal(focal, width, height, f"{name}: focal length")
    if pp is not None:
        check_principal_point(pp, width, height, f"{name}: principal point")


def per_image(value, count: int, name: str, width: int = 1) -> list:
    """A per-image argument as a list of ``count`` values.

    ``value``: None (-> ``count`` Nones), one value for every image (a number for ``width`` 1, an
    (x, y) pair of numbers for ``width`` 2), or a sequence of one value (or None) per image.
    A sequence of the wrong length is an FRInputError naming ``name``; the values themselves are
    checked per image later (:func:`check_camera`), so one bad value fails only its image.
    """
    if value is None:
        return [None] * count
    if np.isscalar(value) or (width == 2 and len(value) == 2 and np.isscalar(value[0])):
        return [value] * count
    value = list(value)
    if len(value) != count:
        raise FRInputError(f"{name}: expected one value per image ({count}), got {len(value)}")
    return value


def positive_int(value, name: str, minimum: int = 1) -> int:
    if value is None or int(value) != value or value < minimum:
        raise FRInputError(f"{name} must be an integer >= {minimum}, got {value!r}")
    return int(value)


def positive_number(value, name: str) -> float:
    number = finite_number(value, name)
    if not number > 0:
        raise FRInputError(f"{name} must be > 0, got {value!r}")
    return number


# --------------------------------------------------------------------------- JSON output


def resolve_device(device) -> "torch.device":
    """A usable torch device from a name ('cpu', 'cuda', 'cuda:1') or a torch.device; else FRInputError."""

    try:
        resolved = torch.device(device)
    except (RuntimeError, TypeError, ValueError):
        raise FRInputError(f"--device: unknown device {device!r} (use cpu or cuda)") from None
    if resolved.type not in ("cpu", "cuda"):
        raise FRInputError(f"--device: {resolved.type!r} cannot run fR (use cpu or cuda)")
    if resolved.type == "cuda":
        if not torch.cuda.is_available():
            raise FRInputError("--device cuda requested but no CUDA device is available")
        if resolved.index is not None and resolved.index >= torch.cuda.device_count():
            raise FRInputError(f"--device {device}: only {torch.cuda.device_count()} CUDA device(s)")
    return resolved
