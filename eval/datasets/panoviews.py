"""Loader for planar-view datasets generated from panoramas by ``fr make-dataset``.

A generated folder holds ``gt.csv`` (one row per view), ``dataset.json`` and ``images/``; see
:mod:`fr_eval.datasets.make_dataset` for the columns.  Registered datasets:

* ``zind-fr``: ``<cache_root>/zind-fr`` (``$FR_CACHE``, default ``<repo>/data_local``), built with
  the command in :mod:`fr_eval.datasets.make_dataset`'s docstring;
* ``yud-crop-400x300``, ``yud-crop-480x360``: ``<cache_root>/<name>``, YorkUrbanDB crops around the
  calibrated principal point (narrow cameras, 33.0 and 39.2 deg), built by :mod:`fr_eval.datasets.crop_views`
  (``eval/reproduce.sh crops``);
* ``zind-fr-d``, ``yud-crop-480x360-d``: the same views through a division-model lens of known k
  (``gt.csv`` column ``k``, ``extra["distortion_k"]``), built by ``eval/reproduce.sh distortion``;
* ``panoviews``: any generated folder, passed as ``path=`` (or as ``root`` when ``root`` itself holds
  a ``gt.csv``).

Each view becomes a :class:`fr_eval.datasets.registry.CalibrationSample` with the exact ground truth
(focal, principal point, R world->camera, tilt / roll / pitch from
:func:`fr_torch.core.geometry.conventions.horizon_angles`).  The principal point is ``gt.csv``'s ``cx``, ``cy``
(pixels; the generators write the image centre :func:`fr_torch.core.geometry.conventions.image_centre`); a
``gt.csv`` without those columns was rendered with the principal point at ``(w / 2, h / 2)``
(:func:`unrecorded_principal_point`), which the loader then uses.  When the panorama's Manhattan
yaw was unknown (``manhattan_known`` False) ``rotation`` is still the exact camera orientation but
in the panorama frame, so its columns 0 and 2 are not vanishing directions: the sample's
``extra["manhattan_known"]`` says so, and ``rotation`` is set to ``None`` unless
``keep_unknown_manhattan_rotation=True`` (gravity-based numbers -- tilt, roll, pitch, focal -- are
always ground truth).
"""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator

import numpy as np
import pandas as pd

from fr_eval.datasets.registry import CalibrationSample, register_dataset
from fr_eval.paths import cache_root
from fr_torch.core.geometry.camera import Camera
from fr_torch.core.geometry.conventions import image_centre

R_COLUMNS = [f"r{i}{j}" for i in range(3) for j in range(3)]
#: The columns of ``gt.csv``, in order, as written by ``fr make-dataset`` and ``fr_eval.datasets.crop_views``
#: (``cx``, ``cy``: the principal point, pixels).
GT_COLUMNS = ["file", "pano", "group", "split", "width", "height", "cx", "cy", "focal_px", "hfov_deg", "pan_deg",
              "tilt_deg", "roll_deg", "pitch_deg", *R_COLUMNS, "manhattan_known", "manhattan_yaw_deg"]


def unrecorded_principal_point(width: int, height: int) -> tuple[float, float]:
    """The principal point (pixels) of a view whose ``gt.csv`` has no ``cx``, ``cy`` columns:
    ``(w / 2, h / 2)``, the centre those folders were rendered with."""
    return (width / 2.0, height / 2.0)
SPLITS = ("train", "test", "all")


@dataclass
class PanoView:
    """One generated view with its ground truth (conventions of :mod:`fr_torch.core.geometry.conventions`)."""

    name: str
    image_path: Path
    pano: str
    split: str
    width: int
    height: int
    focal_px: float
    hfov_deg: float
    rotation: np.ndarray  # (3, 3) world->camera (room Manhattan frame when manhattan_known)
    pan_deg: float
    tilt_deg: float
    roll_deg: float
    pitch_deg: float
    manhattan_known: bool
    distortion_k: float = 0.0  # division model's k (fr_torch.core.geometry.lens); 0 = a pinhole view
    principal_point: tuple[float, float] | None = None  # (x, y) pixels; None = image_centre(width, height)

    def __post_init__(self) -> None:
        if self.principal_point is None:
            self.principal_point = image_centre(self.width, self.height)


