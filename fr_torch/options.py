"""The estimator options shared by every front end: ``fr calibrate``, ``fr track`` and the
``fr`` / ``fast-fr`` Calibrators (:mod:`fr_torch.methods`).

One definition of the command-line arguments (:func:`add_estimator_arguments`) and one conversion
to :class:`fr_torch.estimator.FREstimator` keyword arguments (:func:`estimator_kwargs`); the
horizontal-FOV search range is turned into a :class:`~fr_torch.search.SearchConfig` by
:func:`hfov_search_config` for all of them.
"""
from __future__ import annotations

import argparse
from typing import Any

MEASURE_CHOICES = tuple("abcde")


def add_estimator_arguments(parser: argparse.ArgumentParser) -> None:
    """``--fast``, ``--measure``, ``--detector``, ``--likelihood``, ``--hfov-range``, ``--pitch-range``,
    ``--roll-range``, ``--device``, ``--compile``."""
    parser.add_argument("--fast", action="store_true", help="Fast-fR: at most 10 refinement iterations")
    parser.add_argument("--measure", choices=MEASURE_CHOICES, default=None, help="deviation measure (default b)")
    parser.add_argument("--detector", default="lsd", help="line segment detector (default lsd)")
    parser.add_argument("--likelihood", default=None, metavar="NAME|JSON",
                        help="likelihood config: 'paper', 'fitted' or a JSON path (default configs/likelihood.json)")
    parser.add_argument("--hfov-range", default=None, metavar="MIN,MAX|paper",
                        help="search range of the field of view across the image's long side, degrees "
                             "(default 30,120; 'paper' = the paper's 50,130; narrow for zoomed-in PTZ or "
                             "traffic cameras)")
    parser.add_argument("--pitch-range", default=None, metavar="MIN,MAX",
                        help="search range of the camera's pitch, degrees (default -35,35; widen for cameras "
                             "that look steeply down, e.g. -70,20 for traffic cameras: a coarser grid, so level "
                             "views lose some accuracy; a pitch found at the range's edge is marked unreliable)")
    parser.add_argument("--roll-range", default=None, metavar="MIN,MAX",
                        help="search range of the camera's roll, degrees (default -15,15; an estimate at the "
                             "edge is marked unreliable)")
    parser.add_argument("--device", default="cpu", help="cpu or cuda")
    parser.add_argument("--compile", action="store_true",
                        help="run the search with kernels compiled by torch.compile (needs a C++ compiler on CPU, "
                             "Triton on CUDA; 10-25 s of compilation per process, then faster: for long batch "
                             "jobs and video; falls back with a warning where it cannot compile)")


#: Options whose MIN,MAX value may start with a minus sign.
RANGE_OPTIONS = ("--hfov-range", "--pitch-range", "--roll-range")


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


def hfov_search_config(hfov_min=None, hfov_max=None, base=None):
    """The search configuration (``base``, default ``configs/search.json``) with the horizontal-FOV
    range replaced where ``hfov_min`` / ``hfov_max`` (degrees; numbers or strings) are given.
    Raises FRInputError (a ValueError) for a range outside ``1 <= min < max <= 179``."""
    from .search import SearchConfig

    base = base or SearchConfig.from_config()
    if hfov_min is None and hfov_max is None:
        return base
    low, high = base.hfov_range_deg
    return base.with_fov_range((low if hfov_min is None else hfov_min, high if hfov_max is None else hfov_max))


def camera_options(args: argparse.Namespace) -> tuple[float | None, tuple[float, float] | None]:
    """The known focal length (``--focal``, pixels, > 0) and principal point (``--pp X,Y``, pixels,
    finite) for all images of a command, or None; FRInputError (one line) when malformed.  Whether
    they fit each image is checked per image (:func:`fr_torch.validate.check_camera`)."""
    from . import validate
    from .segments import FRInputError

    principal_point = None
    if getattr(args, "pp", None):
        parts = args.pp.split(",")
        if len(parts) != 2:
            raise FRInputError(f"--pp expects X,Y in pixels, got {args.pp!r}")
        principal_point = tuple(validate.finite_number(v, "--pp") for v in parts)
    focal = getattr(args, "focal", None)
    if focal is not None:
        focal = validate.positive_number(focal, "--focal")
    return focal, principal_point


def estimator_kwargs(args: argparse.Namespace) -> dict[str, Any]:
    """FREstimator keyword arguments from the options of :func:`add_estimator_arguments`."""
    from .segments import FRInputError

    kwargs: dict[str, Any] = dict(mode="fast" if args.fast else "fr", measure=args.measure, detector=args.detector,
                                  likelihood=args.likelihood, device=args.device)
    compile_search = bool(getattr(args, "compile", False))  # front ends without --compile: off
    angle_ranges = {name: getattr(args, f"{name}_range", None) for name in ("pitch", "roll")}
    if args.hfov_range or compile_search or any(angle_ranges.values()):
        from .search import SearchConfig

        config = SearchConfig.from_config(**({"compile_search": True} if compile_search else {}))
        if args.hfov_range:  # a name ('paper') or MIN,MAX; FRInputError if invalid
            try:
                config = config.with_fov_range(args.hfov_range)
            except ValueError as exc:
                raise FRInputError(f"--hfov-range: {exc}") from None
        for name, value in angle_ranges.items():
            if value:
                try:
                    config = config.with_angle_range(name, value)
                except ValueError as exc:
                    raise FRInputError(f"--{name}-range: {exc}") from None
        kwargs["search_config"] = config
    return kwargs
