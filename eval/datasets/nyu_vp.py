"""NYU-VP (Kluger et al., CVPR 2020; photos of NYU Depth v2) as a harness dataset: given segments, no pixels.

Layout (``<data_root>/nyu_vp/``, see its PROVENANCE.md): ``data/lsd_lines_XXXX.csv`` (the
dataset's LSD segments), ``data/vps_XXXX.csv`` (hand-labelled vanishing points, pixels) and
``data/labelled_lines_XXXX.csv`` (up to 8 hand-drawn segments per labelled vanishing point), ids
0000-1223.

Conventions (decided here, used by every NYU-VP number this project reports)
---------------------------------------------------------------------------
* **Splits**: ``train`` = photos 0-999, ``val`` = 1000-1223 (the dataset's own); ``test`` is an
  alias of ``val`` (the dataset's test split is held out and not stored), ``all`` = both.
* **Camera**: one Kinect camera, 640 x 480, ``fx`` = 518.8579 px (HFOV 63.3 deg; ``fy`` 519.47 is
  not used: square pixels), calibrated principal point (325.5824, 253.7362) px, taken as 0-based
  pixel coordinates like the segment endpoints.
* **No pixels**: ``image_path`` is None; the dataset's LSD segments (N, 4) ``[x1, y1, x2, y2]``
  are in ``extra["detected_segments"]`` and ``fr eval`` hands them to every method as
  ``ImageMeta.segments`` (the methods run on them instead of detecting).
* **Vertical**: the direction closest to the camera's y axis among the labelled vanishing
  directions ``K^-1 [X, Y, 1]`` (calibrated K) and the cross products of labelled pairs within
  :data:`HORIZONTAL_TOLERANCE_DEG` of perpendicular (a photo labelled with its two horizontal VPs
  only: 9 of 224 val photos would otherwise take a horizontal direction, 27-88 deg from the y axis,
  for the vertical; 2 of them get it back this way), signed to point down (positive y).  Ground-truth roll / tilt / pitch and the
  zenith come from it.  Farther than :data:`MAX_VERTICAL_FROM_Y_DEG` from the y axis: no vertical
  is known (``rotation`` None: focal errors only; 7 val and 3 train photos).
* **Rotation** (world -> camera, vertical in column 1): column 0 is the labelled direction that is
  most nearly perpendicular to the vertical among those within :data:`HORIZONTAL_TOLERANCE_DEG` of
  perpendicular (ties: more hand-drawn lines, then the file order), made exactly perpendicular;
  column 2 completes the right-handed frame (signed forward).  Without such a direction only
  gravity is known (``pan_known=False``).
* **Hand-labelled segments** (``segments`` / ``segment_labels``): the hand-drawn lines of every
  labelled vanishing direction within :data:`LABEL_TOLERANCE_DEG` of a column of the rotation,
  labelled with that column; lines of other (non-Manhattan) directions are left out.  The number of
  labelled vanishing points is ``extra["num_labelled_vps"]``.
* **Horizon** (the horizon task, :mod:`fr_eval.protocols.horizon_eval`): ``extra["horizons"]["labelled"]``,
  the line through the labelled horizontal vanishing points (those within
  :data:`HORIZONTAL_TOLERANCE_DEG` of perpendicular to the vertical; the least-squares plane of their
  directions, which for two is the line through both), where there are at least two; the ``frame``
  definition is the ground-truth camera's (the labelled vertical's) horizon ``K^-T R[:, 1]``.
* **Vanishing-point labels** (the VP task, :mod:`fr_eval.scoring.vp_metric`): every labelled VP as a unit
  direction ``K_vp^-1 [X, Y, 1]`` in ``extra["vp_directions"]`` (M, 3), file order, with
  ``K_vp`` = ``extra["vp_calibration"]`` the dataset's full calibration (``fx``, ``fy`` =
  519.4696, calibrated principal point, :data:`VP_CALIBRATION`): the matrix CONSAC's evaluation uses, so that the metric
  is theirs.
"""
from __future__ import annotations

import math
from functools import lru_cache
from pathlib import Path

import numpy as np

from fr_eval.datasets.registry import CalibrationSample, register_dataset
from fr_eval.paths import data_root
from fr_torch.core.geometry.camera import Camera
from fr_torch.core.geometry.conventions import rotation_from_angles

FOLDER = "nyu_vp"
WIDTH, HEIGHT = 640, 480
FOCAL_PX = 518.8579
# The calibration at full precision (fx, fy, cx, cy; NYU Depth v2's toolbox, as CONSAC's code holds it):
# the VP metric's K (vp_calibration_matrix).
VP_CALIBRATION = (5.1885790117450188e+02, 5.1946961112127485e+02, 3.2558244941119034e+02, 2.5373616633400465e+02)
PRINCIPAL_POINT = (325.5824, 253.7362)
SPLIT_IDS = {"train": range(0, 1000), "val": range(1000, 1224)}
SPLITS = ("train", "val", "test", "all")
HORIZONTAL_TOLERANCE_DEG = 10.0
LABEL_TOLERANCE_DEG = 5.0
MAX_VERTICAL_FROM_Y_DEG = 50.0


