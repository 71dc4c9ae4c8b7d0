"""``fr eval``: the camera task (:mod:`fr_eval.protocols.run_eval`, focal length and rotation), with
``--task vp`` the vanishing-point task (:mod:`fr_eval.protocols.vp_eval`, CONSAC's metric) or, with
``--task horizon``, the horizon benchmark (:mod:`fr_eval.protocols.horizon_eval`, Lezama 2014's metric)."""
from __future__ import annotations

import argparse
from typing import Sequence

from fr_eval.protocols import horizon_eval, run_eval, vp_eval

TASKS = ("camera", "vp", "horizon")
RUNS = {"camera": run_eval.run, "vp": vp_eval.run, "horizon": horizon_eval.run}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    run_eval.add_arguments(parser)
    parser.add_argument("--task", choices=TASKS, default="camera",
                        help="camera: focal length and rotation tables (default); vp: vanishing points with "
                             "CONSAC's metric (datasets nyu-vp, yud, yud+; docs/vp.md); horizon: the horizon "
                             "benchmark's AUC (datasets yud, ecd-tune, nyu-vp; docs/horizon.md)")
    vp_eval.add_arguments(parser)


def run(args: argparse.Namespace) -> int:
    return RUNS[args.task](args)


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="fr eval", description=__doc__.split("\n")[0])
    add_arguments(parser)
    return run(parser.parse_args(argv))


if __name__ == "__main__":
    raise SystemExit(main())
