"""Parallel pipelines around the estimator: images calibrated in worker processes, decode +
detection ahead of a GPU search, and a batch of segment sets sharded over worker processes.

* :func:`calibrate_paths` calibrates images (paths or arrays) batch by batch, yielding
  ``(images, results)`` per batch in input order; ``fr calibrate --workers N`` uses it.  With
  ``workers > 0`` on a **CPU** estimator every worker process decodes, detects *and* searches its
  own chunks of images with one thread (images are independent, so throughput grows with the
  number of cores: intra-op threads of one process stop paying past a few cores, and OpenCV's LSD
  runs on one core).  On a **GPU** estimator the workers decode and detect while this process
  searches the previous batch on the device.
* :func:`calibrate_stream` does the same for a stream of frames of unknown length (``fr track``),
  reading it only as far as the work in flight.
* :func:`iter_detections` decodes and detects images in ``workers`` processes (0 = in this
  process), yielding one :class:`Detection` per image in input order.
* :func:`calibrate_segments_sharded` splits a large batch of segment sets into ``workers``
  contiguous shards, each calibrated by a single-threaded worker process (every image's result is
  its own, so the output equals the in-process call).  On a shared machine this scales where
  intra-op threads do not: an OpenMP parallel region waits for its slowest thread, and a thread
  that lost its core stalls every op.

Every pool keeps a bounded number of tasks in flight (memory does not grow with the folder) and
returns results in input order; a bad file is that file's failure (an ``FRInputError`` message,
or the exception's one line).  A worker that dies (a native crash in a decoder or detector) fails
only the image it was on: the chunk it lost is retried one image at a time, each alone in a fresh
pool, and only an image that kills its worker when alone fails (:func:`ordered_pool_map`).  Work
still in flight when the caller stops reading (CTRL-C, SIGTERM, an early ``close()``) is not
waited for: its workers are killed.  Workers end with this process however it ends, SIGKILL
included (:mod:`fr_torch.runtime.workers`).

Workers are forked from a fork server that has loaded the library (:mod:`fr_torch.runtime.workers`;
``spawn`` where there is no fork server); each runs with one torch thread and one OpenCV thread.
A pool pays for folders and large batches, not for a few images (:func:`fr_torch.runtime.workers.default_workers`).
"""
from __future__ import annotations

import copy
import functools
import itertools
import pickle
import time
from collections import deque
from concurrent.futures import ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from pathlib import Path
from typing import Iterable, Iterator, Sequence

import cv2
import numpy as np
import torch

from fr_torch.core.likelihood.segments import SegmentFilter
from fr_torch.core.result import CalibrationResult
from fr_torch.core.settings.checks import image_names, per_image, segment_sets
from fr_torch.core.settings.checks import image_sizes as checked_image_sizes
from fr_torch.detectors.registry import detect_segments, get_detector
from fr_torch.errors import FRInputError
from fr_torch.images.io import WORKING_LONG_SIDE, read_working
from fr_torch.runtime.detection import Detection, failure_reason
from fr_torch.runtime.device_pipeline import calibrate_on_device, device_path_gap
from fr_torch.runtime.workers import WorkerPool


def detect_image(image, name: str, detector, segment_filter: SegmentFilter,
                 working_long_side: int | None = WORKING_LONG_SIDE) -> Detection:
    """Decode (path, bounded) or normalise (array) one image, bring it to the working resolution
    (long side at most ``working_long_side`` pixels) and detect its segments there.

    An unreadable or invalid image is a :class:`Detection` with ``error`` set, never an exception.
    """
    start = time.perf_counter()
    try:
        gray, scale, input_size = read_working(image, name, working_long_side)
        segments = detect_segments(gray, detector, segment_filter)
        return Detection(segments, (gray.shape[1], gray.shape[0]), None, time.perf_counter() - start, scale,
                         input_size)
    except FRInputError as exc:
        error = str(exc)
    except Exception as exc:  # a decoder or detector failing on one image must not stop the others
        error = failure_reason(name, exc)
    return Detection.failed(error, time.perf_counter() - start)


# --------------------------------------------------------------------------- worker processes

_WORKER: dict = {}


