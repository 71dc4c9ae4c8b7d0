"""Train-split comparison of ``torch-lines`` settings against LSD (issue 37's tuning; train only).

    FR_DATA=/work/shared/data python tools/tune_tensor_lines.py --dataset yud --split train \
        --variant lsd --variant "torch-lines[nms=1]" --out data_local/tune37

Each variant is a detector spec; fR and Fast-fR run on the dataset with it (FOV range [30, 120]
deg, the library default) and one summary line per (variant, method) is printed and appended to
``<out>/summary.csv`` (mean and standard error of roll, tilt, focal %; detector ms per image).
Detections are computed once per variant and shared by the two methods.
"""
from __future__ import annotations

import argparse
import csv
import time
from pathlib import Path

import numpy as np

from fr_eval.datasets.registry import load_dataset
from fr_eval.scoring.metrics import summarize
from fr_eval.protocols.run_eval import evaluate_method
from fr_torch.plugins.methods import FRCalibrator
from fr_torch.detectors.registry import get_detector


class _Memo:
    """A detector that remembers its answers per image (keyed by the image bytes)."""

    def __init__(self, detector):
        self.detector, self.name, self.cache, self.seconds = detector, getattr(detector, "name", "x"), {}, []

    def __call__(self, gray: np.ndarray) -> np.ndarray:
        key = hash(gray.tobytes())
        if key not in self.cache:
            start = time.perf_counter()
            self.cache[key] = self.detector(gray)
            self.seconds.append(time.perf_counter() - start)
        return self.cache[key]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--dataset", required=True)
    parser.add_argument("--split", default="train")
    parser.add_argument("--variant", action="append", required=True)
    parser.add_argument("--out", default="data_local/tune37")
    parser.add_argument("--limit", type=int, default=None)
    parser.add_argument("--stride", type=int, default=1, help="every STRIDE-th sample only (a quick screen)")
    args = parser.parse_args()
    samples = load_dataset(args.dataset, split=args.split)[:: args.stride][: args.limit]
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    for variant in args.variant:
        detector = _Memo(get_detector(variant))
        for mode, label in (("fr", "fr"), ("fast", "fast-fr")):
            rows = evaluate_method(label, samples, calibrator=FRCalibrator(mode=mode, detector=detector),
                                   dataset=args.dataset, progress=False)
            s = summarize(label, rows)
            safe = "".join(c if c.isalnum() or c in "-=." else "_" for c in variant)
            keys = ("image", "failed", "roll_err_deg", "tilt_err_deg", "focal_err_pct")
            with (out / f"rows_{args.dataset}_{args.split}_{args.stride}_{safe}_{label}.csv").open("w", newline="") as fh:
                writer = csv.writer(fh)
                writer.writerow(keys)
                writer.writerows([[r.get(k) for k in keys] for r in rows])
            ms = 1000 * float(np.median(detector.seconds))
            line = {"dataset": args.dataset, "split": f"{args.split}/{args.stride}", "variant": variant, "method": label,
                    "n": s.n_images, "failures": s.failures, "det_ms": round(ms, 1),
                    **{f"{m}": round(s.mean[m], 3) for m in ("roll_err_deg", "tilt_err_deg", "focal_err_pct")},
                    **{f"{m}_se": round(s.se[m], 3) for m in ("roll_err_deg", "tilt_err_deg", "focal_err_pct")}}
            print(" | ".join(f"{k}={v}" for k, v in line.items()), flush=True)
            path = out / "summary.csv"
            new = not path.exists()
            with path.open("a", newline="") as fh:
                writer = csv.DictWriter(fh, fieldnames=list(line))
                if new:
                    writer.writeheader()
                writer.writerow(line)


if __name__ == "__main__":
    main()
