"""Where ``fr track`` reads its frames: video files and folders, and live sources.

:meth:`Source.parse` reads the command line's SOURCE:

=================================  ========  =====================================================
SOURCE                             kind      read by
=================================  ========  =====================================================
``-``                              stdin     :func:`fr_torch.images.stream.split_images`: JPEG,
                                             PNG, PNM or BMP images back to back, as
                                             ``ffmpeg ... -f image2pipe -`` writes them
``scheme://...``                   stream    OpenCV's FFmpeg back end: ``rtsp://``, ``http(s)://``
                                             (multipart MJPEG, HLS), ``udp://``, ...
an existing folder                 folder    its images, sorted by name
an existing file                   file      OpenCV ``VideoCapture``, frame by frame
``0``, ``1``, ... or a device      camera    OpenCV ``VideoCapture`` (``/dev/video0``)
=================================  ========  =====================================================

**Files and folders** (:class:`FileFrames`) are read on demand, as the search asks for frames:
every frame (``every``) is processed, none is dropped, and ``start`` skips the frames before it
(a resumed run).  Their frame index is the frame's number in the video (the position in the
sorted folder).

**Live sources** (:class:`LiveFrames`) are read without pause by a thread, so the source never
waits for the search.  In **real time** (the default for live sources) only the newest frame
waits: one that arrives while the search is busy replaces it, and the replaced one is *dropped*
(never processed); the search always takes the newest frame.  Without real time, frames wait in a
queue of :data:`QUEUE_LENGTH` (when it is full the reader waits: a pipe's writer blocks, a network
stream's frames are lost upstream).  A live frame's index counts every frame read from the source
in this run, so the gaps between processed indices are the drops.

**Only the frames taken are decoded.**  A stream whose codec is Motion JPEG (an HTTP MJPEG
camera; any stream whose codec FFmpeg reports as MJPEG) is read undecoded (:data:`ENCODED_CODECS`; OpenCV's raw mode): the reader
keeps each frame's JPEG bytes, and only a frame that the search takes is decoded, by the bounded
decoder of ``fr calibrate`` (:func:`fr_torch.images.io.decode_image_bytes`), as a frame from
stdin is.  So a 25 frames/s camera searched once a second costs one decode a second, not 25, and
its frame is decoded as the same JPEG saved to a file would be.  Other codecs (H.264, H.265, ...)
predict each frame from the ones before it: every frame is decoded by FFmpeg as it arrives (such a
stream is opened twice per connection: once to learn its codec, once decoding).

A live source that ends or fails (the connection drops, a read times out after
``read_timeout_s``, the camera is unplugged) is opened again with back-off when
:class:`Reconnect` allows it: an outage is one line when it starts and one when the source is back
(or given up), however many tries it took; standard input is never reopened (its end is the end).
A frame that cannot be decoded is skipped with one line.  Each line starts with ``fr track: NAME:``
(``name``: a fleet camera's name; else the source, its URL's secrets hidden, :meth:`Source.__str__`).

OpenCV's and FFmpeg's own messages (``[tcp @ 0x...] Connection refused``, ``[ WARN:0@...]
VIDEOIO(FFMPEG) ...``, a decoder's complaints) are kept off stderr (:func:`quiet_video_logs`):
they would break the progress line and may name the source again.  To see them, set
``OPENCV_LOG_LEVEL=INFO`` (OpenCV, on stderr) or ``OPENCV_FFMPEG_LOGLEVEL=24`` (FFmpeg's warnings,
which OpenCV prints on **stdout**) before the run.
"""
from __future__ import annotations

import itertools
import math
import os
import re
import stat
import sys
import threading
import time
from collections import deque
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterator
from urllib.parse import urlsplit

import cv2
import numpy as np

from fr_torch.errors import FRInputError
from fr_torch.images.io import decode_image_bytes, load_image
from fr_torch.images.stream import split_images
from fr_torch.redaction import SCHEME, redact_text, redact_url