def _init_worker(detector_spec, segment_filter, working_long_side=WORKING_LONG_SIDE) -> None:
    torch.set_num_threads(1)
    cv2.setNumThreads(1)
    _WORKER["detector"] = get_detector(detector_spec) if detector_spec is not None else None
    _WORKER["filter"] = segment_filter
    _WORKER["working_long_side"] = working_long_side


def _detect_task(image, name):
    return detect_image(image, name, _WORKER["detector"], _WORKER["filter"], _WORKER["working_long_side"])


def _portable_detector(detector):
    """The detector itself when it pickles, else its registered name (workers rebuild it)."""
    try:
        pickle.dumps(detector)
        return detector
    except Exception:
        name = getattr(detector, "name", None)
        try:  # checked here: a worker that cannot build it would fail every image
            if isinstance(name, str) and type(get_detector(name)) is type(detector):
                return name
        except FRInputError:
            pass
        raise FRInputError(f"detector {name or type(detector).__name__!r} cannot be sent to worker processes "
                           "(it does not pickle and its name is not a registered detector or module:attribute); "
                           "use workers=0") from None


#: Pools in a row that may die before finishing a task (crashing images) before we give up (workers
#: that cannot start would otherwise fail every image, one fresh pool each).
MAX_BROKEN_POOLS = 5


def ordered_pool_map(function, items: Iterable, chunk_size: int, workers: int, initializer, initargs,
                     on_crash, queue_size: int | None = None) -> Iterator:
    """Yield ``function(chunk)``'s results item by item, in input order, computing chunks of at
    most ``chunk_size`` consecutive ``items`` in ``workers`` processes (``initializer(*initargs)``
    runs once in each).  ``function`` returns one result per item of its chunk.  ``items`` may be
    any iterable (a video's frames): it is read only as chunks are submitted.

    At most ``queue_size`` chunks (default 2 per worker) are in flight.  When a worker dies, every
    task in flight is lost; the one being waited for may be innocent (a neighbour's crash), so its
    items are retried one at a time *alone* in a fresh pool, the other lost chunks as they were.
    Only an item whose worker dies while it is the only task in flight gives ``on_crash(item)``.
    """
    queue_size = queue_size or 2 * workers
    source = iter(items)
    todo: deque = deque()  # (chunk, alone) to submit before reading more items; "alone" = nothing else in flight
    pending: deque = deque()
    broken_in_a_row = 0  # pools that died before finishing any task (workers that cannot start)

    def next_todo() -> bool:
        if not todo:
            chunk = list(itertools.islice(source, chunk_size))
            if chunk:
                todo.append((chunk, False))
        return bool(todo)

    def start_pool():
        return WorkerPool(workers, initializer, initargs)

    def restart(pool):
        nonlocal broken_in_a_row
        broken_in_a_row += 1
        if broken_in_a_row > MAX_BROKEN_POOLS:
            raise RuntimeError(f"worker processes died {broken_in_a_row} times in a row without "
                               "finishing a task; run in-process (workers=0) to see why")
        _shutdown(pool, kill=True)
        return start_pool()

    pool = start_pool()
    try:
        while next_todo() or pending:
            broken = False
            while len(pending) < queue_size and next_todo() and not (pending and (todo[0][1] or pending[-1][1])):
                chunk, alone = todo[0]
                try:
                    future = pool.submit(function, chunk)
                except (BrokenProcessPool, OSError):  # a worker died since the last result: blamed below
                    # (OSError: submit was starting a worker while the pool broke, and the pool had already
                    # closed the queue that worker would read; CPython < 3.14.  No process was started.)
                    broken = True
                    break
                todo.popleft()
                pending.append((chunk, alone, future))
            if not pending:  # broken with nothing in flight to blame (e.g. a worker killed from outside)
                pool = restart(pool)
                continue
            chunk, alone, future = pending.popleft()
            try:
                results = future.result()
            except BrokenProcessPool:
                if alone and len(chunk) == 1:
                    yield on_crash(chunk[0])  # it died with nothing else running: this item did it
                    retry = []
                else:
                    retry = [([item], True) for item in chunk]
                todo.extendleft(reversed(retry + [(c, a) for c, a, _ in pending]))
                pending.clear()
                pool = restart(pool)
                continue
            if not broken:
                broken_in_a_row = 0
            yield from results
    finally:  # work still in flight is never read (CTRL-C, SIGTERM, a caller that stopped early): kill it
        _shutdown(pool, kill=bool(pending) or bool(getattr(pool, "_broken", False)))


