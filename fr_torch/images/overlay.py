"""Draw an fR result over its image: segments coloured by Manhattan family, and the horizon.

A result with radial distortion (``distortion_k != 0``) is drawn twice, side by side: the photo
with its segments where they were detected and the horizon as the curve the lens makes of it, and
the straightened image (:func:`fr_torch.images.lens.undistort_image`) with the segments as the
estimate sees them (undistorted) and the straight horizon.
"""
from __future__ import annotations

import os
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np

from fr_torch.core.estimator import BACKGROUND_LABEL
from fr_torch.core.geometry.conventions import resize_points
from fr_torch.core.geometry.horizon import border_columns, horizon_border_y, horizon_line
from fr_torch.core.result import CalibrationResult
from fr_torch.images.convert import to_bgr8
from fr_torch.images.io import encode_png, read_image
from fr_torch.images.lens import undistort_image
from fr_torch.output import write_bytes

# BGR colours: family of column 0 red, vertical (column 1) green, column 2 blue, background grey.
FAMILY_COLOURS = {0: (40, 40, 230), 1: (40, 200, 40), 2: (230, 120, 30), BACKGROUND_LABEL: (150, 150, 150)}
HORIZON_COLOUR = (0, 220, 255)
CAPTION_BOX, CAPTION_TEXT = (20, 20, 20), (245, 245, 245)


def _horizon_line(result: CalibrationResult) -> np.ndarray | None:
    """The horizon's line (3,) in the undistorted image (:func:`fr_torch.core.geometry.horizon.horizon_line`),
    or None without an estimate or when the horizon is at infinity."""
    if result.camera is None or result.camera.K is None or result.camera.rotation is None:
        return None
    return horizon_line(result.camera.K, result.camera.rotation, result.vertical_axis)


def _darkened(image_bgr: np.ndarray) -> np.ndarray:
    """The image at 60 % brightness (the overlay's background), uint8."""
    return (image_bgr.astype(np.float32) * 0.6).astype(np.uint8)


def _draw_straight_horizon(canvas: np.ndarray, result: CalibrationResult) -> None:
    ends = horizon_endpoints(result)
    if ends is not None:
        a, b = (tuple(int(round(v)) for v in p) for p in ends)
        cv2.line(canvas, a, b, HORIZON_COLOUR, 2, cv2.LINE_AA)


def horizon_endpoints(result: CalibrationResult):
    """The horizon of the undistorted image (:func:`_horizon_line`) clipped to the image.

    Returns ((x1, y1), (x2, y2)) in pixels, or None when the horizon is outside the image.
    """
    line = _horizon_line(result)
    if line is None:
        return None
    w, h = result.width, result.height
    # intersections with the left and right borders, then with the top and bottom ones
    points = [(x, y) for x, y in zip(border_columns(w), horizon_border_y(line, w, h)) if y is not None]
    if abs(line[0]) > 1e-12:
        points += [(-(line[1] * y + line[2]) / line[0], y) for y in (0.0, h - 1.0)]
    inside = [(x, y) for x, y in points if -0.5 <= x <= w - 0.5 and -0.5 <= y <= h - 0.5]
    if len(inside) < 2:
        return None
    inside.sort()
    return inside[0], inside[-1]


def horizon_curve(result: CalibrationResult, samples: int = 400) -> np.ndarray | None:
    """The horizon of a result with radial distortion as it runs through the photo: (M, 2) photo
    pixels (the straight horizon of the undistorted image, sampled over 7 image widths around the
    image and bent by the estimate's lens), the parts inside the image; None when none is."""
    line = _horizon_line(result)
    if line is None:
        return None
    w, h = result.width, result.height
    span = np.linspace(-3.0, 4.0, samples)
    if abs(line[1]) >= abs(line[0]):  # mostly horizontal: x runs, y follows
        xs = span * w
        points = np.stack([xs, -(line[0] * xs + line[2]) / line[1]], -1)
    else:
        ys = span * h
        points = np.stack([-(line[1] * ys + line[2]) / line[0], ys], -1)
    photo = result.distort_points(points)
    inside = np.isfinite(photo).all(-1) & (photo[:, 0] >= -0.5) & (photo[:, 0] <= w - 0.5) \
        & (photo[:, 1] >= -0.5) & (photo[:, 1] <= h - 0.5)
    return photo[inside] if inside.sum() >= 2 else None


