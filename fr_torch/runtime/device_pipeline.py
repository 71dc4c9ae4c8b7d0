"""The GPU path from image files to results: decode, detect and search on the device.

:func:`fr_torch.runtime.pipeline.calibrate_paths` (and so ``FREstimator.calibrate_images``,
``fr calibrate`` and ``fr batch``) takes this path for an estimator on a CUDA device whose detector
detects whole batches (``detect_batch``, e.g. ``torch-lines``) when torchvision's ``decode_jpeg``
loads (:func:`device_path_gap`); ``DevicePolicy.decode = "host"`` (``--decode host``) keeps the
host pipeline of decoding + detection worker processes.  Per batch of images:

1. **Decode** (:func:`decode_batch`), in a reader thread one batch ahead of the search: a JPEG
   file that needs no EXIF rotation and whose long side is at most
   :data:`DEVICE_DECODE_MAX_LONG_SIDE` pixels is decoded to grey on the device by torchvision
   (``decode_jpeg`` with a CUDA device, all such files of the batch in one call); any other input
   (PNG, a large photo that the host decodes at a native 1/2-1/8 reduction, a rotated photo, an
   array) is read on the host by the bounded decoder (:func:`fr_torch.images.io.read_working`),
   several at once in threads, and uploaded.  A batch the device decoder refuses is decoded file by file, and a file it refuses
   alone is read on the host, whose one-line reason a corrupt file then gets.  Images larger than
   the working resolution are reduced on the device by area averaging (as ``cv2.INTER_AREA``).
2. **Detect** (:func:`detect_decoded`): images of one size are detected together by the detector's
   ``detect_batch`` on the device (in chunks of at most :data:`DETECT_PIXELS` pixels), the
   estimator's segment filter is applied, and the segments cross to the host once per chunk
   (B x N x 4 float32, a few KB per image) for the per-image checks.
3. **Search**: :meth:`fr_torch.runtime.estimator.FREstimator.calibrate_detections` on the device,
   results in the input image's pixels.

:func:`calibrate_decoded` is the same detection + search for a batch that is already on the device.
"""
from __future__ import annotations

import contextlib
import os
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from functools import lru_cache
from typing import Iterator, Sequence

import numpy as np
import torch
import torch.nn.functional as F

from fr_torch.errors import FRInputError
from fr_torch.images.io import (
    MAX_IMAGE_PIXELS,
    WORKING_LONG_SIDE,
    check_regular_file,
    jpeg_header,
    read_working,
    working_size,
)
from fr_torch.runtime.detection import Detection, failure_reason
from fr_torch.runtime.workers import usable_cores

#: Largest long side (pixels) of a JPEG decoded on the device; larger photos are decoded on the
#: host at a native DCT reduction (1/2 to 1/8), which costs less than a full-size device decode.
DEVICE_DECODE_MAX_LONG_SIDE = 2 * WORKING_LONG_SIDE
#: Threads that detect and search batches at once on a GPU (each on its own CUDA stream): while one
#: does its host work (Python, launches, per-image checks) the device runs another's kernels.
SEARCH_THREADS = 2
#: Pixels detected in one ``detect_batch`` call (512 images of 640 x 480, ~6 GB of device memory
#: for torch-lines' intermediate maps).
DETECT_PIXELS = 512 * 640 * 480


@dataclass
class DecodedImage:
    """One image on the device at the working resolution, or its failure.

    ``pixels``: (H, W) uint8 grey levels on the device (None on error); ``scale``: input pixels per
    working pixel (>= 1); ``input_size``: the input's (width, height), pixels; ``error``: the
    one-line reason or None; ``seconds``: this image's share of the batch's decoding time.
    """

    pixels: torch.Tensor | None
    scale: float
    input_size: tuple[int, int]
    error: str | None = None
    seconds: float = 0.0


