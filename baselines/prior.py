"""``prior``: the "no information" row of the tables.

Principal point at the image centre, a fixed 60 deg horizontal field of view and an upright
camera: roll = tilt = pitch = 0 and ``R = I`` (the level camera of :mod:`fr_torch.camera`; the
heading is unknown, so ``pan_deg`` is None).  It needs only the image width (from ``meta.width``
or the image); without either it is a flagged failure.
"""
from __future__ import annotations

import numpy as np

from fr_torch.camera import focal_from_hfov
from fr_torch.interface import CameraEstimate, ImageMeta, Timer

from . import vp_geometry as vg


class Prior:
    """Fixed 60 deg HFOV, upright camera."""

    name = "prior"

    def __init__(self, hfov_deg: float = 60.0):
        self.hfov_deg = float(hfov_deg)

    def estimate(self, image: np.ndarray | None, meta: ImageMeta) -> CameraEstimate:
        with Timer() as timer:
            width, _ = vg.image_size(image, meta)
            if width <= 0:
                result = CameraEstimate.failure(self.name, "unknown image width")
            else:
                result = CameraEstimate(
                    method=self.name, focal_px=float(focal_from_hfov(self.hfov_deg, width)),
                    hfov_deg=self.hfov_deg, rotation=np.eye(3), roll_deg=0.0, tilt_deg=0.0, pitch_deg=0.0,
                    pan_deg=None)
        result.runtime_s = timer.seconds
        return result
