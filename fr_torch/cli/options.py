"""The option groups the commands share, each parsed once into the library's types.

* :func:`add_estimator_arguments` -> :func:`estimator_kwargs`: the method (``--fast``,
  ``--measure``, ``--detector``, ``--likelihood``), the search box (``--fov-range``,
  ``--pitch-range``, ``--roll-range``) and the lens model (``--distortion``, ``--k``) as one
  :class:`~fr_torch.core.settings.config.SearchConfig`, and ``--atlanta`` as one
  :class:`~fr_torch.core.geometry.vanishing.AtlantaConfig`.
* :func:`add_device_arguments` -> :func:`device_policy`: ``--device`` (and, where the command
  takes them, ``--workers`` / ``--batch-size``) as one
  :class:`~fr_torch.runtime.device.DevicePolicy`.
* :func:`add_camera_arguments` -> :func:`camera_options`: ``--focal`` / ``--pp``.

``fr calibrate``, ``fr track``, ``fr batch`` and the evaluation harness's commands use the same
groups, so an option means the same thing everywhere.
"""
from __future__ import annotations

import argparse
from typing import Any

from fr_torch.core.geometry.vanishing import AtlantaConfig
from fr_torch.core.settings.checks import finite_number, positive_number
from fr_torch.core.settings.config import Mode, SearchConfig
from fr_torch.core.settings.distortion import DistortionMode
from fr_torch.errors import FRInputError
from fr_torch.images.io import WORKING_LONG_SIDE, parse_working_long_side
from fr_torch.runtime.device import DECODE_CHOICES, DevicePolicy

MEASURE_CHOICES = tuple("abcde")


def add_estimator_arguments(parser: argparse.ArgumentParser, device: bool = True) -> None:
    """``--fast``, ``--measure``, ``--detector``, ``--likelihood``, ``--fov-range``,
    ``--pitch-range``, ``--roll-range``, ``--atlanta`` and (``device``) ``--device``; the removed
    ``--compile`` and ``--fit`` are still parsed, to fail with a one-line reason
    (:data:`~fr_torch.core.settings.config.REMOVED_SETTINGS`)."""
    group = parser.add_argument_group("estimator")
    group.add_argument("--fast", action="store_true", help="Fast-fR: 10 refinement iterations")
    group.add_argument("--measure", choices=MEASURE_CHOICES, default=None, help="deviation measure (default b)")
    group.add_argument("--detector", default=None,
                       help="line segment detector (default: lsd on a CPU, torch-lines on a GPU)")
    group.add_argument("--likelihood", default=None, metavar="NAME|JSON",
                       help="likelihood config: 'paper', 'fitted' or a JSON path (default configs/likelihood.json)")
    add_fov_range_argument(group)
    group.add_argument("--pitch-range", default=None, metavar="MIN,MAX",
                       help="search range of the camera's pitch, degrees (default -35,35; widen for cameras "
                            "that look steeply down, e.g. -70,20 for traffic cameras: a coarser grid, so level "
                            "views lose some accuracy; a pitch found at the range's edge is marked unreliable)")
    group.add_argument("--roll-range", default=None, metavar="MIN,MAX",
                       help="search range of the camera's roll, degrees (default -15,15; an estimate at the "
                            "edge is marked unreliable)")
    group.add_argument("--distortion", choices=tuple(m.value for m in DistortionMode), default=None,
                       help="lens model: pinhole (default), division (radial distortion k estimated with f and R: "
                            "wide-angle, CCTV, action cameras; docs/distortion.md) or auto (division where the lines "
                            "bend, else pinhole)")
    group.add_argument("--k", type=float, default=None, metavar="K",
                       help="known radial distortion k of the division model (normalised by half the image diagonal; "
                            "negative = barrel); implies --distortion division unless auto is given")
    group.add_argument("--families", default=None, metavar="auto|off|SETTINGS",
                       help="extra horizontal families inside the likelihood (opt-in): after the Manhattan fit, up "
                            "to two more horizontal families with vanishing points on the horizon are refitted with f "
                            "and R, their count per photo chosen by a held-out likelihood of its own segments; 'auto' or "
                            "key=value pairs joined by ':' (max_extra, prior, min_support, exclusion_deg, window_deg); "
                            "the extra vanishing points join ranked_vanishing_points")
    group.add_argument("--working-long-side", default=None, metavar="PX|input",
                       help=f"detect the lines on a copy of each image whose long side is at most PX pixels "
                            f"(default {WORKING_LONG_SIDE}; 'input' = the input's own resolution, slower for large "
                            f"photos); results are always in the input's pixels")
    group.add_argument("--compile", action="store_true", help=argparse.SUPPRESS)  # removed: one-line error
    group.add_argument("--fit", default=None, help=argparse.SUPPRESS)  # removed: one-line error
    group.add_argument("--atlanta", nargs="?", const="on", default=None, metavar="SETTINGS",
                       help="also find extra horizontal vanishing points at free azimuths (Atlanta world) and rank "
                            "them with the Manhattan three in ranked_vanishing_points; f and R do not change. "
                            "SETTINGS: 'on' (default when the option is given) or key=value pairs joined by ':' "
                            "(max_extra, prior, min_support, exclusion_deg, step_deg; docs/vp.md)")
    if device:
        add_device_arguments(parser)