@lru_cache(maxsize=1)
def _decoder_gap() -> str | None:
    try:
        from torchvision.io import decode_jpeg  # noqa: F401
    except Exception as exc:  # noqa: BLE001 - missing, or built for another torch (RuntimeError)
        return f"torchvision's decode_jpeg does not load ({type(exc).__name__}: {str(exc).splitlines()[0][:120]})"
    return None


def device_path_gap(estimator) -> str | None:
    """Why ``estimator`` does not take the device path for image files, or None when it does: it
    runs on the CPU, its policy says ``decode="host"``, its detector has no ``detect_batch``, or
    torchvision's ``decode_jpeg`` does not load.  With ``decode="device"`` a gap is an
    :class:`~fr_torch.errors.FRInputError` (the user asked for it)."""
    policy = estimator.policy
    if policy.on_cpu or policy.decode == "host":
        gap = "the estimator runs on the CPU" if policy.on_cpu else "decode='host'"
    elif not callable(getattr(estimator.detector, "detect_batch", None)):
        gap = f"detector {getattr(estimator.detector, 'name', type(estimator.detector).__name__)!r} detects one " \
              "image at a time (use torch-lines)"
    else:
        gap = _decoder_gap()
    if gap is not None and policy.decode == "device":
        raise FRInputError(f"--decode device: {gap}")
    return gap


def _host_decode(image, name: str, working_long_side: int | None):
    """``image`` (path or array) read by the bounded host decoder at the working resolution:
    (grey (H, W) uint8, scale, input size) as :func:`fr_torch.images.io.read_working` gives them,
    or the one-line reason it failed."""
    try:
        return read_working(image, name, working_long_side)
    except FRInputError as exc:
        return str(exc)
    except Exception as exc:  # noqa: BLE001 - one image's failure, never the batch's
        return failure_reason(name, exc)


def _upload(decoded, device: torch.device) -> DecodedImage:
    """A :func:`_host_decode` result on ``device``."""
    if isinstance(decoded, str):
        return DecodedImage(None, 1.0, (0, 0), decoded)
    gray, scale, input_size = decoded
    return DecodedImage(torch.from_numpy(np.ascontiguousarray(gray)).to(device), scale, input_size)


def _device_jpeg(image, name: str) -> bytes | None:
    """The file's bytes when the device may decode it (an upright JPEG within the size limits),
    else None (the host reads it, and reports it when it is bad).  Only the header is read to
    decide.  A photo with an EXIF rotation goes to the host, which applies it
    (:func:`fr_torch.images.io.read_image`), so that every path sees the same upright picture."""
    if not isinstance(image, (str, os.PathLike)):
        return None
    try:
        check_regular_file(image)
        with open(image, "rb") as handle:
            head = handle.read(2)
            if head != b"\xff\xd8":
                return None
            size, rotated = jpeg_header(head, handle.read)  # the header only: most files the host takes are big
            if rotated or size is None or min(size) <= 0 or max(size) > DEVICE_DECODE_MAX_LONG_SIDE \
                    or size[0] * size[1] > MAX_IMAGE_PIXELS:
                return None
            handle.seek(0)
            return handle.read()
    except (FRInputError, OSError):
        return None


def _decode_jpegs(data: list[bytes], device: torch.device) -> list[torch.Tensor | None]:
    """Grey (H, W) uint8 device tensors of JPEG bytes; None for a file the device decoder refuses."""
    from fr_torch.detectors.tensor_lines import decode_jpeg_batch

    try:
        return [t[0] for t in decode_jpeg_batch(data, device)]
    except RuntimeError:  # one bad file fails the batched call: decode them one by one
        out: list[torch.Tensor | None] = []
        for one in data:
            try:
                out.append(decode_jpeg_batch([one], device)[0][0])
            except RuntimeError:
                out.append(None)
        return out


