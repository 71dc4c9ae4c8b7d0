"""Validation at the boundaries (CLI options, API arguments, JSON output): one-line errors.

Everything here raises :class:`~fr_torch.errors.FRInputError` (a ``ValueError``) with a message
that names the offending value; the CLI prints it as one line (no traceback).
"""
from __future__ import annotations

import math
import numbers
import reprlib
from collections.abc import Iterable
from enum import StrEnum

import numpy as np
import torch

from fr_torch.core.geometry.conventions import focal_from_hfov, image_centre
from fr_torch.core.settings.fov import FOV_LIMITS_DEG
from fr_torch.errors import FRInputError

# How far from an image's centre a point given in its pixels (a principal point, a segment's
# endpoint) may lie, in image sizes (the long side): beyond, the number is nonsense, not geometry.
MAX_REACH_IMAGE_SIZES = 10


def enum_member(enum: type[StrEnum], value, name: str):
    """The member of ``enum`` whose value is ``value`` (or ``value`` itself, a member), else
    FRInputError naming ``name`` and the choices."""
    try:
        return enum(value)
    except ValueError:
        raise FRInputError(f"{name} must be one of {', '.join(m.value for m in enum)}, got {value!r}") from None


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
    field of view on the long side within :data:`~fr_torch.core.settings.fov.FOV_LIMITS_DEG` ([1, 179] degrees)."""
    f = finite_number(focal, name)
    long_side = max(width, height)
    min_fov, max_fov = FOV_LIMITS_DEG
    low, high = focal_from_hfov(max_fov, long_side), focal_from_hfov(min_fov, long_side)
    if not f > 0:
        raise FRInputError(f"{name} must be a positive number of pixels, got {focal}")
    if not low <= f <= high:
        raise FRInputError(f"{name} {f:g} px is outside [{low:.3g}, {high:.4g}] px, a field of view of "
                           f"{min_fov:g}-{max_fov:g} deg on this {width} x {height} image")
    return f


def check_principal_point(pp, width: float, height: float, name: str = "principal point") -> tuple[float, float]:
    """A finite (x, y) in pixels no further than 10 image sizes from the image centre."""
    try:
        x, y = pp
    except (TypeError, ValueError):
        raise FRInputError(f"{name} must be (x, y) in pixels, got {pp!r}") from None
    x, y = finite_number(x, f"{name} x"), finite_number(y, f"{name} y")
    reach = MAX_REACH_IMAGE_SIZES * max(width, height)
    cx, cy = image_centre(width, height)
    if abs(x - cx) > reach or abs(y - cy) > reach:
        raise FRInputError(f"{name} ({x:g}, {y:g}) is absurdly far from the {width} x {height} image")
    return x, y


def check_camera(focal, pp, size: tuple[int, int], name: str) -> None:
    """Per-image check of the user's focal / principal point (None = unknown / image centre)."""
    width, height = size
    if focal is not None:
        check_focal(focal, width, height, f"{name}: focal length")
    if pp is not None:
        check_principal_point(pp, width, height, f"{name}: principal point")


def shown(value) -> str:
    """``value`` for a one-line message: an array or tensor by its shape, anything else by a short repr."""
    if isinstance(value, np.ndarray) or torch.is_tensor(value):
        return f"an array of shape {tuple(value.shape)}"
    return reprlib.repr(value)


def _plain(value):
    """An array or tensor as nested Python lists / a Python scalar; anything else unchanged."""
    if torch.is_tensor(value):
        value = value.detach().cpu().numpy()
    return value.tolist() if isinstance(value, (np.ndarray, np.generic)) else value


def _is_real(value) -> bool:
    return isinstance(value, numbers.Real) and not isinstance(value, bool)


def _is_value(value, width: int) -> bool:
    """A number (``width`` 1) or an (x, y) pair of numbers (``width`` 2); strings and bools are not."""
    if width == 1:
        return _is_real(value)
    return (isinstance(value, (list, tuple)) and len(value) == width and all(_is_real(v) for v in value))


_PER_IMAGE_FORMS = {1: "None, a number (pixels) for every image, or a sequence of one number or None per image",
                    2: "None, an (x, y) pair of numbers (pixels) for every image, or a sequence of one pair or "
                       "None per image"}


def per_image(value, count: int, name: str, width: int = 1) -> list:
    """A per-image argument as a list of ``count`` values.

    ``value``: None (-> ``count`` Nones), one value for every image (a number for ``width`` 1, an
    (x, y) pair of numbers for ``width`` 2), or a sequence (list, tuple, array, tensor) of one value
    (or None) per image.  Anything else -- a string, a bool, a sequence of the wrong length or
    holding something that is not such a value -- is an FRInputError naming ``name`` and the
    expected form; the values themselves (finite, in range) are checked per image later
    (:func:`check_camera`), so one bad value fails only its image.
    """
    if value is None:
        return [None] * count
    plain = _plain(value)
    if _is_value(plain, width):
        return [plain] * count
    form = _PER_IMAGE_FORMS[width]
    if isinstance(plain, (str, bytes)) or not isinstance(plain, Iterable):
        raise FRInputError(f"{name}: expected {form}; got {shown(value)}")
    items = [_plain(v) for v in plain]
    if len(items) != count:
        raise FRInputError(f"{name}: expected one value per image ({count}), got {len(items)}")
    for i, item in enumerate(items):
        if item is not None and not _is_value(item, width):
            raise FRInputError(f"{name}[{i}]: expected {form}; got {shown(item)}")
    return items


