"""YorkUrbanDB (Denis, Elder & Estrada, ECCV 2008) loader, converted to the project conventions.

Layout (``<data_root>/yorkurbandb/``, see its PROVENANCE.md): ``cameraParameters.mat``,
``Manhattan_Image_DB_Names.mat``, ``ECCV_TrainingAndTestImageNumbers.mat`` and one folder per image
``P*/`` with ``P*.jpg``, ``P*LinesAndVP.mat`` and ``P*GroundTruthVP_Orthogonal_CamParams.mat``.

Conversions (decided here, used by every YUD number this project reports)
------------------------------------------------------------------------
* **Focal length**: ``focal / pixelSize`` = 674.918 px (one camera for all 102 images).
* **Principal point**: the calibrated ``pp`` = (307.551, 251.454) is MATLAB 1-based; our pixel
  coordinates have their origin at the centre of the top-left pixel (0-based), so we subtract 1:
  ``principal_point = (306.551, 250.454)``.  The same -1 shift is applied to the labelled segment
  endpoints (``lines``), so labels and pp stay consistent.
* **Rotation**: ``vp_orthogonal`` holds the three Manhattan directions (columns) in YUD's camera
  frame, which is **y-up** (x right, z forward): the image vanishing point of column k is
  ``K diag(1,-1,1) vp(:,k)``.  Column 2 (1-based) is the vertical in all 102 images.  Our R (world ->
  camera, camera x right / y down / z forward) is ``diag(1,-1,1) @ vp_orthogonal`` with
  - column order kept (YUD 1, 2, 3 -> ours 0, 1, 2): the vertical already sits in our column 1;
  - the vertical column's sign chosen to point **down** in the camera (positive y component:
    world y = gravity);
  - the third column's sign chosen so that it points forward (z >= 0), then the first column's
    sign fixed so that det R = +1 (the y flip makes the raw matrix improper).  Horizontal column
    signs carry no information (vanishing points are sign-free); frame error ignores them.
* **Segment labels**: ``vp_association`` 1..3 -> our column index 0..2 (vertical = 1).
* **Horizon** (``extra["horizons"]``, the horizon task, :mod:`fr_eval.protocols.horizon_eval`): the
  line through the two labelled horizontal vanishing points, columns 1 and 3 of
  ``P*GroundTruthVP_CamParams.mat``'s ``vp`` (fitted to the labelled lines, not orthogonalised), as the
  horizon benchmark defines YUD's ground truth: ``labelled`` projects them with the calibrated K
  (``K diag(1,-1,1) vp``), ``lezama-code`` as Lezama et al.'s ``yud_benchmark.m`` does, with a focal
  length of 1.08 w = 691.2 px instead of 674.918 (same principal point).  The orthogonalised frame's
  horizon (``K^-T R[:, 1]``) is the third definition, ``frame``, derived from ``camera``.
* **Split**: the ECCV 2008 51/51 split of ``ECCV_TrainingAndTestImageNumbers.mat`` (1-based
  indices into ``Manhattan_Image_DB_Names``, names stored with a trailing backslash) -- the split
  the authors' ``evaluation_onlinefR.m`` uses.

GT roll / tilt / pitch come from :func:`fr_torch.core.geometry.conventions.horizon_angles` (paper definitions).
"""
from __future__ import annotations

from functools import lru_cache
from pathlib import Path

import numpy as np
import scipy.io as sio

from fr_eval.datasets.registry import CalibrationSample, register_dataset
from fr_eval.paths import data_root
from fr_torch.core.geometry.camera import Camera

FOLDER = "yorkurbandb"
WIDTH, HEIGHT = 640, 480
Y_FLIP = np.diag([1.0, -1.0, 1.0])
SPLITS = ("train", "test", "all")
#: The focal length (pixels) of Lezama et al.'s ``yud_benchmark.m``: ``focal_ratio`` 1.08 x the width.
LEZAMA_FOCAL_RATIO = 1.08
HORIZON_NOTES = {
    "labelled": "the line through the two labelled horizontal VPs (GroundTruthVP_CamParams.mat), calibrated K",
    "lezama-code": "the line through the two labelled horizontal VPs projected as Lezama 2014's yud_benchmark.m "
                   "does (f = 1.08 w)",
}


def yud_root(root: str | Path | None = None) -> Path:
    """``<data_root>/yorkurbandb`` (``root`` may be the data root or the YUD folder itself)."""
    base = Path(root) if root is not None else data_root()
    if (base / "cameraParameters.mat").is_file():
        return base
    path = base / FOLDER
    if not (path / "cameraParameters.mat").is_file():
        raise FileNotFoundError(f"YorkUrbanDB not found under {base} (expected {FOLDER}/cameraParameters.mat)")
    return path


def _loadmat(path: Path) -> dict:
    return sio.loadmat(str(path))


def camera_parameters(root: Path) -> tuple[float, tuple[float, float]]:
    """(focal_px, principal_point 0-based) of the YUD camera."""
    cam = _loadmat(root / "cameraParameters.mat")
    focal_px = float(cam["focal"].item() / cam["pixelSize"].item())
    pp = np.asarray(cam["pp"], dtype=np.float64).ravel() - 1.0  # MATLAB 1-based -> 0-based
    return focal_px, (float(pp[0]), float(pp[1]))


