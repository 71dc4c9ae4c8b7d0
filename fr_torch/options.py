"""The estimator options shared by every front end: ``fr calibrate``, ``fr track`` and the
``fr`` / ``fast-fr`` Calibrators (:mod:`fr_torch.methods`).

One definition of the command-line arguments (:func:`add_estimator_arguments`) and one conversion
to :class:`fr_torch.estimator.FREstimator` keyword arguments (:func:`estimator_kwargs`); the
horizontal-FOV search range is turned into a :class:`~fr_torch.search.SearchConfig` by
:func:`hfov_search_config` for all of them.
"""
from __future__ import annotations

import argparse
from dataclasses import replace
from typing import Any

MEASURE_CHOICES = tuple("abcde")


def add_estimator_arguments(parser: argparse.ArgumentParser) -> None:
    """``--fast``, ``--measure``, ``--detector``, ``--likelihood``, ``--hfov-range``, ``--device``."""
    parser.add_argument("--fast", action="store_true", help="Fast-fR: at most 10 refinement iterations")
    parser.add_argument("--measure", choices=MEASURE_CHOICES, default=None, help="deviation measure (default b)")
    parser.add_argument("--detector", default="lsd", help="line segment detector (default lsd)")
    parser.add_argument("--likelihood", default=None, metavar="NAME|JSON",
                        help="likelihood config: 'paper', 'fitted' or a JSON path (default configs/likelihood.json)")
    parser.add_argument("--hfov-range", default=None, metavar="MIN,MAX|paper",
                        help="search range of the field of view across the image's long side, degrees "
                             "(default 30,120; 'paper' = the paper's 50,130; narrow for zoomed-in PTZ or "
                             "traffic cameras)")
    parser.add_argument("--device", default="cpu", help="cpu or cuda")


def hfov_search_config(hfov_min=None, hfov_max=None, base=None):
    """The search configuration (``base``, default ``configs/search.json``) with the horizontal-FOV
    range replaced where ``hfov_min`` / ``hfov_max`` (degrees; numbers or strings) are given.
    Raises FRInputError (a ValueError) for a range outside ``1 <= min < max <= 179``."""
    from .search import SearchConfig

    base = base or SearchConfig.from_config()
    if hfov_min is None and hfov_max is None:
        return base
    low, high = base.hfov_range_deg
    return replace(base, hfov_range_deg=(float(low if hfov_min is None else hfov_min),
                                         float(high if hfov_max is None else hfov_max)))


def estimator_kwargs(args: argparse.Namespace) -> dict[str, Any]:
    """FREstimator keyword arguments from the options of :func:`add_estimator_arguments`."""
    from .segments import FRInputError

    kwargs: dict[str, Any] = dict(mode="fast" if args.fast else "fr", measure=args.measure, detector=args.detector,
                                  likelihood=args.likelihood, device=args.device)
    if args.hfov_range:  # a name ('paper') or MIN,MAX; FRInputError if invalid
        from .search import SearchConfig

        try:
            kwargs["search_config"] = SearchConfig.from_config().with_fov_range(args.hfov_range)
        except ValueError as exc:
            raise FRInputError(f"--hfov-range: {exc}") from None
    return kwargs