def _shutdown(pool: ProcessPoolExecutor, kill: bool) -> None:
    """Stop ``pool`` without waiting for its queued work.  With ``kill`` (a broken pool, or tasks
    still running whose results nobody will read) its workers are killed (:func:`_kill_workers`)
    and the pool is joined: a broken pool's manager thread can otherwise hang the interpreter's exit
    on Python < 3.14 (CPython gh-132969), and a running task would delay it by its whole length.
    Without, idle workers exit on their own as the pool tells them to."""
    if kill:
        _kill_workers(pool)
    pool.shutdown(wait=kill, cancel_futures=True)


def _kill_workers(pool: ProcessPoolExecutor) -> None:
    """Kill every worker process of ``pool`` (broken, or running work nobody will read).

    The pool's manager thread terminates the workers of a broken pool itself, but on Python < 3.14
    a worker that ``submit`` was still starting at that moment escapes: it is neither terminated
    nor sent a stop sentinel, waits for work forever, and joining the pool then hangs (seen once in
    CI, in ``test_worker_crash_fails_only_its_image``; CPython gh-152978 closes this gap in 3.14).
    Only this (the submitting) thread starts workers, so by the time it shuts the pool down every
    worker is in ``pool._processes`` (a private attribute; if it is gone, nothing is killed)."""
    processes = getattr(pool, "_processes", None) or {}
    for process in list(processes.values()):
        try:
            process.kill()
        except (OSError, ValueError):  # already reaped / closed
            pass


def _detect_chunk(chunk):
    return [_detect_task(image, name) for image, name in chunk]


def crash_reason(name: str) -> str:
    """The failure reason of an image whose worker process died on it (every kind of worker)."""
    return f"{name}: a worker process crashed on this image"


def _detection_crash(item) -> Detection:
    return Detection.failed(crash_reason(item[1]))


def iter_detections(images: Sequence, names: Sequence[str], detector, segment_filter: SegmentFilter | None = None,
                    workers: int = 0, queue_size: int | None = None,
                    working_long_side: int | None = WORKING_LONG_SIDE) -> Iterator[Detection]:
    """Yield a :class:`Detection` per image of ``images``, in input order (see module docstring).

    ``workers`` processes (0 = this process) decode and detect, at most ``queue_size`` images
    (default 4 per worker) in flight.
    """
    yield from _detections_of_pairs(zip(images, names), detector, segment_filter, workers, queue_size,
                                    working_long_side)


def _detections_of_pairs(pairs: Iterable, detector, segment_filter: SegmentFilter | None, workers: int,
                         queue_size: int | None, working_long_side: int | None) -> Iterator[Detection]:
    """:func:`iter_detections` of an iterable of ``(image, name)`` pairs, read only as far as the
    work in flight (a video's frames)."""
    segment_filter = segment_filter or SegmentFilter()
    if workers <= 0:
        for image, name in pairs:
            yield detect_image(image, name, detector, segment_filter, working_long_side)
        return
    yield from ordered_pool_map(_detect_chunk, pairs, 1, workers, _init_worker,
                                (_portable_detector(detector), segment_filter, working_long_side),
                                _detection_crash, queue_size or 4 * workers)


def _init_calibrate_worker(estimator) -> None:
    _init_worker(None, None)
    if isinstance(estimator.detector, str):  # sent by name: rebuilt here (see _portable_detector)
        estimator.detector = get_detector(estimator.detector)
    _WORKER["estimator"] = estimator


def _calibrate_chunk(chunk):
    """Decode, detect and search a chunk of (image, name, focal_px, principal_point) in a worker."""
    estimator = _WORKER["estimator"]
    detections = [detect_image(image, name, estimator.detector, estimator.segment_filter,
                               estimator.working_long_side) for image, name, _, _ in chunk]
    return estimator.calibrate_detections(detections, [c[1] for c in chunk], [c[2] for c in chunk],
                                          [c[3] for c in chunk])


