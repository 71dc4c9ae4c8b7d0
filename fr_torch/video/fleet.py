"""Many cameras in one process: ``fr track SOURCE SOURCE ...`` or ``fr track --sources FILE``.

Every camera is read as ``fr track`` reads one source (:mod:`fr_torch.video.sources`: a live one
by a thread of its own that keeps only the newest frame), and has its own fusion, records and
calibration.json (:class:`fr_torch.video.track.Tracking`, each in ``OUT/<name>/``).  What the
cameras share is the estimator: :func:`track_fleet` repeats a *turn* --

1. the cameras that have a frame ready (a live one: a frame arrived since its last turn; a file:
   always) and whose rate cap allows it (``max_rate``: at most that many frames per second) are
   taken **least recently served first**, at most ``batch_size`` of them, one frame each (a live
   camera's newest);
2. their frames are decoded, detected and searched **as one batch** (one
   ``calibrate_images`` call per distinct search setting, i.e. per ``--fov-range``; a camera's
   known focal length is per image); on a CPU the batch is split over worker processes
   (:class:`fr_torch.runtime.pipeline.CalibrationPool`), away from the reader threads;
3. each result is fused and recorded by its own camera.

So no camera waits for more than one turn behind the others however fast another one streams,
a stalled or reconnecting camera is simply not ready (the others go on), and a camera that ends
or fails ends alone (one line; its calibration.json says why).  Memory is bounded by the number
of cameras: one waiting frame and one fusion state each; the records are on disk.

**Sources file** (``--sources FILE``), one camera per line; ``#`` starts a comment, blank lines
are skipped, words are split as a shell would (quote a path with spaces)::

    # [NAME] SOURCE [--fov-range MIN,MAX] [--every N] [--focal PX] [--max-rate HZ] [--reconnect [SECONDS]]
    gate    rtsp://user:pass@10.0.0.5/stream1   --fov-range 30,60 --reconnect
    lobby   http://10.0.0.6/mjpg/video.mjpg     --focal 1210 --max-rate 2 --reconnect 600
    archive /data/site3.mp4                     --every 25
    rtsp://10.0.0.7/stream1

``NAME`` (letters, digits, ``_ . -``) names the camera's output folder and fills the ``camera``
column; without it the source's short name is used (``Source.label``), followed by ``_<n>`` (its
position in the fleet, from 1) when two cameras would share it.  ``--every`` applies to files and
folders, as for one source; ``--fov-range`` is the search range of ``fr calibrate``; ``--focal``
a known focal length (pixels, then only the rotation is searched); ``--max-rate`` caps the
camera's frames searched per second (default: the command's ``--max-rate``, or none);
``--reconnect [SECONDS]`` reopens the camera when it drops, as the command's ``--reconnect`` (which
is the default of every live camera).  A file or folder is read to its end whatever
``--reconnect`` says: its end is its camera's end.
"""
from __future__ import annotations

import math
import re
import shlex
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterator, Sequence

from fr_torch.core.settings.config import SearchConfig
from fr_torch.errors import FRInputError
from fr_torch.video.sources import Frame, Reconnect, Source
from fr_torch.video.track import Tracking, plot_requests, stop_reason

#: A camera's name: its output folder.
CAMERA_NAME = re.compile(r"^[A-Za-z0-9_.-]+$")
#: The options of a sources file's line, and the CameraSpec field each sets.
CAMERA_OPTIONS = {"--fov-range": "fov_range", "--every": "every", "--focal": "focal_px", "--max-rate": "max_rate",
                  "--reconnect": "reconnect"}


@dataclass(frozen=True)
class CameraSpec:
    """One camera of a fleet as given: ``name`` (its output folder and ``camera`` column),
    ``source``, ``fov_range`` (``MIN,MAX`` degrees or ``paper``; None: the command's),
    ``every`` (files: every N-th frame), ``focal_px`` (known focal length, pixels, or None),
    ``max_rate`` (frames searched per second at most, or None), ``reconnect`` (what a live
    camera does when it drops; a file's is never used)."""

    name: str
    source: Source
    fov_range: str | None = None
    every: int = 1
    focal_px: float | None = None
    max_rate: float | None = None
    reconnect: Reconnect = Reconnect()

    @property
    def min_interval_s(self) -> float:
        """Seconds between two of its frames searched at least (0 without a rate cap)."""
        return 1.0 / self.max_rate if self.max_rate else 0.0


def _number(text: str, option: str, where: str, integer: bool = False) -> float:
    try:
        value = int(text) if integer else float(text)
    except ValueError:
        value = math.nan
    if not (math.isfinite(value) and value > 0) or (integer and value < 1):
        kind = "an integer >= 1" if integer else "a number > 0"
        raise FRInputError(f"{where}: {option} expects {kind}, got {text!r}")
    return value


