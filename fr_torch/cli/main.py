"""The ``fr`` command line.

Each subcommand lives in its own module exposing ``add_arguments(parser)`` and
``run(args) -> int``, imported only when used (so ``fr calibrate`` starts fast); the option groups
they share are :mod:`fr_torch.cli.options`.  The core's commands are :data:`SUBCOMMANDS`; the evaluation harness
adds its own through the ``fr_torch.commands`` entry-point group (:mod:`fr_torch.registry`).  Errors
in user input print one line and exit non-zero; set ``FR_DEBUG=1`` to see tracebacks.

CTRL-C (SIGINT) and SIGTERM stop every command the same way: the command's clean-up runs (finished
output kept, worker processes stopped), one line on stderr says so (with what a command adds as a
note to the exception, e.g. ``fr batch``'s resume hint), and the exit status is 128 + the signal's
number: 130 and 143 (:func:`fr_torch.runtime.workers.interrupt_on_signals`).
"""
from __future__ import annotations

import argparse
import importlib
import os
import signal
import sys

from fr_torch.errors import FRInputError
from fr_torch.redaction import redact_text
from fr_torch.registry import entry_points, load_object
from fr_torch.runtime.workers import interrupt_exit_status, interrupt_on_signals

# name -> (module, one-line help).  The module provides add_arguments(parser) and run(args).
SUBCOMMANDS: dict[str, tuple[str, str]] = {
    "calibrate": ("fr_torch.cli.calibrate", "estimate focal length and rotation of images"),
    "track": ("fr_torch.cli.track", "online recalibration from a video or a folder of frames"),
    "batch": ("fr_torch.cli.batch", "calibrate many images into a resumable Parquet dataset (local or Ray)"),
    "undistort": ("fr_torch.cli.undistort", "straighten wide-angle photos (radial distortion estimated) and give their K"),
}


def all_subcommands(extra: dict[str, tuple[str, str]] | None = None) -> dict[str, tuple[str, str]]:
    """The core's commands, then those declared in the ``fr_torch.commands`` entry-point group
    (value: an object ``(module, one-line help)``, see :mod:`fr_torch.registry`)."""

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
    parser.command_parsers = {}  # name -> its parser: a command's usage errors show its own usage
    for name, (module, help_text) in (commands or SUBCOMMANDS).items():
        sp = parser.command_parsers[name] = sub.add_parser(name, help=help_text)
        if name == command:
            importlib.import_module(module).add_arguments(sp)
    return parser


def main(argv: list[str] | None = None, extra_commands: dict[str, tuple[str, str]] | None = None) -> int:
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
    args, unknown = parser.parse_known_args(argv)
    if unknown:  # argparse would show the top-level usage; the command's is the one that helps
        parser.command_parsers.get(args.command, parser).error(f"unrecognized arguments: {' '.join(unknown)}")
    if args.command is None:
        parser.print_help()
        return 2

    module = importlib.import_module(commands[args.command][0])
    try:
        with interrupt_on_signals():
            return int(module.run(args) or 0)
    except (FRInputError, FileNotFoundError, ValueError) as exc:
        if os.environ.get("FR_DEBUG"):
            raise
        print(redact_text(f"fr {args.command}: error: {exc}"), file=sys.stderr)
        return 2
    except KeyboardInterrupt as interrupt:
        print(redact_text(stopped_line(args.command, interrupt)), file=sys.stderr)
        return interrupt_exit_status(interrupt)
    except BrokenPipeError:  # output piped into `head` & co.: stop quietly, as Unix tools do
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 141
    except (OSError, RuntimeError, TypeError, KeyError, AttributeError, ZeroDivisionError, OverflowError) as exc:
        if os.environ.get("FR_DEBUG"):  # last guard: one line, never a traceback (FR_DEBUG=1 shows it)
            raise
        print(redact_text(f"fr {args.command}: error: {type(exc).__name__}: {exc}"), file=sys.stderr)
        return 2


def stopped_line(command: str, interrupt: KeyboardInterrupt) -> str:
    """The one line a command stopped by ``interrupt`` prints: the signal (SIGINT for CTRL-C), then
    the notes the command added to it (``BaseException.add_note``)."""
    name = signal.Signals(getattr(interrupt, "signum", signal.SIGINT)).name
    notes = "; ".join(note for note in getattr(interrupt, "__notes__", ()) if note)
    return f"fr {command}: stopped by {name}" + (f"; {notes}" if notes else "")


#: Options whose MIN,MAX value may start with a minus sign.
RANGE_OPTIONS = ("--fov-range", "--hfov-range", "--pitch-range", "--roll-range")


def attach_range_values(argv: list[str]) -> list[str]:
    """``["--pitch-range", "-70,20"]`` -> ``["--pitch-range=-70,20"]`` for :data:`RANGE_OPTIONS`:
    argparse reads a separate value that starts with ``-`` (and is not a plain number) as an option."""
    out: list[str] = []
    pending = False
    for arg in argv:
        if pending and arg[:1] == "-" and (arg[1:2].isdigit() or arg[1:2] == "."):
            out[-1] = f"{out[-1]}={arg}"
        else:
            out.append(arg)
        pending = arg in RANGE_OPTIONS
    return out
