"""The public estimator: :class:`FREstimator` calibrates images (paths or arrays), detected
segments and user-supplied segments, on CPU or CUDA.

Usage::

    from fr_torch import FREstimator
    est = FREstimator(mode="fr")                      # or "fast" (Fast-fR)
    [result] = est.calibrate_images(["photo.jpg"])    # paths or arrays; batches welcome
    result.focal_px, result.roll_deg, result.rotation

    est.calibrate_segments([segments], image_sizes=[(640, 480)])   # your own (N, 4) segments

The search itself is the engine's (:class:`fr_torch.core.estimator.SegmentEstimator`); this class
adds the line detector and the decoding pipeline (:mod:`fr_torch.runtime.pipeline`).
Conventions: see :mod:`fr_torch.core.geometry.conventions`.
"""
from __future__ import annotations

from typing import Sequence

import numpy as np
import torch

from fr_torch.core.estimator import SegmentEstimator, _Image, keep_sane_segments
from fr_torch.core.likelihood.segments import validate_segments
from fr_torch.core.reliability.sanity import finite_record
from fr_torch.core.result import CalibrationResult
from fr_torch.core.settings.checks import (
    batch_of,
    check_camera,
    check_image_size,
    image_names,
    per_image,
    positive_number,
    shown,
)
from fr_torch.core.settings.config import Mode
from fr_torch.detectors.registry import get_detector
from fr_torch.errors import FRInputError
from fr_torch.images.io import (
    WORKING_LONG_SIDE,
    focal_and_pp_to_working,
    parse_working_long_side,
    result_to_input_pixels,
)
from fr_torch.runtime.device import DevicePolicy
from fr_torch.runtime.pipeline import Detection, calibrate_paths


