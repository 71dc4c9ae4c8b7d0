"""How much of a photo's resolution the line detection should use: the same photos calibrated with
the working resolution capped at several long sides.

    python -m fr_eval.protocols.working_resolution --dataset yud --split train --mode fr --caps 320,640
    python -m fr_eval.protocols.working_resolution --dataset yud --split train --mode fr --caps 640,1280 --upscale 2

A cap below a photo's long side stands for a larger photo brought down to it: YUD's and ZInD-fR's
640-pixel photos detected at 320 are what a 1280-pixel photo detected at 640 would lose (half the
resolution); detected at 640 they keep it.  ``--upscale K`` enlarges every photo by K (bicubic)
first: a photo with no more detail than its pixels say (a digital zoom), where a higher cap can only
cost time.  Per cap: focal, tilt and roll errors (mean +- standard error), the horizon AUC (Lezama's,
against the labelled horizon, or the ground-truth camera's own with ``--upscale``, which needs
a ground-truth camera), how many
estimates are ``reliable`` and how many of those are within the promise's limits (10 % focal, 3 deg
tilt), and the CPU seconds per photo of the whole ``calibrate_images`` call (one thread; decode
excluded).  Writes ``--out/<dataset>_<split>_<mode>[_x<K>].md`` when ``--out`` is given.
"""
from __future__ import annotations

import argparse
import sys
import time
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import torch
from tqdm import tqdm

from fr_eval.datasets.registry import load_dataset
from fr_eval.machine import machine_description
from fr_eval.scoring.horizon_metric import FRAME, lezama_auc, truth_horizons
from fr_eval.scoring.metrics import image_errors, mean_se
from fr_torch import FREstimator
from fr_torch.core.geometry.horizon import Horizon
from fr_torch.core.reliability.bounds import DEFAULT_LIMITS
from fr_torch.errors import FRInputError
from fr_torch.images.io import load_image, parse_working_long_side

METRICS = ("focal_err_pct", "tilt_err_deg", "roll_err_deg")
#: The promise's limits (:data:`fr_torch.core.reliability.bounds.DEFAULT_LIMITS`) by the error they
#: bound: a reliable estimate within them is a kept promise.
PROMISE_LIMITS = {"focal_err_pct": DEFAULT_LIMITS["focal_pct"], "tilt_err_deg": DEFAULT_LIMITS["tilt_deg"]}


def _caps(text: str) -> list[int | None]:
    try:
        return [parse_working_long_side(v.strip(), "--caps") for v in text.split(",")]
    except FRInputError as exc:  # a usage error of this command
        raise argparse.ArgumentTypeError(str(exc)) from None


def _sample_at(sample, image: np.ndarray, k: int):
    """The sample and its image enlarged k times (bicubic), the ground-truth camera with it."""
    if k == 1:
        return sample, image
    big = cv2.resize(image, None, fx=k, fy=k, interpolation=cv2.INTER_CUBIC)
    return replace(sample, width=sample.width * k, height=sample.height * k,
                   camera=sample.camera.resized(sample.width * k, sample.height * k)), big


