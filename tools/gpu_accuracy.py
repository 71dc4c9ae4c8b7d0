"""Score per-image records against YorkUrbanDB: ``tools/gpu_probe.py``'s accuracy stage (a JSON
list with ``mode``) or ``fr calibrate``'s JSON lines (``.jsonl``, or gzipped ``.jsonl.gz``) (``gpu_check.sh``'s distortion phase: the
photos and their copies through a barrel lens, named ``STEM_bent.jpg``, the same camera undistorted).

    python tools/gpu_accuracy.py OUT/accuracy_cuda.json [OUT/distortion_auto.jsonl ...]

Prints one row per file and mode (JSON lines: per photo / bent copy): mean +- standard error of
roll, tilt (deg) and focal length (% of the calibrated 674.9 px) over the images of the file, the
failure count, the median estimated k and the share flagged ``reliable``, with the same per-image
errors as ``fr eval`` (:func:`fr_eval.scoring.metrics.image_errors`).
"""
from __future__ import annotations

import gzip
import json
import sys
from pathlib import Path

from fr_eval.datasets.yud import load_yud
from fr_eval.scoring.metrics import image_errors, mean_se


def load_records(path: Path) -> list[dict]:
    """The records of ``path``, each with ``mode`` and ``image`` (YorkUrbanDB's photo name)."""
    if not path.name.endswith((".jsonl", ".jsonl.gz")):
        return json.loads(path.read_text())
    text = gzip.decompress(path.read_bytes()).decode() if path.suffix == ".gz" else path.read_text()
    records = []
    for line in text.splitlines():
        record = json.loads(line)
        stem = Path(record["image"]).stem
        record["mode"] = "bent copy" if stem.endswith("_bent") else "photo"
        record["image"] = stem.removesuffix("_bent")
        records.append(record)
    return records


def score(path: Path) -> list[str]:
    records = load_records(path)
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
        ks = sorted((r.get("distortion") or {}).get("k", 0.0) for r in rows)
        reliable = sum(bool(r.get("reliable")) for r in rows)
        lines.append(f"| {path.name} | {mode} | {len(rows)} | {' | '.join(cells)} | {failed} | "
                     f"{ks[len(ks) // 2]:+.3f} | {reliable} |")
    return lines


def main(argv=None) -> int:
    paths = [Path(p) for p in (argv if argv is not None else sys.argv[1:])]
    print("| file | mode | images | roll deg | tilt deg | focal % | failed | median k | reliable |\n"
          "|---|---|---|---|---|---|---|---|---|")
    for path in paths:
        print("\n".join(score(path)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
