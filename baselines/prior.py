"""``prior``: the "no information" row of the tables.

Principal point at the image centre, a fixed 60 deg horizontal field of view and an upright
camera: roll = tilt = pitch = 0 and ``R = I`` (the level camera of :mod:`fr_torch.core.geometry.conventions`, whose
pan 0 stands for the unknown heading).  It needs only the image width (from ``meta.width``
or the image); without either it is a flagged failure.
"""
from __future__ import annotations

import numpy as np

from fr_torch.core.geometry.camera import Camera
from fr_torch.plugins.interface import CameraEstimate, ImageMeta, Timer

from . import vp_geometry as vg


class Prior:
    """Fixed 60 deg HFOV, upright camera."""

    name = "prior"

    def __init__(self, hfov_deg: float = 60.0):
        self.hfov_deg = float(hfov_deg)

    def estimate(self, image: np.ndarray | None, meta: ImageMeta) -> CameraEstimate:
        with Timer() as timer:
            width, height = vg.image_size(image, meta)
            if width <= 0:
                result = CameraEstimate.failure(self.name, "unknown image width")
            else:  # the guess R = I: level camera (roll = tilt = pitch = 0), pan 0
                camera = Camera.from_hfov(self.hfov_deg, width, height, rotation=np.eye(3))
                result = CameraEstimate(method=self.name, camera=camera)
        result.runtime_s = timer.seconds
        return result