def _calibration_crash(item):
    return CalibrationResult(image=item[1], width=0, height=0, ok=False, reason=crash_reason(item[1]))


def _calibrate_in_workers(estimator, items: Iterable, chunk_size: int, workers: int,
                          queue_size: int | None = None) -> Iterator:
    """Results of (image, name, focal_px, principal_point) ``items``, in order, each chunk decoded,
    detected and searched by one of ``workers`` single-threaded processes (a copy of ``estimator``),
    at most ``queue_size`` chunks in flight (default :func:`ordered_pool_map`'s)."""
    return ordered_pool_map(_calibrate_chunk, items, chunk_size, workers, _init_calibrate_worker,
                            (_portable_estimator(estimator),), _calibration_crash, queue_size)


def _portable_estimator(estimator):
    """A copy of ``estimator`` that pickles (its detector by name where needed), or FRInputError --
    checked here, not when a pool starts its workers (a traceback deep in multiprocessing)."""
    portable = copy.copy(estimator)
    portable.detector = _portable_detector(estimator.detector)
    try:
        pickle.dumps(portable)
    except Exception as exc:
        raise FRInputError(f"this estimator cannot be sent to worker processes ({type(exc).__name__}: {exc}); "
                           "use workers=0") from None
    return portable


def in_shards(pool, workers: int, function, items: Sequence) -> list:
    """``function(shard)`` of ``items`` cut into at most ``workers`` contiguous, non-empty shards of
    near-equal size, each submitted to ``pool``; the shards' results (one list per shard, one
    result per item) joined in input order.  A worker's death raises as ``Future.result`` does."""
    bounds = np.linspace(0, len(items), min(workers, len(items)) + 1).round().astype(int)
    futures = [pool.submit(function, items[a:b]) for a, b in zip(bounds[:-1], bounds[1:]) if b > a]
    return [result for future in futures for result in future.result()]


class CalibrationPool:
    """Whole images (arrays or paths) decoded, detected and searched by ``workers`` single-threaded
    processes that each hold a copy of ``estimator``, kept from one call to the next (the turns of a
    fleet, :mod:`fr_torch.video.fleet`).  :meth:`calibrate_images` splits its images into one
    contiguous chunk per worker and returns the results in input order, as the estimator's own
    ``calibrate_images`` would.  A worker that dies fails only the image it was on: the call is
    redone with crash isolation (:func:`ordered_pool_map`) and the pool restarted.  A stop or an
    error while waiting kills the workers; :meth:`close` ends them.
    """

    def __init__(self, estimator, workers: int):
        self.workers = max(1, int(workers))
        self.mode = estimator.mode
        self._portable = _portable_estimator(estimator)
        self._pool: WorkerPool | None = None

    def calibrate_images(self, images: Sequence, names: Sequence[str], focal_px=None) -> list:
        """Results of ``images`` (``names`` one each; ``focal_px``: None, one value or one per image)."""
        focal_list = per_image(focal_px, len(images), "focal_px")
        items = [(image, name, focal, None) for image, name, focal in zip(images, names, focal_list)]
        if self._pool is None:
            self._pool = WorkerPool(self.workers, _init_calibrate_worker, (self._portable,))
        try:
            return in_shards(self._pool, self.workers, _calibrate_chunk, items)
        except (BrokenProcessPool, OSError):
            self.close()  # one image killed its worker: find it, each image alone
            return list(ordered_pool_map(_calibrate_chunk, items, 1, self.workers, _init_calibrate_worker,
                                         (self._portable,), _calibration_crash))
        except BaseException:
            self.close()
            raise

    def close(self) -> None:
        if self._pool is not None:
            _shutdown(self._pool, kill=True)
            self._pool = None


def _ahead_of_search(workers: int, batch_size: int) -> int:
    """Images in flight in detection workers that feed a search in this process: up to two batches,
    so that the workers detect the whole next batch while this one is searched (a queue shorter
    than a batch would stall them halfway through every search), and at least 4 per worker."""
    return max(4 * workers, 2 * batch_size)