def image_sizes(value, count: int, name: str = "image_sizes") -> list[tuple]:
    """``image_sizes`` of an API call as ``count`` (width, height) tuples of numbers.

    Expected: one (width, height) pair of numbers (pixels) per image -- a sequence of pairs, or a
    (count, 2) array or tensor.  Anything else (a flat ``[640, 480]``, strings, None, a wrong count)
    is an FRInputError naming ``name`` and that form.  Whether a pair is a usable size (finite,
    > 0) is checked per image (:func:`check_image_size`), so one bad size fails only its image.
    """
    form = "one (width, height) pair of numbers (pixels) per image, e.g. [(640, 480)]"
    plain = _plain(value)
    if isinstance(plain, (str, bytes)) or not isinstance(plain, Iterable):
        raise FRInputError(f"{name}: expected {form}; got {shown(value)}")
    items = [_plain(v) for v in plain]
    if items and all(_is_real(v) for v in items):
        raise FRInputError(f"{name}: expected {form}; got the flat sequence {shown(value)}")
    for i, item in enumerate(items):
        if not _is_value(item, 2):
            raise FRInputError(f"{name}[{i}]: expected {form}; got {shown(item)}")
    if len(items) != count:
        raise FRInputError(f"{name}: expected one (width, height) pair per image ({count}), got {len(items)}")
    return [tuple(item) for item in items]


def check_image_size(size: tuple, name: str) -> tuple:
    """Per-image check of an image's size: a (width, height) pair of finite numbers > 0 (pixels)."""
    try:
        usable = _is_value(_plain(size), 2) and all(math.isfinite(float(v)) and v > 0 for v in size)
    except (OverflowError, TypeError):  # an int beyond float
        usable = False
    if not usable:
        raise FRInputError(f"{name}: image size must be (width, height) > 0, got {size}")
    return size


def image_names(names, count: int, default: list[str], name: str = "names") -> list[str]:
    """``names`` of an API call as ``count`` strings (``default`` when None): a sequence of one
    name (a string or a path) per image; a single string or a wrong count is an FRInputError."""
    if names is None:
        return list(default)
    if isinstance(names, (str, bytes)) or not isinstance(names, Iterable):
        raise FRInputError(f"{name}: expected a sequence of one name per image, got {shown(names)}")
    names = [str(n) for n in names]
    if len(names) != count:
        raise FRInputError(f"{name}: expected one name per image ({count}), got {len(names)}")
    return names


def batch_of(value, name: str, what: str) -> list:
    """An API call's per-image sequence (``images``, ``segments``, ``detections``) as a list.

    ``what``: what one image's item is, for the message.  A string, a path, a mapping or anything
    not iterable is an FRInputError naming ``name``; so is an array or tensor of fewer than 3
    dimensions (one image's segments, or one grey image, given without the enclosing list).
    """
    problem = None
    if hasattr(value, "__fspath__") or isinstance(value, (str, bytes)):
        problem = " (one image's? wrap it in a list)"
    elif (isinstance(value, np.ndarray) or torch.is_tensor(value)) and value.ndim < 3:
        problem = " (one image's? wrap it in a list)"
    elif not isinstance(value, Iterable) or isinstance(value, dict):
        problem = ""
    if problem is not None:
        raise FRInputError(f"{name}: expected a sequence of {what}, one per image; got {shown(value)}{problem}")
    return list(value)


def segment_sets(value, name: str = "segments") -> list:
    """``segments`` of an API call: a sequence of one (N_i, 4) array per image (lists, arrays,
    tensors; ragged counts welcome), as a list.  One image's segments given without the enclosing
    list (an (N, 4) array, or a list of 4-number rows) is an FRInputError saying to wrap them; each
    image's array itself is checked per image (:func:`fr_torch.core.likelihood.segments.validate_segments`)."""
    sets = batch_of(value, name, "(N, 4) segment arrays [x1, y1, x2, y2]")
    if sets:
        first = sets[0]
        row = (first.ndim == 1 and first.shape[0] == 4 if isinstance(first, np.ndarray) or torch.is_tensor(first)
               else isinstance(first, (list, tuple)) and len(first) == 4 and all(_is_real(v) for v in first))
        if row:
            raise FRInputError(f"{name}: expected a sequence of (N, 4) segment arrays, one per image; its first "
                               f"item is a single segment {shown(first)} (one image's segments? wrap them in a "
                               "list)")
    return sets


def positive_int(value, name: str, minimum: int = 1) -> int:
    if value is None or int(value) != value or value < minimum:
        raise FRInputError(f"{name} must be an integer >= {minimum}, got {value!r}")
    return int(value)


def positive_number(value, name: str) -> float:
    number = finite_number(value, name)
    if not number > 0:
        raise FRInputError(f"{name} must be > 0, got {value!r}")
    return number





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