def nyu_root(root: str | Path | None = None) -> Path:
    """``<data_root>/nyu_vp`` (``root`` may be the data root or the NYU-VP folder itself)."""
    base = Path(root) if root is not None else data_root()
    for path in (base, base / FOLDER):
        if (path / "data" / "vps_0000.csv").is_file():
            return path
    raise FileNotFoundError(f"NYU-VP not found under {base} (expected {FOLDER}/data/vps_0000.csv)")


def calibration_matrix() -> np.ndarray:
    """The calibrated K (3, 3) of the NYU-VP camera (square pixels, ``fx``)."""
    return np.array([[FOCAL_PX, 0.0, PRINCIPAL_POINT[0]], [0.0, FOCAL_PX, PRINCIPAL_POINT[1]], [0.0, 0.0, 1.0]])


def vp_calibration_matrix() -> np.ndarray:
    """The full calibrated K (3, 3) with ``fx`` and ``fy`` (:data:`VP_CALIBRATION`), as the VP metric
    (CONSAC's) uses it."""
    fx, fy, cx, cy = VP_CALIBRATION
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])


def vp_directions(vps_px: np.ndarray) -> np.ndarray:
    """Unit directions (M, 3) ``K_vp^-1 [X, Y, 1]`` of labelled VPs (M, 2) in pixels."""
    dirs = np.c_[np.asarray(vps_px, np.float64).reshape(-1, 2), np.ones(len(vps_px))] @ np.linalg.inv(
        vp_calibration_matrix()).T
    return dirs / np.linalg.norm(dirs, axis=1, keepdims=True)


def _rows(path: Path) -> list[list[str]]:
    """Data rows of a space-separated file with a header row (empty fields kept as '')."""
    lines = path.read_text().splitlines()[1:]
    return [line.rstrip("\n").split(" ") for line in lines if line.strip()]


def read_lsd_segments(path: Path) -> np.ndarray:
    """(N, 4) ``[x1, y1, x2, y2]`` pixels from an ``lsd_lines_XXXX.csv`` file."""
    rows = _rows(path)
    if not rows:
        return np.zeros((0, 4))
    table = np.array([[float(v) for v in row if v != ""] for row in rows], np.float64)
    return table[:, [6, 7, 9, 10]]


def read_vanishing_points(path: Path) -> np.ndarray:
    """(M, 2) labelled vanishing points (pixels) from a ``vps_XXXX.csv`` file."""
    rows = _rows(path)
    return np.array([[float(row[1]), float(row[2])] for row in rows], np.float64).reshape(-1, 2)


