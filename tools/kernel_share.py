"""How much of a photo's search is the measure-b kernels' arithmetic, and how much is around them.

``python tools/kernel_share.py fast|fr`` (CPU, 2 threads, kernels built): the first 8 YUD train
photos' LSD segments, one photo per ``calibrate_segments`` call after one warm-up.  Prints per photo:

* ``score``: the deviations every scoring call computed (images x hypotheses x segments x 3, every
  stage: grid, focal sweep, lattice passes, the cues, the lines-bend check), ``score_ms`` the
  kernels' wall time for them;
* ``refine``: the refinement kernel's deviations times its steps, ``refine_ms`` its wall time;
* ``search_ms``: the median search (``calibrate_segments``) wall time.

The deviations times the bench's in-cache atan2 + exp cost (``fr bench``'s grid floor) is the
arithmetic's floor; ``search_ms`` minus the kernels' times is the work around them.
"""
from __future__ import annotations

import argparse
import inspect
import statistics
import time

import torch


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("mode", choices=("fast", "fr"))
    parser.add_argument("--photos", type=int, default=8)
    parser.add_argument("--threads", type=int, default=2)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)

    import fr_torch.core.likelihood.native as native
    from fr_eval.datasets.registry import detected_segments, load_dataset
    from fr_torch import FREstimator
    from fr_torch.detectors.lsd import LSDDetector

    totals = {"score": 0, "score_ms": 0.0, "refine": 0, "refine_ms": 0.0}
    scores, refine = native.measure_b_scores, native.measure_b_refine
    signature = inspect.signature(refine)

    def counted_scores(line_along, factor, scale, flat, *rest, **options):
        images, segments = factor.shape
        totals["score"] += images * (flat.shape[2] // 3) * segments * 3
        start = time.perf_counter()
        try:
            return scores(line_along, factor, scale, flat, *rest, **options)
        finally:
            totals["score_ms"] += 1e3 * (time.perf_counter() - start)

    def counted_refine(u, line_along, weight, *rest, **options):
        steps = signature.bind(u, line_along, weight, *rest, **options).arguments["steps"]  # (S, 2): Adam's per step
        images, starts = u.shape[:2]
        totals["refine"] += len(steps) * images * starts * weight.shape[1] * 3
        start = time.perf_counter()
        try:
            return refine(u, line_along, weight, *rest, **options)
        finally:
            totals["refine_ms"] += 1e3 * (time.perf_counter() - start)

    native.measure_b_scores, native.measure_b_refine = counted_scores, counted_refine
    detector = LSDDetector()
    photos = []
    for sample in load_dataset("yud", split="train")[:args.photos]:
        photos.append((detected_segments(sample, detector), (sample.width, sample.height)))
    estimator = FREstimator(mode=args.mode)
    estimator.calibrate_segments([photos[0][0]], [photos[0][1]])
    totals.update(score=0, score_ms=0.0, refine=0, refine_ms=0.0)
    times = []
    for segments, size in photos:
        start = time.perf_counter()
        estimator.calibrate_segments([segments], [size])
        times.append(1e3 * (time.perf_counter() - start))
    per_photo = {key: value / len(photos) for key, value in totals.items()}
    print(f"{args.mode}: score {per_photo['score'] / 1e6:.2f} M deviations in {per_photo['score_ms']:.1f} ms; "
          f"refine {per_photo['refine'] / 1e6:.2f} M deviation-steps in {per_photo['refine_ms']:.1f} ms; "
          f"search_ms {statistics.median(times):.1f} (median of {len(photos)} photos)")


if __name__ == "__main__":
    main()
