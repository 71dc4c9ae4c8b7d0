"""Parallel pipelines around the estimator: decode + detection in worker processes, overlapping
the search in the main process, and a batch of segment sets sharded over worker processes.

* :func:`iter_detections` decodes and detects images in ``workers`` processes (0 = in this
  process).  At most ``queue_size`` images are in flight (a bounded queue: memory does not grow
  with the folder), results come back **in input order**, and a bad file is that file's failure
  (an ``FRInputError`` message, or the exception's one line; a crashed worker fails only the
  image it was on, and the pool is restarted for the rest).
* :func:`calibrate_paths` feeds those detections to :meth:`FREstimator.calibrate_detections` in batches of
  ``batch_size``: while the main process searches batch k, the workers decode and detect the next
  images.  It yields ``(paths, results)`` per batch; ``fr calibrate --workers N`` uses it.
* :func:`calibrate_segments_sharded` splits a large batch of segment sets into ``workers``
  contiguous shards, each calibrated by a single-threaded worker process (every image's result is
  its own, so the output equals the in-process call).  On a shared machine this scales where
  intra-op threads do not: an OpenMP parallel region waits for its slowest thread, and a thread
  that lost its core stalls every op.

Workers are started with ``forkserver`` where available (else ``spawn``), so no OpenMP state or
lock of the parent is inherited; each worker runs with one torch thread and one OpenCV thread.
Starting a pool costs about a second (importing torch once in the fork server), so it pays for
folders and large batches, not for one image.
"""
from __future__ import annotations

import copy
import multiprocessing
import os
import pickle
import time
from collections import deque
from concurrent.futures import ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from pathlib import Path
from typing import Iterator, NamedTuple, Sequence

import numpy as np

from . import image_io, validate
from .segments import FRInputError, SegmentFilter, detect_segments, get_detector


def default_workers() -> int:
    """A sensible default for ``--workers``: min(4, cores - 1), 0 (in-process) on 1-2 cores."""
    cores = os.cpu_count() or 1
    return 0 if cores <= 2 else min(4, cores - 1)


class Detection(NamedTuple):
    """One image decoded and detected at the working resolution (see :func:`detect_image`).

    ``segments``: (N, 4) in working pixels (empty on error); ``size``: working (width, height),
    (0, 0) on error; ``error``: the image's failure message or None; ``seconds``: decode + detect
    time; ``scale``: input pixels per working pixel (>= 1); ``input_size``: the input's (width, height).
    """

    segments: np.ndarray
    size: tuple[int, int]
    error: str | None
    seconds: float
    scale: float = 1.0
    input_size: tuple[int, int] = (0, 0)


def detect_image(image, name: str, detector, segment_filter: SegmentFilter,
                 working_long_side: int | None = image_io.WORKING_LONG_SIDE) -> Detection:
    """Decode (path, bounded) or normalise (array) one image, bring it to the working resolution
    (long side at most ``working_long_side`` pixels) and detect its segments there.

    An unreadable or invalid image is a :class:`Detection` with ``error`` set, never an exception.
    """
    start = time.perf_counter()
    try:
        gray, input_size = image_io.read_any(image, name, working_long_side)
        gray, scale = image_io.working_image(gray, input_size, working_long_side)
        segments = detect_segments(gray, detector, segment_filter)
        return Detection(segments, (gray.shape[1], gray.shape[0]), None, time.perf_counter() - start, scale,
                         tuple(input_size))
    except FRInputError as exc:
        error = str(exc)
    except Exception as exc:  # a decoder or detector failing on one image must not stop the others
        error = f"{name}: {type(exc).__name__}: {exc}".splitlines()[0]
    return Detection(np.zeros((0, 4)), (0, 0), error, time.perf_counter() - start)


# --------------------------------------------------------------------------- worker processes

_WORKER: dict = {}


def _init_worker(detector_spec, segment_filter, working_long_side=image_io.WORKING_LONG_SIDE) -> None:
    import cv2
    import torch

    torch.set_num_threads(1)
    cv2.setNumThreads(1)
    _WORKER["detector"] = get_detector(detector_spec) if detector_spec is not None else None
    _WORKER["filter"] = segment_filter
    _WORKER["working_long_side"] = working_long_side


def _detect_task(image, name):
    return detect_image(image, name, _WORKER["detector"], _WORKER["filter"], _WORKER["working_long_side"])


def _context():
    methods = multiprocessing.get_all_start_methods()
    return multiprocessing.get_context("forkserver" if "forkserver" in methods else "spawn")


def _portable_detector(detector):
    """The detector itself when it pickles, else its registered name (workers rebuild it)."""
    try:
        pickle.dumps(detector)
        return detector
    except Exception:
        name = getattr(detector, "name", None)
        if not isinstance(name, str):
            raise FRInputError("this detector cannot be sent to worker processes; use workers=0") from None
        return name


