"""Calibrate a batch of decoded images with a batched tensor detector on the estimator's device.

:func:`calibrate_decoded` is the GPU batch path from images to results: the images (already on
the device, e.g. from :func:`fr_torch.detectors.tensor_lines.decode_jpeg_batch`) go through the
detector's ``detect_batch`` on the device; the padded segments (B x N x 4 float32, a few KB per
image) then cross to the host once for the segment filter and the per-image validation of
:meth:`fr_torch.runtime.estimator.FREstimator.calibrate_segments`, which runs the search on the
estimator's device.
"""
from __future__ import annotations

import numpy as np
import torch


def calibrate_decoded(estimator, detector, images: torch.Tensor, names=None, focal_px=None,
                      principal_point=None) -> list:
    """Results (one :class:`fr_torch.core.estimator.CalibrationResult` each) for ``images``
    (B, 1, H, W) or (B, H, W), grey levels 0..255 (uint8 or float), on any device.

    ``detector``: an object with ``detect_batch(images) -> (segments (B, N, 4), mask (B, N))``,
    e.g. :class:`fr_torch.detectors.tensor_lines.TensorLinesDetector`.  ``focal_px`` /
    ``principal_point`` as in ``calibrate_segments`` (pixels of these images).
    """
    if images.ndim == 3:
        images = images[:, None]
    if images.ndim != 4 or images.shape[1] != 1:
        raise ValueError(f"expected images of shape (B, 1, H, W) or (B, H, W), got {tuple(images.shape)}")
    batch, _, height, width = images.shape
    per_image = as_numpy_lists(*detector.detect_batch(images))
    sizes = [(width, height)] * batch
    return estimator.calibrate_segments(per_image, sizes, names=names, focal_px=focal_px,
                                        principal_point=principal_point)


def as_numpy_lists(segments: torch.Tensor, mask: torch.Tensor) -> list[np.ndarray]:
    """The padded batch ``segments`` (B, N, 4) / ``mask`` (B, N) as one (N_b, 4) float64 array per image."""
    segments, mask = segments.double().cpu().numpy(), mask.cpu().numpy()
    return [segments[b][mask[b]] for b in range(segments.shape[0])]