IMAGE_SUFFIXES = {".jpg", ".jpeg", ".png", ".bmp", ".tif", ".tiff", ".webp", ".pgm", ".ppm"}
#: Frames a live source may queue without real time (then the reader waits for the search).
QUEUE_LENGTH = 64
#: Codecs (OpenCV's ``CAP_PROP_FOURCC``) whose every frame is a whole JPEG image: a stream of them is
#: read undecoded and only the frames taken are decoded (module docstring).
ENCODED_CODECS = frozenset({"MJPG", "mjpg", "MJPA", "AVRN", "JPEG", "jpeg"})


def log_line(message: str) -> None:
    """One line on stderr, flushed, URLs redacted (the default ``log`` of the frame sources)."""
    print(redact_text(message), file=sys.stderr, flush=True)


def quiet_video_logs() -> None:
    """Keep OpenCV's and FFmpeg's own messages off stderr, for the whole process: OpenCV's log
    level becomes ERROR (its warnings, e.g. ``VIDEOIO(FFMPEG): backend is generally available but
    can't be used to capture by name``, go), and FFmpeg's ``av_log`` is silenced (its
    ``[tcp @ 0x...] Connection refused``, ``[rtsp @ 0x...] method DESCRIBE failed: 404``, ``[h264 @
    0x...]`` decoder lines go).  Either is left as it is where the environment sets it
    (``OPENCV_LOG_LEVEL``; ``OPENCV_FFMPEG_LOGLEVEL`` or ``OPENCV_FFMPEG_DEBUG``).

    FFmpeg's level is ``OPENCV_FFMPEG_LOGLEVEL=-8`` (AV_LOG_QUIET), which OpenCV reads when it
    first uses FFmpeg in the process: called after that (a capture already opened), FFmpeg keeps
    OpenCV's default, its errors on stderr."""
    if "OPENCV_LOG_LEVEL" not in os.environ:
        cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_ERROR)
    if "OPENCV_FFMPEG_LOGLEVEL" not in os.environ and "OPENCV_FFMPEG_DEBUG" not in os.environ:
        os.environ["OPENCV_FFMPEG_LOGLEVEL"] = "-8"


# ---------------------------------------------------------------------------------- what to read

@dataclass(frozen=True)
class Source:
    """A frame source as given on the command line: ``kind`` (``file``, ``folder``, ``stream``,
    ``camera``, ``stdin``) and ``target`` (the path, URL, camera index or device, ``-``)."""

    kind: str
    target: str

    LIVE_KINDS = ("stream", "camera", "stdin")

    @classmethod
    def parse(cls, text: str | os.PathLike) -> Source:
        """The source named by ``text`` (module docstring); FileNotFoundError for a path that is
        none of them."""
        text = os.fspath(text)
        if text == "-":
            return cls("stdin", "-")
        if SCHEME.match(text):
            return cls("stream", text)
        path = Path(text)
        if path.is_dir():
            return cls("folder", text)
        if path.is_file():
            return cls("file", text)
        try:
            if stat.S_ISCHR(path.stat().st_mode):
                return cls("camera", text)
        except OSError:
            pass
        if text.isdigit():
            return cls("camera", text)
        raise FileNotFoundError(f"{text}: no such video file or folder (nor a stream URL scheme://..., a camera "
                                "index or device, or - for frames on stdin)")

    @property
    def live(self) -> bool:
        """True for a stream, a camera or stdin: frames come at the source's pace, without end."""
        return self.kind in self.LIVE_KINDS

    def __str__(self) -> str:
        """The source as every message, record, file and metric shows it: a URL's password and
        credential parameters hidden (:func:`fr_torch.redaction.redact_url`)."""
        if self.kind != "stream":
            return "stdin" if self.kind == "stdin" else self.target
        return redact_url(self.target)

    @property
    def label(self) -> str:
        """A short name: the default output folder is ``track_<label>``, frames are ``<label>_<index>``."""
        if self.kind == "stdin":
            return "stdin"
        if self.kind == "camera":
            return f"camera{self.target}" if self.target.isdigit() else Path(self.target).name
        if self.kind == "stream":
            parts = urlsplit(str(self))  # the redacted URL: a malformed user part cannot pass for the host
            name = Path(parts.path).stem or parts.hostname or parts.scheme
            return re.sub(r"[^A-Za-z0-9_.-]+", "_", name)
        path = Path(self.target)
        return path.stem or path.name


