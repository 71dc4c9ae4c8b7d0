"""``fr batch``'s inputs: folders, globs, files and manifests (local paths or fsspec URIs) into rows."""
from __future__ import annotations

import glob as globlib
import os
from pathlib import Path
from typing import Any, Sequence

import cv2
import numpy as np
import pandas as pd
import pyarrow as pa

from fr_torch.batch.table import result_schema
from fr_torch.errors import FRInputError
from fr_torch.images.convert import to_bgr8

IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png", ".bmp", ".tif", ".tiff", ".webp", ".pgm", ".ppm", ".jp2")


MANIFEST_SUFFIXES = (".csv", ".parquet", ".pq", ".txt")


PATH_COLUMNS = ("image", "path", "file", "filename")


def has_scheme(path: str) -> bool:
    """True for URIs such as ``s3://b/k.jpg`` (read with fsspec); False for local paths."""
    head, sep, _ = str(path).partition("://")
    return bool(sep) and head.isidentifier() and len(head) > 1 and head != "file"


def _strip_file_scheme(path: str) -> str:
    return path[len("file://"):] if path.startswith("file://") else path


def _fsspec_fs(uri: str):
    try:
        import fsspec
    except ImportError:
        raise ValueError(f"{uri}: reading URIs needs fsspec (pip install fsspec and the filesystem package)") from None
    try:
        return fsspec.core.url_to_fs(uri)
    except (ImportError, ValueError) as exc:
        raise ValueError(f"{uri}: cannot open this filesystem ({exc})") from None


def _is_image(name: str) -> bool:
    return name.lower().endswith(IMAGE_SUFFIXES)


def _read_manifest(path: str) -> list[dict[str, Any]]:
    """Rows of a manifest file: dicts with ``image`` plus the manifest's other columns."""

    lower = path.lower()
    if lower.endswith(".txt"):
        opener = _fsspec_fs(path)[0].open if has_scheme(path) else open
        with opener(path, "r") as handle:
            lines = [line.strip() for line in handle]
        return [{"image": line} for line in lines if line and not line.startswith("#")]
    frame = pd.read_parquet(path) if lower.endswith((".parquet", ".pq")) else pd.read_csv(path)
    if frame.empty:
        return []
    column = next((c for c in PATH_COLUMNS if c in frame.columns), frame.columns[0])
    frame = frame.rename(columns={column: "image"})
    frame["image"] = frame["image"].astype(str)
    # Paths relative to the manifest's folder (local manifests only).
    base = os.path.dirname(path)
    if base and not has_scheme(path):
        frame["image"] = [p if has_scheme(p) or os.path.isabs(p) else os.path.join(base, p) for p in frame["image"]]
    frame = frame.astype(object).where(frame.notna(), None)  # missing cells -> None, not NaN
    return frame.to_dict("records")


def collect_inputs(inputs: Sequence[str]) -> list[dict[str, Any]]:
    """Expand folders, globs, files and manifests into rows ``{"image": path, <manifest columns>}``.

    Order: inputs in the order given; within a folder or glob, sorted.  Duplicate paths are kept
    once (the first row wins).  A path that does not exist is kept (it becomes a failed row); a
    glob or folder that matches nothing raises ValueError.
    """
    rows: list[dict[str, Any]] = []
    for raw in inputs:
        item = _strip_file_scheme(str(raw))
        remote = has_scheme(item)
        if item.lower().endswith(MANIFEST_SUFFIXES):
            rows += _read_manifest(item)
            continue
        if remote:
            fs, root = _fsspec_fs(item)
            protocol = item.split("://", 1)[0]
            if any(ch in item for ch in "*?["):
                found = [p for p in fs.glob(root) if _is_image(p)]
            elif fs.isdir(root):
                found = [p for p in fs.find(root) if _is_image(p)]
            else:
                rows.append({"image": item})
                continue
            if not found:
                raise ValueError(f"{item}: no images found")
            rows += [{"image": f"{protocol}://{p}" if "://" not in p else p} for p in sorted(found)]
            continue
        if os.path.isdir(item):
            found = sorted(str(p) for p in Path(item).rglob("*") if p.is_file() and _is_image(p.name))
            if not found:
                raise ValueError(f"{item}: no images found in this folder")
            rows += [{"image": p} for p in found]
        elif any(ch in item for ch in "*?[") and not os.path.exists(item):
            found = sorted(p for p in globlib.glob(item, recursive=True) if os.path.isfile(p))
            if not found:
                raise ValueError(f"{item}: the pattern matches no file")
            rows += [{"image": p} for p in found]
        else:
            rows.append({"image": item})
    seen, unique = set(), []
    for row in rows:
        if row["image"] not in seen:
            seen.add(row["image"])
            unique.append(row)
    return unique


def extra_columns(rows: Sequence[dict[str, Any]]):
    """Arrow fields of the manifest columns carried through (``focal_px`` -> ``known_focal_px``;
    a name that clashes with a result field gets the prefix ``input_``)."""

    names = [k for k in dict.fromkeys(k for row in rows for k in row) if k != "image"]
    if not names:
        return []
    table = pa.Table.from_pylist([{k: row.get(k) for k in names} for row in rows])
    reserved = set(result_schema().names)
    fields = []
    for field in table.schema:
        target = output_column_name(field.name, reserved)
        kind = pa.float64() if field.name == "focal_px" else (pa.string() if pa.types.is_null(field.type) else field.type)
        fields.append((field.name, target, kind))
    return fields


def output_column_name(name: str, reserved: set[str]) -> str:
    if name == "focal_px":
        return "known_focal_px"
    return f"input_{name}" if name in reserved else name


def read_remote_image(uri: str) -> np.ndarray:
    """Read and decode an image at an fsspec URI -> 8-bit BGR (H, W, 3)."""

    fs, path = _fsspec_fs(uri)
    with fs.open(path, "rb") as handle:
        data = np.frombuffer(handle.read(), np.uint8)
    if data.size == 0:
        raise FRInputError(f"{uri}: empty file")
    image = cv2.imdecode(data, cv2.IMREAD_UNCHANGED)
    if image is None:
        raise FRInputError(f"{uri}: not a readable image")
    return to_bgr8(image, uri)