def camera_line(text: str, where: str) -> tuple[str | None, Source, dict[str, Any]] | None:
    """One line of a sources file (module docstring): ``(name or None, source, options)``, or None
    for a blank or comment line.  ``where`` (``FILE:LINE``) starts every error's one line."""
    try:
        words = shlex.split(text, comments=True)
    except ValueError as exc:
        raise FRInputError(f"{where}: {exc}") from None
    if not words:
        return None
    positional, options = [], {}
    i = 0
    while i < len(words):
        word = words[i]
        if word.startswith("--"):
            option, equals, value = word.partition("=")
            if option not in CAMERA_OPTIONS:
                raise FRInputError(f"{where}: unknown option {option!r} (a camera takes "
                                   f"{', '.join(CAMERA_OPTIONS)})")
            if not equals and option == "--reconnect":  # its SECONDS may be left out: for ever
                if i + 1 < len(words) and _seconds(words[i + 1]):
                    i += 1
                    value = words[i]
                else:
                    value = "inf"
            elif not equals:
                if i + 1 >= len(words):
                    raise FRInputError(f"{where}: {option} needs a value")
                i += 1
                value = words[i]
            options[CAMERA_OPTIONS[option]] = _option_value(option, value, where)
        else:
            positional.append(word)
        i += 1
    if not 1 <= len(positional) <= 2:
        raise FRInputError(f"{where}: expected [NAME] SOURCE [options], got {len(positional)} words that are no "
                           f"option ({' '.join(positional)})")
    name = positional[0] if len(positional) == 2 else None
    if name is not None and not CAMERA_NAME.match(name):
        raise FRInputError(f"{where}: camera name {name!r}: use letters, digits, '_', '.', '-'")
    return name, _source(positional[-1], where), options


def _seconds(word: str) -> bool:
    try:
        float(word)
    except ValueError:
        return False
    return True


def _option_value(option: str, value: str, where: str):
    if option == "--reconnect":
        try:
            return Reconnect.parse(value)
        except FRInputError as exc:
            raise FRInputError(f"{where}: {exc}") from None
    if option == "--fov-range":
        try:
            SearchConfig.from_config().with_fov_range(value)
        except ValueError as exc:
            raise FRInputError(f"{where}: --fov-range: {exc}") from None
        return value
    return _number(value, option, where, integer=option == "--every")


def _source(text: str, where: str) -> Source:
    try:
        return Source.parse(text)
    except FileNotFoundError as exc:
        raise FRInputError(f"{where}: {exc}") from None


def read_sources_file(path: str | Path) -> list[tuple[str | None, Source, dict[str, Any]]]:
    """The cameras of a sources file, one :func:`camera_line` each, in order; FRInputError (one
    line naming the file and line) for an unreadable file, a bad line or a file of no camera."""
    path = Path(path)
    try:
        lines = path.read_text(encoding="utf-8").splitlines()
    except (OSError, UnicodeDecodeError) as exc:
        raise FRInputError(f"--sources {path}: cannot read ({getattr(exc, 'strerror', None) or exc})") from None
    cameras = [camera for number, line in enumerate(lines, 1) if (camera := camera_line(line, f"{path}:{number}"))]
    if not cameras:
        raise FRInputError(f"--sources {path}: no camera in it (one per line: [NAME] SOURCE [options])")
    return cameras


def camera_specs(sources: Sequence[str], sources_file: str | Path | None = None,
                 max_rate: float | None = None, reconnect: Reconnect = Reconnect()) -> list[CameraSpec]:
    """The fleet of the command line: each SOURCE, then each line of ``sources_file``, as a
    :class:`CameraSpec` with a unique name (module docstring); ``max_rate``, ``reconnect``: the
    command's, each camera's unless its line gives its own.
    FRInputError (one line) for a bad source, line or name."""
    given = [(None, _source(text, "SOURCE"), {}) for text in sources]
    if sources_file is not None:
        given += read_sources_file(sources_file)
    explicit = [name for name, _, _ in given if name is not None]
    repeated = sorted({name for name in explicit if explicit.count(name) > 1})
    if repeated:
        raise FRInputError(f"--sources: two cameras named {repeated[0]!r}: each name is an output folder")
    labels = [name or source.label for name, source, _ in given]
    specs = []
    for position, ((name, source, options), label) in enumerate(zip(given, labels), 1):
        if name is None and (labels.count(label) > 1 or label in explicit):
            label = f"{label}_{position}"
        specs.append(CameraSpec(label, source, **{"max_rate": max_rate, "reconnect": reconnect, **options}))
    names = [spec.name for spec in specs]
    if len(set(names)) != len(names):
        clash = next(name for name in names if names.count(name) > 1)
        raise FRInputError(f"--sources: two cameras named {clash!r}: name them (NAME SOURCE in the sources file)")
    return specs


