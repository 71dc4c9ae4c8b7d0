"""The ``fr`` command line.

``fr calibrate IMAGE...`` is defined here; the other subcommands live in their own modules, each
exposing ``add_arguments(parser)`` and ``run(args) -> int``, and are imported only when used (so
``fr calibrate`` starts fast).  Errors in user input print one line and exit non-zero; set
``FR_DEBUG=1`` to see tracebacks.
"""
from __future__ import annotations

import argparse
import importlib
import json
import os
import sys
from pathlib import Path

# name -> (module, one-line help).  The module provides add_arguments(parser) and run(args).
SUBCOMMANDS: dict[str, tuple[str, str]] = {
    "calibrate": ("fr_torch.cli", "estimate focal length and rotation of images"),
    "eval": ("eval.run_eval", "evaluate methods on a dataset and write tables and figures"),
    "fit-likelihood": ("eval.fit_likelihood", "fit the deviation-measure likelihoods from labelled data"),
    "make-dataset": ("eval.make_dataset", "cut planar views with known camera from panoramas"),
    "train-reliability": ("fr_torch.reliability_train", "train the error predictor (reliability model)"),
    "track": ("fr_torch.track", "online recalibration from a video or a folder of frames"),
    "bench": ("eval.bench", "speed benchmark (latency, throughput, memory)"),
}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments of ``fr calibrate``."""
    parser.add_argument("images", nargs="+", help="image files (any format OpenCV reads)")
    parser.add_argument("--fast", action="store_true", help="Fast-fR: at most 10 refinement iterations")
    parser.add_argument("--focal", type=float, default=None, metavar="PX",
                        help="known focal length in pixels (then only the rotation is searched)")
    parser.add_argument("--pp", type=str, default=None, metavar="X,Y",
                        help="principal point in pixels (default: image centre)")
    parser.add_argument("--measure", choices=list("abcde"), default=None, help="deviation measure (default b)")
    parser.add_argument("--detector", default="lsd", help="line segment detector (default lsd)")
    parser.add_argument("--likelihood", default=None, metavar="NAME|JSON",
                        help="likelihood config: 'paper', 'fitted' or a JSON path (default configs/likelihood.json)")
    parser.add_argument("--hfov-range", default=None, metavar="MIN,MAX|paper",
                        help="search range of the field of view across the image's long side, degrees "
                             "(default 30,120; 'paper' = the paper's 50,130; narrow for zoomed-in PTZ or "
                             "traffic cameras)")
    parser.add_argument("--device", default="cpu", help="cpu or cuda")
    parser.add_argument("--batch-size", type=int, default=16, help="images searched together")
    parser.add_argument("--json", type=Path, default=None, metavar="OUT", help="also write a JSON list to OUT")
    parser.add_argument("--overlay", type=Path, default=None, metavar="DIR",
                        help="write <image>_fr.png overlays (segments by family, horizon) to DIR")
    parser.add_argument("--segments", action="store_true", help="include segments and labels in the JSON")


def run(args: argparse.Namespace) -> int:
    """``fr calibrate``: one JSON object per image on stdout; non-zero exit if any image failed."""
    from .estimator import FREstimator
    from .search import SearchConfig
    from .segments import FRInputError, load_image

    principal_point = None
    if args.pp:
        try:
            principal_point = tuple(float(v) for v in args.pp.split(","))
            assert len(principal_point) == 2
        except (ValueError, AssertionError):
            raise FRInputError(f"--pp expects X,Y in pixels, got {args.pp!r}") from None
    if args.focal is not None and not args.focal > 0:
        raise FRInputError(f"--focal must be a positive number of pixels, got {args.focal}")
    if args.batch_size < 1:
        raise FRInputError("--batch-size must be at least 1")
    search_config = None
    if args.hfov_range:
        search_config = SearchConfig.from_config().with_fov_range(args.hfov_range)  # FRInputError if invalid
    estimator = FREstimator(mode="fast" if args.fast else "fr", measure=args.measure, detector=args.detector,
                            likelihood=args.likelihood, device=args.device, search_config=search_config)
    reliability = _load_reliability()
    if args.overlay:
        args.overlay.mkdir(parents=True, exist_ok=True)
    everything, failures = [], 0
    paths = [str(p) for p in args.images]
    for start in range(0, len(paths), args.batch_size):
        chunk = paths[start:start + args.batch_size]
        results = estimator.calibrate_images(chunk, focal_px=args.focal, principal_point=principal_point)
        for path, result in zip(chunk, results):
            if reliability is not None and result.ok:
                reliability.annotate(result, mode=estimator.mode)
            record = result.to_json(include_segments=args.segments)
            everything.append(record)
            print(json.dumps(record), flush=True)
            if not result.ok:
                failures += 1
                print(f"fr: {path}: {result.reason}", file=sys.stderr)
            if args.overlay and result.width > 0:
                from .overlay import draw_overlay
                import cv2

                try:
                    image = load_image(path)
                except FRInputError:
                    continue
                target = args.overlay / f"{Path(path).stem}_fr.png"
                cv2.imwrite(str(target), draw_overlay(image, result))
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(everything, indent=1))
    return 1 if failures else 0


def _load_reliability():
    """The default reliability model, if one is installed (adds predicted errors)."""
    try:
        from .reliability import ReliabilityModel
    except ImportError:
        return None
    return ReliabilityModel.load_default()


def build_parser(command: str | None = None) -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="fr", description="fR: focal length and camera rotation from one image "
                                     "(Qian & Elder, ECCV 2022).")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name, (module, help_text) in SUBCOMMANDS.items():
        sp = sub.add_parser(name, help=help_text)
        if name == command:
            importlib.import_module(module).add_arguments(sp)
    return parser


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    command = argv[0] if argv and argv[0] in SUBCOMMANDS else None
    try:
        parser = build_parser(command)
    except ModuleNotFoundError as exc:
        print(f"fr: the '{command}' command is not available in this installation ({exc})", file=sys.stderr)
        return 2
    args = parser.parse_args(argv)
    if args.command is None:
        parser.print_help()
        return 2
    from .segments import FRInputError

    module = importlib.import_module(SUBCOMMANDS[args.command][0])
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


if __name__ == "__main__":
    sys.exit(main())