def horizon_error(sample, result, upscaled: bool) -> float:
    """The horizon benchmark's error (fraction of the height) against the labelled horizon (the
    camera's own when ``upscaled``: the labelled lines are in the original pixels); a failure is 1."""
    truths = truth_horizons(sample)
    key = FRAME if upscaled or "labelled" not in truths else "labelled"
    estimate = Horizon.from_camera(result.camera) if result.ok else None
    return 1.0 if estimate is None or key not in truths else min(1.0, estimate.error(truths[key]))


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--dataset", default="yud")
    parser.add_argument("--split", default="train")
    parser.add_argument("--mode", default="fr", choices=("fast", "fr"))
    parser.add_argument("--caps", default="320,640", type=_caps, help="working long sides, pixels, or 'input'")
    parser.add_argument("--upscale", default=1, type=int, help="enlarge every photo k times first (bicubic)")
    parser.add_argument("--limit", type=int, default=None, help="the first N photos only")
    parser.add_argument("--data-root", default=None)
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args(argv)
    if args.upscale < 1:
        parser.error("--upscale: expected a whole factor >= 1")
    samples = load_dataset(args.dataset, root=args.data_root, split=args.split)[: args.limit]
    if args.upscale > 1 and any(s.camera is None for s in samples):
        parser.error(f"--upscale needs a ground-truth camera per photo; {args.dataset} has none")
    torch.set_num_threads(1)
    estimators = {cap: FREstimator(mode=args.mode, working_long_side=cap) for cap in args.caps}
    rows = {cap: [] for cap in args.caps}
    for sample in tqdm(samples, desc=f"{args.dataset} {args.mode}", unit="img", file=sys.stderr):
        truth, image = _sample_at(sample, load_image(sample.image_path), args.upscale)
        for cap, estimator in estimators.items():
            start = time.process_time()
            [result] = estimator.calibrate_images([image], names=[sample.name])
            errors = image_errors(truth, result)
            errors.update(cpu_s=time.process_time() - start, reliable=bool(result.ok and result.reliable),
                          horizon=horizon_error(truth, result, args.upscale > 1))
            rows[cap].append(errors)
    long_sides = sorted({max(s.width, s.height) * args.upscale for s in samples})
    size = (f"{samples[0].width * args.upscale}x{samples[0].height * args.upscale}" if len(long_sides) == 1
            else f"long side {long_sides[0]}–{long_sides[-1]} px")
    lines = [f"# Working resolution: {args.dataset} {args.split} ({len(samples)} photos, {size}"
             f"{f', upscaled {args.upscale}x' if args.upscale > 1 else ''}), {args.mode}", "",
             "| cap (long side, px) | " + " | ".join(METRICS) + " | horizon AUC | reliable | within the limits "
             "| CPU s per photo (median) |", "|---" * (len(METRICS) + 5) + "|"]
    for cap, cap_rows in rows.items():
        cells = []
        for metric in METRICS:
            mean, se, n = mean_se(r[metric] for r in cap_rows if r[metric] is not None)
            cells.append(f"{mean:.3f} ± {se:.3f} ({n})" if n else "n/a")
        reliable = [r for r in cap_rows if r["reliable"]]
        scored = any(r["focal_err_pct"] is not None for r in cap_rows)
        kept = sum(all(r[m] is not None and r[m] <= limit for m, limit in PROMISE_LIMITS.items())
                   for r in reliable) if scored else "n/a"
        auc = 100 * lezama_auc([r["horizon"] for r in cap_rows])[0]
        lines.append(f"| {cap or 'input'} | " + " | ".join(cells) + f" | {auc:.2f} | {len(reliable)} | {kept} | "
                     f"{np.median([r['cpu_s'] for r in cap_rows]):.3f} |")
    machine = machine_description("cpu")
    low, high = next(iter(estimators.values())).search.fov_range
    command = " ".join(argv if argv is not None else sys.argv[1:])
    lines += ["", f"Command: `python -m fr_eval.protocols.working_resolution {command}`. Means ± standard error "
              "(valid estimates in brackets); horizon AUC: Lezama's, "
              + ("against the ground-truth camera's horizon" if args.upscale > 1 else "against the labelled horizon")
              + "; within the limits: reliable estimates within 10 % focal and 3° tilt. FOV search range "
              f"[{low:g}°, {high:g}°] across the long side, principal point at the image centre. CPU: one thread, {machine['cpu']}, torch "
              f"{machine['torch']}; the whole calibrate_images call, decode excluded."]
    text = "\n".join(lines) + "\n"
    print(text)
    if args.out:
        args.out.mkdir(parents=True, exist_ok=True)
        suffix = f"_x{args.upscale}" if args.upscale > 1 else ""
        (args.out / f"{args.dataset}_{args.split}_{args.mode}{suffix}.md").write_text(text, encoding="utf-8")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