def add_device_arguments(parser: argparse.ArgumentParser, workers_help: str | None = None,
                         batch_help: str | None = None, default: str = "cpu", device_help: str | None = None) -> None:
    """``--device`` (default ``default``) and, when their help text is given, ``--workers`` /
    ``--batch-size``."""
    group = parser.add_argument_group("device")
    group.add_argument("--device", default=default, help=(device_help or f"cpu, cuda or cuda:N (default {default})")
                       + "; CPU threads per search: $FR_THREADS = auto (default: the cores other processes leave "
                         "free), torch or N (docs/cpu-threads.md)")
    if workers_help:
        group.add_argument("--workers", type=int, default=None, metavar="N", help=workers_help)
        group.add_argument("--decode", choices=DECODE_CHOICES, default="auto",
                           help="on a GPU, where image files are decoded and detected: auto (default: on the "
                                "device when the detector detects batches, as torch-lines does, and torchvision "
                                "loads), device, or host (worker processes)")
    if batch_help:
        group.add_argument("--batch-size", type=int, default=None, metavar="N", help=batch_help)


def add_fov_range_argument(parser, help_text: str | None = None) -> None:
    """``--fov-range`` (alias ``--hfov-range``): the FOV search range across the long side."""
    parser.add_argument("--fov-range", "--hfov-range", dest="fov_range", default=None, metavar="MIN,MAX|paper",
                        help=help_text or "search range of the field of view across the image's long side, degrees "
                                          "(default 30,120; 'paper' = the paper's 50,130; narrow for zoomed-in PTZ "
                                          "or traffic cameras)")


def add_camera_arguments(parser: argparse.ArgumentParser, focal_help: str | None = None) -> None:
    """``--focal`` (known focal length) and ``--pp`` (principal point)."""
    group = parser.add_argument_group("camera")
    group.add_argument("--focal", type=float, default=None, metavar="PX",
                       help=focal_help or "known focal length in pixels (then only the rotation is searched)")
    group.add_argument("--pp", type=str, default=None, metavar="X,Y",
                       help="principal point in pixels (default: image centre)")


def camera_options(args: argparse.Namespace) -> tuple[float | None, tuple[float, float] | None]:
    """The known focal length (``--focal``, pixels, > 0) and principal point (``--pp X,Y``, pixels,
    finite) for all images of a command, or None; FRInputError (one line) when malformed.  Whether
    they fit each image is checked per image (:func:`fr_torch.core.settings.checks.check_camera`)."""
    principal_point = None
    if getattr(args, "pp", None):
        parts = args.pp.split(",")
        if len(parts) != 2:
            raise FRInputError(f"--pp expects X,Y in pixels, got {args.pp!r}")
        principal_point = tuple(finite_number(v, "--pp") for v in parts)
    focal = getattr(args, "focal", None)
    if focal is not None:
        focal = positive_number(focal, "--focal")
    return focal, principal_point


def search_config(args: argparse.Namespace) -> SearchConfig:
    """The :class:`SearchConfig` of ``--fov-range``, ``--pitch-range``, ``--roll-range`` and ``--families``
    over the shipped defaults; FRInputError (one line) naming a malformed option, or saying what
    replaced the removed ``--compile`` or ``--fit``."""
    removed = {"compile_search": getattr(args, "compile", False), "fit": getattr(args, "fit", None)}
    config = SearchConfig.from_config(**{name: value for name, value in removed.items() if value})
    if getattr(args, "fov_range", None):
        try:
            config = config.with_fov_range(args.fov_range)
        except ValueError as exc:
            raise FRInputError(f"--fov-range: {exc}") from None
    for name in ("pitch", "roll"):
        value = getattr(args, f"{name}_range", None)
        if value:
            try:
                config = config.with_angle_range(name, value)
            except ValueError as exc:
                raise FRInputError(f"--{name}-range: {exc}") from None
    if getattr(args, "families", None):
        config = config.with_families(args.families)
    distortion, k = getattr(args, "distortion", None), getattr(args, "k", None)
    if distortion is not None or k is not None:
        try:
            config = config.with_distortion(distortion, k)
        except ValueError as exc:
            raise FRInputError(f"--{'k' if k is not None else 'distortion'}: {exc}") from None
    return config


def estimator_kwargs(args: argparse.Namespace) -> dict[str, Any]:
    """FREstimator keyword arguments from :func:`add_estimator_arguments`'s options (picklable)."""
    return dict(mode=Mode.FAST if args.fast else Mode.FR, measure=args.measure, detector=args.detector,
                likelihood=args.likelihood, device=args.device, decode=getattr(args, "decode", "auto"),
                search_config=search_config(args), atlanta=AtlantaConfig.parse(getattr(args, "atlanta", None)),
                working_long_side=working_long_side(args))


def working_long_side(args: argparse.Namespace) -> int | None:
    """The working resolution's cap of ``--working-long-side`` (pixels; None = the input's own), the
    shipped default when the option is absent; FRInputError (one line) when malformed."""
    value = getattr(args, "working_long_side", None)
    return WORKING_LONG_SIDE if value is None else parse_working_long_side(value, "--working-long-side")


def device_policy(args: argparse.Namespace) -> DevicePolicy:
    """The :class:`DevicePolicy` of ``--device``; ``--workers`` < 0 or ``--batch-size`` < 1 are
    one-line errors."""
    workers = getattr(args, "workers", None)
    if workers is not None and workers < 0:
        raise FRInputError("--workers must be 0 (in-process) or more")
    batch_size = getattr(args, "batch_size", None)
    if batch_size is not None and batch_size < 1:
        raise FRInputError("--batch-size must be at least 1")
    return DevicePolicy.resolve(args.device, decode=getattr(args, "decode", "auto"))