class PanoViews:
    """A generated dataset folder: ``len()``, iteration over :class:`PanoView`, split filter."""

    def __init__(self, folder: str | Path, split: str = "all"):
        self.folder = Path(folder)
        gt_path = self.folder / "gt.csv"
        if not gt_path.is_file():
            raise FileNotFoundError(f"{gt_path} not found: generate it with `fr make-dataset` "
                                    "(see eval/datasets/make_dataset.py)")
        if split not in SPLITS:
            raise ValueError(f"split must be one of {SPLITS}, got {split!r}")
        table = pd.read_csv(gt_path)
        if split != "all":
            table = table[table["split"] == split]
        self.table = table.reset_index(drop=True)
        self.split = split
        info = self.folder / "dataset.json"
        # A folder cut from another dataset's images (fr_eval.datasets.crop_views) names it: its views show
        # the same scenes, so grouped cross-validation keeps a crop with its source photo.
        self.scene_source = json.loads(info.read_text()).get("source") if info.is_file() else None

    def __len__(self) -> int:
        return len(self.table)

    def __iter__(self) -> Iterator[PanoView]:
        for i in range(len(self)):
            yield self[i]

    def __getitem__(self, i: int) -> PanoView:
        r = self.table.iloc[i]
        width, height = int(r["width"]), int(r["height"])
        recorded = "cx" in r.index and "cy" in r.index
        principal_point = (float(r["cx"]), float(r["cy"])) if recorded else unrecorded_principal_point(width, height)
        return PanoView(
            name=Path(r["file"]).stem, image_path=self.folder / r["file"], pano=str(r["pano"]),
            split=str(r["split"]), width=width, height=height,
            focal_px=float(r["focal_px"]), hfov_deg=float(r["hfov_deg"]),
            rotation=r[R_COLUMNS].to_numpy(dtype=np.float64).reshape(3, 3),
            pan_deg=float(r["pan_deg"]), tilt_deg=float(r["tilt_deg"]), roll_deg=float(r["roll_deg"]),
            pitch_deg=float(r["pitch_deg"]), manhattan_known=bool(r["manhattan_known"]),
            distortion_k=float(r["k"]) if "k" in r.index else 0.0, principal_point=principal_point,
        )

    def samples(self, keep_unknown_manhattan_rotation: bool = False) -> list[CalibrationSample]:
        """The views as evaluation-harness :class:`CalibrationSample` records."""
        out = []
        for v in self:
            # without a known Manhattan frame only gravity is ground truth (roll / tilt / pitch, no rotation)
            camera = Camera(v.width, v.height, v.focal_px, v.principal_point, v.rotation,
                            pan_known=v.manhattan_known or keep_unknown_manhattan_rotation)
            out.append(CalibrationSample(
                name=v.name, image_path=v.image_path, width=v.width, height=v.height, camera=camera,
                split=v.split,
                extra={"pano": v.pano, "pan_deg": v.pan_deg, "manhattan_known": v.manhattan_known,
                       "scene_source": self.scene_source, "distortion_k": v.distortion_k},
            ))
        return out


def dataset_folder(root, path, default_name: str | None) -> Path:
    """The folder of a generated dataset: ``path`` when given, else ``root`` when it holds a
    ``gt.csv``, else ``<cache_root>/<default_name>``."""
    if path is not None:
        return Path(path)
    if root is not None and (Path(root) / "gt.csv").is_file():
        return Path(root)
    if default_name is None:
        raise ValueError("panoviews: pass path=<generated dataset folder>")
    return cache_root() / default_name


@register_dataset("panoviews")
def load_panoviews(root=None, split: str = "test", path=None, **kwargs) -> list[CalibrationSample]:
    """Any ``fr make-dataset`` folder (``path=`` or ``root`` holding gt.csv)."""
    return PanoViews(dataset_folder(root, path, None), split).samples(**kwargs)


def _cache_folder_loader(name: str):
    """A loader for the generated folder ``<cache_root>/<name>``; ``root`` is the *data* root and is
    ignored unless it holds a gt.csv itself, ``path=`` names another folder."""
    def load(root=None, split: str = "test", path=None, **kwargs) -> list[CalibrationSample]:
        return PanoViews(dataset_folder(root, path, name), split).samples(**kwargs)
    load.__doc__ = f"Views in ``<cache_root>/{name}`` (``root`` / ``path`` as for any cache folder)."
    return load


#: Generated datasets read from the cache root (module docstring): ZInD-fR and the YUD crops.
YUD_CROP_SIZES = ("400x300", "480x360")
#: The same views through a division-model lens of known k (issue 46; ``extra["distortion_k"]``):
#: ZInD-fR-D (``fr make-dataset --k-range``) and YUD crops warped (``fr_eval.datasets.crop_views --k-range``).
DISTORTED_DATASETS = ("zind-fr-d", "yud-crop-480x360-d")
CACHE_DATASETS = ("zind-fr",) + tuple(f"yud-crop-{size}" for size in YUD_CROP_SIZES) + DISTORTED_DATASETS
for _name in CACHE_DATASETS:
    register_dataset(_name)(_cache_folder_loader(_name))
