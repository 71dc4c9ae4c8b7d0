"""``fr undistort IMAGE... --out DIR``: straighten photos taken through a wide-angle lens.

Each image is calibrated with the division model (``--distortion division`` unless given; ``--k``
for a known k), its straightened image written as ``<stem>_undistorted.png`` and the record of
that image -- its pinhole ``K``, rotation and the lens removed -- printed as one JSON line (and
written as ``<stem>_undistorted.json``).
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

from fr_torch.cli.options import (
    add_camera_arguments,
    add_estimator_arguments,
    camera_options,
    device_policy,
    estimator_kwargs,
)
from fr_torch.errors import FRInputError
from fr_torch.images.lens import undistorted_path, write_undistorted
from fr_torch.output import dumps, json_safe, output_folder, write_text_atomic
from fr_torch.runtime.estimator import FREstimator
from fr_torch.runtime.pipeline import calibrate_paths
from fr_torch.runtime.workers import settle_heap


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments of ``fr undistort``."""
    parser.add_argument("images", nargs="+", help="image files")
    parser.add_argument("--out", required=True, type=Path, metavar="DIR",
                        help="folder for <image>_undistorted.png and <image>_undistorted.json")
    add_estimator_arguments(parser)
    add_camera_arguments(parser)
    parser.add_argument("--no-reliability", action="store_true", help="no predicted errors (faster)")
    parser.set_defaults(distortion="division")


def run(args: argparse.Namespace) -> int:
    """``fr undistort``: one JSON line per image; non-zero exit if any image failed."""
    policy = device_policy(args)
    policy.apply_threads()
    output_folder(args.out, "--out")
    focal_px, principal_point = camera_options(args)
    estimator = FREstimator(**estimator_kwargs(args), reliability=None if args.no_reliability else "default")
    settle_heap()
    failures = 0
    for chunk, results in calibrate_paths(estimator, [str(p) for p in args.images], policy.default_batch_size, 0,
                                          focal_px, principal_point):
        for path, result in zip(chunk, results):
            try:
                record = json_safe(write_undistorted(path, result, args.out))
            except (FRInputError, ValueError) as exc:
                failures += 1
                print(f"fr undistort: {exc}", file=sys.stderr)
                continue
            write_text_atomic(undistorted_path(path, args.out).with_suffix(".json"), dumps(record, indent=1))
            print(dumps(record), flush=True)
    return 1 if failures else 0
