"""``fr calibrate IMAGE...``: estimate focal length and rotation of images, one JSON object each."""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

from tqdm import tqdm

from fr_torch.cli.focal import add_arguments as add_focal_arguments
from fr_torch.cli.focal import run as run_focal_options
from fr_torch.cli.options import (
    add_camera_arguments,
    add_device_arguments,
    add_estimator_arguments,
    camera_options,
    device_policy,
    estimator_kwargs,
)
from fr_torch.core.exports import ColmapModel, colmap_cameras_txt
from fr_torch.errors import FRInputError
from fr_torch.images.overlay import write_overlay
from fr_torch.output import dumps, json_safe, output_folder, write_text_atomic
from fr_torch.redaction import redact_text
from fr_torch.runtime.device_pipeline import device_path_gap
from fr_torch.runtime.estimator import FREstimator
from fr_torch.runtime.pipeline import calibrate_paths
from fr_torch.runtime.schema import result_record
from fr_torch.runtime.workers import settle_heap, start_worker_server


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments of ``fr calibrate``."""
    parser.add_argument("images", nargs="+", help="image files (any format OpenCV reads)")
    add_estimator_arguments(parser, device=False)
    add_device_arguments(
        parser, batch_help="images searched together (default 16 on a CPU, 256 on a GPU)",
        workers_help="worker processes (0 = in-process). CPU: each decodes, detects and searches its share of "
                     "the images (default: one per core, up to 8, for 64+ images); GPU with --decode host: they decode + "
                     "detect ahead of the search (default: cores - 1, up to 16; 0 on 1-2 cores)")
    add_camera_arguments(parser)
    output = parser.add_argument_group("output")
    output.add_argument("--json", type=Path, default=None, metavar="OUT", help="also write a JSON list to OUT")
    output.add_argument("--overlay", type=Path, default=None, metavar="DIR",
                        help="write <image>_fr.png overlays (segments by family, horizon) to DIR")
    output.add_argument("--segments", action="store_true", help="include segments and labels in the JSON")
    output.add_argument("--format", choices=FORMATS, default="json",
                        help="what stdout holds: json (default: one fR record per image), opencv (one JSON object "
                             "per image that cv2.FileStorage reads: camera_matrix, distortion_coefficients k1 k2 "
                             "[k3] fitted to the division model, the fit's residual in pixels) or colmap (a "
                             "cameras.txt, one camera per image: SIMPLE_PINHOLE, or for a division estimate "
                             "--colmap-model's); --json still writes the fR records")
    output.add_argument("--colmap-model", choices=tuple(m.value for m in ColmapModel), default=None,
                        help="with --format colmap, a division estimate as: division (default: SIMPLE_DIVISION, "
                             "the same model exactly; COLMAP >= 4.0) or radial (RADIAL k1 k2 fitted to it, for "
                             "older COLMAP; the fit's residual in pixels on the camera's comment line)")
    output.add_argument("--no-reliability", action="store_true",
                        help="no predicted errors or error bounds, reliable = the sanity checks only (fR then "
                             "skips the focal_profile_gap cue, a quarter of its time per photo, and both modes the "
                             "bounds' spread cues)")
    output.add_argument("--no-progress", action="store_true",
                        help="no progress bar (shown on a terminal's stderr when stdout goes to a file or pipe)")
    add_focal_arguments(parser)


FORMATS = ("json", "opencv", "colmap")


def opencv_record(path, result) -> dict:
    """One image's ``--format opencv`` object: the image, whether the estimate is reliable (and
    why not), then :meth:`~fr_torch.core.result.CalibrationResult.opencv`'s nodes."""
    head = {"image": str(path), "ok": bool(result.ok), "reliable": bool(result.reliable), "reason": result.reason}
    return dict(head, **result.opencv()) if result.ok else head


def run(args: argparse.Namespace) -> int:
    """``fr calibrate``: one JSON object per image on stdout; non-zero exit if any image failed."""
    paths = [str(p) for p in args.images]
    if args.colmap_model is not None and args.format != "colmap":
        raise FRInputError("--colmap-model applies to --format colmap only")
    colmap_model = ColmapModel.parse(args.colmap_model or ColmapModel.DIVISION)
    policy = device_policy(args)
    policy.apply_threads()
    focal_px, principal_point = camera_options(args)  # per image: within a 1-179 deg field of view
    batch_size = policy.default_batch_size if args.batch_size is None else args.batch_size
    estimator = FREstimator(**estimator_kwargs(args), reliability=None if args.no_reliability else "default")
    settle_heap()
    if device_path_gap(estimator) is None:  # decoded and detected on the GPU: no host workers
        workers = 0
    else:
        workers = policy.default_workers(len(paths)) if args.workers is None else args.workers
        workers = min(workers, max(0, len(paths) - 1))  # a pool does not pay for a single image
    if workers > 0:
        start_worker_server()
    if args.overlay:
        output_folder(args.overlay, "--overlay")
    if args.json and args.json.is_dir():
        raise FRInputError(f"--json {args.json}: is a folder, not a file")
    everything, failures = [], 0
    # A bar when the JSON lines go to a file or pipe and stderr is a terminal (else they show progress).
    show_bar = not args.no_progress and len(paths) > 1 and sys.stderr.isatty() and not sys.stdout.isatty()
    bar = tqdm(total=len(paths), unit="img", desc="fr calibrate", disable=not show_bar, file=sys.stderr)

    colmap_lines = []

    def emit(path, result, extra=None):
        """Write one image's overlay, then print (and keep) its record and report a failure: the
        files come first, so a reader that closes the pipe early (``| head``) loses no overlay."""
        nonlocal failures
        if args.overlay and result.width > 0:
            try:
                write_overlay(path, result, args.overlay)
            except FRInputError as exc:
                bar.write(redact_text(f"fr: {exc}"), file=sys.stderr)
        record = json_safe(dict(result_record(result, include_segments=args.segments), **(extra or {})))
        everything.append(record)
        if args.format == "json":
            print(dumps(record), flush=True)
        elif args.format == "opencv":
            print(dumps(json_safe(opencv_record(path, result))), flush=True)
        elif result.ok:
            colmap_lines.append((redact_text(str(path)), result.width, result.height, *result.colmap(colmap_model)))
        else:
            colmap_lines.append((redact_text(str(path)), redact_text(result.reason)))
        if not result.ok:
            failures += 1
            reason = result.reason  # image reading reasons already start with the path
            bar.write(redact_text(f"fr: {reason}" if reason.startswith(f"{path}:") else f"fr: {path}: {reason}"),
                      file=sys.stderr)
        bar.update(1)

    try:
        if args.shared_focal or args.focal_prior:
            run_focal_options(args, estimator, paths, batch_size, workers, principal_point, emit)
        else:
            for chunk, results in calibrate_paths(estimator, paths, batch_size, workers, focal_px,
                                                  principal_point):
                for path, result in zip(chunk, results):
                    emit(path, result)
    finally:  # the JSON holds every result so far, written atomically (never a truncated file)
        bar.close()
        if args.format == "colmap":
            sys.stdout.write(colmap_cameras_txt(colmap_lines))
        if args.json:
            write_text_atomic(args.json, dumps(everything, indent=1))
    return 1 if failures else 0