def to_working_resolution(pixels: torch.Tensor, working_long_side: int | None) -> tuple[torch.Tensor, float]:
    """``pixels`` (H, W) uint8 on any device brought to a long side of at most ``working_long_side``
    by area averaging (the target size of :func:`fr_torch.images.io.working_size`); returns
    (image, input pixels per working pixel)."""
    height, width = pixels.shape
    target_width, target_height = working_size((width, height), working_long_side)
    if (target_width, target_height) == (width, height):
        return pixels, 1.0
    reduced = F.interpolate(pixels[None, None].float(), size=(target_height, target_width), mode="area")[0, 0]
    return reduced.round_().clamp_(0, 255).to(torch.uint8), width / target_width


def decode_batch(images: Sequence, names: Sequence[str], device: torch.device,
                 working_long_side: int | None = WORKING_LONG_SIDE) -> list[DecodedImage]:
    """Decode a batch of images (paths or arrays) onto ``device`` at the working resolution (module
    docstring, step 1); one :class:`DecodedImage` per input, in order; never raises for one image."""
    start = time.perf_counter()
    out: list[DecodedImage | None] = [None] * len(images)
    on_device = [(i, data) for i, (image, name) in enumerate(zip(images, names))
                 if (data := _device_jpeg(image, name)) is not None]
    for i, pixels in zip([i for i, _ in on_device], _decode_jpegs([d for _, d in on_device], device)
                         if on_device else []):
        if pixels is not None:
            input_size = (int(pixels.shape[1]), int(pixels.shape[0]))
            pixels, scale = to_working_resolution(pixels, working_long_side)
            out[i] = DecodedImage(pixels, scale, input_size)
    host = [i for i in range(len(images)) if out[i] is None]
    # The host decoder (OpenCV, which releases the GIL) on every core: large photos take 50 ms each.
    with ThreadPoolExecutor(max(1, min(len(host), usable_cores())), thread_name_prefix="fr-host-decode") as pool:
        for i, decoded in zip(host, pool.map(lambda i: _host_decode(images[i], names[i], working_long_side), host)):
            out[i] = _upload(decoded, device)  # uploads from this thread, on its stream
    share = (time.perf_counter() - start) / max(1, len(images))
    for decoded in out:
        decoded.seconds = share
    return out


def as_numpy_lists(segments: torch.Tensor, mask: torch.Tensor) -> list[np.ndarray]:
    """The padded batch ``segments`` (B, N, 4) / ``mask`` (B, N) as one (N_b, 4) float64 array per image."""
    segments, mask = segments.double().cpu().numpy(), mask.cpu().numpy()
    return [segments[b][mask[b]] for b in range(segments.shape[0])]