def read_labelled_lines(path: Path, count: int) -> list[np.ndarray]:
    """For each of the ``count`` labelled vanishing points, its hand-drawn segments (n_k, 4)."""
    out = [np.zeros((0, 4)) for _ in range(count)]
    for row in _rows(path):
        index = int(row[0])
        values = [float(v) for v in row[1:] if v != ""]
        if 0 <= index < count:
            out[index] = np.array(values[: len(values) // 4 * 4], np.float64).reshape(-1, 4)
    return out


def ground_truth_frame(vps_px: np.ndarray, line_counts: list[int]) -> tuple[np.ndarray | None, bool, np.ndarray]:
    """(rotation (3, 3) world -> camera or None, pan_known, column of each labelled VP (M,), -1 = none).

    ``vps_px`` (M, 2) labelled vanishing points in pixels; ``line_counts`` (M,) hand-drawn lines of
    each (module docstring: vertical = the direction closest to the camera y axis)."""
    dirs = np.c_[vps_px, np.ones(len(vps_px))] @ np.linalg.inv(calibration_matrix()).T
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    candidates = [d for d in dirs]  # the labelled directions and those completing a labelled pair
    for i in range(len(dirs)):
        for j in range(i + 1, len(dirs)):
            if abs(dirs[i] @ dirs[j]) <= math.sin(math.radians(HORIZONTAL_TOLERANCE_DEG)):
                c = np.cross(dirs[i], dirs[j])
                candidates.append(c / np.linalg.norm(c))
    vertical_index = int(np.argmax([abs(c[1]) for c in candidates]))
    vertical = candidates[vertical_index] * np.sign(candidates[vertical_index][1] or 1.0)
    if math.degrees(math.acos(min(abs(vertical[1]), 1.0))) > MAX_VERTICAL_FROM_Y_DEG:
        return None, False, np.full(len(dirs), -1, np.int64)
    off = np.degrees(np.abs(np.arcsin(np.clip(np.abs(dirs @ vertical), 0.0, 1.0))))  # deg from perpendicular
    candidates = [i for i in range(len(dirs)) if i != vertical_index and off[i] <= HORIZONTAL_TOLERANCE_DEG]
    if candidates:
        h_index = min(candidates, key=lambda i: (round(off[i], 6), -line_counts[i], i))
        h = dirs[h_index] - (dirs[h_index] @ vertical) * vertical
        h /= np.linalg.norm(h)
        third = np.cross(h, vertical)
        if third[2] < 0:
            third = -third
        rotation = np.stack([h, vertical, third], 1)
        if np.linalg.det(rotation) < 0:
            rotation[:, 0] = -rotation[:, 0]
        pan_known = True
    else:  # gravity only: any frame with this vertical
        pitch = np.degrees(np.arcsin(np.clip(-vertical[2], -1, 1)))
        roll = np.degrees(np.arctan2(-vertical[0], vertical[1]))
        rotation = rotation_from_angles(0.0, pitch, roll).numpy()
        if rotation[:, 1] @ vertical < 0.999:  # build it exactly from the vertical instead
            h = np.cross(vertical, [0.0, 0.0, 1.0])
            h /= np.linalg.norm(h)
            rotation = np.stack([h, vertical, np.cross(h, vertical)], 1)
        pan_known = False
    columns = np.full(len(dirs), -1, np.int64)
    for i, d in enumerate(dirs):
        cosines = np.abs(rotation.T @ d)
        j = int(np.argmax(cosines))
        if (pan_known or j == 1) and np.degrees(np.arccos(np.clip(cosines[j], -1, 1))) <= LABEL_TOLERANCE_DEG:
            columns[i] = j
    return rotation, pan_known, columns


HORIZON_NOTES = {"labelled": "the line through the labelled horizontal VPs (>= 2 within 10 deg of perpendicular "
                            "to the labelled vertical)"}


def labelled_horizon(vps_px: np.ndarray, rotation: np.ndarray | None) -> np.ndarray | None:
    """The line (3,) through the labelled horizontal VPs ``vps_px`` (M, 2) pixels (module docstring),
    or None with fewer than two of them or no vertical."""
    if rotation is None or len(vps_px) < 2:
        return None
    K = calibration_matrix()
    dirs = np.c_[vps_px, np.ones(len(vps_px))] @ np.linalg.inv(K).T
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    horizontal = dirs[np.abs(dirs @ rotation[:, 1]) <= math.sin(math.radians(HORIZONTAL_TOLERANCE_DEG))]
    if len(horizontal) < 2:
        return None
    normal = np.linalg.eigh(horizontal.T @ horizontal)[1][:, 0]  # the plane the directions span
    return np.linalg.solve(K.T, normal)


def load_sample(folder: Path, index: int, split: str) -> CalibrationSample:
    """One photo ``index`` (0-1223) as a :class:`CalibrationSample` (module docstring)."""
    tag = f"{index:04d}"
    vps = read_vanishing_points(folder / f"vps_{tag}.csv")
    lines = read_labelled_lines(folder / f"labelled_lines_{tag}.csv", len(vps))
    rotation, pan_known, columns = ground_truth_frame(vps, [len(x) for x in lines]) if len(vps) else (None, False, [])
    kept = [(seg, col) for seg, col in zip(lines, columns) if col >= 0 and len(seg)]
    segments = np.concatenate([s for s, _ in kept]) if kept else np.zeros((0, 4))
    labels = np.concatenate([np.full(len(s), c, np.int64) for s, c in kept]) if kept else np.zeros(0, np.int64)
    return CalibrationSample(
        name=f"nyu_{tag}", image_path=None, width=WIDTH, height=HEIGHT,
        camera=Camera(WIDTH, HEIGHT, FOCAL_PX, PRINCIPAL_POINT, rotation, pan_known=pan_known),
        segments=segments, segment_labels=labels, split=split,
        extra={"detected_segments": read_lsd_segments(folder / f"lsd_lines_{tag}.csv"),
               "num_labelled_vps": int(len(vps)), "num_manhattan_vps": int((columns >= 0).sum()),
               "vp_directions": vp_directions(vps), "vp_calibration": vp_calibration_matrix(),
               **horizon_extra(labelled_horizon(vps, rotation))},
    )


def horizon_extra(line: np.ndarray | None) -> dict:
    """The sample's ``extra`` keys of a labelled horizon (none without one)."""
    return {} if line is None else {"horizons": {"labelled": line}, "horizon_notes": dict(HORIZON_NOTES)}


@lru_cache(maxsize=4)
def _load_split(folder: Path, split: str) -> tuple[CalibrationSample, ...]:
    return tuple(load_sample(folder, i, split) for i in SPLIT_IDS[split])


@register_dataset("nyu-vp")
def load_nyu_vp(root: str | Path | None = None, split: str = "val", **_: object) -> list[CalibrationSample]:
    """NYU-VP samples of split ``train`` (0-999), ``val`` / ``test`` (1000-1223) or ``all``."""
    if split not in SPLITS:
        raise ValueError(f"NYU-VP split must be one of {SPLITS}, got {split!r}")
    folder = nyu_root(root).resolve() / "data"
    names = ("train", "val") if split == "all" else ("val",) if split == "test" else (split,)
    return [s for name in names for s in _load_split(folder, name)]
