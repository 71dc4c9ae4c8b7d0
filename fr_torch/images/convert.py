"""Image arrays in any common format (grey, BGR, BGRA; 8/16-bit or float) to 8-bit BGR or grey."""
from __future__ import annotations

import cv2
import numpy as np

from fr_torch.errors import FRInputError


def to_bgr8(image: np.ndarray, name: str = "image") -> np.ndarray:
    """Normalise grey / BGR / BGRA, 8- or 16-bit or float images to 8-bit BGR (H, W, 3)."""
    image = np.asarray(image)
    if image.ndim not in (2, 3) or (image.ndim == 3 and image.shape[2] not in (1, 3, 4)):
        raise FRInputError(f"{name}: expected an H x W or H x W x {{1,3,4}} image, got shape {image.shape}")
    if image.shape[0] == 0 or image.shape[1] == 0:
        raise FRInputError(f"{name}: zero-size image {image.shape}")
    if image.dtype == np.uint16:
        image = (image / 257.0).round().astype(np.uint8)
    elif image.dtype.kind == "f":
        if not np.isfinite(image).all():
            raise FRInputError(f"{name}: image has NaN or infinite pixels")
        scale = 255.0 if image.max() <= 1.0 else 1.0
        image = np.clip(image * scale, 0, 255).round().astype(np.uint8)
    elif image.dtype == np.bool_:
        image = image.astype(np.uint8) * 255
    elif image.dtype != np.uint8:
        image = np.clip(image, 0, 255).astype(np.uint8)
    if image.ndim == 2:
        return cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)
    if image.shape[2] == 1:
        return cv2.cvtColor(image[:, :, 0], cv2.COLOR_GRAY2BGR)
    if image.shape[2] == 4:
        return cv2.cvtColor(image, cv2.COLOR_BGRA2BGR)
    return image


def to_gray8(image: np.ndarray) -> np.ndarray:
    """8-bit single-channel grey image from any image :func:`to_bgr8` accepts."""
    return cv2.cvtColor(to_bgr8(image), cv2.COLOR_BGR2GRAY)
