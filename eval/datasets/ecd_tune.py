"""``ecd-tune``: the 25 tuning photos of the Eurasian Cities horizon benchmark (Barinova et al., ECCV
2010), outdoor urban street scenes with a hand-labelled horizon and no other ground truth.

Layout (``<data_root>/ecd_tune/``, see its PROVENANCE.md): ``000.jpg`` ... ``024.jpg`` and
``horizons.csv`` (``name,width,height,a,b,c``: the labelled horizon ``a x + b y + c = 0`` in pixels).

Conventions (decided here, used by every ``ecd-tune`` number this project reports)
------------------------------------------------------------------------------
* **Split**: the 25 photos are the benchmark's tuning images (Lezama 2014 and its successors tune
  on the first 25 and report the other 78, which are held out and not stored): ``all`` (default
  for this dataset's callers), ``tune`` and ``train`` name them; ``test`` is an error that says so.
* **Ground truth**: only the horizon, ``extra["horizons"]["labelled"]`` (3,) ``(a, b, c)`` as the
  file stores it (the dataset's horizon, fitted by its authors to the labelled horizontal vanishing
  points); ``camera`` is None (no focal length, no rotation).  The line is read in our pixel
  coordinates as it is: with it, fR's scores reproduce the ones measured when the data was added
  (the benchmark's own code evaluates the label at MATLAB columns 1 and W; reading the label as
  1-based instead moves fR's AUC by 0.2 point).
"""
from __future__ import annotations

import csv
from functools import lru_cache
from pathlib import Path

import numpy as np
from fr_eval.datasets.registry import CalibrationSample, register_dataset
from fr_eval.paths import data_root

FOLDER = "ecd_tune"
SPLITS = ("all", "tune", "train")
HORIZON_NOTES = {"labelled": "the dataset's labelled horizon (Barinova 2010: fitted to the labelled horizontal VPs)"}


def ecd_tune_root(root: str | Path | None = None) -> Path:
    """``<data_root>/ecd_tune`` (``root`` may be the data root or the folder itself)."""
    base = Path(root) if root is not None else data_root()
    for path in (base, base / FOLDER):
        if (path / "horizons.csv").is_file():
            return path
    raise FileNotFoundError(f"ecd_tune not found under {base} (expected {FOLDER}/horizons.csv)")


@lru_cache(maxsize=4)
def _load(folder: Path) -> tuple[CalibrationSample, ...]:
    samples = []
    with open(folder / "horizons.csv", newline="", encoding="utf-8") as handle:
        for row in csv.DictReader(handle):
            line = np.array([float(row["a"]), float(row["b"]), float(row["c"])])
            samples.append(CalibrationSample(
                name=Path(row["name"]).stem, image_path=folder / row["name"], width=int(row["width"]),
                height=int(row["height"]), camera=None, split="tune",
                extra={"horizons": {"labelled": line}, "horizon_notes": dict(HORIZON_NOTES)}))
    return tuple(samples)


@register_dataset("ecd-tune")
def load_ecd_tune(root: str | Path | None = None, split: str = "all", **_: object) -> list[CalibrationSample]:
    """The 25 tuning photos (split ``all`` / ``tune`` / ``train``; module docstring)."""
    if split == "test":
        raise ValueError("ecd-tune holds the benchmark's 25 tuning photos only (its 78 test photos are held out): "
                         "use --split all")
    if split not in SPLITS:
        raise ValueError(f"ecd-tune split must be one of {SPLITS}, got {split!r}")
    return list(_load(ecd_tune_root(root).resolve()))