def calibrate_stream(estimator, frames: Iterable, batch_size: int = 8, workers: int = 0,
                     whole_frames: bool | None = None, in_flight: int | None = None) -> Iterator:
    """Calibrate a stream of ``(image, name)`` pairs (a video's frames: arrays or paths), yielding one
    :class:`~fr_torch.core.result.CalibrationResult` per frame, in order, without reading the stream
    ahead by more than what is in flight (one batch in-process).  ``workers > 0`` with
    ``whole_frames`` (the default for a CPU estimator): two chunks of ``batch_size`` frames per
    worker, each calibrated whole in a worker process, as :func:`calibrate_paths` does.  Without
    (always for a GPU estimator): the workers decode and detect up to two batches of frames ahead
    while this process searches on the device, or, for a detector of batches on a GPU, this process
    decodes and detects each batch on the device (:mod:`fr_torch.runtime.device_pipeline`).
    ``in_flight``: with workers, at most this many chunks (whole frames) or frames (detection)
    read ahead of the results instead of those defaults; ``workers`` with ``batch_size=1`` keeps
    every worker busy with one frame and none waiting (a live source in real time).
    """
    if workers > 0 and estimator.policy.whole_image_workers and whole_frames is not False:
        yield from _calibrate_in_workers(estimator, ((image, name, None, None) for image, name in frames),
                                         batch_size, workers, in_flight)
        return
    if workers > 0 and device_path_gap(estimator) is not None:
        names: deque = deque()  # the names of the frames read so far and not yet searched, in order

        def named():
            for image, name in frames:
                names.append(name)
                yield image, name

        detections = _detections_of_pairs(named(), estimator.detector, estimator.segment_filter, workers,
                                          in_flight or _ahead_of_search(workers, batch_size),
                                          estimator.working_long_side)
        try:
            while batch := list(itertools.islice(detections, batch_size)):
                yield from estimator.calibrate_detections(batch, [names.popleft() for _ in batch])
        finally:
            detections.close()
        return
    source = iter(frames)
    while batch := list(itertools.islice(source, batch_size)):
        yield from estimator.calibrate_images([image for image, _ in batch], names=[name for _, name in batch])


