"""Milliseconds per photo in each stage of the search, from timers around the estimator's calls.

``python tools/stage_times.py [--mode fr|fast] [--photos 8] [--threads 1]``: YUD test photos (LSD
segments detected here, not timed), one batch, after one warm-up call; prints each stage's mean time
per photo, largest first.  The stages are the functions the estimator calls (stage-1 grid, focal
sweep, lattice passes, refinement, the cues' lattice fit, focal profile and resampling spreads, the
lines-bend check, the vanishing-point ranking); a function called from another is counted in both.
"""
from __future__ import annotations

import argparse
import collections
import functools
import time

import torch


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--mode", default="fr")
    parser.add_argument("--photos", type=int, default=8)
    parser.add_argument("--threads", type=int, default=1)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)

    import fr_torch.core.estimator as estimator_module
    import fr_torch.core.reliability.cues as cues
    import fr_torch.core.search.grid as grid
    import fr_torch.core.search.manhattan as manhattan
    import fr_torch.core.search.refine as refine
    from fr_eval.datasets.registry import detected_segments, load_dataset
    from fr_torch import FREstimator
    from fr_torch.detectors.lsd import LSDDetector

    spent = collections.defaultdict(float)

    def timed(module, name):
        function = getattr(module, name)

        @functools.wraps(function)
        def wrapper(*a, **k):
            start = time.perf_counter()
            try:
                return function(*a, **k)
            finally:
                spent[name] += time.perf_counter() - start
        setattr(module, name, wrapper)

    for module, name in ((grid, "score_grid"), (manhattan, "sweep_focal"), (manhattan, "subdivide_starts"),
                         (refine, "refine"), (estimator_module, "bend_test"), (estimator_module, "rank_vanishing_points")):
        timed(module, name)
    for name in ("local_quadratic", "focal_profile", "resample_spreads", "focal_profile_spread"):
        timed(cues, name)
    detector = LSDDetector()
    photos = []
    for sample in load_dataset("yud", split="test")[:args.photos]:
        photos.append((detected_segments(sample, detector), (sample.width, sample.height)))
    estimator = FREstimator(mode=args.mode)
    estimator.calibrate_segments([photos[0][0]], [photos[0][1]])
    spent.clear()
    start = time.perf_counter()
    estimator.calibrate_segments([p[0] for p in photos], [p[1] for p in photos])
    total = time.perf_counter() - start
    print(f"{args.mode}: {1000 * total / len(photos):.0f} ms per photo ({args.threads} thread(s))")
    for name, seconds in sorted(spent.items(), key=lambda item: -item[1]):
        print(f"  {name:24s} {1000 * seconds / len(photos):8.1f} ms  {100 * seconds / total:5.1f} %")


if __name__ == "__main__":
    main()
