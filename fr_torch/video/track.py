"""Online recalibration from a stream of frames: what ``fr track SOURCE`` runs (:func:`track`).

Python use, frame by frame, from wherever the frames come (a camera SDK's callback, a ROS topic,
a queue)::

    from fr_torch import FREstimator
    from fr_torch.video.fusion import OnlineCalibrator

    est = FREstimator(mode="fast")              # its reliability stage fills result.predicted_error
    tracker = OnlineCalibrator()
    for image in frames:                        # BGR or grey arrays
        [result] = est.calibrate_images([image])
        state = tracker.update(result)          # FusedState: focal_px, rotation, roll/tilt, status, ...
        if state.valid:
            use(state.focal_px, state.rotation)

The pieces of ``fr track``: frame sources, files and live ones, with real time, dropping and
reconnection (:mod:`fr_torch.video.sources`); the fusion (:mod:`fr_torch.video.fusion`: rejection
of unreliable frames, weighted chordal mean of the rotations, log-focal mean, forgetting,
camera-moved detection and restart of a fusion *epoch*); the outputs written as frames are
processed, resuming and the figure (:mod:`fr_torch.video.records`); many cameras in one process, their
frames searched together (:mod:`fr_torch.video.fleet`), each fused and recorded by a
:class:`Tracking` as one source is here.
"""
from __future__ import annotations

import contextlib
import signal
import threading
from collections import deque
from typing import Callable, Iterator

from fr_torch.runtime.pipeline import calibrate_stream
from fr_torch.runtime.workers import stops_held
from fr_torch.video.fusion import FusedState, OnlineCalibrator
from fr_torch.video.records import CHANGES_FUSION, TrackOutput, frame_record
from fr_torch.video.sources import Frame, FrameStream, limited

#: The signal that asks a running ``fr track`` to draw its figure now.
PLOT_SIGNAL = getattr(signal, "SIGUSR1", None)


@contextlib.contextmanager
def plot_requests() -> Iterator[Callable[[], bool]]:
    """While the block runs, :data:`PLOT_SIGNAL` (SIGUSR1) only raises a flag; yields a function
    that says whether it came since the last call.  A no-op (never) outside the main thread or
    where the signal does not exist."""
    raised = threading.Event()

    def requested() -> bool:
        was = raised.is_set()
        raised.clear()
        return was

    if PLOT_SIGNAL is None or threading.current_thread() is not threading.main_thread():
        yield requested
        return
    previous = signal.signal(PLOT_SIGNAL, lambda signum, frame: raised.set())
    try:
        yield requested
    finally:
        signal.signal(PLOT_SIGNAL, previous)


def stop_reason(exc: BaseException) -> str:
    """How a run that ``exc`` ended is recorded (calibration.json's ``run``): a stop
    (``KeyboardInterrupt``) as ``stopped by SIGTERM`` (the signal of a
    :class:`fr_torch.runtime.workers.Stopped`; SIGINT for CTRL-C), anything else as
    ``error: TYPE: message``."""
    if isinstance(exc, KeyboardInterrupt):
        return f"stopped by {signal.Signals(getattr(exc, 'signum', signal.SIGINT)).name}"
    return f"error: {type(exc).__name__}: {exc}"


class Tracking:
    """One source's fusion and outputs, frame by frame: what :func:`track` does for its source and
    :func:`fr_torch.video.fleet.track_fleet` for each camera.

    :meth:`begin` writes calibration.json before the first frame; :meth:`fuse` fuses one frame's
    result and writes its record (appended and flushed) and, when the fusion changed,
    calibration.json (atomically), without a stop in between
    (:func:`fr_torch.runtime.workers.stops_held`); :meth:`finish` writes how the run ended and
    closes the files.  ``say``: where a restart's line goes; ``prefix``: what starts it (``fr track: SOURCE``,
    or the camera's name after it).
    """

    def __init__(self, stream: FrameStream, tracker: OnlineCalibrator, output: TrackOutput,
                 say: Callable[[str], None], prefix: str = "fr track"):
        self.stream, self.tracker, self.output, self.say, self.prefix = stream, tracker, output, say, prefix
        self.ended = False  # finish() ran

    def begin(self) -> None:
        self.output.write_calibration(None, self.tracker.checkpoint(), self.stream)

    def fuse(self, frame: Frame, result) -> FusedState:
        state = self.tracker.update(result, frame.index)
        record = frame_record(frame, result, state, self.output.segment, self.stream)
        with stops_held():
            self.output.append(record)
            if state.status in CHANGES_FUSION:
                self.output.write_calibration(state, self.tracker.checkpoint(), self.stream)
        if state.restarted:
            self.say(f"{self.prefix}: camera moved at frame {frame.index}: fusion restarted")
        return state

    def finish(self, run: str) -> None:
        """calibration.json with the latest fusion and ``run`` (how the run ended); files closed.
        The stream is closed first (its counters are final)."""
        self.stream.close()
        with stops_held():
            self.output.write_calibration(None, self.tracker.checkpoint(), self.stream, run)
            self.output.close()
        self.ended = True


def track(stream: FrameStream, estimator, tracker: OnlineCalibrator, output: TrackOutput, batch_size: int = 8,
          workers: int = 0, max_frames: int | None = None, progress=None, title: str = "",
          tracking: Tracking | None = None) -> str:
    """Calibrate, fuse and record the frames of ``stream`` until it ends (or ``max_frames``
    frames); returns how the run ended (``ended: ...``), as calibration.json's ``run`` says.

    Each frame's record is appended and flushed as soon as its result is fused, and
    calibration.json is rewritten whenever the fusion changes (:class:`Tracking`).  A live source
    in real time is searched one frame at a time (``batch_size`` 1; with ``workers``, one frame per
    worker), so that the frame searched is always the newest.  A stop (``KeyboardInterrupt``:
    CTRL-C, or SIGTERM / SIGHUP made :class:`~fr_torch.runtime.workers.Stopped`) or an error ends
    the run the same way -- calibration.json gets the latest fusion and ``run`` says why, the
    figure is drawn -- and is raised again.  ``progress``: a tqdm-like bar (``update``, ``write``)
    or None; SIGUSR1 draws the figure after the next frame.  ``tracking``: the :class:`Tracking` of
    these stream, tracker and output (None: made here), for a caller that watches it (metrics).
    """
    realtime = stream.live and getattr(stream, "realtime", False)
    if realtime:
        batch_size = 1
    waiting: deque = deque()  # frames read and not yet recorded, in order

    def pairs():
        for frame in limited(iter(stream), max_frames):
            waiting.append(frame)
            yield frame.image, frame.name

    if tracking is None:
        tracking = Tracking(stream, tracker, output, progress.write if progress is not None else output.log)
    run = "error"
    tracking.begin()
    try:
        with plot_requests() as plot_requested:
            results = calibrate_stream(estimator, pairs(), batch_size, workers,
                                       in_flight=workers if realtime and workers else None)
            try:
                for result in results:
                    tracking.fuse(waiting.popleft(), result)
                    if progress is not None:
                        progress.update(1)
                    if plot_requested():
                        output.plot(title)
            finally:
                results.close()
        run = "ended: --max-frames" if max_frames is not None and output.processed >= max_frames \
            else f"ended: {stream.end_reason or 'end of the source'}"
    except BaseException as exc:
        run = stop_reason(exc)
        raise
    finally:
        tracking.finish(run)
        output.plot(title)
    return run