def _draw_segments(canvas: np.ndarray, segments: np.ndarray | None, labels: np.ndarray | None) -> None:
    if segments is None or labels is None:
        return
    order = np.argsort(labels == BACKGROUND_LABEL)[::-1]  # background first, families on top
    for idx in order:
        x1, y1, x2, y2 = segments[idx]
        colour = FAMILY_COLOURS[int(labels[idx])]
        cv2.line(canvas, (int(round(x1)), int(round(y1))), (int(round(x2)), int(round(y2))), colour, 2, cv2.LINE_AA)


def draw_overlay(image_bgr: np.ndarray, result: CalibrationResult) -> np.ndarray:
    """A copy of the image (darkened) with coloured segments, the horizon and a caption; with radial
    distortion, the photo (horizon as a curve) and the straightened image side by side (module
    docstring)."""
    canvas = _darkened(image_bgr)
    _draw_segments(canvas, result.segments, result.labels)
    if not (result.ok and result.distortion_k != 0.0):
        _draw_straight_horizon(canvas, result)
    else:
        curve = horizon_curve(result)
        if curve is not None:
            cv2.polylines(canvas, [np.round(curve).astype(np.int32)[:, None, :]], False, HORIZON_COLOUR, 2,
                          cv2.LINE_AA)
        straight = _darkened(undistort_image(image_bgr, result.distortion_k, result.camera.principal_point))
        if result.segments is not None:
            ends = result.undistort_points(np.asarray(result.segments, np.float64).reshape(-1, 2, 2))
            _draw_segments(straight, ends.reshape(-1, 4), result.labels)
        _draw_straight_horizon(straight, result)
        draw_caption(straight, f"straightened (division model, k = {result.distortion_k:+.3f})", at_bottom=True)
        canvas = np.concatenate([canvas, straight], 1)
    if result.ok:
        caption = (f"f={result.focal_px:.0f}px hfov={result.hfov_deg:.1f}  roll={result.roll_deg:+.2f}  "
                   f"tilt={result.tilt_deg:+.2f}  pan={result.pan_deg:+.1f} deg")
        if result.distortion_model != "pinhole":
            caption += f"  k={result.distortion_k:+.3f}"
        horizon = result.horizon
        if horizon is not None and horizon.bound_pct is not None:
            caption += f"  horizon +-{horizon.bound_pct:.1f}% of h"
        if not result.reliable:
            caption += "  [UNRELIABLE]"
    else:
        caption = f"no estimate: {result.reason}"
    draw_caption(canvas, caption)
    return canvas


def draw_caption(canvas: np.ndarray, text: str, margin: int = 6, at_bottom: bool = False) -> None:
    """Light text on a dark box in the top-left (or bottom-left) corner, drawn once; shrunk to fit
    the image width."""
    font, thickness = cv2.FONT_HERSHEY_SIMPLEX, 1
    scale = 0.5
    (tw, th), base = cv2.getTextSize(text, font, scale, thickness)
    if tw > canvas.shape[1] - 2 * margin:
        scale *= (canvas.shape[1] - 2 * margin) / tw
        (tw, th), base = cv2.getTextSize(text, font, scale, thickness)
    top = canvas.shape[0] - (th + base + 2 * margin) if at_bottom else 0
    cv2.rectangle(canvas, (0, top), (tw + 2 * margin, top + th + base + 2 * margin), CAPTION_BOX, -1)
    cv2.putText(canvas, text, (margin, top + margin + th), font, scale, CAPTION_TEXT, thickness, cv2.LINE_AA)


def overlay_path(image_path, folder) -> Path:
    """``folder/<image stem>_fr.png``; works for any file name (bytes that are not UTF-8 included)."""
    return Path(folder) / f"{Path(os.fsdecode(image_path)).stem}_fr.png"


def write_overlay(image_path, result: CalibrationResult, folder) -> Path:
    """Load the image (bounded decode), draw the result and write ``<stem>_fr.png`` into ``folder``.

    The PNG is encoded in memory and written with Python's file I/O (``cv2.imwrite`` crashes on file
    names that are not valid UTF-8).  A huge image is drawn at its reduced decode size.  Raises
    FRInputError with a one-line reason (unreadable image, existing folder in the way, read-only...).
    """

    image, size = read_image(image_path)
    image = to_bgr8(image)
    size = (image.shape[1], image.shape[0])
    if size != (result.width, result.height) and result.width > 0 and result.ok:
        result = replace(result, width=size[0], height=size[1], camera=result.camera.resized(*size),
                         segments=None if result.segments is None else
                         resize_points(result.segments, (result.width, result.height), size))
    target = overlay_path(image_path, folder)
    write_bytes(target, encode_png(draw_overlay(image, result)))
    return target
