"""Validation at the boundaries (CLI options, API arguments, JSON output): one-line errors.

Everything here raises :class:`~fr_torch.segments.FRInputError` (a ``ValueError``) with a message
that names the offending value; the CLI prints it as one line (no traceback).
"""
from __future__ import annotations

import json
import math
import os
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

from .camera import focal_from_hfov
from .segments import FRInputError

# A pinhole camera whose field of view (on the image's long side) is outside [MIN, MAX] degrees
# means nothing we can estimate: a user focal length outside that range is refused.
MIN_FOV_DEG, MAX_FOV_DEG = 1.0, 179.0


def resolve_device(device) -> "torch.device":
    """A usable torch device from a name ('cpu', 'cuda', 'cuda:1') or a torch.device; else FRInputError."""
    import torch

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

def json_safe(value: Any) -> Any:
    """A copy of ``value`` with every NaN / inf float replaced by None (JSON null) and numpy
    scalars / arrays turned into Python numbers / lists: the last guard before serialisation."""
    if isinstance(value, dict):
        return {str(k): json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_safe(v) for v in value]
    if isinstance(value, np.ndarray):
        return json_safe(value.tolist())
    if isinstance(value, (np.floating, float)):
        number = float(value)
        return number if math.isfinite(number) else None
    if isinstance(value, np.integer):
        return int(value)
    if isinstance(value, np.bool_):
        return bool(value)
    return value


def dumps(value: Any, **kwargs) -> str:
    """json.dumps of :func:`json_safe` (never writes NaN / Infinity)."""
    return json.dumps(json_safe(value), allow_nan=False, **kwargs)


def write_text_atomic(path: Path, text: str) -> None:
    """Write ``text`` to ``path`` via a temporary file in the same folder and a rename, so the file is
    never seen truncated.  Errors are FRInputError one-liners."""
    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        handle, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
        try:
            with os.fdopen(handle, "w") as out:
                out.write(text)
            os.replace(tmp, path)
        except BaseException:
            with _suppress():
                os.unlink(tmp)
            raise
    except OSError as exc:
        raise FRInputError(f"cannot write {path}: {exc.strerror or exc}") from None


def write_bytes(path: Path, data: bytes) -> None:
    """Write bytes (any file name, including ones that are not valid UTF-8); one-line errors."""
    try:
        Path(path).write_bytes(data)
    except OSError as exc:
        raise FRInputError(f"cannot write {os.fsdecode(path)!r}: {exc.strerror or exc}") from None


def output_folder(path: Path, option: str = "--overlay") -> Path:
    """Create (if needed) and check a writable output folder; FRInputError otherwise."""
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise FRInputError(f"{option} {path}: exists and is not a folder")
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise FRInputError(f"{option} {path}: cannot create the folder ({exc.strerror or exc})") from None
    if not os.access(path, os.W_OK | os.X_OK):
        raise FRInputError(f"{option} {path}: folder is not writable")
    return path


class _suppress:
    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return True


def track_options(args) -> None:
    """``fr track`` options: memory >= 1 frame, change_k > 0, patience >= 1 (one-line errors)."""
    memory = finite_number(args.memory, "--memory")
    if memory < 1:
        raise FRInputError(f"--memory must be at least 1 frame, got {args.memory!r}")
    positive_number(args.change_k, "--change-k")
    positive_int(args.patience, "--patience")
    if args.max_frames is not None:
        positive_int(args.max_frames, "--max-frames")