@dataclass(frozen=True)
class Reconnect:
    """What a live source does when it drops: try again after ``first_wait_s`` seconds, then
    after waits doubling up to ``max_wait_s``, until no frame has come for ``give_up_s`` seconds
    (``inf``: never give up; 0: do not reconnect, the drop ends the stream)."""

    give_up_s: float = 0.0
    first_wait_s: float = 0.5
    max_wait_s: float = 30.0

    @classmethod
    def parse(cls, value: str | float | None) -> Reconnect:
        """``--reconnect [SECONDS]``: None (option absent) -> no reconnection; ``inf`` (the option
        alone) -> for ever; a number of seconds >= 0 -> give up after it.  FRInputError otherwise."""
        if value is None:
            return cls()
        try:
            seconds = float(value)
        except (TypeError, ValueError):
            seconds = math.nan
        if math.isnan(seconds) or seconds < 0:
            raise FRInputError(f"--reconnect: expected seconds >= 0 or inf, got {value!r}")
        return cls(give_up_s=seconds)

    @property
    def enabled(self) -> bool:
        return self.give_up_s > 0

    def waits(self) -> Iterator[float]:
        """The waits before each try, in seconds: first_wait_s, doubling, capped at max_wait_s."""
        wait = self.first_wait_s
        while True:
            yield wait
            wait = min(self.max_wait_s, 2 * wait)


@dataclass
class Frame:
    """One frame to process.

    ``index``: a file's frame number (a folder's position), or a live frame's count of frames
    read from the source before it in this run; ``image``: BGR or grey array; ``read_at``:
    ``time.monotonic()`` when it was read from the source (seconds); ``dropped``: live frames read
    since the previous frame handed out that were never processed (replaced by a newer one)."""

    index: int
    name: str
    image: np.ndarray
    read_at: float
    dropped: int = 0


