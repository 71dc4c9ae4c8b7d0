"""``fr calibrate --shared-focal`` and ``fr calibrate --focal-prior``: the front end of
:mod:`fr_torch.runtime.shared_focal` and :mod:`fr_torch.runtime.focal_prior` (``docs/shared-focal.md``).

Every image's JSON record gets two keys besides :data:`fr_torch.core.result.JSON_KEYS`:
``focal_prior`` (``{source, focal_px, sigma_pct}`` of the prior used for it, or null; with
``--focal-prior exif`` and no usable EXIF, ``focal_prior_reason`` says why) and, with
``--shared-focal``, ``shared_focal`` (:meth:`fr_torch.runtime.shared_focal.SharedFocalResult.to_json`, the
same for every image of the call; its ``principal_point`` is the camera's estimated one, null with
``--pp``, ``--fixed-pp`` or fewer than 5 usable images).
"""
from __future__ import annotations

import argparse
import sys

from fr_torch.cli.options import search_config
from fr_torch.errors import FRInputError
from fr_torch.runtime.focal_prior import group_prior, image_priors, parse_focal_prior
from fr_torch.runtime.pipeline import calibrate_paths
from fr_torch.runtime.shared_focal import apply_focal_priors, require_pinhole, shared_from_results


def add_focal_prior_argument(parser: argparse.ArgumentParser) -> None:
    """``--focal-prior`` (``fr calibrate``, ``fr batch``)."""
    parser.add_argument("--focal-prior", default=None, metavar="PX[,SIGMA%]|exif[,SIGMA%]",
                        help="a soft log-normal prior on the focal length: PX pixels with SIGMA %% width "
                             "(default 10), or 'exif' to read it from each JPEG's EXIF (FocalLengthIn35mmFilm, or "
                             "FocalLength with the focal plane resolution; default width 10 %%; no EXIF = no prior)")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """``--shared-focal`` and ``--focal-prior`` (added to ``fr calibrate``)."""
    parser.add_argument("--shared-focal", action="store_true",
                        help="the images come from one camera: estimate one focal length for all of them "
                             "(robust to photos that do not constrain it), its principal point (from 5 images, "
                             "unless --pp or --fixed-pp) and each image's rotation at them")
    parser.add_argument("--fixed-pp", action="store_true",
                        help="with --shared-focal: keep the principal point at the image centre instead of "
                             "estimating the camera's")
    add_focal_prior_argument(parser)


def focal_options(args: argparse.Namespace):
    """The parsed ``--focal-prior`` (a :class:`~fr_torch.runtime.focal_prior.FocalPriorOption` or None),
    checked against ``--focal``; FRInputError (one line) when they conflict or are malformed."""
    if getattr(args, "focal", None) is not None and (getattr(args, "shared_focal", False) or args.focal_prior):
        raise FRInputError("--focal fixes the focal length: it cannot be combined with --shared-focal or "
                           "--focal-prior (use --focal-prior PX,SIGMA% for a soft value)")
    if getattr(args, "shared_focal", False) or getattr(args, "shared_focal_by", None):
        require_pinhole(search_config(args).distortion)
    return parse_focal_prior(args.focal_prior) if args.focal_prior else None


def run(args: argparse.Namespace, estimator, paths: list[str], batch_size: int, workers: int, principal_point,
        emit) -> None:
    """Calibrate ``paths`` with the focal options of ``args``; ``emit(path, result, extra)`` prints
    one image's record (``extra``: the keys above), in input order."""
    option = focal_options(args)
    if not args.shared_focal:
        for chunk, results in calibrate_paths(estimator, paths, batch_size, workers, None, principal_point):
            priors, reasons = image_priors(option, chunk, results)
            results = apply_focal_priors(estimator, results, priors)
            for path, result, prior, reason in zip(chunk, results, priors, reasons):
                extra = {"focal_prior": prior.to_json() if prior is not None else None}
                if reason:
                    extra["focal_prior_reason"] = reason
                emit(path, result, extra)
        return
    alone, chunks = [], []
    for chunk, results in calibrate_paths(estimator, paths, batch_size, workers, None, principal_point):
        alone += results
        chunks += chunk
    priors, reasons = image_priors(option, chunks, alone)
    prior = group_prior(priors)
    shared = shared_from_results(estimator, alone, focal_prior=prior,
                                 estimate_principal_point=principal_point is None and not args.fixed_pp)
    summary = shared.to_json()
    if not shared.ok:
        print(f"fr: shared focal length: {shared.reason}", file=sys.stderr)
    for path, result, reason in zip(chunks, shared.results, reasons):
        extra = {"focal_prior": shared.focal_prior, "shared_focal": summary}
        if reason:
            extra["focal_prior_reason"] = reason
        emit(path, result, extra)
