"""Resolution independence of fR: YUD test images upscaled by 1x, 2x, 4x (bicubic) give the same errors.

    python -m fr_eval.protocols.resolution_check --scales 1,2,4 --mode fast --out results/resolution

For every scale k the test images are upscaled by k (``cv2.INTER_CUBIC``), calibrated from the
arrays (detection runs at the estimator's working resolution), and compared with the ground truth
(focal length scaled by k).  Prints, per scale, how many estimates are valid (a failed or non-finite
estimate counts against it and is left out of the means), mean +- SE per metric over the valid ones,
the paired mean |difference| to 1x, and the median time per image (decode excluded; detection +
search); writes a Markdown table to ``--out/resolution_<mode>.md`` when ``--out`` is given.
"""
from __future__ import annotations

import argparse
import sys
import time
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
from fr_eval.machine import machine_description
from fr_eval.datasets.registry import load_dataset
from fr_eval.scoring.metrics import failure_reason, image_errors, is_failure, mean_se
from tqdm import tqdm

from fr_torch import FREstimator
from fr_torch.images.io import WORKING_LONG_SIDE, load_image

METRICS = ("roll_err_deg", "tilt_err_deg", "focal_err_pct", "frame_err_deg")


def _scales(text: str) -> list[int]:
    """``"1,2,4"`` -> [1, 2, 4]; anything but whole factors >= 1 is a one-line usage error."""
    try:
        scales = [int(v) for v in text.split(",")]
    except ValueError:
        scales = []
    if not scales or min(scales) < 1:
        raise argparse.ArgumentTypeError(f"expected whole factors >= 1 such as 1,2,4, got {text!r}")
    return scales


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scales", default="1,2,4", type=_scales, help="comma-separated whole upscaling factors >= 1")
    parser.add_argument("--mode", default="fast", choices=("fast", "fr"))
    parser.add_argument("--split", default="test")
    parser.add_argument("--limit", type=int, default=None)
    parser.add_argument("--data-root", default=None)
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args(argv)
    samples = load_dataset("yud", root=args.data_root, split=args.split)
    samples = samples[: args.limit] if args.limit else samples
    images = [load_image(s.image_path) for s in samples]
    estimator = FREstimator(mode=args.mode)
    estimator.calibrate_images(images[:1])  # warm-up
    lines = [f"# Resolution independence, YUD {args.split} ({len(samples)} images), {args.mode}", "",
             "| scale | input | valid | " + " | ".join(METRICS) + " | segments (median) | ms/image (median) |",
             "|---" * (len(METRICS) + 5) + "|"]
    per_scale, failed_at = {}, {}
    for k in args.scales:
        rows, times, counts, failures = [], [], [], []
        for sample, image in tqdm(list(zip(samples, images)), desc=f"{args.mode} {k}x", unit="img", leave=False,
                                  file=sys.stderr):
            big = image if k == 1 else cv2.resize(image, None, fx=k, fy=k, interpolation=cv2.INTER_CUBIC)
            start = time.perf_counter()
            [result] = estimator.calibrate_images([big], names=[sample.name])
            times.append(time.perf_counter() - start)
            counts.append(result.num_segments)
            truth = replace(sample, width=sample.width * k, height=sample.height * k,
                            camera=sample.camera.resized(sample.width * k, sample.height * k))
            rows.append(image_errors(truth, result))
            if is_failure(result):
                failures.append(f"{sample.name} ({failure_reason(result)})")
        per_scale[k] = rows
        failed_at[k] = failures
        cells = []
        for m in METRICS:
            mean, se, n = mean_se(r[m] for r in rows if r[m] is not None)
            cells.append(f"{mean:.3f} ± {se:.3f}" if n > 1 else f"{mean:.3f}" if n == 1 else "n/a")
        valid = len(rows) - len(failures)
        lines.append(f"| {k}x | {samples[0].width * k}x{samples[0].height * k} | {valid}/{len(rows)} | "
                     + " | ".join(cells)
                     + f" | {int(np.median(counts))} | {1000 * np.median(times):.0f} |")
    if 1 in per_scale and len(per_scale) > 1:
        lines += ["", "Paired mean |difference| of the per-image error to 1x:", ""]
        for k, rows in per_scale.items():
            if k == 1:
                continue
            diffs = {m: [abs(a[m] - b[m]) for a, b in zip(rows, per_scale[1]) if a[m] is not None and b[m] is not None]
                     for m in METRICS}
            lines.append(f"- {k}x: " + ", ".join(f"{m} {np.mean(v):.3f}" for m, v in diffs.items()))
    failed = [f"- {k}x: " + "; ".join(names) for k, names in failed_at.items() if names]
    if failed:
        lines += ["", "Failed estimates (counted in `valid`, left out of the means):", ""] + failed
    low, high = estimator.search.fov_range
    machine = machine_description("cpu")
    command = " ".join(argv if argv is not None else sys.argv[1:])
    lines += ["", f"Command: `python -m fr_eval.protocols.resolution_check {command}` (YUD {args.split}, bicubic upscaling; "
              f"every row with the FOV search range [{low:g}°, {high:g}°] across the long side and the principal "
              f"point at the image centre; means ± standard error over the valid estimates). {machine['cpu']}, "
              f"{machine['usable_cores']} usable cores, torch {machine['torch']}, {machine['threads']} threads; "
              f"ms = detection at the working resolution (long side <= {WORKING_LONG_SIDE} px, "
              f"`fr_torch.images.io.WORKING_LONG_SIDE`; the {estimator.segment_filter.max_segments} longest segments) "
              f"+ search, decode excluded."]
    text = "\n".join(lines) + "\n"
    print(text)
    if args.out:
        args.out.mkdir(parents=True, exist_ok=True)
        (args.out / f"resolution_{args.mode}.md").write_text(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
