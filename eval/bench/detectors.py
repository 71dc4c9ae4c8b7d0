"""``fr bench`` rows for line-segment detectors (section ``detectors``).

* :func:`detector_rows`: per image, the wall time (ms, median) of LSD and of ``torch-lines`` on the
  CPU, measured in the same loop (the detectors alternate, so machine load hits both alike), and
  their ratio.  Torch runs with the bench's ``--threads`` (default 1; LSD is single-threaded).
* :func:`device_end_to_end`: on a CUDA device only, images/s from JPEG bytes to results for a batch
  of 640 x 480 JPEGs: ``torchvision.io.decode_jpeg`` on the device, ``torch-lines`` on the device
  (:meth:`~fr_torch.detectors.tensor_lines.TensorLinesDetector.detect_batch`), then the search
  (:func:`fr_torch.runtime.device_pipeline.calibrate_decoded`); rows are skipped on a CPU-only machine.
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
                      modes=("fast", "fr")) -> list[dict]:
    """Images/s from JPEG bytes to results on ``device`` (CUDA only; [] elsewhere), per mode and
    batch size; the batch repeats ``paths`` (same-size images; other formats are JPEG-encoded,
    quality 95, before timing) to the batch size."""
    import torch

    if not paths or not str(device).startswith("cuda") or not torch.cuda.is_available():
        return []
    from fr_torch.detectors.tensor_lines import TensorLinesDetector, decode_jpeg_batch
    from fr_torch.runtime.device_pipeline import calibrate_decoded
    from fr_torch.runtime.estimator import FREstimator

    data = [_jpeg_bytes(p) for p in paths]
    detector = TensorLinesDetector(device=device)
    rows = []
    for mode in modes:
        estimator = FREstimator(mode=mode, device=device)
        for batch in batch_sizes:
            if progress.out_of_time(f"device end to end {mode} batch {batch}"):
                continue
            payload = [data[i % len(data)] for i in range(batch)]

            def once():
                images = torch.stack(decode_jpeg_batch(payload, device=device))
                return calibrate_decoded(estimator, detector, images)

            row = {"device": device, "mode": mode, "batch": batch}
            try:
                once()  # warm-up
                seconds = []
                for _ in range(max(1, repeats)):
                    torch.cuda.synchronize()
                    start = time.perf_counter()
                    results = once()
                    torch.cuda.synchronize()
                    seconds.append(time.perf_counter() - start)
                wall = statistics.median(seconds)
                row.update(seconds=wall, images_per_s=batch / wall,
                           ok_share=float(np.mean([r.ok for r in results])))
            except Exception as exc:  # noqa: BLE001 - a failed setting is reported, the bench goes on
                row["error"] = f"{type(exc).__name__}: {exc}"
            rows.append(row)
            progress.update(1, "device_end_to_end", row)
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
        lines += ["## End to end on the device: JPEG bytes -> decode_jpeg -> torch-lines -> search", "",
                  "| device | mode | batch | images/s | s per batch | valid share |", "|---|---|---|---|---|---|"]
        for r in rows:
            if "error" in r:
                lines.append(f"| {r['device']} | {r['mode']} | {r['batch']} | failed: {r['error']} | | |")
            else:
                lines.append(f"| {r['device']} | {r['mode']} | {r['batch']} | {r['images_per_s']:.0f} | "
                             f"{r['seconds']:.3f} | {r['ok_share']:.2f} |")
        lines.append("")
    return lines