class FrameStream:
    """The frames of a source, in order (iterate once), and what became of the others.

    Counters (this run): ``arrived`` frames read from the source, ``dropped`` of them never
    processed because a newer one replaced them (real time), ``skipped`` that could not be read or
    decoded, ``reconnects`` successful reconnections, ``outage`` True while a live source is away
    (between a drop and its reconnection).  ``end_reason`` says why the iteration ended.
    :meth:`close` stops reading (a live source's thread).  ``log`` takes each line, which starts
    with ``fr track: NAME:`` (``name``: a fleet camera's name; None: the source)."""

    live = False
    outage = False

    def __init__(self, source: Source, log: Callable[[str], None] = log_line, name: str | None = None):
        self.source, self.log = source, log
        self.name = name or str(source)
        self.arrived = self.dropped = self.skipped = self.reconnects = 0
        self.end_reason = ""

    @property
    def dropped_share(self) -> float:
        """Share of the arrived frames that were dropped (0 for files)."""
        return self.dropped / self.arrived if self.arrived else 0.0

    def __iter__(self) -> Iterator[Frame]:
        raise NotImplementedError

    def ready(self) -> bool:
        """True when the next frame (or the end) can be taken without waiting for the source:
        always for files, which are read on demand."""
        return True

    def close(self) -> None:
        pass

    def __enter__(self) -> FrameStream:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class FileFrames(FrameStream):
    """Every ``every``-th frame of a video file or folder of images from frame ``start`` on,
    read on demand; an unreadable image of a folder is skipped with one line."""

    def __init__(self, source: Source, every: int = 1, start: int = 0, log: Callable[[str], None] = log_line,
                 name: str | None = None):
        super().__init__(source, log, name)
        self.every, self.start = max(1, int(every)), max(0, int(start))

    def _wanted(self, index: int) -> bool:
        return index >= self.start and index % self.every == 0

    def __iter__(self) -> Iterator[Frame]:
        path = Path(self.source.target)
        if self.source.kind == "folder":
            yield from self._folder(path)
        else:
            yield from self._video(path)
        self.end_reason = self.end_reason or "end of the source"

    def _folder(self, path: Path) -> Iterator[Frame]:
        files = sorted(p for p in path.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
        if not files:
            raise FRInputError(f"{path}: no image files ({', '.join(sorted(IMAGE_SUFFIXES))})")
        for index, file in enumerate(files):
            if not self._wanted(index):
                continue
            try:
                image = load_image(str(file))
            except FRInputError as exc:
                self.skipped += 1
                self.log(f"fr track: {self.name}: skipping {file.name}: {exc}")
                continue
            self.arrived += 1
            yield Frame(index, file.name, image, time.monotonic())

    def _video(self, path: Path) -> Iterator[Frame]:
        capture = cv2.VideoCapture(str(path))
        if not capture.isOpened():
            raise FRInputError(f"{path}: OpenCV cannot open this video")
        index = 0
        try:  # frames not wanted are grabbed (decoded, never converted): exact indices, no seeking
            while capture.grab():
                if self._wanted(index):
                    ok, image = capture.retrieve()
                    if ok:
                        self.arrived += 1
                        yield Frame(index, f"{path.stem}_{index:06d}", image, time.monotonic())
                    else:
                        self.skipped += 1
                        self.log(f"fr track: {self.name}: skipping frame {index} of {path.name}: it cannot be decoded")
                index += 1
        finally:
            capture.release()
        if index == 0:
            raise FRInputError(f"{path}: no frames could be read")


class LiveFrames(FrameStream):
    """Frames of a live source, read by a thread without pause (module docstring).

    ``realtime``: keep only the newest frame (True) or queue up to ``queue_length``; ``reconnect``:
    when and how long to reopen a dropped source; ``open_timeout_s`` / ``read_timeout_s``: how long
    a stream's connection or next frame may take before it counts as dropped.  The thread starts
    with the iteration."""

    live = True

    def __init__(self, source: Source, realtime: bool = True, reconnect: Reconnect = Reconnect(),
                 queue_length: int = QUEUE_LENGTH, open_timeout_s: float = 10.0, read_timeout_s: float = 5.0,
                 log: Callable[[str], None] = log_line, stdin_fd: int | None = None, name: str | None = None):
        super().__init__(source, log, name)
        self.realtime, self.reconnect = realtime, reconnect
        self.queue_length = 1 if realtime else max(1, int(queue_length))
        self.open_timeout_s, self.read_timeout_s = open_timeout_s, read_timeout_s
        self.stdin_fd = sys.stdin.fileno() if stdin_fd is None and source.kind == "stdin" else stdin_fd
        self._waiting: deque = deque()  # (index, image or encoded bytes, read_at)
        self._condition = threading.Condition()
        self._stop = threading.Event()
        self._ended = False
        self._failure: str | None = None  # why the source could not be read at all
        self._thread = threading.Thread(target=self._read, name="fr-track-reader", daemon=True)

    # ------------------------------------------------------------ the reader thread

    def _connections(self) -> Iterator[Iterator]:
        """One iterator of frames (arrays, or encoded bytes: stdin, a Motion JPEG stream) per connection."""
        if self.source.kind == "stdin":
            yield split_images(lambda size: os.read(self.stdin_fd, size), on_skip=self._skipped_bytes)
            return
        while True:
            yield self._capture()

    def _capture(self) -> Iterator[np.ndarray | bytes]:
        """One connection's frames: BGR arrays, or a Motion JPEG stream's encoded frames (bytes)."""
        target = self.source.target
        encoded = False
        if self.source.kind == "stream":
            capture, encoded = self._open_stream(target)
        else:
            capture = cv2.VideoCapture(int(target) if target.isdigit() else target)
        try:
            if not capture.isOpened():
                raise FRInputError(f"OpenCV cannot open this {self.source.kind}")
            while not self._stop.is_set():
                ok, image = capture.read()
                if not ok:
                    return
                yield image.tobytes() if encoded else image
        finally:
            capture.release()

    def _open_stream(self, url: str) -> tuple[cv2.VideoCapture, bool]:
        """The stream's capture and whether it hands out encoded frames: opened in OpenCV's raw
        mode (``CAP_PROP_FORMAT`` -1: each read is one packet, undecoded) and kept so when the codec
        is in :data:`ENCODED_CODECS`; else closed and opened again decoding (a second connection)."""
        timeouts = [cv2.CAP_PROP_OPEN_TIMEOUT_MSEC, int(self.open_timeout_s * 1000),
                    cv2.CAP_PROP_READ_TIMEOUT_MSEC, int(self.read_timeout_s * 1000)]
        capture = cv2.VideoCapture(url, cv2.CAP_FFMPEG, timeouts + [cv2.CAP_PROP_FORMAT, -1])
        if not capture.isOpened() or capture.get(cv2.CAP_PROP_FORMAT) != -1:  # failed, or decoding anyway
            return capture, False
        if codec(capture) in ENCODED_CODECS:
            return capture, True
        capture.release()
        return cv2.VideoCapture(url, cv2.CAP_FFMPEG, timeouts), False

    def _skipped_bytes(self, count: int) -> None:
        with self._condition:
            self.skipped += 1
        self.log(f"fr track: {self.name}: skipping {count} bytes that are no complete image")

    def _read(self) -> None:
        waits: Iterator[float] | None = None  # the back-off of the outage in progress (None: none)
        tries = 0
        last_frame_at = time.monotonic()
        end = "the stream ended"
        try:
            for connection in self._connections():
                problem = "the stream ended"
                try:
                    for image in connection:
                        if self._stop.is_set():
                            return
                        if waits is not None:  # the outage's second line: the source is back
                            self.reconnects += 1
                            self.outage = False
                            self.log(f"fr track: {self.name}: reconnected after {time.monotonic() - last_frame_at:.1f}"
                                     f" s ({tries} {'try' if tries == 1 else 'tries'})")
                            waits, tries = None, 0
                        self._put(image)
                        last_frame_at = time.monotonic()
                except FRInputError as exc:
                    problem = redact_text(str(exc))
                except Exception as exc:  # a decoder's or a socket's failure ends this connection only
                    problem = redact_text(f"{type(exc).__name__}: {exc}")
                if self._stop.is_set():
                    return
                if self.source.kind == "stdin" or not self.reconnect.enabled:
                    end = problem
                    if self.arrived == 0 and problem != "the stream ended":
                        self._failure = f"{self.source}: {problem}"
                    return
                first = waits is None
                waits = waits or self.reconnect.waits()
                wait = next(waits)
                silent = time.monotonic() - last_frame_at
                if silent + wait > self.reconnect.give_up_s:
                    self.outage = False
                    end = f"{problem}; no frame for {silent:.0f} s: gave up reconnecting (--reconnect)"
                    if self.arrived == 0:  # the iteration raises it: the command's error line
                        self._failure = f"{self.source}: {end}"
                    else:
                        self.log(f"fr track: {self.name}: {end}")
                    return
                if first:  # the outage's first line; its retries are silent
                    self.outage = True
                    self.log(f"fr track: {self.name}: {problem}; reconnecting in {wait:g} s (--reconnect)")
                tries += 1
                if self._stop.wait(wait):
                    return
        finally:
            with self._condition:
                self.end_reason = self.end_reason or end
                self._ended = True
                self._condition.notify_all()

    def _put(self, image) -> None:
        with self._condition:
            index = self.arrived
            self.arrived += 1
            if self.realtime:
                self.dropped += len(self._waiting)
                self._waiting.clear()
            else:
                while len(self._waiting) >= self.queue_length and not self._stop.is_set():
                    self._condition.wait(0.25)
            self._waiting.append((index, image, time.monotonic()))
            self._condition.notify_all()

    # ------------------------------------------------------------ the consumer

    def __iter__(self) -> Iterator[Frame]:
        self.start()
        return self._take()

    def start(self) -> None:
        """Start reading (the iteration does; a second call does nothing)."""
        if self._thread.ident is None:
            self._thread.start()

    def ready(self) -> bool:
        """True when a frame waits or the reader has ended."""
        with self._condition:
            return bool(self._waiting) or self._ended

    def _take(self) -> Iterator[Frame]:
        """The frames the reader leaves, as they come, until it has ended and none is left."""
        previous = -1
        while True:
            with self._condition:
                while not self._waiting and not self._ended:
                    self._condition.wait(0.25)
                if not self._waiting:
                    break
                index, image, read_at = self._waiting.popleft()
                self._condition.notify_all()
            name = f"{self.source.label}_{index:06d}"
            if isinstance(image, (bytes, bytearray)):
                try:
                    image = decode_image_bytes(image, name)[0]
                except FRInputError as exc:
                    with self._condition:
                        self.skipped += 1
                    self.log(f"fr track: {self.name}: skipping frame {index}: {exc}")
                    previous = index  # skipped, not dropped
                    continue
            dropped, previous = index - previous - 1, index
            yield Frame(index, name, image, read_at, dropped)
        if self._failure is not None:
            raise FRInputError(self._failure)

    def close(self) -> None:
        """Stop the reader and wait for it (a stream's read returns within ``read_timeout_s``)."""
        self._stop.set()
        with self._condition:
            self._condition.notify_all()
        if self._thread.is_alive():
            self._thread.join(self.read_timeout_s + 1.0)


def codec(capture: cv2.VideoCapture) -> str:
    """The four characters of an opened capture's codec (``CAP_PROP_FOURCC``: ``MJPG``, ``h264``, ...)."""
    code = int(capture.get(cv2.CAP_PROP_FOURCC)) & 0xFFFFFFFF
    return code.to_bytes(4, "little").decode("latin-1")


def open_frames(source: Source, every: int = 1, start: int = 0, realtime: bool | None = None,
                reconnect: Reconnect = Reconnect(), stream_timeout_s: float = 5.0,
                log: Callable[[str], None] = log_line, name: str | None = None) -> FrameStream:
    """The :class:`FrameStream` of ``source``: :class:`FileFrames` (``every``, ``start``) for a
    file or folder, :class:`LiveFrames` for a live source (``realtime``: default True;
    ``reconnect``, which a file or folder ignores: it is read to its end; a stream's read may take
    ``stream_timeout_s``, its connection at least 10 s).  ``name``: what its lines start with
    after ``fr track:`` (a fleet camera's name; None: the source).  FRInputError for options that
    do not fit the source.  OpenCV's and FFmpeg's own messages are silenced from here on
    (:func:`quiet_video_logs`)."""
    quiet_video_logs()
    if not source.live:
        if realtime:
            raise FRInputError(f"--realtime: {source} is a file; its frames are read one after another, none dropped")
        return FileFrames(source, every, start, log, name)
    if every != 1:
        raise FRInputError("--every applies to files and folders: a live source in real time takes the newest "
                           "frame whenever the search is free (--no-realtime queues them all)")
    return LiveFrames(source, True if realtime is None else realtime, reconnect,
                      open_timeout_s=max(10.0, stream_timeout_s), read_timeout_s=stream_timeout_s, log=log, name=name)


def limited(frames: Iterator[Frame], max_frames: int | None) -> Iterator[Frame]:
    """The first ``max_frames`` frames (all with None)."""
    return frames if max_frames is None else itertools.islice(frames, max_frames)
