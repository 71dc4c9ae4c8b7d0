"""``fr bench`` sections that time the search: end-to-end latency per photo, throughput given
segments per batch size, the work outside the search, and scaling with segments and grid size."""
from __future__ import annotations

import statistics
import time

from fr_eval.bench.timing import STAGES, bench_estimator, device_sync, median_times, scene_segments


def transcendental_ns(device: str = "cpu") -> float:
    """ns per element of atan2 + exp on an in-cache float32 buffer (the grid's floor per deviation)."""
    import torch

    n = 1 << 17
    x, y = torch.rand(n, device=device), torch.rand(n, device=device)
    z = torch.empty(n, device=device)
    ta = statistics.median(median_times(lambda: torch.atan2(x, y, out=z), 15, 3, device_sync(device)))
    te = statistics.median(median_times(lambda: torch.exp(x, out=z), 15, 3, device_sync(device)))
    return (ta + te) / n * 1e9


def end_to_end(images: list[tuple[str, str]], repeats: int, progress, modes=("fast", "fr")) -> list[dict]:
    """Latency of calibrate_images on single images (batch 1), per stage, medians (ms), after a
    warm-up call."""
    from fr_torch.core.search.grid import stage1_hypothesis_count
    from fr_torch.detectors.registry import get_detector
    from fr_torch.images.convert import to_gray8
    from fr_torch.images.io import load_image

    rows = []
    detector = get_detector("lsd")
    for label, path in images:
        gray = to_gray8(load_image(path))
        decode = statistics.median(median_times(lambda: load_image(path), repeats))
        lsd = statistics.median(median_times(lambda: detector(gray), repeats))
        for mode in modes:
            if progress.out_of_time(f"end_to_end {label} {mode}"):
                continue
            est = bench_estimator(mode)
            est.calibrate_images([path])  # warm-up
            runs = []
            for _ in range(repeats):
                start = time.perf_counter()
                [result] = est.calibrate_images([path])
                wall = time.perf_counter() - start
                runs.append(dict(result.runtime_s, wall=wall))
            row = {"image": label, "mode": mode, "segments": result.num_segments,
                   "width": result.width, "height": result.height}
            for key in STAGES + ("wall",):
                row[f"{key}_ms"] = 1000 * statistics.median(r.get(key, 0.0) for r in runs)
            row["decode_ms"], row["lsd_ms"] = 1000 * decode, 1000 * lsd
            row["iterations"] = est.iterations
            row["grid_hypotheses"] = est.search.grid_points_per_dim ** 4
            row["grid_hypotheses_scored"] = stage1_hypothesis_count(est.search)
            rows.append(row)
            progress.update(1, "end_to_end", row)
    return rows


def throughput(batch_sizes, n_segments: int, device: str, repeats: int, progress, mode: str = "fast",
               reliability: bool = True) -> list[dict]:
    """Images/s of calibrate_segments (grid + refinement + cues) for each batch size, after a
    warm-up call.  ``reliability=False``: without the reliability stage (rows marked
    ``reliability: false``)."""
    est = bench_estimator(mode, device, reliability=reliability)
    pool = [scene_segments(n_segments, seed=i) for i in range(8)]
    est.calibrate_segments(pool[:1], [(640, 480)])  # warm-up
    rows = []
    for batch in batch_sizes:
        if progress.out_of_time(f"throughput {device} {mode}{'' if reliability else ' no-reliability'} {batch}"):
            continue
        segs = [pool[i % len(pool)] for i in range(batch)]
        sizes = [(640, 480)] * batch
        reps = repeats if batch <= 64 else 1 if batch > 4096 else max(1, min(repeats, 2))
        if device.startswith("cuda"):
            import torch

            torch.cuda.reset_peak_memory_stats()
        times = median_times(lambda: est.calibrate_segments(segs, sizes), reps, warmup=1 if batch <= 64 else 0,
                              sync=device_sync(device))
        t = statistics.median(times)
        row = {"device": device, "mode": mode, "batch": batch, "segments": n_segments, "seconds": t,
               "images_per_s": batch / t, "ms_per_image": 1000 * t / batch, "repeats": reps, "reliability": reliability}
        if device.startswith("cuda"):  # over the timed runs (no extra run: a batch of 16384 takes seconds)
            row["peak_memory_mb"] = torch.cuda.max_memory_allocated() / 2 ** 20
        rows.append(row)
        progress.update(1, "throughput", row)
    return rows


def outside_search(batch: int, n_segments: int, device: str, repeats: int, progress) -> dict | None:
    """ms per image of everything but the search: ``calibrate_segments`` on ``batch`` images with a
    minimal search (k = 2, one start, no focal sweep, no passes, one step), default reliability
    stage included."""
    from fr_torch import FREstimator
    from fr_torch.core.settings.config import SearchConfig

    if progress.out_of_time(f"outside-search {device}"):
        return None
    config = SearchConfig.from_config(grid_points_per_dim=2, top_l=1, focal_sweep_points=0, grid_passes=0,
                                      refine_iterations=1)
    est = FREstimator(mode="fast", device=device, search_config=config)
    pool = [scene_segments(n_segments, seed=i) for i in range(8)]
    segs, sizes = [pool[i % len(pool)] for i in range(batch)], [(640, 480)] * batch
    times = median_times(lambda: est.calibrate_segments(segs, sizes), repeats, warmup=1, sync=device_sync(device))
    ms = 1000 * statistics.median(times) / batch
    row = {"device": device, "batch": batch, "segments": n_segments, "ms_per_image": ms,
           "ceiling_images_per_s": 1000 / ms}
    progress.update(1, "outside_search", row)
    return row



def scaling(segment_counts, grid_sizes, device: str, repeats: int, progress, mode: str = "fast") -> dict:
    """Per-image time (ms, batch 1, given segments) against N segments and against grid size k (with
    the hypotheses stage 1 scores at each k: coarse to fine where 2 divides k)."""
    from fr_torch.core.search.grid import stage1_hypothesis_count

    out = {"segments": [], "grid": []}
    est = bench_estimator(mode, device)
    for n in segment_counts:
        if progress.out_of_time(f"scaling segments {n}"):
            continue
        seg = scene_segments(n, seed=1)
        runs = []
        est.calibrate_segments([seg], [(640, 480)])
        for _ in range(repeats):
            [r] = est.calibrate_segments([seg], [(640, 480)])
            runs.append(r.runtime_s)
        out["segments"].append({"segments": n, **{f"{k}_ms": 1000 * statistics.median(x[k] for x in runs)
                                                  for k in ("grid", "refine", "cues", "total")}})
        progress.update(1, "scaling", out["segments"][-1])
    seg = scene_segments(500, seed=1)
    for k in grid_sizes:
        if progress.out_of_time(f"scaling k {k}"):
            continue
        est_k = bench_estimator(mode, device, k)
        est_k.calibrate_segments([seg], [(640, 480)])
        runs = []
        for _ in range(repeats):
            [r] = est_k.calibrate_segments([seg], [(640, 480)])
            runs.append(r.runtime_s)
        out["grid"].append({"k": k, "hypotheses": stage1_hypothesis_count(est_k.search), "segments": 500,
                            **{f"{key}_ms": 1000 * statistics.median(x[key] for x in runs)
                               for key in ("grid", "refine", "cues", "total")}})
        progress.update(1, "scaling", out["grid"][-1])
    return out
