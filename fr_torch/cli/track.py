"""``fr track``: the command-line front end of :mod:`fr_torch.video.track` (one source) and of
:mod:`fr_torch.video.fleet` (several SOURCEs, or ``--sources FILE``: a fleet of cameras).

SIGINT (CTRL-C), SIGTERM and SIGHUP (a closed terminal, a service manager's reload) stop it the
same way: every processed frame is on disk, calibration.json holds the latest fusion, the figure
is drawn, each camera's summary line is printed as at the end of a run, one line says so, and the
exit status is 128 + the signal's number (130, 143, 129).

Standard error is a log: one line per event, each naming its camera (``fr track: NAME: ...``),
every URL's secrets hidden (:func:`fr_torch.redaction.redact_text`); the progress bar is drawn
only on a terminal (and never with ``--no-progress``).  ``--metrics [HOST:]PORT`` serves live
metrics for Prometheus (:mod:`fr_torch.video.metrics`).
"""
from __future__ import annotations

import argparse
import json
import signal
import sys
from pathlib import Path

from tqdm import tqdm

from fr_torch.cli.options import (
    add_estimator_arguments,
    device_policy,
    estimator_kwargs,
)
from fr_torch.core.settings.checks import finite_number, positive_int, positive_number
from fr_torch.errors import FRInputError
from fr_torch.redaction import redact_text
from fr_torch.runtime.estimator import FREstimator
from fr_torch.runtime.pipeline import CalibrationPool
from fr_torch.runtime.workers import interrupt_on_signals, settle_heap, start_worker_server, usable_cores
from fr_torch.video.fleet import FleetCamera, camera_specs, track_fleet
from fr_torch.video.fusion import OnlineCalibrator
from fr_torch.video.metrics import MetricsAddress, MetricsServer
from fr_torch.video.records import TrackOutput
from fr_torch.video.sources import Reconnect, Source, open_frames
from fr_torch.video.track import Tracking, track

#: Stops of ``fr track`` beyond the SIGINT and SIGTERM of every command.
TRACK_STOP_SIGNALS = tuple(s for s in (getattr(signal, "SIGHUP", None),) if s is not None)