def calibrate_paths(estimator, images: Sequence, batch_size: int = 16, workers: int = 0, focal_px=None,
                    principal_point=None, names: Sequence[str] | None = None,
                    whole_images: bool | None = None) -> Iterator[tuple[list, list]]:
    """Calibrate images (paths or arrays) batch by batch; yields ``(images, results)`` per batch of
    at most ``batch_size`` images, in input order.

    Same results as ``estimator.calibrate_images`` on each batch (to the batched == one-by-one
    tolerances).  ``workers > 0`` with ``whole_images`` (the default for a CPU estimator): chunks
    of at most ``batch_size`` images are calibrated in that many single-threaded processes (a copy
    of the estimator in each).  Without (always for a GPU estimator): this process searches while
    the workers decode and detect the next images, up to two batches ahead (module docstring);
    on a GPU whose detector detects batches, this process decodes and detects on the device too
    (:mod:`fr_torch.runtime.device_pipeline`; ``workers`` is then unused).
    ``focal_px`` / ``principal_point``: as for ``calibrate_images`` (one value or one per image).
    """
    images = list(images)
    names = image_names(names, len(images), [str(im) if isinstance(im, (str, Path)) else f"image{i}"
                                             for i, im in enumerate(images)])
    focal_list = per_image(focal_px, len(images), "focal_px")
    pp_list = per_image(principal_point, len(images), "principal_point", width=2)
    if device_path_gap(estimator) is None:  # decode, detect and search on the GPU
        yield from calibrate_on_device(estimator, images, names, focal_list, pp_list, batch_size)
        return
    if workers > 0 and estimator.policy.whole_image_workers and whole_images is not False:
        # Chunks small enough that every worker gets several (the last ones finish together).
        chunk_size = max(1, min(batch_size, -(-len(images) // (4 * workers))))
        results = _calibrate_in_workers(estimator, zip(images, names, focal_list, pp_list), chunk_size, workers)
        try:
            for start in range(0, len(images), batch_size):
                chunk = images[start:start + batch_size]
                yield chunk, [next(results) for _ in chunk]
        finally:  # a caller that stops early shuts the pool down now, not at garbage collection
            results.close()
        return
    detections = iter_detections(images, names, estimator.detector, estimator.segment_filter, workers,
                                 queue_size=_ahead_of_search(workers, batch_size),
                                 working_long_side=estimator.working_long_side)
    try:
        for start in range(0, len(images), batch_size):
            stop = start + batch_size
            chunk = images[start:stop]
            batch = [next(detections) for _ in chunk]
            yield chunk, estimator.calibrate_detections(batch, names[start:stop], focal_list[start:stop],
                                                        pp_list[start:stop])
    finally:
        detections.close()


# --------------------------------------------------------------------------- sharded search

def _calibrate_segment_items(estimator, chunk) -> list:
    """``estimator.calibrate_segments`` of a chunk of (segments, name, size, focal_px,
    principal_point, apply_filter) items (one ``apply_filter`` for the whole call)."""
    return estimator.calibrate_segments([c[0] for c in chunk], [c[2] for c in chunk], names=[c[1] for c in chunk],
                                        focal_px=[c[3] for c in chunk], principal_point=[c[4] for c in chunk],
                                        apply_filter=chunk[0][5])


def _shard_task(estimator, chunk):
    """A shard in a caller's pool (its workers have no estimator of their own)."""

    torch.set_num_threads(1)
    return _calibrate_segment_items(estimator, chunk)


def _segments_chunk(chunk):
    """A chunk in a worker of :func:`ordered_pool_map` (estimator from :func:`_init_calibrate_worker`)."""
    return _calibrate_segment_items(_WORKER["estimator"], chunk)


def calibrate_segments_sharded(estimator, segments: Sequence, image_sizes: Sequence, workers: int,
                               names: Sequence[str] | None = None, focal_px=None, principal_point=None,
                               apply_filter: bool = True, pool: ProcessPoolExecutor | None = None) -> list:
    """:meth:`FREstimator.calibrate_segments` over ``workers`` single-threaded processes.

    The batch is cut into ``workers`` contiguous shards; results come back in input order and
    equal the in-process call's.  ``focal_px`` / ``principal_point``: None, one value for all,
    or one per image (sliced with the shards).  Pass a long-lived ``pool`` (a
    ``ProcessPoolExecutor``, e.g. from :func:`worker_pool`) to avoid the start-up per call.
    A worker that dies (out of memory, a native crash) fails only the image it was on, as in
    :func:`ordered_pool_map`: without a ``pool`` the shards run through it; a given ``pool`` that
    breaks is left to the caller and the batch is redone through it.
    """
    segments = segment_sets(segments)
    count = len(segments)
    if workers <= 1 or count < 2 or not estimator.policy.whole_image_workers:
        return estimator.calibrate_segments(segments, image_sizes, names=names, focal_px=focal_px,
                                            principal_point=principal_point, apply_filter=apply_filter)
    image_sizes = checked_image_sizes(image_sizes, count)  # the form; each size is checked in its worker
    names = image_names(names, count, [f"image{i}" for i in range(count)])
    focal_list = per_image(focal_px, count, "focal_px")
    pp_list = per_image(principal_point, count, "principal_point", width=2)
    portable = copy.copy(estimator)
    portable.detector = None  # detectors need not pickle; the search does not use them
    items = [(segments[i], names[i], tuple(image_sizes[i]), focal_list[i], pp_list[i], apply_filter)
             for i in range(count)]
    if pool is not None:
        try:
            return in_shards(pool, workers, functools.partial(_shard_task, portable), items)
        except (BrokenProcessPool, OSError):
            pass  # the caller's pool died under some image: redo the batch with crash isolation
    return list(ordered_pool_map(_segments_chunk, items, -(-count // workers), workers, _init_calibrate_worker,
                                 (portable,), _calibration_crash))


def worker_pool(workers: int) -> WorkerPool:
    """A process pool of ``workers`` single-threaded workers (:class:`~fr_torch.runtime.workers.WorkerPool`)."""
    return WorkerPool(workers, _init_worker, (None, None))
