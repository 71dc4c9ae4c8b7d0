"""``external``: per-image predictions of a method run elsewhere, read from a CSV file.

For methods we cannot run here, e.g. Hold-Geoffroy et al. 2018 ("A perceptual measure for deep
single image camera calibration", CVPR 2018), whose results come from the authors' web interface.

CSV format (header row required, any column order, extra columns ignored, empty cells = unknown):

``image``
    image name as the dataset gives it (``ImageMeta.name``), or its file name, or its file stem.
``focal_px``, ``hfov_deg``
    focal length in pixels and/or horizontal field of view in degrees (the missing one is derived
    from the image width).
``roll_deg``, ``tilt_deg``, ``pitch_deg``, ``pan_deg``
    angles in degrees with the conventions of :mod:`fr_torch.core.geometry.conventions` (paper roll / tilt).
``r00`` ... ``r22``
    the world->camera rotation (row-major, vertical Manhattan direction in column 1); when all
    nine are given, the angles not given explicitly are derived from it.

The prediction becomes one :class:`fr_torch.core.geometry.camera.Camera`: from the rotation when all nine
entries are given (the angle columns are then ignored: every angle is derived from it), else from
roll and pitch or tilt (``tan(tilt) = tan(pitch) / cos(roll)``), with pan when given (otherwise a
horizon-only camera, ``pan_known=False``).  Angles without roll and tilt or pitch are an
incomplete prediction (flagged failure); ``hfov_deg`` needs the image width.  The file comes from the constructor argument
``csv_path`` or the environment variable named by ``env_var`` (``FR_EXTERNAL_CSV``); the reported
method name is the ``method`` argument (e.g. ``"hold-geoffroy2018"``).  An image without a row (or without a file)
is a flagged failure with reason ``"n/a (not supplied)"``.
"""
from __future__ import annotations

import csv
import math
import os
from pathlib import Path

import numpy as np

from fr_torch.core.geometry.camera import Camera
from fr_torch.core.geometry.conventions import focal_from_hfov
from fr_torch.errors import FRInputError
from fr_torch.plugins.interface import CameraEstimate, ImageMeta, Timer
from fr_torch.registry import NOT_SUPPLIED

from . import vp_geometry as vg
from .provenance import sha256

VALUE_COLUMNS = ("focal_px", "hfov_deg", "roll_deg", "tilt_deg", "pitch_deg", "pan_deg")
ROTATION_COLUMNS = tuple(f"r{i}{j}" for i in range(3) for j in range(3))


def _number(text) -> float | None:
    if text is None:
        return None
    text = str(text).strip()
    if not text:
        return None
    try:
        value = float(text)
    except ValueError:
        return None
    return value if math.isfinite(value) else None


def read_predictions(path: str | os.PathLike) -> dict[str, dict[str, float | None]]:
    """Rows of a predictions CSV keyed by their ``image`` entry (values parsed to float / None)."""
    path = Path(path)
    if not path.is_file():
        raise FRInputError(f"{path}: predictions CSV not found")
    with path.open(newline="", encoding="utf-8") as handle:
        reader = csv.DictReader(handle)
        if reader.fieldnames is None or "image" not in [c.strip() for c in reader.fieldnames]:
            raise FRInputError(f"{path}: needs a header row with an 'image' column")
        rows: dict[str, dict[str, float | None]] = {}
        for line_no, raw in enumerate(reader, start=2):
            raw = {(k or "").strip(): v for k, v in raw.items()}
            key = (raw.get("image") or "").strip()
            if not key:
                continue
            if key in rows:
                raise FRInputError(f"{path}:{line_no}: duplicate row for image {key!r}")
            rows[key] = {c: _number(raw.get(c)) for c in VALUE_COLUMNS + ROTATION_COLUMNS}
    return rows


