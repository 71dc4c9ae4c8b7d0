"""How far fR's estimates move when every segment endpoint moves by one part in 10^7.

``python tools/perturbation.py [--mode fr|fast] [--dataset yud] [--split train] [--eps 1e-7]``:
LSD segments of the photos (detected once), calibrated as they are and with each endpoint
coordinate multiplied by ``1 +- eps`` (random signs, seed 0); prints the distribution of the
relative focal differences, the mean focal error of both runs and the ``reliable`` flips.  A
stand-in for the last-bit differences between machines (docs/reproducibility.md).
"""
from __future__ import annotations

import argparse

import numpy as np


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--mode", default="fr")
    parser.add_argument("--dataset", default="yud")
    parser.add_argument("--split", default="train")
    parser.add_argument("--eps", type=float, default=1e-7)
    args = parser.parse_args()

    from fr_eval.datasets.registry import detected_segments, load_dataset
    from fr_torch import FREstimator
    from fr_torch.detectors.lsd import LSDDetector

    detector = LSDDetector()
    photos = []
    for sample in load_dataset(args.dataset, split=args.split):
        photos.append((detected_segments(sample, detector), (sample.width, sample.height), sample.camera.focal_px))
    estimator = FREstimator(mode=args.mode)
    rng = np.random.default_rng(0)
    sizes = [p[1] for p in photos]
    plain = estimator.calibrate_segments([p[0] for p in photos], sizes)
    moved = estimator.calibrate_segments([p[0] * (1 + args.eps * rng.choice([-1.0, 1.0], p[0].shape))
                                          for p in photos], sizes)
    rel = np.array([abs(a.focal_px - b.focal_px) / a.focal_px for a, b in zip(plain, moved)])
    error = [np.mean([abs(r.focal_px - p[2]) / p[2] * 100 for r, p in zip(run, photos)]) for run in (plain, moved)]
    print(f"{args.mode}, {args.dataset} {args.split} ({len(photos)} photos), endpoints x (1 +- {args.eps:g}): "
          f"focal moves by a median {np.median(rel):.1e}, beyond 1e-4 on {int((rel > 1e-4).sum())}, beyond 1 % on "
          f"{int((rel > 1e-2).sum())}, at most {rel.max():.3f}; mean focal error {error[0]:.2f} % -> {error[1]:.2f} %; "
          f"reliable flips {sum(a.reliable != b.reliable for a, b in zip(plain, moved))}")


if __name__ == "__main__":
    main()
