"""The ``fr`` command line.

``fr calibrate IMAGE...`` is defined here; the other subcommands live in their own modules, each
exposing ``add_arguments(parser)`` and ``run(args) -> int``, and are imported only when used (so
``fr calibrate`` starts fast).  The core's commands are :data:`SUBCOMMANDS`; the evaluation harness
adds its own through the ``fr_torch.commands`` entry-point group (:mod:`fr_torch.registry`).  Errors
in user input print one line and exit non-zero; set ``FR_DEBUG=1`` to see tracebacks.
"""
from __future__ import annotations

import argparse
import importlib
import os
import sys
from pathlib import Path

# name -> (module, one-line help).  The module provides add_arguments(parser) and run(args).
SUBCOMMANDS: dict[str, tuple[str, str]] = {
    "calibrate": ("fr_torch.cli", "estimate focal length and rotation of images"),
    "track": ("fr_torch.track", "online recalibration from a video or a folder of frames"),
    "batch": ("fr_torch.batch", "calibrate many images into a resumable Parquet dataset (local or Ray)"),
}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments of ``fr calibrate``."""
    from .options import add_estimator_arguments

    parser.add_argument("images", nargs="+", help="image files (any format OpenCV reads)")
    add_estimator_arguments(parser)
    parser.add_argument("--focal", type=float, default=None, metavar="PX",
                        help="known focal length in pixels (then only the rotation is searched)")
    parser.add_argument("--pp", type=str, default=None, metavar="X,Y",
                        help="principal point in pixels (default: image centre)")
    parser.add_argument("--batch-size", type=int, default=None,
                        help="images searched together (default 16 on a CPU, 256 on a GPU)")
    parser.add_argument("--workers", type=int, default=None, metavar="N",
                        help="worker processes (0 = in-process). CPU: each decodes, detects and searches its "
                             "share of the images (default: one per core, up to 8, for 64+ images); GPU: they "
                             "decode + detect ahead of the search (default: cores - 1, up to 16; 0 on 1-2 cores)")
    parser.add_argument("--json", type=Path, default=None, metavar="OUT", help="also write a JSON list to OUT")
    parser.add_argument("--overlay", type=Path, default=None, metavar="DIR",
                        help="write <image>_fr.png overlays (segments by family, horizon) to DIR")
    parser.add_argument("--segments", action="store_true", help="include segments and labels in the JSON")
    parser.add_argument("--no-reliability", action="store_true",
                        help="no predicted errors and reliable = the sanity checks only (fR then skips the "
                             "focal_profile_gap cue, a quarter of its time per photo)")
    parser.add_argument("--no-progress", action="store_true",
                        help="no progress bar (shown on a terminal's stderr when stdout goes to a file or pipe)")
    from .shared_focal_cli import add_arguments as add_focal_arguments

    add_focal_arguments(parser)


def run(args: argparse.Namespace) -> int:
    """``fr calibrate``: one JSON object per image on stdout; non-zero exit if any image failed."""
    paths = [str(p) for p in args.images]
    from .workers import default_batch_size, default_workers, fit_threads_to_cores, start_worker_server

    workers = default_workers(len(paths), args.device) if args.workers is None else args.workers
    workers = min(workers, max(0, len(paths) - 1))  # a pool does not pay for a single image
    if workers > 0:  # the workers' server loads the library while this process does the same
        start_worker_server()
    from .estimator import FREstimator
    from .options import camera_options, estimator_kwargs
    from .segments import FRInputError

    from . import validate

    fit_threads_to_cores()
    if args.workers is not None and args.workers < 0:
        raise FRInputError("--workers must be 0 (in-process) or more")
    focal_px, principal_point = camera_options(args)  # per image: within a 1-179 deg field of view
    batch_size = default_batch_size(args.device) if args.batch_size is None else args.batch_size
    if batch_size < 1:
        raise FRInputError("--batch-size must be at least 1")
    estimator = FREstimator(**estimator_kwargs(args), reliability=None if args.no_reliability else "default")
    if args.overlay:
        validate.output_folder(args.overlay, "--overlay")
    if args.json and args.json.is_dir():
        raise FRInputError(f"--json {args.json}: is a folder, not a file")
    everything, failures = [], 0
    from tqdm import tqdm

    from .pipeline import calibrate_paths

    # A bar when the JSON lines go to a file or pipe and stderr is a terminal (else they show progress).
    show_bar = not args.no_progress and len(paths) > 1 and sys.stderr.isatty() and not sys.stdout.isatty()
    bar = tqdm(total=len(paths), unit="img", desc="fr calibrate", disable=not show_bar, file=sys.stderr)

    def emit(path, result, extra=None):
        nonlocal failures
        record = validate.json_safe(dict(result.to_json(include_segments=args.segments), **(extra or {})))
        everything.append(record)
        print(validate.dumps(record), flush=True)
        if not result.ok:
            failures += 1
            reason = result.reason  # image_io reasons already start with the path
            bar.write(f"fr: {reason}" if reason.startswith(f"{path}:") else f"fr: {path}: {reason}",
                      file=sys.stderr)
        if args.overlay and result.width > 0:
            from .overlay import write_overlay

            try:
                write_overlay(path, result, args.overlay)
            except FRInputError as exc:
                bar.write(f"fr: {exc}", file=sys.stderr)
        bar.update(1)

    try:
        if args.shared_focal or args.focal_prior:
            from .shared_focal_cli import run as run_focal_options

            run_focal_options(args, estimator, paths, batch_size, workers, principal_point, emit)
        else:
            for chunk, results in calibrate_paths(estimator, paths, batch_size, workers, focal_px,
                                                  principal_point):
                for path, result in zip(chunk, results):
                    emit(path, result)
    finally:  # the JSON holds every result so far, written atomically (never a truncated file)
        bar.close()
        if args.json:
            validate.write_text_atomic(args.json, validate.dumps(everything, indent=1))
    return 1 if failures else 0


def all_subcommands(extra: dict[str, tuple[str, str]] | None = None) -> dict[str, tuple[str, str]]:
    """The core's commands, then those declared in the ``fr_torch.commands`` entry-point group
    (value: an object ``(module, one-line help)``, see :mod:`fr_torch.registry`)."""
    from .registry import entry_points, load_object

    commands = dict(SUBCOMMANDS)
    for name, target in entry_points("fr_torch.commands").items():
        try:
            commands.setdefault(name, tuple(load_object(target)))
        except (ImportError, AttributeError) as exc:  # a plugin whose package is broken or partly installed
            commands.setdefault(name, (target.partition(":")[0], f"(unavailable: {exc})"))
    commands.update(extra or {})
    return commands


def build_parser(command: str | None = None, commands: dict[str, tuple[str, str]] | None = None
                 ) -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="fr", description="fR: focal length and camera rotation from one image "
                                     "(Qian & Elder, ECCV 2022).")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name, (module, help_text) in (commands or SUBCOMMANDS).items():
        sp = sub.add_parser(name, help=help_text)
        if name == command:
            importlib.import_module(module).add_arguments(sp)
    return parser


def main(argv: list[str] | None = None, extra_commands: dict[str, tuple[str, str]] | None = None) -> int:
    from .options import attach_range_values

    argv = attach_range_values(list(sys.argv[1:] if argv is None else argv))
    commands = all_subcommands(extra_commands)
    if argv and not argv[0].startswith("-") and argv[0] not in commands:
        print(f"fr: unknown command {argv[0]!r} (commands: {', '.join(commands)}; the evaluation commands "
              "come with a pip-installed checkout)", file=sys.stderr)
        return 2
    command = argv[0] if argv else None
    try:
        parser = build_parser(command, commands)
    except ModuleNotFoundError as exc:
        print(f"fr: the '{command}' command is not available in this installation ({exc})", file=sys.stderr)
        return 2
    args = parser.parse_args(argv)
    if args.command is None:
        parser.print_help()
        return 2
    from .segments import FRInputError

    module = importlib.import_module(commands[args.command][0])
    try:
        return int(module.run(args) or 0)
    except (FRInputError, FileNotFoundError, ValueError) as exc:
        if os.environ.get("FR_DEBUG"):
            raise
        print(f"fr {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130
    except BrokenPipeError:  # output piped into `head` & co.: stop quietly, as Unix tools do
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 141
    except (OSError, RuntimeError, TypeError, KeyError, AttributeError, ZeroDivisionError, OverflowError) as exc:
        if os.environ.get("FR_DEBUG"):  # last guard: one line, never a traceback (FR_DEBUG=1 shows it)
            raise
        print(f"fr {args.command}: error: {type(exc).__name__}: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