class ExternalPredictions:
    """Predictions read from a CSV (see the module docstring for the columns)."""

    def __init__(self, csv_path: str | os.PathLike | None = None, method: str = "external",
                 env_var: str = "FR_EXTERNAL_CSV"):
        path = csv_path if csv_path is not None else os.environ.get(env_var) or None
        self.csv_path = Path(path) if path else None
        self.name = str(method)
        self._rows = read_predictions(self.csv_path) if self.csv_path is not None else {}
        self._by_stem: dict[str, str] = {}
        for key in self._rows:
            for alias in (Path(key).name, Path(key).stem):
                self._by_stem.setdefault(alias, key)

    @property
    def available(self) -> bool:
        return self.csv_path is not None

    @property
    def weights(self) -> str | None:
        """What produced this row, for table captions: the CSV's file name + sha256 (None without)."""
        if self.csv_path is None or not self.csv_path.is_file():
            return None
        return f"predictions {self.csv_path.name} (sha256 {sha256(self.csv_path)})"

    def lookup(self, name: str) -> dict[str, float | None] | None:
        """The row for an image name (exact, then file name, then file stem), or None."""
        if not name:
            return None
        if name in self._rows:
            return self._rows[name]
        for alias in (Path(name).name, Path(name).stem):
            if alias in self._rows:
                return self._rows[alias]
            if alias in self._by_stem:
                return self._rows[self._by_stem[alias]]
        return None

    def estimate(self, image: np.ndarray | None, meta: ImageMeta) -> CameraEstimate:
        with Timer() as timer:
            result = self._estimate(image, meta)
        # The runtime of an external method is unknown; report the look-up time only in extra.
        result.extra["lookup_s"] = timer.seconds
        return result

    def _estimate(self, image, meta: ImageMeta) -> CameraEstimate:
        row = self.lookup(meta.name)
        if row is None:
            return CameraEstimate.failure(self.name, NOT_SUPPLIED)
        width, height = vg.image_size(image, meta)
        focal, hfov = row["focal_px"], row["hfov_deg"]
        if focal is not None and focal <= 0:
            return CameraEstimate.failure(self.name, f"invalid focal_px {focal}")
        if hfov is not None and not 0 < hfov < 180:
            return CameraEstimate.failure(self.name, f"invalid hfov_deg {hfov}")
        if focal is None and hfov is not None:
            if width <= 0:
                return CameraEstimate.failure(self.name, "unknown image width (needed to use hfov_deg)")
            focal = float(focal_from_hfov(hfov, width))

        roll, tilt, pitch, pan = row["roll_deg"], row["tilt_deg"], row["pitch_deg"], row["pan_deg"]
        r_values = [row[c] for c in ROTATION_COLUMNS]
        if all(v is not None for v in r_values):
            rotation = np.asarray(r_values, dtype=np.float64).reshape(3, 3)
            if (np.abs(rotation.T @ rotation - np.eye(3)).max() > 1e-3 or np.linalg.det(rotation) < 0):
                return CameraEstimate.failure(self.name, "invalid rotation (not a proper rotation matrix)")
            camera = Camera(width, height, focal, meta.principal_point, vg.nearest_rotation(rotation))
        elif roll is not None and (pitch is not None or tilt is not None):
            camera = Camera.from_angles(width, height, focal, roll_deg=roll, pitch_deg=pitch, tilt_deg=tilt,
                                        pan_deg=pan, principal_point=meta.principal_point)
        elif any(v is not None for v in (roll, tilt, pitch, pan)):
            return CameraEstimate.failure(self.name, "n/a (incomplete prediction: the angles need roll and "
                                                     "tilt or pitch, or r00..r22)")
        elif focal is not None:
            camera = Camera(width, height, focal, meta.principal_point)
        else:
            return CameraEstimate.failure(self.name, "n/a (empty prediction)")
        return CameraEstimate(method=self.name, camera=camera)


def make_hold_geoffroy2018(csv_path: str | os.PathLike | None = None) -> ExternalPredictions:
    """Hold-Geoffroy et al. 2018 (a row of the paper's tables): its predictions cannot be computed here
    (the authors serve the model through a web interface), so they are read from the CSV in
    ``csv_path`` or ``$FR_HOLD_GEOFFROY_CSV`` (columns as above); without one every image is
    ``n/a (not supplied)``."""
    return ExternalPredictions(csv_path, method="hold-geoffroy2018", env_var="FR_HOLD_GEOFFROY_CSV")
