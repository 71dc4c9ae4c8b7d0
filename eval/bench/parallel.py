"""``fr bench``'s CPU parallelism section: intra-op threads in one process vs single-threaded worker
processes."""
from __future__ import annotations

import statistics

from fr_eval.bench.timing import bench_estimator, median_times, scene_segments


def parallel_scaling(counts, batch: int, n_segments: int, repeats: int, progress, modes=("fast", "fr")) -> list[dict]:
    """CPU images/s given segments with T intra-op threads (one process) and with W single-threaded
    worker processes (:func:`fr_torch.runtime.pipeline.calibrate_segments_sharded`, pool started before timing)."""
    import torch

    from fr_torch.runtime.pipeline import calibrate_segments_sharded, worker_pool

    pool = [scene_segments(n_segments, seed=i) for i in range(8)]
    segs = [pool[i % len(pool)] for i in range(batch)]
    sizes = [(640, 480)] * batch
    from fr_torch.runtime.device import DevicePolicy

    rows, threads_before = [], torch.get_num_threads()
    for mode in modes:
        est = bench_estimator(mode, DevicePolicy.resolve("cpu", threads="torch"))  # exactly T threads, whatever the load
        for count in counts:
            for kind in ("threads", "workers"):
                if progress.out_of_time(f"parallel {mode} {kind} {count}"):
                    continue
                workers = None
                if kind == "threads":
                    torch.set_num_threads(count)
                    fn = lambda: est.calibrate_segments(segs, sizes)  # noqa: E731
                else:
                    torch.set_num_threads(1)
                    workers = worker_pool(count)
                    fn = lambda: calibrate_segments_sharded(est, segs, sizes, count, pool=workers)  # noqa: E731
                try:
                    t = statistics.median(median_times(fn, max(1, min(repeats, 3)), warmup=1))
                finally:
                    torch.set_num_threads(threads_before)
                    if workers is not None:
                        workers.shutdown()
                row = {"mode": mode, "kind": kind, "count": count, "batch": batch, "segments": n_segments,
                       "images_per_s": batch / t, "ms_per_image": 1000 * t / batch}
                rows.append(row)
                progress.update(1, "parallel", row)
    return rows