def track_options(args) -> None:
    """``fr track`` options: memory >= 1 frame, change_k > 0, patience >= 1, timeouts > 0 (one-line errors)."""
    memory = finite_number(args.memory, "--memory")
    if memory < 1:
        raise FRInputError(f"--memory must be at least 1 frame, got {args.memory!r}")
    positive_number(args.change_k, "--change-k")
    positive_int(args.patience, "--patience")
    if args.max_frames is not None:
        positive_int(args.max_frames, "--max-frames")
    positive_number(args.stream_timeout, "--stream-timeout")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments of ``fr track``."""
    parser.add_argument("source", nargs="*",
                        help="video file, folder of frames (sorted by name), stream URL (rtsp://, http(s):// MJPEG "
                             "or HLS, anything OpenCV's FFmpeg opens), camera index or device (0, /dev/video0), or - "
                             "for images on stdin (ffmpeg -f image2pipe); several: a fleet, their frames searched "
                             "together (docs/track.md)")
    parser.add_argument("--sources", type=Path, default=None, metavar="FILE",
                        help="a fleet's cameras, one per line: [NAME] SOURCE [--fov-range MIN,MAX] [--every N] "
                             "[--focal PX] [--max-rate HZ] [--reconnect [SECONDS]] (# comments)")
    parser.add_argument("--out", type=Path, default=None,
                        help="output folder (default track_<source name>, for a fleet track_fleet with a folder "
                             "per camera); a second run with the same --out appends a new segment (a file "
                             "continues after its last recorded frame)")
    parser.add_argument("--json", default=None, metavar="PATH|-",
                        help="also write each frame's record as one JSON line to PATH as it comes (- = stdout)")
    parser.add_argument("--every", type=int, default=1, metavar="N", help="process every N-th frame (files)")
    parser.add_argument("--max-frames", type=int, default=None,
                        help="stop after this many processed frames (a fleet: each camera)")
    parser.add_argument("--batch-size", type=int, default=None,
                        help="frames searched together (default 8; 1 for one live source in real time; a fleet: "
                             "one frame per camera, at most this many, default every camera)")
    parser.add_argument("--max-rate", type=float, default=None, metavar="HZ",
                        help="a fleet: frames of each camera searched per second at most (default: as many as "
                             "its turns allow)")
    parser.add_argument("--workers", type=int, default=None, metavar="N",
                        help="CPU: calibrate frames in N single-threaded worker processes, in order; GPU: "
                             "N processes decode and detect frames ahead of the search (default 0: this "
                             "process; worth it for long videos on many cores). A fleet on a CPU: each turn's "
                             "frames are split over N worker processes (default: the usable cores, at most one "
                             "per camera; 0: searched in this process)")
    parser.add_argument("--no-progress", action="store_true",
                        help="no progress bar (it is drawn only when standard error is a terminal)")
    parser.add_argument("--metrics", default=None, metavar="[HOST:]PORT",
                        help="serve live metrics for Prometheus at http://HOST:PORT/metrics (HOST default "
                             "127.0.0.1: this machine only; 0.0.0.0 for every interface; PORT 0: any free port)")
    live = parser.add_argument_group("live sources")
    live.add_argument("--realtime", action=argparse.BooleanOptionalAction, default=None,
                      help="process the newest frame whenever the search is free and drop the frames that "
                           "arrived meanwhile (default for live sources); --no-realtime queues every frame")
    live.add_argument("--reconnect", nargs="?", const="inf", default=None, metavar="SECONDS",
                      help="reopen a stream or camera that drops, with back-off (0.5 s doubling to 30 s), "
                           "giving up after SECONDS without a frame (alone: never give up); one line when it "
                           "drops, one when it is back. A file or folder is read to its end. In a fleet: "
                           "every live camera's, unless its line in --sources gives its own")
    live.add_argument("--stream-timeout", type=float, default=5.0, metavar="SECONDS",
                      help="a stream's connection or next frame taking longer counts as a drop (default 5)")
    add_estimator_arguments(parser)  # the estimator options shared with fr calibrate and fr batch
    fusion = parser.add_argument_group("fusion")
    fusion.add_argument("--memory", type=float, default=30.0, help="fusion memory in accepted frames (forgetting)")
    fusion.add_argument("--change-k", type=float, default=3.0, help="camera-moved threshold in predicted sigmas")
    fusion.add_argument("--patience", type=int, default=2,
                        help="consecutive disagreeing reliable frames that mean the camera moved")
    fusion.add_argument("--no-reliability", action="store_true",
                        help="ignore the reliability stage: frames kept on the sanity checks alone, not the "
                             "reliable promise, and weighed the same (fR then skips the focal_profile_gap cue, a "
                             "quarter of its time)")


def run(args: argparse.Namespace) -> int:
    with interrupt_on_signals(TRACK_STOP_SIGNALS):
        return _run(args)


def _progress(args: argparse.Namespace, desc: str) -> tqdm:
    """The progress bar: drawn only on a terminal's stderr and without ``--no-progress``; its
    ``write`` prints a line either way (above the bar when there is one)."""
    return tqdm(desc=desc, unit="frame", file=sys.stderr, disable=args.no_progress or not sys.stderr.isatty())


def _say(bar: tqdm):
    """One line on stderr (above the progress bar), its URLs' secrets hidden."""
    return lambda message: bar.write(redact_text(message), file=sys.stderr)


def _metrics(args: argparse.Namespace, cameras, say) -> MetricsServer | None:
    """The metrics server of ``--metrics`` (None without it), and one line saying where."""
    if args.metrics is None:
        return None
    server = MetricsServer(args.metrics_address, lambda: cameras)
    say(f"fr track: metrics at {server.url}")
    return server


def _summaries(outputs, to_stderr: bool) -> int:
    """Print each output's summary line (stdout, or stderr when the records go to stdout); returns
    how many cameras have a calibration."""
    calibrated = 0
    for output in outputs:
        summary = json.loads(output.calibration_path.read_text())
        calibrated += summary["calibration"] is not None
        print(json.dumps(_summary_line(summary)), file=sys.stderr if to_stderr else sys.stdout, flush=True)
    return calibrated