@dataclass
class FleetCamera:
    """A camera while the fleet runs: its ``spec``, its :class:`Tracking` (stream, fusion,
    outputs), the ``estimator`` of its search setting (an ``FREstimator``, or a
    :class:`fr_torch.runtime.pipeline.CalibrationPool` of worker processes: anything with
    ``calibrate_images(images, names, focal_px)``), when it was last served (``served_at``,
    ``time.monotonic()`` seconds) and, once it has ended, how (``run``)."""

    spec: CameraSpec
    tracking: Tracking
    estimator: Any
    served_at: float = -math.inf
    run: str | None = None
    frames: Iterator[Frame] | None = field(default=None, repr=False)

    def due(self, now: float) -> bool:
        """Its rate cap allows a frame now and the frame (or its end) is there."""
        return now >= self.served_at + self.spec.min_interval_s and self.tracking.stream.ready()


def take_turns(cameras: Sequence[FleetCamera], batch_size: int, now: float,
               end: Callable[[FleetCamera, str], None]) -> list[tuple[FleetCamera, Frame]]:
    """This turn's frames: one from each camera that is due, least recently served first, at
    most ``batch_size``.  A camera whose stream has ended or failed is passed to ``end`` with how
    (``ended: ...`` or ``error: ...``) and takes no place."""
    taken = []
    for camera in sorted((c for c in cameras if c.due(now)), key=lambda c: c.served_at):
        if len(taken) >= batch_size:
            break
        stream = camera.tracking.stream
        try:
            frame = next(camera.frames)
        except StopIteration:
            end(camera, f"ended: {stream.end_reason or 'end of the source'}")
            continue
        except Exception as exc:  # its source cannot be read: this camera's end, not the fleet's
            end(camera, f"error: {exc}" if isinstance(exc, FRInputError) else f"error: {type(exc).__name__}: {exc}")
            continue
        camera.served_at = now
        taken.append((camera, frame))
    return taken


def search(taken: Sequence[tuple[FleetCamera, Frame]]) -> list:
    """The results of ``taken``'s frames, in order: one ``calibrate_images`` call per estimator
    (search setting), each camera's known focal length with its frame."""
    results: list = [None] * len(taken)
    groups: dict[int, list[int]] = {}
    for i, (camera, _) in enumerate(taken):
        groups.setdefault(id(camera.estimator), []).append(i)
    for members in groups.values():
        estimator = taken[members[0]][0].estimator
        found = estimator.calibrate_images([taken[i][1].image for i in members], names=[taken[i][1].name for i in members],
                                           focal_px=[taken[i][0].spec.focal_px for i in members])
        for i, result in zip(members, found):
            results[i] = result
    return results


def close_all(cameras: Sequence[FleetCamera]) -> None:
    """Close every camera's stream at once (each waits for its reader; a stalled one up to its read
    timeout, so they are closed side by side, not one after another)."""
    closers = [threading.Thread(target=c.tracking.stream.close, daemon=True) for c in cameras]
    for closer in closers:
        closer.start()
    for closer in closers:
        closer.join()


def track_fleet(cameras: Sequence[FleetCamera], batch_size: int, max_frames: int | None = None, progress=None,
                say: Callable[[str], None] = print, idle_s: float = 0.005,
                plot: Callable[[FleetCamera], Any] = lambda camera: None) -> None:
    """Run the fleet (module docstring) until every camera has ended (its source's end, an error,
    ``max_frames`` frames of its own); each camera's ``run`` says how it ended.

    ``batch_size``: frames searched together at most per turn; ``progress``: a tqdm-like bar
    (``update``) or None; ``say``: one line (a camera's end or failure, a restart); ``idle_s``:
    the pause when no camera has a frame ready; ``plot(camera)`` draws a camera's figure (at the
    end of the run, and on SIGUSR1).  A stop (``KeyboardInterrupt``, as :func:`fr_torch.video.track.track`)
    or an error ends every camera still running the same way -- its calibration.json gets the
    latest fusion and ``run`` says why -- and is raised again.
    """
    running = list(cameras)

    def end(camera: FleetCamera, run: str) -> None:
        camera.run = run
        running.remove(camera)
        camera.tracking.finish(run)
        say(f"fr track: {camera.spec.name}: {run}")

    run = "error"
    for camera in cameras:
        camera.tracking.begin()
        camera.frames = iter(camera.tracking.stream)
    try:
        with plot_requests() as plot_requested:
            while running:
                taken = take_turns(running, batch_size, time.monotonic(), end)
                if not taken:
                    time.sleep(idle_s)
                    continue
                for (camera, frame), result in zip(taken, search(taken)):
                    camera.tracking.fuse(frame, result)
                    if progress is not None:
                        progress.update(1)
                    if max_frames is not None and camera.tracking.output.processed >= max_frames:
                        end(camera, "ended: --max-frames")
                if plot_requested():
                    for camera in cameras:
                        plot(camera)
        run = ""
    except BaseException as exc:
        run = stop_reason(exc)
        raise
    finally:
        close_all(running)
        for camera in running:
            camera.run = run
            camera.tracking.finish(run)
        for camera in cameras:
            plot(camera)
