"""Evaluation datasets: the common sample record and a small name -> loader registry.

Dataset interface (all a new dataset has to provide)
----------------------------------------------------
A dataset loader is a callable ``loader(root, split, **kwargs) -> Sequence[CalibrationSample]``
(any iterable with ``len`` works; a plain list is fine) where

* ``root`` is the data root (:func:`fr_eval.paths.data_root`, i.e. the folder that holds
  ``yorkurbandb/`` ...) or ``None`` for the default, and
* ``split`` is a split name (``"train"``, ``"test"``, ``"all"``; a dataset may define more).

Each sample is a :class:`CalibrationSample` (or any object with the same attributes) holding its
ground truth as one :class:`fr_torch.core.geometry.camera.Camera`.  All fields follow :mod:`fr_torch.core.geometry.conventions`:
pixels with a 0-based pixel-centre origin, degrees, ``rotation`` the 3x3 world->camera matrix
(camera x right / y down / z forward, world y = gravity/down, vertical Manhattan direction in
column 1, det +1), ``roll/tilt/pitch`` from :func:`fr_torch.core.geometry.conventions.horizon_angles` and ``hfov_deg``
the horizontal field of view, all derived from the camera.  Quantities a dataset does not know are
``None`` (the metrics then show "n/a").  ``segments`` (N, 4)
``[x1, y1, x2, y2]`` and ``segment_labels`` (N,) (column of ``rotation`` each segment belongs to,
-1 = none/background) are optional hand labels, used by oracle runs and likelihood fitting.

Register a loader with the decorator::

    from fr_eval.datasets.registry import register_dataset

    @register_dataset("zind-fr")
    def load_panoviews(root=None, split="test", **kwargs):
        return [CalibrationSample(name, path, w, h, Camera(w, h, focal_px, pp, rotation)), ...]

and add its module to ``_BUILTIN_MODULES`` below (modules that are missing are skipped), declare it
as an entry point of group ``fr_torch.datasets`` in another package, or name it by import path on
the command line: ``fr eval --dataset my_pkg.my_mod:load_my_data``.  A loader named by import path
must be registered (the decorator above runs when its module is imported) or marked
``@fr_torch.registry.plugin("dataset")``; any other callable is refused, never called.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np

from fr_torch.core.geometry.camera import Camera, camera_record
from fr_torch.registry import Registry


@camera_record
@dataclass
class CalibrationSample:
    """One evaluation image with its ground truth (see the module docstring for conventions).

    ``camera``: the ground-truth :class:`fr_torch.core.geometry.camera.Camera` (None when the dataset knows
    neither focal length nor orientation; its principal point is the calibrated one, default the
    image centre; ``pan_known=False`` when only gravity is known, e.g. a panorama view whose
    Manhattan frame is unknown).  ``focal_px``, ``hfov_deg``, ``principal_point``, ``rotation``
    ((3, 3) world->camera, vertical in column 1, det +1; None unless the Manhattan frame is known),
    ``roll_deg``, ``tilt_deg``, ``pitch_deg`` are read-only views of it.
    """

    name: str
    image_path: Path
    width: int
    height: int
    camera: Camera | None
    segments: np.ndarray | None = None  # (N, 4) hand-labelled segments, pixels, 0-based
    segment_labels: np.ndarray | None = None  # (N,) column index of `rotation`, -1 = unlabelled
    split: str = ""
    extra: dict[str, Any] = field(default_factory=dict)


def detected_segments(sample: CalibrationSample, detector: Callable[[np.ndarray], np.ndarray]) -> np.ndarray:
    """The line segments fR sees in ``sample``, (N, 4) ``[x1, y1, x2, y2]`` pixels: ``detector`` (e.g.
    :class:`fr_torch.detectors.lsd.LSDDetector`) on its photo read as ``fr calibrate`` reads it
    (:func:`fr_torch.images.io.read_working`); for a dataset without pixels, its own detections
    (``extra["detected_segments"]``, float64; NYU-VP's LSD segments)."""
    if sample.image_path is None:
        return np.asarray(sample.extra["detected_segments"], np.float64)
    from fr_torch.images.io import read_working

    gray, _, _ = read_working(str(sample.image_path), sample.name)
    return detector(gray)


DatasetLoader = Callable[..., Sequence[CalibrationSample]]

# Modules that register datasets when imported (a module that does not exist is skipped); other
# packages add datasets through entry points of group ``fr_torch.datasets``.
_BUILTIN_MODULES = ("fr_eval.datasets.yud", "fr_eval.datasets.panoviews", "fr_eval.datasets.nyu_vp",
                    "fr_eval.datasets.yud_plus", "fr_eval.datasets.ecd_tune", "fr_eval.datasets.synthetic_streets")
DATASETS: Registry[Sequence[CalibrationSample]] = Registry("dataset", group="fr_torch.datasets",
                                                           modules=_BUILTIN_MODULES)


def register_dataset(name: str) -> Callable[[DatasetLoader], DatasetLoader]:
    """Decorator registering ``loader(root, split, **kwargs)`` under ``name``."""
    return DATASETS.register(name)


def available_datasets() -> list[str]:
    return DATASETS.names()


def get_dataset_loader(spec: str) -> DatasetLoader:
    """Loader for a registered dataset name, an entry point or an import path ``module:attribute``."""
    return DATASETS.factory(spec)


def load_dataset(spec: str, root: str | Path | None = None, split: str = "test", **kwargs) -> list[CalibrationSample]:
    """Samples of dataset ``spec`` (name or import path) for ``split`` as a list."""
    return list(get_dataset_loader(spec)(root=root, split=split, **kwargs))
