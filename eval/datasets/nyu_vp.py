"""NYU-VP (Kluger et al., CVPR 2020) loader: LSD segments and labelled vanishing points of NYU Depth v2
photos, in the project conventions.  Segments only (the photos are not in the data folder).

Layout (``<data_root>/nyu_vp/data/``, see its PROVENANCE.md): ``lsd_lines_XXXX.csv`` (space-separated,
header; ``point1_x point1_y point2_x point2_y`` are the endpoints in pixels, origin top-left) and
``vps_XXXX.csv`` (``idx X Y``: vanishing points in pixels) for photos 0000-1223.

Conventions decided here:

* Splits: the dataset's own ``train`` (photos 0-999) and ``val`` (1000-1223); ``all`` = both.
* Camera: one Kinect camera, 640 x 480, focal length fx = 518.8579 px (fy differs by 0.1 %), calibrated
  principal point (325.5824, 253.7362).  ``camera.principal_point`` is the calibrated one; a method
  that assumes the image centre is told nothing.
* Rotation: the vertical direction is the labelled vanishing direction ``K^-1 [X, Y, 1]`` closest to
  the camera's y axis, signed to point down (+y).  Only gravity is known reliably, so the camera has
  ``pan_known = False`` and the rotation is ``rotation_from_angles(0, pitch, roll)`` of that vertical
  (roll / tilt / pitch are the ground truth; pan and frame errors are not reported).
* ``extra["lsd_segments"]``: the dataset's LSD segments (N, 4) ``[x1, y1, x2, y2]`` pixels, the
  method's input.  ``segments`` / ``segment_labels`` (hand labels) are not loaded.
"""
from __future__ import annotations

import math
from functools import lru_cache
from pathlib import Path

import numpy as np
from fr_eval.datasets.registry import CalibrationSample, register_dataset
from fr_eval.paths import data_root

from fr_torch.core.camera import Camera

FOLDER = "nyu_vp"
WIDTH, HEIGHT = 640, 480
FOCAL_PX = 518.8579
PRINCIPAL_POINT = (325.5824, 253.7362)
SPLIT_IDS = {"train": range(0, 1000), "val": range(1000, 1224), "all": range(0, 1224)}


def nyu_vp_root(root: str | Path | None = None) -> Path:
    """``<data_root>/nyu_vp/data`` (``root`` may be the data root, ``nyu_vp`` or its ``data`` folder)."""
    base = Path(root) if root is not None else data_root()
    for path in (base, base / "data", base / FOLDER / "data"):
        if (path / "lsd_lines_0000.csv").is_file():
            return path
    raise FileNotFoundError(f"NYU-VP not found under {base} (expected {FOLDER}/data/lsd_lines_0000.csv)")


def read_lsd_segments(path: Path) -> np.ndarray:
    """(N, 4) float64 segments [x1, y1, x2, y2] in pixels from a ``lsd_lines_XXXX.csv``."""
    table = np.loadtxt(path, skiprows=1, ndmin=2)
    if table.size == 0:
        return np.zeros((0, 4))
    return table[:, [6, 7, 9, 10]].astype(np.float64)


def read_vps(path: Path) -> np.ndarray:
    """(M, 2) labelled vanishing points in pixels from a ``vps_XXXX.csv``."""
    table = np.loadtxt(path, skiprows=1, ndmin=2)
    return table[:, 1:3].astype(np.float64) if table.size else np.zeros((0, 2))


def vertical_direction(vps: np.ndarray) -> np.ndarray | None:
    """Unit vertical direction in the camera frame (x right, y down, z forward; y component > 0) from
    the labelled vanishing points (M, 2): the direction ``K^-1 [X, Y, 1]`` closest to the y axis."""
    if len(vps) == 0:
        return None
    k_inv = np.linalg.inv(np.array([[FOCAL_PX, 0, PRINCIPAL_POINT[0]], [0, FOCAL_PX, PRINCIPAL_POINT[1]], [0, 0, 1]]))
    directions = (k_inv @ np.c_[vps, np.ones(len(vps))].T).T
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    best = directions[np.argmax(np.abs(directions[:, 1]))]
    return best if best[1] > 0 else -best


def _camera(vertical: np.ndarray | None) -> Camera:
    if vertical is None:
        return Camera(WIDTH, HEIGHT, FOCAL_PX, PRINCIPAL_POINT)
    # R[:, 1] = vertical (down); world-up in the y-up camera frame is (-v_x, v_y, -v_z) up to the y flip.
    roll = math.degrees(math.atan2(vertical[0], vertical[1]))
    pitch = math.degrees(math.asin(float(np.clip(-vertical[2], -1.0, 1.0))))
    camera = Camera.from_angles(WIDTH, HEIGHT, FOCAL_PX, roll_deg=roll, pitch_deg=pitch,
                                principal_point=PRINCIPAL_POINT)
    return camera


@lru_cache(maxsize=2)
def _load_all(root: Path) -> tuple[CalibrationSample, ...]:
    samples = []
    for index in SPLIT_IDS["all"]:
        lines = root / f"lsd_lines_{index:04d}.csv"
        if not lines.is_file():
            continue
        vertical = vertical_direction(read_vps(root / f"vps_{index:04d}.csv"))
        samples.append(CalibrationSample(
            name=f"nyu_{index:04d}", image_path=lines, width=WIDTH, height=HEIGHT, camera=_camera(vertical),
            split="train" if index < 1000 else "val",
            extra={"index": index, "lsd_segments": read_lsd_segments(lines)}))
    return tuple(samples)


@register_dataset("nyu-vp")
def load_nyu_vp(root: str | Path | None = None, split: str = "val", **_: object) -> list[CalibrationSample]:
    """NYU-VP samples of split ``train`` (0-999), ``val`` (1000-1223) or ``all``, in id order."""
    if split not in SPLIT_IDS:
        raise ValueError(f"NYU-VP split must be one of {tuple(SPLIT_IDS)}, got {split!r}")
    samples = _load_all(nyu_vp_root(root).resolve())
    return [s for s in samples if split == "all" or s.split == split]
