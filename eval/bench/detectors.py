"""``fr bench`` rows for line-segment detectors (section ``detectors``).

* :func:`detector_rows`: per image, the wall time (ms, median) of LSD and of ``torch-lines`` on the
  CPU, measured in the same loop (the detectors alternate, so machine load hits both alike), and
  their ratio.  Torch runs with the bench's ``--threads`` (default 1; LSD is single-threaded).
* :func:`device_end_to_end`: on a CUDA device only, images/s from JPEG files to results for
  batches of 640 x 480 JPEGs through the library's GPU path (``decode_jpeg``, ``torch-lines`` and
  the search on the device: :mod:`fr_torch.runtime.device_pipeline`); rows are skipped on a
  CPU-only machine.
"""
from __future__ import annotations

import statistics
import time
from pathlib import Path

import numpy as np

DETECTORS = ("lsd", "torch-lines")


def detector_rows(images: list[tuple[str, str]], repeats: int, progress) -> list[dict]:
    """One row per image: ``{image, width, height, <name>_ms, <name>_segments, ratio}`` where
    ratio = torch-lines ms / LSD ms (CPU, wall time, median over ``repeats`` alternating runs)."""
    from fr_torch.detectors.registry import get_detector
    from fr_torch.images.convert import to_gray8
    from fr_torch.images.io import load_image

    detectors = {name: get_detector(name) for name in DETECTORS}
    rows = []
    for label, path in images:
        if progress.out_of_time(f"detectors {label}"):
            continue
        gray = to_gray8(load_image(path))
        counts = {name: len(detector(gray)) for name, detector in detectors.items()}  # warm-up
        times: dict[str, list[float]] = {name: [] for name in detectors}
        for _ in range(max(1, repeats)):
            for name, detector in detectors.items():
                start = time.perf_counter()
                detector(gray)
                times[name].append(time.perf_counter() - start)
        row = {"image": label, "width": int(gray.shape[1]), "height": int(gray.shape[0])}
        for name in detectors:
            row[f"{name}_ms"] = 1000 * statistics.median(times[name])
            row[f"{name}_segments"] = counts[name]
        row["ratio"] = row["torch-lines_ms"] / row["lsd_ms"]
        rows.append(row)
        progress.update(1, "detectors", row)
    return rows


def device_end_to_end(paths: list[str], device: str, batch_sizes, repeats: int, progress,
                      modes=("fast", "fr"), batches_per_row: int = 4) -> list[dict]:
    """Images/s from JPEG files to results on ``device`` (CUDA only; [] elsewhere), per mode and
    batch size, through the path ``calibrate_images``, ``fr calibrate`` and ``fr batch`` take there
    (:func:`fr_torch.runtime.pipeline.calibrate_paths`: decode_jpeg, torch-lines and the search on
    the device, a reader thread one batch ahead; :mod:`fr_torch.runtime.device_pipeline`).

    ``paths``: same-size images (other formats are written as JPEGs, quality 95, first); each row
    calibrates ``batches_per_row`` batches of them (the files repeated), after one warm-up batch;
    the median of ``repeats`` such runs (one for batches of 256 and more).  ``path`` says whether the
    device path was taken."""
    import tempfile

    import torch

    if not paths or not str(device).startswith("cuda") or not torch.cuda.is_available():
        return []
    from fr_torch.runtime.device_pipeline import device_path_gap
    from fr_torch.runtime.estimator import FREstimator
    from fr_torch.runtime.pipeline import calibrate_paths

    folder = tempfile.TemporaryDirectory()
    files = []
    for i, path in enumerate(paths):
        files.append(str(Path(folder.name) / f"image{i}.jpg"))
        Path(files[-1]).write_bytes(_jpeg_bytes(path))
    rows = []
    for mode in modes:
        estimator = FREstimator(mode=mode, device=device)
        gap = device_path_gap(estimator)
        for batch in batch_sizes:
            if progress.out_of_time(f"device end to end {mode} batch {batch}"):
                continue
            todo = [files[i % len(files)] for i in range(batches_per_row * batch)]
            row = {"device": device, "mode": mode, "batch": batch, "images": len(todo),
                   "path": "device" if gap is None else f"host ({gap})"}
            try:
                list(calibrate_paths(estimator, todo[:batch], batch))  # warm-up at this batch size
                seconds = []
                for _ in range(max(1, repeats if batch < 256 else 1)):  # a large row: one timed run
                    torch.cuda.synchronize()
                    start = time.perf_counter()
                    results = [r for _, chunk in calibrate_paths(estimator, todo, batch) for r in chunk]
                    torch.cuda.synchronize()
                    seconds.append(time.perf_counter() - start)
                wall = statistics.median(seconds)
                row.update(seconds=wall, images_per_s=len(todo) / wall,
                           ok_share=float(np.mean([r.ok for r in results])))
            except Exception as exc:  # noqa: BLE001 - a failed setting is reported, the bench goes on
                row["error"] = f"{type(exc).__name__}: {exc}"
            rows.append(row)
            progress.update(1, "device_end_to_end", row)
    folder.cleanup()
    return rows


def _jpeg_bytes(path: str) -> bytes:
    """The file's bytes if it is a JPEG, else the image encoded as JPEG (quality 95)."""
    raw = Path(path).read_bytes()
    if raw[:2] == b"\xff\xd8":
        return raw
    import cv2

    ok, encoded = cv2.imencode(".jpg", cv2.imread(path, cv2.IMREAD_COLOR), [cv2.IMWRITE_JPEG_QUALITY, 95])
    if not ok:
        raise ValueError(f"{path}: cannot encode as JPEG")
    return encoded.tobytes()


def markdown_lines(report: dict) -> list[str]:
    """bench.md's detector tables (empty when the report has no detector rows)."""
    lines = []
    rows = report.get("detectors") or []
    if rows:
        lines += ["## Line-segment detectors per image (CPU, wall ms, same loop)", "",
                  "| image | size | LSD ms | torch-lines ms | torch-lines / LSD | LSD segments | torch-lines segments |",
                  "|---|---|---|---|---|---|---|"]
        for r in rows:
            lines.append(f"| {r['image']} | {r['width']}x{r['height']} | {r['lsd_ms']:.1f} | {r['torch-lines_ms']:.1f} | "
                         f"{r['ratio']:.2f} | {r['lsd_segments']} | {r['torch-lines_segments']} |")
        lines += ["", f"Median ratio: {statistics.median(r['ratio'] for r in rows):.2f}.", ""]
    rows = report.get("device_end_to_end") or []
    if rows:
        lines += ["## End to end on the device: JPEG files -> decode_jpeg -> torch-lines -> search", "",
                  "| device | mode | batch | images | images/s | s per row | valid share | decoded on |",
                  "|---|---|---|---|---|---|---|---|"]
        for r in rows:
            if "error" in r:
                lines.append(f"| {r['device']} | {r['mode']} | {r['batch']} | | failed: {r['error']} | | | |")
            else:
                lines.append(f"| {r['device']} | {r['mode']} | {r['batch']} | {r.get('images', r['batch'])} | "
                             f"{r['images_per_s']:.0f} | {r['seconds']:.3f} | {r['ok_share']:.2f} | "
                             f"{r.get('path', 'device')} |")
        lines.append("")
    return lines
