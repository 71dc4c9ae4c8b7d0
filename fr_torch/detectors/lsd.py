"""The default detector: OpenCV's LSD."""
from __future__ import annotations

import cv2
import numpy as np


class LSDDetector:
    """OpenCV's LSD (von Gioi et al.) with its default parameters (same as LSD 1.5)."""

    name = "lsd"

    def __init__(self, refine: int = cv2.LSD_REFINE_STD):
        factory = getattr(cv2, "createLineSegmentDetector", None)
        if factory is None:  # LSD may move to opencv-contrib's ximgproc in a later OpenCV 5.x
            factory = getattr(getattr(cv2, "ximgproc", None), "createLineSegmentDetector", None)
        if factory is None:
            raise RuntimeError("this OpenCV build has no LSD (cv2.createLineSegmentDetector)")
        self._lsd = factory(refine)

    def __call__(self, gray: np.ndarray) -> np.ndarray:
        lines = self._lsd.detect(gray)[0]
        if lines is None:  # OpenCV returns None when nothing is found
            return np.zeros((0, 4))
        return lines.reshape(-1, 4).astype(np.float64)  # OpenCV 4: (N,1,4); OpenCV 5: (N,4)
