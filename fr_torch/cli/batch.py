"""``fr batch``: the command-line front end of :mod:`fr_torch.batch.jobs`."""
from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

from fr_torch.batch.jobs import run_batch
from fr_torch.cli.focal import add_focal_prior_argument, focal_options
from fr_torch.cli.options import (
    add_camera_arguments,
    add_device_arguments,
    add_estimator_arguments,
    camera_options,
    device_policy,
    estimator_kwargs,
)
from fr_torch.redaction import redact_text
from fr_torch.runtime.device import DevicePolicy
from fr_torch.runtime.workers import start_worker_server


#: Failed images the summary line names (each one also had its own line as it failed).
FAILED_NAMED = 5


def estimator_options(args: argparse.Namespace) -> dict[str, Any]:
    """Picklable options from the CLI arguments (shipped to every worker): ``estimator`` = the
    FREstimator keyword arguments of the shared estimator options (:mod:`fr_torch.cli.options`), plus
    the known focal length / principal point for all images, the parsed ``--focal-prior``, whether
    reliability is on and whether shared-focal groups estimate their principal point."""

    focal, pp = camera_options(args)
    return {"estimator": estimator_kwargs(args), "principal_point": pp, "focal_px": focal,
            "focal_prior": focal_options(args),
            "reliability": not getattr(args, "no_reliability", False),
            "shared_principal_point": pp is None and not getattr(args, "fixed_pp", False)}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments of ``fr batch``."""
    parser.add_argument("inputs", nargs="+", metavar="INPUT",
                        help="folders (recursive), globs, image files or manifests (.csv/.parquet/.txt); "
                             "fsspec URIs (s3://...) when the filesystem package is installed")
    parser.add_argument("--out", required=True, type=Path, help="output Parquet dataset (a folder of part files)")
    parser.add_argument("--engine", choices=("local", "ray"), default="local",
                        help="local: this machine (default); ray: Ray Data actor pool (pip install 'fr-torch[ray]')")
    parser.add_argument("--address", default=None,
                        help="ray: cluster to join (e.g. auto, ray://host:10001); default $RAY_ADDRESS, "
                             "else a local cluster (--workers CPUs, default all)")
    parser.add_argument("--threads-per-worker", type=int, default=None,
                        help="ray: CPUs (torch threads) per actor (default 1)")
    parser.add_argument("--gpus-per-worker", type=float, default=None,
                        help="ray with --device cuda: GPUs per actor (default 1; 0.5 puts two actors on a GPU)")
    parser.add_argument("--rows-per-part", type=int, default=0, metavar="N",
                        help="gather batches into part files of at least N rows (default 0: one part per batch)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    parser.add_argument("--no-reliability", action="store_true",
                        help="do not add predicted errors or error bounds (reliable = the sanity checks only; "
                             "fR then skips the focal_profile_gap cue: about twice the images per second)")
    add_estimator_arguments(parser, device=False)
    add_device_arguments(
        parser, batch_help="images per batch (= per part file; default 16 on a CPU, 256 on a GPU)",
        workers_help="ray: number of actors, one estimator each (default: the cluster's CPUs); local on a CPU: "
                     "single-threaded worker processes (default: one per core, up to 8, for 32+ images each; "
                     "1 = this process), on a GPU: decode + detection processes feeding the search (default: "
                     "every core but one, up to 16; 0 = none)")
    add_camera_arguments(parser, focal_help="known focal length in pixels for all images (a manifest's "
                                            "focal_px column wins)")
    parser.add_argument("--shared-focal-by", default=None, metavar="COLUMN",
                        help="manifest column (e.g. a camera id): the rows of each value share one focal length "
                             "(docs/shared-focal.md; each group is searched by one process or Ray actor) and, "
                             "unless --pp or --fixed-pp, one principal point (groups of 5 or more usable images)")
    add_focal_prior_argument(parser)
    parser.add_argument("--fixed-pp", action="store_true",
                        help="with --shared-focal-by: keep the principal point at the image centre instead of "
                             "estimating each group's")


def run(args: argparse.Namespace) -> int:
    """``fr batch``: prints a one-line summary; exit 0 even when some images failed (they are rows
    with ok=false), non-zero on a usage error."""
    local = args.engine == "local"
    # Local: a device that cannot run is a one-line error before any work.  Ray: each actor
    # resolves the device on its own node.
    policy = device_policy(args) if local else DevicePolicy.resolve("cpu")
    # Host workers (started ahead, while this process loads torch) unless a GPU decodes and detects
    # itself (fr_torch.runtime.device_pipeline; where it cannot after all, the pool starts them then).
    host_path = policy.on_cpu or policy.decode == "host"
    if local and host_path and (args.workers is None or args.workers > (1 if policy.on_cpu else 0)):
        start_worker_server()
    options = estimator_options(args)
    policy.apply_threads()  # this process's threads (an explicit local --workers 1 still sets its own)
    summary = run_batch([str(p) for p in args.inputs], args.out, options, engine=args.engine,
                        workers=args.workers, batch_size=args.batch_size, address=args.address,
                        progress=not args.no_progress, threads_per_worker=args.threads_per_worker,
                        gpus_per_worker=args.gpus_per_worker, rows_per_part=args.rows_per_part,
                        shared_focal_by=args.shared_focal_by)
    failed = summary["failed_images"]
    named = ": " + ", ".join(failed[:FAILED_NAMED]) + (f", ... ({len(failed) - FAILED_NAMED} more)"
                                                       if len(failed) > FAILED_NAMED else "") if failed else ""
    print(redact_text(f"fr batch: {summary['total']} images, {summary['skipped']} already done, {summary['processed']} "
                      f"processed ({summary['failed']} failed{named}) in {summary['seconds']:.1f} s "
                      f"({summary['images_per_s']:.1f} img/s) -> {args.out}"), file=sys.stderr)
    return 0