def image_names(root: Path) -> list[str]:
    """The 102 folder names in ``Manhattan_Image_DB_Names`` order (1-based index = position + 1)."""
    cell = _loadmat(root / "Manhattan_Image_DB_Names.mat")["Manhattan_Image_DB_Names"]
    names = []
    for entry in np.asarray(cell).ravel():
        name = str(np.asarray(entry).ravel()[0])
        names.append(name.rstrip("\\/"))
    return names


def eccv_split(root: Path) -> dict[str, list[int]]:
    """0-based image indices of the ECCV 2008 ``train`` and ``test`` sets (51 + 51)."""
    mat = _loadmat(root / "ECCV_TrainingAndTestImageNumbers.mat")
    return {
        "train": [int(i) - 1 for i in np.asarray(mat["trainingSetIndex"]).ravel()],
        "test": [int(i) - 1 for i in np.asarray(mat["testSetIndex"]).ravel()],
    }


def rotation_from_vp_orthogonal(vp_orthogonal: np.ndarray) -> np.ndarray:
    """Our world->camera R (y-down camera, vertical in column 1, det +1) from YUD ``vp_orthogonal``."""
    r = Y_FLIP @ np.asarray(vp_orthogonal, dtype=np.float64)  # y-up -> y-down camera frame
    if r[1, 1] < 0:  # vertical direction must point down in the camera (gravity)
        r[:, 1] = -r[:, 1]
    if r[2, 2] < 0:  # second horizontal direction: forward-pointing representative
        r[:, 2] = -r[:, 2]
    if np.linalg.det(r) < 0:  # the y flip makes the frame improper: fix with the first column
        r[:, 0] = -r[:, 0]
    return r


def labelled_horizons(vp: np.ndarray, focal_px: float, principal_point, width: int) -> dict[str, np.ndarray]:
    """The horizon definitions of one photo from its labelled VP directions ``vp`` (3 x 3, YUD's y-up
    camera frame, the vertical in column 2): ``{"labelled", "lezama-code"}`` -> line (3,) in
    0-based pixels (module docstring)."""
    out = {}
    for name, focal in (("labelled", focal_px), ("lezama-code", LEZAMA_FOCAL_RATIO * width)):
        K = np.array([[focal, 0.0, principal_point[0]], [0.0, focal, principal_point[1]], [0.0, 0.0, 1.0]])
        points = K @ Y_FLIP @ np.asarray(vp, np.float64)
        out[name] = np.cross(points[:, 0], points[:, 2])
    return out


def load_segments(folder: Path, name: str) -> tuple[np.ndarray, np.ndarray]:
    """Hand-labelled segments (N, 4) 0-based pixels and labels (N,) in our column indices."""
    mat = _loadmat(folder / f"{name}LinesAndVP.mat")
    lines = np.asarray(mat["lines"], dtype=np.float64) - 1.0  # 1-based -> 0-based
    segments = lines.reshape(-1, 4)  # rows 2i, 2i+1 are the endpoints [x y] of segment i
    labels = np.asarray(mat["vp_association"]).ravel().astype(np.int64) - 1  # YUD k -> column k-1
    if len(labels) != len(segments):
        raise ValueError(f"{name}: {len(segments)} segments but {len(labels)} labels")
    return segments, labels


@lru_cache(maxsize=4)
def _load_all(root: Path) -> tuple[CalibrationSample, ...]:
    focal_px, pp = camera_parameters(root)
    names = image_names(root)
    split_of = {}
    for split, indices in eccv_split(root).items():
        for i in indices:
            split_of[i] = split
    samples = []
    for index, name in enumerate(names):
        folder = root / name
        vp = _loadmat(folder / f"{name}GroundTruthVP_Orthogonal_CamParams.mat")["vp_orthogonal"]
        horizons = labelled_horizons(_loadmat(folder / f"{name}GroundTruthVP_CamParams.mat")["vp"], focal_px, pp, WIDTH)
        segments, labels = load_segments(folder, name)
        samples.append(CalibrationSample(
            name=name,
            image_path=folder / f"{name}.jpg",
            width=WIDTH,
            height=HEIGHT,
            camera=Camera(WIDTH, HEIGHT, focal_px, pp, rotation_from_vp_orthogonal(vp)),
            segments=segments,
            segment_labels=labels,
            split=split_of.get(index, ""),
            extra={"index_1based": index + 1, "horizons": horizons, "horizon_notes": dict(HORIZON_NOTES)},
        ))
    return tuple(samples)


@register_dataset("yud")
def load_yud(root: str | Path | None = None, split: str = "test", **_: object) -> list[CalibrationSample]:
    """YorkUrbanDB samples of the ECCV split ``train`` / ``test`` (51 each, in the .mat order) or ``all``."""
    if split not in SPLITS:
        raise ValueError(f"YUD split must be one of {SPLITS}, got {split!r}")
    path = yud_root(root).resolve()
    samples = _load_all(path)
    if split == "all":
        return list(samples)
    order = eccv_split(path)[split]
    return [samples[i] for i in order]