class FREstimator(SegmentEstimator):
    """fR / Fast-fR on images: :class:`~fr_torch.core.estimator.SegmentEstimator` plus a line
    detector.

    ``detector``: name of a registered detector (:mod:`fr_torch.detectors`) or a detector object;
    None (default) = the device's default, ``lsd`` on a CPU and ``torch-lines`` on a GPU
    (:attr:`~fr_torch.runtime.device.DevicePolicy.default_detector`), where image files are then
    decoded and detected on the device (:mod:`fr_torch.runtime.device_pipeline`).  ``device``: a name (``cpu``, ``cuda``, ``cuda:1``), a torch.device or a
    :class:`~fr_torch.runtime.device.DevicePolicy` (:attr:`policy` holds the resolved one).
    ``decode``: where a GPU estimator decodes image files, ``"auto"``, ``"device"`` or ``"host"``
    (:attr:`~fr_torch.runtime.device.DevicePolicy.decode`; a given policy keeps its own).
    ``working_long_side``: images are detected at a long side of at most this many pixels
    (default :data:`~fr_torch.images.io.WORKING_LONG_SIDE`; ``"input"`` or None: at the input's
    own resolution; :func:`~fr_torch.images.io.parse_working_long_side`), held in
    :attr:`working_long_side`; every result is reported in the input image's pixels.  The other
    arguments are the engine's.
    """

    def __init__(self, mode: Mode | str = Mode.FR, measure: str | None = None, detector=None,
                 device: str | torch.device | DevicePolicy = "cpu", decode: str = "auto",
                 working_long_side: int | str | None = WORKING_LONG_SIDE, **kwargs):
        self.working_long_side = parse_working_long_side(working_long_side)
        self.policy = DevicePolicy.resolve(device, decode=decode)
        super().__init__(mode=mode, measure=measure, device=self.policy.device, **kwargs)
        self.detector = get_detector(self.policy.default_detector if detector is None else detector)

    def _calibrate(self, items, focal_list, pp_list, **kwargs) -> list[CalibrationResult]:
        """The engine's search, with the intra-op threads of :meth:`DevicePolicy.search_threads`."""
        with self.policy.search_threads():
            return super()._calibrate(items, focal_list, pp_list, **kwargs)

    def calibrate_images(self, images: Sequence, names: Sequence[str] | None = None, focal_px=None,
                         principal_point=None) -> list[CalibrationResult]:
        """Calibrate images given as file paths or arrays (grey, BGR, BGRA; 8/16-bit or float).

        ``images``: a sequence (list, tuple, (B, H, W[, C]) array) of images, one per result, even
        for one image (``[image]``).  ``names``: one per image (default: the path, or ``image<i>``).
        ``focal_px``: None (unknown), a number for all images, or one value (or None) per image.
        ``principal_point``: None (image centre), an (x, y) pair for all, or one per image.
        An argument of the wrong form or length is an FRInputError naming it; a bad image (or a bad
        value of one image) yields a result with ``ok=False`` and the reason; the others are unaffected.
        """

        if (isinstance(images, np.ndarray) or torch.is_tensor(images)) and images.ndim == 3 and images.shape[-1] in (3, 4):
            raise FRInputError(f"images: expected a sequence of images (paths or arrays), one per image; got "
                               f"{shown(images)} (one colour image? wrap it in a list)")
        images = batch_of(images, "images", "images (file paths or arrays)")
        return [r for _, batch in calibrate_paths(self, images, max(1, len(images)), 0, focal_px, principal_point,
                                                  names) for r in batch]

    def calibrate_detections(self, detections: Sequence, names: Sequence[str], focal_px=None,
                             principal_point=None) -> list[CalibrationResult]:
        """Calibrate images that were already decoded and detected, one
        :class:`fr_torch.runtime.pipeline.Detection` each (from :func:`fr_torch.runtime.pipeline.iter_detections`,
        possibly in worker processes).

        A detection holds its segments in *working* pixels (the image brought to a long side of at
        most :attr:`working_long_side`) and ``scale``, input pixels per working pixel.
        ``focal_px`` / ``principal_point`` are in the **input** image's pixels (None, one value for
        all, or one per image), and so is every result: they are brought to working pixels for the
        search and the results back to the input's pixels.  A detection with ``error`` set, or an
        image whose focal length / principal point is invalid, gives ``ok=False`` with the reason.
        """

        detections = batch_of(detections, "detections", "Detection records")
        count = len(detections)
        for i, d in enumerate(detections):
            if not isinstance(d, Detection):
                raise FRInputError(f"detections[{i}]: expected a fr_torch.runtime.pipeline.Detection (from "
                                   f"iter_detections or detect_image), got {shown(d)}")
        names = image_names(names, count, [f"image{i}" for i in range(count)])
        focal_list = per_image(focal_px, count, "focal_px")
        pp_list = per_image(principal_point, count, "principal_point", width=2)
        items, focal_work, pp_work = [], [], []
        for d, name, f, pp in zip(detections, names, focal_list, pp_list):
            item = _Image(name, d.size, d.segments, error=d.error, detect_s=d.seconds)
            try:  # a failed detection has size (0, 0): its own error stays the reason
                check_image_size(d.size, f"{name}: working")
                check_image_size(d.input_size, name)
                positive_number(d.scale, f"{name}: scale")
            except FRInputError as exc:
                item.error, item.size, f, pp = item.error or str(exc), (0, 0), None, None
            if item.error is None:
                try:  # checked in the input's pixels, so the message quotes the user's numbers
                    segments = validate_segments(d.segments, f"{name} segments", finite=False)
                    item.segments, item.dropped = keep_sane_segments(segments, d.size, name)
                    check_camera(f, pp, d.input_size, name)
                    f, pp = focal_and_pp_to_working(f, pp, d.scale, d.input_size, d.size)
                except FRInputError as exc:
                    item.error, f, pp = str(exc), None, None
            items.append(item)
            focal_work.append(f)
            pp_work.append(pp)
        results = self._calibrate(items, focal_work, pp_work, detected=True)
        for result, d in zip(results, detections):
            result_to_input_pixels(result, d.scale, d.input_size)
            finite_record(result)  # the last check, in the input's pixels
        return results


def calibrate(inputs: Sequence, mode: str = "fr", **kwargs) -> list[CalibrationResult]:
    """One-call API: calibrate images (paths or arrays) with fR (``mode="fr"``) or Fast-fR (``"fast"``).

    Keyword arguments go to :class:`FREstimator` (measure, detector, device, dtype, ...) or to
    :meth:`FREstimator.calibrate_images` (focal_px, principal_point, names).
    """
    call_keys = {"focal_px", "principal_point", "names"}
    call_kwargs = {k: kwargs.pop(k) for k in list(kwargs) if k in call_keys}
    return FREstimator(mode=mode, **kwargs).calibrate_images(inputs, **call_kwargs)