def detect_decoded(detector, decoded: Sequence[DecodedImage], segment_filter=None) -> list[Detection]:
    """One :class:`~fr_torch.runtime.detection.Detection` per decoded image (module docstring, step
    2): same-size images detected together by ``detector.detect_batch``, ``segment_filter`` (a
    :class:`~fr_torch.core.likelihood.segments.SegmentFilter`, or None) applied to each image's segments."""
    detections: list[Detection | None] = [None] * len(decoded)
    by_size: dict[tuple[int, int], list[int]] = {}
    for i, d in enumerate(decoded):
        if d.error is not None or d.pixels is None:
            detections[i] = Detection.failed(d.error or "not decoded", d.seconds)
        else:
            by_size.setdefault(tuple(d.pixels.shape), []).append(i)
    for (height, width), members in by_size.items():
        chunk = max(1, DETECT_PIXELS // (height * width))
        for first in range(0, len(members), chunk):
            index = members[first:first + chunk]
            start = time.perf_counter()
            stacked = torch.stack([decoded[i].pixels for i in index])[:, None]
            lists = as_numpy_lists(*detector.detect_batch(stacked))
            if segment_filter is not None:
                lists = segment_filter.many(lists, [(width, height)] * len(index))
            share = (time.perf_counter() - start) / len(index)
            for i, segments in zip(index, lists):
                d = decoded[i]
                detections[i] = Detection(segments, (width, height), None, d.seconds + share, d.scale, d.input_size)
    return detections


def device_detector(estimator):
    """The estimator's batch detector on the estimator's device (``detector.to(device)`` when the
    detector has it, else the detector itself)."""
    move = getattr(estimator.detector, "to", None)
    return move(estimator.device) if callable(move) else estimator.detector


def calibrate_on_device(estimator, images: Sequence, names: Sequence[str], focal_list: Sequence,
                        pp_list: Sequence, batch_size: int, searchers: int | None = None) -> Iterator[tuple[list, list]]:
    """``(images, results)`` per batch of at most ``batch_size`` images, in input order (module
    docstring): a reader thread decodes the next batches while earlier ones are detected and
    searched by ``searchers`` threads (None = :data:`SEARCH_THREADS`),
    each on a CUDA stream of its own, so that one batch's host work overlaps another's device work
    (the first batch is searched alone).
    ``focal_list`` / ``pp_list``: one focal length / principal point (or None) per image, input pixels."""
    detector = device_detector(estimator)
    device = estimator.device
    working = estimator.working_long_side
    cuda = device.type == "cuda"
    if searchers is None:
        searchers = SEARCH_THREADS
    streams = [torch.cuda.Stream(device) for _ in range(searchers + 1)] if cuda else []

    def on(stream):  # work queued on ``stream`` (a CUDA device), or as it comes (any other)
        return torch.cuda.stream(stream) if stream is not None else contextlib.nullcontext()

    def read(start: int) -> list[DecodedImage]:
        stream = streams[0] if cuda else None
        with on(stream):
            decoded = decode_batch(images[start:start + batch_size], names[start:start + batch_size], device,
                                   working)
        if stream is not None:
            stream.synchronize()  # the reader waits; the searchers' streams never do
        return decoded

    def search(start: int, decoded: list[DecodedImage], stream) -> list:
        stop = start + batch_size
        with on(stream):
            for d in decoded if stream is not None else ():  # made on the reader's stream, used on this one
                if d.pixels is not None:
                    d.pixels.record_stream(stream)
            detections = detect_decoded(detector, decoded, estimator.segment_filter)
            results = estimator.calibrate_detections(detections, names[start:stop], focal_list[start:stop],
                                                     pp_list[start:stop])
        if stream is not None:
            stream.synchronize()
        return results

    starts = list(range(0, len(images), batch_size))
    count = len(starts)
    with ThreadPoolExecutor(1, thread_name_prefix="fr-decode") as reader, \
            ThreadPoolExecutor(searchers, thread_name_prefix="fr-search") as searching:
        reads, searches = {}, {}
        next_read = next_search = 0

        def read_up_to(last: int) -> None:  # decoding submitted for every batch up to ``last``
            nonlocal next_read
            while next_read <= min(last, count - 1):
                reads[next_read] = reader.submit(read, starts[next_read])
                next_read += 1

        for k, start in enumerate(starts):
            # `searchers` batches detected and searched at once, the next one decoding meanwhile; the
            # first batch alone, so that what CUDA libraries initialise on first use (torch's lazily
            # loaded linear algebra is not thread-safe then: pytorch/pytorch#90613) starts in one thread
            while next_search < min(k + (searchers if k else 1), count):
                read_up_to(next_search + 1)
                stream = streams[1 + next_search % searchers] if cuda else None
                searches[next_search] = searching.submit(search, starts[next_search],
                                                         reads.pop(next_search).result(), stream)
                next_search += 1
            read_up_to(next_search)
            yield images[start:start + batch_size], searches.pop(k).result()


def calibrate_decoded(estimator, detector, images: torch.Tensor, names=None, focal_px=None,
                      principal_point=None) -> list:
    """Results (one :class:`fr_torch.core.result.CalibrationResult` each) for ``images``
    (B, 1, H, W) or (B, H, W), grey levels 0..255 (uint8 or float), already on the device, at the
    resolution they are calibrated at.

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