def iter_detections(images: Sequence, names: Sequence[str], detector, segment_filter: SegmentFilter | None = None,
                    workers: int = 0, queue_size: int | None = None,
                    working_long_side: int | None = image_io.WORKING_LONG_SIDE) -> Iterator[Detection]:
    """Yield a :class:`Detection` per image of ``images``, in input order (see module docstring)."""
    segment_filter = segment_filter or SegmentFilter()
    if workers <= 0:
        for image, name in zip(images, names):
            yield detect_image(image, name, detector, segment_filter, working_long_side)
        return
    spec = _portable_detector(detector)
    queue_size = queue_size or 4 * workers
    todo = deque(enumerate(zip(images, names)))
    pending: deque = deque()

    def start_pool():
        return ProcessPoolExecutor(workers, mp_context=_context(), initializer=_init_worker,
                                   initargs=(spec, segment_filter, working_long_side))

    pool = start_pool()
    try:
        while todo or pending:
            while todo and len(pending) < queue_size:
                index, (image, name) = todo.popleft()
                pending.append((index, image, name, pool.submit(_detect_task, image, name)))
            index, image, name, future = pending.popleft()
            try:
                yield future.result()
            except BrokenProcessPool:
                # The worker died on this image (or a neighbour): fail this one, retry the rest.
                yield Detection(np.zeros((0, 4)), (0, 0), f"{name}: the detector crashed on this image", 0.0)
                todo.extendleft(reversed([(i, (im, n)) for i, im, n, _ in pending]))
                pending.clear()
                pool.shutdown(wait=False, cancel_futures=True)
                pool = start_pool()
    finally:
        pool.shutdown(wait=False, cancel_futures=True)


def calibrate_paths(estimator, images: Sequence, batch_size: int = 16, workers: int = 0, focal_px=None,
                    principal_point=None, names: Sequence[str] | None = None) -> Iterator[tuple[list, list]]:
    """Calibrate images (paths or arrays) batch by batch; yields ``(images, results)`` per batch.

    Same results, in the same order, as ``estimator.calibrate_images`` on each batch; with
    ``workers > 0`` decoding and detection run in worker processes ahead of the search.
    ``focal_px`` / ``principal_point``: as for ``calibrate_images`` (one value or one per image).
    """
    images = list(images)
    names = list(names) if names is not None else [str(im) if isinstance(im, (str, Path)) else f"image{i}"
                                                   for i, im in enumerate(images)]
    focal_list = validate.per_image(focal_px, len(images), "focal_px")
    pp_list = validate.per_image(principal_point, len(images), "principal_point", width=2)
    detections = iter_detections(images, names, estimator.detector, estimator.segment_filter, workers,
                                 working_long_side=estimator.working_long_side)
    for start in range(0, len(images), batch_size):
        stop = start + batch_size
        chunk = images[start:stop]
        batch = [next(detections) for _ in chunk]
        yield chunk, estimator.calibrate_detections(batch, names[start:stop], focal_list[start:stop],
                                                    pp_list[start:stop])


# --------------------------------------------------------------------------- sharded search

def _shard_task(estimator, segments, sizes, names, focal_px, principal_point, apply_filter):
    import torch

    torch.set_num_threads(1)
    return estimator.calibrate_segments(segments, sizes, names=names, focal_px=focal_px,
                                        principal_point=principal_point, apply_filter=apply_filter)


def calibrate_segments_sharded(estimator, segments: Sequence, image_sizes: Sequence, workers: int,
                               names: Sequence[str] | None = None, focal_px=None, principal_point=None,
                               apply_filter: bool = True, pool: ProcessPoolExecutor | None = None) -> list:
    """:meth:`FREstimator.calibrate_segments` over ``workers`` single-threaded processes.

    The batch is cut into ``workers`` contiguous shards; results come back in input order and
    equal the in-process call's.  ``focal_px`` / ``principal_point``: None, one value for all,
    or one per image (sliced with the shards).  Pass a long-lived ``pool`` (a
    ``ProcessPoolExecutor``, e.g. from :func:`worker_pool`) to avoid the start-up per call.
    """
    count = len(segments)
    if workers <= 1 or count < 2 or estimator.device.type != "cpu":
        return estimator.calibrate_segments(segments, image_sizes, names=names, focal_px=focal_px,
                                            principal_point=principal_point, apply_filter=apply_filter)
    names = list(names) if names is not None else [f"image{i}" for i in range(count)]
    focal_list = validate.per_image(focal_px, count, "focal_px")
    pp_list = validate.per_image(principal_point, count, "principal_point", width=2)
    bounds = np.linspace(0, count, min(workers, count) + 1).round().astype(int)
    own_pool = pool is None
    pool = pool or worker_pool(workers)
    portable = copy.copy(estimator)
    portable.detector = None  # detectors need not pickle; the search does not use them
    try:
        futures = [pool.submit(_shard_task, portable, list(segments[a:b]), list(image_sizes[a:b]), names[a:b],
                               focal_list[a:b], pp_list[a:b], apply_filter)
                   for a, b in zip(bounds[:-1], bounds[1:]) if b > a]
        return [result for future in futures for result in future.result()]
    finally:
        if own_pool:
            pool.shutdown()


def worker_pool(workers: int) -> ProcessPoolExecutor:
    """A process pool of ``workers`` single-threaded workers (forkserver / spawn)."""
    return ProcessPoolExecutor(workers, mp_context=_context(), initializer=_init_worker, initargs=(None, None))