def _run(args: argparse.Namespace) -> int:
    if args.every < 1 or (args.batch_size is not None and args.batch_size < 1):
        raise FRInputError("--every and --batch-size must be at least 1")
    if args.workers is not None and args.workers < 0:
        raise FRInputError("--workers must be 0 (this process) or more")
    if args.max_rate is not None:
        positive_number(args.max_rate, "--max-rate")
    track_options(args)
    args.metrics_address = None if args.metrics is None else MetricsAddress.parse(args.metrics)
    if not args.source and args.sources is None:
        raise FRInputError("give a SOURCE (or several), or --sources FILE")
    if len(args.source) > 1 or args.sources is not None:
        return _run_fleet(args)
    args.workers = args.workers or 0
    if args.max_rate is not None:
        raise FRInputError("--max-rate: for a fleet (several SOURCEs or --sources); one live source in real "
                           "time takes the newest frame whenever the search is free")
    source = Source.parse(args.source[0])
    reconnect = Reconnect.parse(args.reconnect)
    if reconnect.enabled and not source.live:
        raise FRInputError(f"--reconnect: {source} is a file, read to its end")
    policy = device_policy(args)
    if args.workers:
        start_worker_server()
    policy.apply_threads()
    estimator, model = _estimator(args)
    mode = estimator.mode
    tracker = _tracker(args)
    output = TrackOutput(args.out or Path(f"track_{source.label}"), source,
                         _settings(args, source, reconnect, estimator), str(mode), json_target=args.json,
                         reliability_model=model)
    _restore(tracker, output)
    bar = _progress(args, "fr track")
    output.log = say = _say(bar)
    if output.resumed:
        first = f"from frame {output.start_frame}" if not source.live else "frames counted from 0 again"
        say(f"fr track: {output.folder} holds earlier records: segment {output.segment}, {first}")
    stream = open_frames(source, args.every, output.start_frame, args.realtime, reconnect, args.stream_timeout, say)
    tracking = Tracking(stream, tracker, output, say, f"fr track: {source}")  # its lines name the source
    try:
        metrics = _metrics(args, [(source.label, tracking)], say)
    except FRInputError:
        output.close()
        raise
    try:
        track(stream, estimator, tracker, output, args.batch_size or 8, args.workers, args.max_frames, bar,
              f"fr track {source.label} ({mode})", tracking=tracking)
    except KeyboardInterrupt as stop:
        bar.close()
        _summaries([output], args.json == "-")
        stop.add_note(f"{output.processed} frames of this run are in {output.records_path}; the same command "
                      "again appends")
        raise
    finally:
        bar.close()
        if metrics is not None:
            metrics.close()
    if output.processed == 0 and not (output.resumed and not source.live):
        raise FRInputError(f"{source}: no frame could be read (all skipped)")
    calibrated = _summaries([output], args.json == "-")
    print(f"fr track: wrote {output.records_path}, {output.calibration_path}, {output.figure_path}", file=sys.stderr)
    return 0 if calibrated else 1


SUMMARY_KEYS = ("run", "segment", "frames_processed", "frames_accepted", "frames_dropped", "dropped_share",
                "restarts_at_frames")


def _summary_line(summary: dict) -> dict:
    """The end-of-run line of a calibration.json (a fleet camera's starts with its name)."""
    return {key: summary[key] for key in (("camera",) if "camera" in summary else ()) + SUMMARY_KEYS}


def _estimator(args: argparse.Namespace, fov_range: str | None = None) -> tuple[FREstimator, bool]:
    """The estimator of the options (``fov_range``: instead of ``--fov-range``) and whether its
    reliability model weighs the frames; one line on stderr when there is none."""
    kwargs = estimator_kwargs(argparse.Namespace(**{**vars(args), "fov_range": fov_range or args.fov_range}))
    estimator = FREstimator(**kwargs, reliability=None if args.no_reliability else "default")
    mode = estimator.mode
    scope_gap = estimator.reliability_scope_gap(detected=True) if estimator.reliability is not None else None
    if scope_gap is not None:  # its "not reliable" would reject every frame: track without it
        estimator = FREstimator(**kwargs, reliability=None)
        print(f"fr track: {scope_gap}: all reliable frames weigh the same", file=sys.stderr)
    model = estimator.reliability
    if model is None and not args.no_reliability and scope_gap is None:
        print(f"fr track: no reliability model for {mode}: all reliable frames weigh the same", file=sys.stderr)
    settle_heap()
    return estimator, model is not None


def _tracker(args: argparse.Namespace) -> OnlineCalibrator:
    return OnlineCalibrator(memory=args.memory, change_k=args.change_k, patience=args.patience)


def _settings(args: argparse.Namespace, source: Source, reconnect: Reconnect, estimator: FREstimator,
              **more) -> dict:
    """calibration.json's ``settings``: the run's (every, fusion, real time, reconnection) and the
    search's as ``fr calibrate`` would run it (ranges in degrees, lens model, known focal length)."""
    realtime = source.live and args.realtime is not False
    search = estimator.search
    return {"every": args.every, "memory": args.memory, "change_k": args.change_k, "patience": args.patience,
            "realtime": realtime, "reconnect_give_up_s": reconnect.give_up_s if reconnect.enabled and source.live
            else None, "fov_range_deg": [search.fov_range.min_deg, search.fov_range.max_deg],
            "pitch_range_deg": list(search.pitch_range_deg), "roll_range_deg": list(search.roll_range_deg),
            "distortion": search.distortion.mode.value, "focal_px": None, "fov_range": None, "max_rate": None,
            **more}


