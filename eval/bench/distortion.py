"""``fr bench --sections distortion``: the time the division model (issue 46) costs.

Per photo (batch 1, end to end from the file) and per image in batches of 16 given segments, fR
and Fast-fR with ``--distortion pinhole`` (the default), ``division`` and ``auto``, on the
benchmark's photos and on the same photos bent through a barrel lens (division model, k = -0.2:
the straight lines at the border bow by 3.2 % of the width in 4:3; :func:`fr_torch.images.lens.distort_image`).
Every row gives its ratio to pinhole fR on the same photo (the first of :data:`SETTINGS`), the issue's yardstick
(``--quick`` runs Fast-fR only, one photo and its bent copy, batches of :data:`QUICK_BATCH`: its
yardstick is pinhole Fast-fR).
"""
from __future__ import annotations

import statistics
import time
from pathlib import Path

#: (mode, distortion) of the rows; the first is the yardstick of the ratios.
SETTINGS = (("fr", "pinhole"), ("fr", "division"), ("fr", "auto"), ("fast", "pinhole"), ("fast", "division"))
#: k of the bent copies of the photos.
BENT_K = -0.2
#: Images per batch of the throughput rows (``--quick``: :data:`QUICK_BATCH`).
BATCH = 16
QUICK_BATCH = 2


def bent_copies(images: list[tuple[str, str]], folder: Path) -> list[tuple[str, str]]:
    """The photos bent through a barrel lens of :data:`BENT_K`, written to ``folder``."""
    import cv2

    from fr_torch.images.io import load_image
    from fr_torch.images.lens import distort_image

    out = []
    for label, path in images:
        image = load_image(path)
        target = Path(folder) / f"bent_{Path(path).stem}.png"
        cv2.imwrite(str(target), distort_image(image, BENT_K, (image.shape[1], image.shape[0])))
        out.append((f"{label}, bent (k {BENT_K:g})", str(target)))
    return out


def distortion_rows(images: list[tuple[str, str]], repeats: int, progress, batch: int = BATCH,
                    modes: tuple[str, ...] = ("fr", "fast")) -> list[dict]:
    """Latency per photo (batch 1) and ms per image in batches of ``batch`` (the photo's
    segments repeated) of every :data:`SETTINGS` row of ``modes`` on every image, with the ratio
    to the image's first row (pinhole fR when ``modes`` has fR)."""
    from fr_eval.bench.timing import bench_estimator, median_times

    from fr_torch.detectors.registry import get_detector
    from fr_torch.images.convert import to_gray8
    from fr_torch.images.io import load_image

    detector = get_detector("lsd")
    rows = []
    for label, path in images:
        gray = to_gray8(load_image(path))
        segments = detector(gray)
        size = (gray.shape[1], gray.shape[0])
        baseline = None
        for mode, distortion in SETTINGS:
            if mode not in modes or progress.out_of_time(f"distortion {label} {mode} {distortion}"):
                continue
            est = bench_estimator(mode, distortion=distortion)
            est.calibrate_images([path])  # warm-up
            walls, stages = [], []
            for _ in range(repeats):
                start = time.perf_counter()
                [result] = est.calibrate_images([path])
                walls.append(time.perf_counter() - start)
                stages.append(result.runtime_s)
            batch_s = statistics.median(median_times(
                lambda: est.calibrate_segments([segments] * batch, [size] * batch), max(1, min(repeats, 3))))
            row = {"image": label, "mode": mode, "distortion": distortion, "segments": result.num_segments,
                   "model": result.distortion_model,
                   "k": result.distortion_k,
                   "latency_ms": 1000 * statistics.median(walls),
                   "grid_ms": 1000 * statistics.median(s.get("grid", 0.0) for s in stages),
                   "refine_ms": 1000 * statistics.median(s.get("refine", 0.0) for s in stages),
                   "cues_ms": 1000 * statistics.median(s.get("cues", 0.0) for s in stages),
                   "batch": batch, "batch_ms_per_image": 1000 * batch_s / batch}
            baseline = baseline or row
            row["latency_ratio"] = row["latency_ms"] / baseline["latency_ms"]
            row["batch_ratio"] = row["batch_ms_per_image"] / baseline["batch_ms_per_image"]
            rows.append(row)
            progress.update(1, "distortion", row)
    return rows


def _table(title: str, yardstick: str, columns: list[str], rows: list[dict], first_cells) -> list[str]:
    """A report table of :func:`distortion_rows`: ``title``, the common wording with ``yardstick``
    (what the ratios divide by), ``columns`` before the timing ones and ``first_cells(row)`` their
    cells."""
    if not rows:
        return []
    names = columns + ["per photo (ms)", "ratio", "batch (ms/image)", "ratio"]
    lines = [f"## {title}", "",
             "Per photo: `calibrate_images` on one photo (decode, LSD, search, cues, reliability), median ms. "
             f"Batch: `calibrate_segments` on {rows[0].get('batch', BATCH)} copies of the photo's segments, ms per "
             f"image. Ratio: to {yardstick} (`fr_eval.bench.distortion`).", "",
             "| " + " | ".join(names) + " |", "|" + "---|" * len(names)]
    for r in rows:
        cells = first_cells(r) + [f"{r['latency_ms']:.1f}", f"{r.get('latency_ratio', float('nan')):.2f}",
                                  f"{r['batch_ms_per_image']:.1f}", f"{r.get('batch_ratio', float('nan')):.2f}"]
        lines.append("| " + " | ".join(cells) + " |")
    return lines + [""]


def markdown_lines(rows: list[dict]) -> list[str]:
    """The report's table of :func:`distortion_rows`."""
    return _table("Radial distortion: what the division model costs (CPU)",
                  f"pinhole fR on the same photo. Bent photos: the photo through a barrel lens of k = {BENT_K:g} "
                  "(division model)", ["image", "mode", "distortion", "model found", "k"], rows,
                  lambda r: [r["image"], r["mode"], r["distortion"], r["model"], f"{r['k']:+.3f}"])
