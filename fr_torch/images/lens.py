"""Images through a division-model lens: straighten a photo, or bend a pinhole image.

The model and its normalisation are :mod:`fr_torch.core.geometry.lens`'s (k normalised by half the
*photo's* diagonal, centre = principal point).  Both warps resample with ``cv2.remap`` (bilinear).
"""
from __future__ import annotations

import os
from pathlib import Path

import cv2
import numpy as np

from fr_torch.core.geometry.conventions import image_centre
from fr_torch.core.geometry.lens import distort_points, normalising_radius, undistort_points
from fr_torch.images.convert import to_bgr8
from fr_torch.images.io import encode_png, read_image
from fr_torch.output import write_bytes


def _pixel_grid(width: int, height: int) -> np.ndarray:
    """(height, width, 2) float64 pixel centres (x, y)."""
    xs, ys = np.meshgrid(np.arange(width, dtype=np.float64), np.arange(height, dtype=np.float64))
    return np.stack([xs, ys], -1)


def _remap(image: np.ndarray, source: np.ndarray, border: int) -> np.ndarray:
    maps = np.nan_to_num(source, nan=-1e6).astype(np.float32)
    return cv2.remap(image, maps[..., 0], maps[..., 1], cv2.INTER_LINEAR, borderMode=border)


def undistort_image(image: np.ndarray, k: float, centre) -> np.ndarray:
    """The straightened (pinhole) image of a photo taken through the division model of ``k``
    (normalised by half the photo's diagonal) with distortion centre ``centre`` (x, y) pixels.

    Same size as the photo; pixel ``u`` of the result shows the photo's pixel
    ``distort_points(u)``, so the result's camera is the pinhole camera of the estimate: the same
    focal length and principal point, ``K`` unchanged.  Barrel distortion (k < 0) pushes the
    photo's border out of the frame; where a result pixel has no photo pixel it is black.
    """
    height, width = image.shape[:2]
    centre = np.asarray(centre, np.float64)
    source = distort_points(_pixel_grid(width, height), k, centre, normalising_radius(width, height))
    return _remap(image, source, cv2.BORDER_CONSTANT)


def distort_image(source_image: np.ndarray, k: float, size: tuple[int, int], centre=None,
                  source_centre=None, border: int = cv2.BORDER_REPLICATE) -> np.ndarray:
    """A photo of ``size`` (width, height) taken through the division model of ``k`` from the
    pinhole image ``source_image`` (the inverse of :func:`undistort_image`).

    ``centre``: the photo's distortion centre (x, y) pixels (default its image centre,
    :func:`fr_torch.core.geometry.conventions.image_centre`); ``source_centre``: the pixel of ``source_image`` at
    the same ray (default: its image centre when the sizes differ, else ``centre``), so a larger
    source (e.g. the full frame of a crop) supplies the pixels barrel distortion pulls in from
    outside the frame.  k is normalised by half the photo's diagonal.  Pixels beyond the source
    follow ``border`` (OpenCV border mode).
    """
    width, height = size
    centre = np.array(image_centre(width, height) if centre is None else centre, np.float64)
    if source_centre is None:
        same = source_image.shape[1] == width and source_image.shape[0] == height
        source_centre = centre if same else np.array(image_centre(source_image.shape[1], source_image.shape[0]))
    undistorted = undistort_points(_pixel_grid(width, height), k, centre, normalising_radius(width, height))
    return _remap(source_image, undistorted - centre + np.asarray(source_centre, np.float64), border)


def undistorted_path(image_path, folder) -> Path:
    """``folder/<image stem>_undistorted.png`` (any file name, as :func:`fr_torch.images.overlay.overlay_path`)."""
    return Path(folder) / f"{Path(os.fsdecode(image_path)).stem}_undistorted.png"


def write_undistorted(image_path, result, folder) -> dict:
    """Straighten the photo ``image_path`` with ``result``'s lens (:func:`undistort_image`) and write
    ``<stem>_undistorted.png`` into ``folder``; returns the record of the straightened image: its
    path, size and pinhole ``K`` (the estimate's: same focal length and principal point), the
    rotation, and the lens that was removed (``distortion``).  A huge photo is straightened at its
    reduced decode size (K scaled to it).  FRInputError (one line) when the image cannot be read or
    the file not written; ValueError for a result without an estimate."""
    if not result.ok or result.camera is None:
        raise ValueError(f"{result.image}: no estimate to undistort with ({result.reason})")
    image, _ = read_image(image_path)
    image = to_bgr8(image)
    camera = result.camera
    if image.shape[1] != result.width:
        camera = camera.resized(image.shape[1], image.shape[0])
    straight = undistort_image(image, result.distortion_k, camera.principal_point)
    target = undistorted_path(image_path, folder)
    write_bytes(target, encode_png(straight))
    return {"image": os.fsdecode(image_path), "undistorted": os.fsdecode(target), "width": int(image.shape[1]),
            "height": int(image.shape[0]), "K": np.asarray(camera.K).tolist(), "focal_px": camera.focal_px,
            "principal_point": list(camera.principal_point),
            "rotation": None if result.rotation is None else np.asarray(result.rotation).tolist(),
            "distortion_removed": result.distortion, "reliable": bool(result.reliable), "reason": result.reason}
