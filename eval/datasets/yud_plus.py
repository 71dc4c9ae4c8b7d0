"""YUD+ (Kluger et al., CVPR 2020): YorkUrbanDB with every vanishing point labelled, CONSAC's split.

Layout: the YUD photos and their Manhattan ground truth come from ``<data_root>/yorkurbandb/``
(:mod:`fr_eval.datasets.yud`, whose conventions hold here too); the extra labels from
``<data_root>/yud_plus/vps/P*GroundTruthVP_CamParams.mat`` (see its PROVENANCE.md).

Conventions (decided here, used by every YUD / YUD+ vanishing-point number this project reports)
---------------------------------------------------------------------------------------------
* **Split** (CONSAC's, not the ECCV 2008 one of ``yud``): the 102 names sorted alphabetically,
  ``train`` = the first 25, ``test`` = the other 77, ``all`` = the 102.
* **Labelled vanishing points**: the columns of ``vp`` (3 x M, M = 3..8; columns 1-3 are YUD's
  own Manhattan labels) are directions in YUD's y-up camera frame; ``extra["vp_directions"]``
  (M, 3) holds them in ours (``diag(1, -1, 1) vp``, unit rows, file order).  The dataset ``yud+``
  keeps all M; ``manhattan_only=True`` (the VP task's ``yud``, as CONSAC evaluates "YUD") keeps
  the first three.
* **Calibration** for the VP metric (``extra["vp_calibration"]``): YUD's K with the focal length
  674.918 px and the calibrated principal point in our 0-based pixels (306.551, 250.454), the
  frame of the segments every method detects on these photos.
* Camera ground truth (focal length, rotation, hand-labelled segments): exactly ``yud``'s.
"""
from __future__ import annotations

from dataclasses import replace
from functools import lru_cache
from pathlib import Path

import numpy as np
import scipy.io as sio
from fr_eval.datasets.registry import CalibrationSample, register_dataset
from fr_eval.datasets.yud import Y_FLIP, _load_all, yud_root
from fr_eval.paths import data_root

FOLDER = "yud_plus"
SPLITS = ("train", "test", "all")
TRAIN_COUNT = 25
MANHATTAN_VPS = 3


def yud_plus_root(root: str | Path | None = None) -> Path:
    """``<data_root>/yud_plus`` (``root`` may be the data root or the YUD+ folder itself)."""
    base = Path(root) if root is not None else data_root()
    for path in (base, base / FOLDER):
        if (path / "vps").is_dir():
            return path
    raise FileNotFoundError(f"YUD+ not found under {base} (expected {FOLDER}/vps/P*GroundTruthVP_CamParams.mat)")


def labelled_directions(path: Path) -> np.ndarray:
    """Unit labelled VP directions (M, 3) in our camera frame (x right, y down, z forward)."""
    vp = np.asarray(sio.loadmat(str(path))["vp"], np.float64)
    dirs = (Y_FLIP @ vp).T
    return dirs / np.linalg.norm(dirs, axis=1, keepdims=True)


@lru_cache(maxsize=4)
def _load(yud_path: Path, plus_path: Path) -> tuple[CalibrationSample, ...]:
    by_name = {sample.name: sample for sample in _load_all(yud_path)}
    names = sorted(p.name.removesuffix("GroundTruthVP_CamParams.mat") for p in (plus_path / "vps").glob("P*.mat"))
    samples = []
    for index, name in enumerate(names):
        sample = by_name[name]
        directions = labelled_directions(plus_path / "vps" / f"{name}GroundTruthVP_CamParams.mat")
        samples.append(replace(sample, split="train" if index < TRAIN_COUNT else "test",
                               extra=dict(sample.extra, vp_directions=directions, vp_calibration=sample.camera.K,
                                          num_labelled_vps=len(directions))))
    return tuple(samples)


@register_dataset("yud+")
def load_yud_plus(root: str | Path | None = None, split: str = "test", manhattan_only: bool = False,
                  **_: object) -> list[CalibrationSample]:
    """YUD+ samples of CONSAC's split ``train`` (25) / ``test`` (77) / ``all``, names sorted.

    ``manhattan_only``: keep only the three original (Manhattan) labelled VPs of each photo.
    """
    if split not in SPLITS:
        raise ValueError(f"YUD+ split must be one of {SPLITS}, got {split!r}")
    samples = _load(yud_root(root).resolve(), yud_plus_root(root).resolve())
    chosen = [s for s in samples if split == "all" or s.split == split]
    if manhattan_only:
        chosen = [replace(s, extra=dict(s.extra, vp_directions=s.extra["vp_directions"][:MANHATTAN_VPS],
                                        num_labelled_vps=MANHATTAN_VPS)) for s in chosen]
    return chosen
