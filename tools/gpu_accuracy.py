"""Score the per-image records of ``tools/gpu_probe.py``'s accuracy stage against YorkUrbanDB.

    python tools/gpu_accuracy.py OUT/accuracy_cuda.json [OTHER.json ...]

Prints one row per file and mode: mean +- standard error of roll, tilt (deg) and focal length
(% of the calibrated 674.9 px) over the images of the file, and the failure count, with the same
per-image errors as ``fr eval`` (:func:`fr_eval.scoring.metrics.image_errors`).
"""
from __future__ import annotations

import json
import sys
from pathlib import Path

from fr_eval.datasets.yud import load_yud
from fr_eval.scoring.metrics import image_errors, mean_se


def score(path: Path) -> list[str]:
    records = json.loads(path.read_text())
    samples = {s.name: s for s in load_yud(split="all")}
    lines = []
    for mode in sorted({r["mode"] for r in records}):
        rows = [r for r in records if r["mode"] == mode]
        errors = [image_errors(samples[r["image"]], r) for r in rows]
        cells = []
        for key in ("roll_err_deg", "tilt_err_deg", "focal_err_pct"):
            mean, se, n = mean_se(e[key] for e in errors if e[key] is not None)
            cells.append(f"{mean:.2f} +- {se:.2f}")
        failed = sum(e["focal_err_pct"] is None for e in errors)
        lines.append(f"| {path.name} | {mode} | {len(rows)} | {' | '.join(cells)} | {failed} |")
    return lines


def main(argv=None) -> int:
    paths = [Path(p) for p in (argv if argv is not None else sys.argv[1:])]
    print("| file | mode | images | roll deg | tilt deg | focal % | failed |\n|---|---|---|---|---|---|---|")
    for path in paths:
        print("\n".join(score(path)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
