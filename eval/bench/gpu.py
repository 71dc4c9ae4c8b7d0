"""``fr bench``'s grid kernel alone on a GPU: stage 1 as deviations per second and the fraction of
the card's FP32 peak."""
from __future__ import annotations

import statistics

from fr_eval.bench.timing import bench_estimator, device_sync, median_times, scene_segments

#: Arithmetic per deviation of the measure-b grid kernel, in FLOPs (an FMA = 2): s and t (two 3-term
#: dot products, 10), |s|, |t| (2), atan2 (a division and a degree-9 polynomial with range
#: reduction, about 20), the exponent's scale, offset and clamp (3), exp (about 10) and the
#: mixture's add (1).  A convention, for the fraction of peak below, not a count of instructions.
FLOPS_PER_DEVIATION = 46
#: FP32 (non-tensor-core) peak of GPUs we have measured on, FLOP/s, from the vendor's data sheets
#: (SXM boards, boost clock).
GPU_FP32_PEAK = {"H100": 66.9e12, "H200": 66.9e12}


def grid_kernel(device: str, batch: int, n_segments: int, repeats: int, progress) -> dict | None:
    """Stage 1 alone: the 8^4 grid of ``batch`` images x ``n_segments`` segments scored by
    :func:`fr_torch.core.search.grid.score_grid`.  Reports deviations per second
    (B x G x N x 3, the nominal count) and, on a GPU of :data:`GPU_FP32_PEAK`, the fraction of its
    FP32 peak that :data:`FLOPS_PER_DEVIATION` per deviation amounts to."""
    import torch

    from fr_torch.core.geometry.conventions import image_centre
    from fr_torch.core.likelihood.measures import SegmentFeatures
    from fr_torch.core.likelihood.segments import SegmentBatch
    from fr_torch.core.search.grid import grid_hypotheses, score_grid

    label = f"grid kernel {device}"
    if progress.out_of_time(label):
        return None
    est = bench_estimator("fast", device)
    pool = [scene_segments(n_segments, seed=i) for i in range(8)]
    sizes = [(640, 480)] * batch
    segments = SegmentBatch.from_list([pool[i % len(pool)] for i in range(batch)], sizes, device, torch.float32)
    centre = torch.tensor([image_centre(640, 480)] * batch, dtype=torch.float32, device=device)
    features = SegmentFeatures.from_batch(segments, centre)
    hypotheses = grid_hypotheses(est.search, torch.full((batch,), 640.0, dtype=torch.float64, device=device))
    k = est.search.grid_points_per_dim
    fn = lambda: score_grid(est.likelihood, features, hypotheses, est.search.max_chunk_elements,  # noqa: E731
                            vertical_block=k)
    fn()  # warm-up
    t = statistics.median(median_times(fn, repeats, warmup=1, sync=device_sync(device)))
    deviations = batch * hypotheses.shape[1] * n_segments * 3
    row = {"device": device, "batch": batch,
           "segments": n_segments, "hypotheses": int(hypotheses.shape[1]), "seconds": t,
           "deviations_per_s": deviations / t, "images_per_s": batch / t}
    if device.startswith("cuda"):
        name = torch.cuda.get_device_name(device)
        peak = next((v for key, v in GPU_FP32_PEAK.items() if key in name), None)
        if peak:
            row["fraction_of_fp32_peak"] = deviations * FLOPS_PER_DEVIATION / t / peak
    progress.update(1, "grid_kernel", row)
    return row
