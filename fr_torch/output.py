"""Writing results: JSON that never holds NaN, atomic files, checked output folders."""
from __future__ import annotations

import json
import math
import os
import stat
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

from fr_torch.errors import FRInputError
from fr_torch.redaction import redact_text


def json_safe(value: Any) -> Any:
    """A copy of ``value`` with every NaN / inf float replaced by None (JSON null), numpy
    scalars / arrays turned into Python numbers / lists and every URL in a text redacted
    (:func:`fr_torch.redaction.redact_text`): the last guard before serialisation."""
    if isinstance(value, str):
        return redact_text(value)
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
    """Write ``text`` (UTF-8) to ``path`` via a temporary file in the same folder and a rename, so
    the file is never seen truncated.  Errors are FRInputError one-liners."""
    write_bytes_atomic(path, text.encode("utf-8"))


def write_bytes_atomic(path: Path, data: bytes) -> None:
    """:func:`write_text_atomic` for bytes (an image).  The file gets the permissions a plain
    ``open(path, "w")`` would give it (those of the file it replaces, else 0666 less the umask),
    not the temporary file's private 0600."""
    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        try:
            mode = stat.S_IMODE(os.stat(path).st_mode)
        except FileNotFoundError:
            mode = 0o666 & ~_umask()
        handle, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
        try:
            with os.fdopen(handle, "wb") as out:
                out.write(data)
            os.chmod(tmp, mode)
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


def _umask() -> int:
    """This process's umask (read by setting it and back: the one way the standard library has)."""
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


class _suppress:
    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return True
