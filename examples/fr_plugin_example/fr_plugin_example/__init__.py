"""Example fR plug-in (see pyproject.toml for the two entry points it declares).

``horizon-lines``: a deliberately simple calibrator.  The roll is the length-weighted median
orientation of the near-horizontal line segments (|angle| < ``max_angle_deg``), the tilt is taken
as 0 (horizon through the principal point) and the horizontal field of view is fixed
(``hfov_deg``, default 60).  Options arrive as strings from a method spec:
``horizon-lines[hfov_deg=70,max_angle_deg=20]``.

``long-lsd``: OpenCV's LSD keeping only segments at least ``min_length`` pixels long.
"""
from __future__ import annotations

import numpy as np

from fr_torch.core.geometry.camera import Camera
from fr_torch.core.geometry.conventions import focal_from_hfov
from fr_torch.detectors.lsd import LSDDetector
from fr_torch.detectors.registry import detect_segments
from fr_torch.plugins.interface import CameraEstimate, ImageMeta, TimedCalibrator


class HorizonFromLines(TimedCalibrator):
    """Roll from near-horizontal segments, fixed FOV, zero tilt (angles in degrees, pixels)."""

    def __init__(self, hfov_deg: float | str = 60.0, max_angle_deg: float | str = 30.0, detector: str = "lsd"):
        self.hfov_deg = float(hfov_deg)
        self.max_angle_deg = float(max_angle_deg)
        self.detector = detector
        self.name = "horizon-lines"

    def _estimate(self, image: np.ndarray | None, meta: ImageMeta) -> CameraEstimate:
        if image is None and meta.segments is None:
            return CameraEstimate.failure(self.name, "bad input: needs the image or segments")
        segments = meta.segments if meta.segments is not None else detect_segments(image, self.detector)
        width, height = meta.width or image.shape[1], meta.height or image.shape[0]
        d = segments[:, 2:4] - segments[:, 0:2]
        d = d * np.where(d[:, :1] < 0, -1.0, 1.0)  # point every segment to the right
        angle = np.degrees(np.arctan2(d[:, 1], d[:, 0]))  # image y is down: positive = clockwise
        length = np.hypot(d[:, 0], d[:, 1])
        keep = np.abs(angle) < self.max_angle_deg
        if not keep.any():
            return CameraEstimate.failure(self.name, "no near-horizontal segments")
        order = np.argsort(angle[keep])
        cumulative = np.cumsum(length[keep][order])
        median = float(angle[keep][order][np.searchsorted(cumulative, cumulative[-1] / 2)])
        # fr_torch.core.geometry.conventions's roll is positive when the horizon turns anticlockwise on screen; the
        # heading is not estimated (pan unknown: a horizon-only camera)
        camera = Camera.from_angles(width, height, focal_from_hfov(self.hfov_deg, width), roll_deg=-median,
                                    tilt_deg=0.0)
        return CameraEstimate(method=self.name, camera=camera, extra={"num_horizontal": int(keep.sum())})


class LongLSD(LSDDetector):
    """LSD keeping segments of at least ``min_length`` pixels; input a 2-D uint8 image, output (N, 4)."""

    def __init__(self, min_length: float | str = 20.0):
        super().__init__()
        self.min_length = float(min_length)

    def __call__(self, gray: np.ndarray) -> np.ndarray:
        segments = super().__call__(gray)
        keep = np.hypot(segments[:, 2] - segments[:, 0], segments[:, 3] - segments[:, 1]) >= self.min_length
        return segments[keep]