def _restore(tracker: OnlineCalibrator, output: TrackOutput) -> None:
    """Continue the fusion of a resumed output folder."""
    if output.checkpoint:
        try:
            tracker.restore(output.checkpoint)
        except ValueError as exc:
            raise FRInputError(f"{output.calibration_path}: {exc}; use another --out") from None


def _close(searches: dict) -> None:
    for search, _ in searches.values():
        if isinstance(search, CalibrationPool):
            search.close()


def _run_fleet(args: argparse.Namespace) -> int:
    """``fr track`` over several sources (:mod:`fr_torch.video.fleet`)."""
    if args.every != 1:
        raise FRInputError("--every: give it per camera in the sources file (SOURCE --every N)")
    specs = camera_specs(args.source, args.sources, args.max_rate, Reconnect.parse(args.reconnect))
    policy = device_policy(args)
    if args.workers and not policy.whole_image_workers:
        raise FRInputError(f"--workers: a fleet on {args.device} searches each turn's frames on the device")
    workers = 0 if not policy.whole_image_workers else \
        min(usable_cores(), len(specs)) if args.workers is None else args.workers
    if workers:
        start_worker_server()
    policy.apply_threads()
    estimators: dict = {}
    for spec in specs:
        if spec.fov_range not in estimators:
            estimators[spec.fov_range] = _estimator(args, spec.fov_range)
    # Searched in worker processes, not among the cameras' reader threads: those threads, each taking
    # this process's interpreter lock at every frame of its camera, slow a search in this process
    # several times over on a busy machine.
    searches = {key: (CalibrationPool(estimator, workers) if workers else estimator, model)
                for key, (estimator, model) in estimators.items()}
    folder = args.out or Path("track_fleet")
    bar = _progress(args, f"fr track ({len(specs)} cameras)")
    say = _say(bar)
    cameras = []
    metrics = None
    try:
        for spec in specs:
            estimator, model = searches[spec.fov_range]
            settings = _settings(args, spec.source, spec.reconnect, estimators[spec.fov_range][0], every=spec.every,
                                 fov_range=spec.fov_range, focal_px=spec.focal_px, max_rate=spec.max_rate)
            output = TrackOutput(folder / spec.name, spec.source, settings, str(estimator.mode), json_target=args.json,
                                 reliability_model=model, log=say, camera=spec.name)
            tracker = _tracker(args)
            _restore(tracker, output)
            if output.resumed:
                first = f"from frame {output.start_frame}" if not spec.source.live else "frames counted from 0 again"
                say(f"fr track: {spec.name}: {output.folder} holds earlier records: segment {output.segment}, {first}")
            stream = open_frames(spec.source, spec.every, output.start_frame, args.realtime, spec.reconnect,
                                 args.stream_timeout, say, name=spec.name)
            cameras.append(FleetCamera(spec, Tracking(stream, tracker, output, say, f"fr track: {spec.name}"),
                                       estimator))
        metrics = _metrics(args, [(camera.spec.name, camera.tracking) for camera in cameras], say)
    except FRInputError as exc:  # named by the camera it is about; nothing was read yet
        for camera in cameras:
            camera.tracking.output.close()
        bar.close()
        _close(searches)
        if len(cameras) < len(specs):
            raise FRInputError(f"{specs[len(cameras)].name}: {exc}") from None
        raise

    def plot(camera: FleetCamera) -> None:
        camera.tracking.output.plot(f"fr track {camera.spec.name} ({camera.estimator.mode})")

    outputs = [camera.tracking.output for camera in cameras]
    try:
        track_fleet(cameras, args.batch_size or len(cameras), args.max_frames, bar, say, plot=plot)
    except KeyboardInterrupt as stop:
        bar.close()
        _summaries(outputs, args.json == "-")
        processed = sum(output.processed for output in outputs)
        stop.add_note(f"{processed} frames of this run are in {folder}/*/frames.csv ({len(cameras)} cameras); "
                      "the same command again appends")
        raise
    finally:
        bar.close()
        _close(searches)
        if metrics is not None:
            metrics.close()
    calibrated = _summaries(outputs, args.json == "-")
    print(f"fr track: wrote {folder}/<camera>/: {', '.join(c.spec.name for c in cameras)}", file=sys.stderr)
    return 0 if calibrated == len(cameras) else 1
