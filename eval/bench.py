"""``fr bench``: speed benchmark of fR / Fast-fR -- latency, throughput, memory, scaling.

Measures (warm-up first, medians over repeats) and writes ``<out>/bench.json``, ``<out>/bench.md``
and ``<out>/scaling.png`` (default ``results/bench``):

1. **End-to-end latency** per 640x480 image on CPU (decode + LSD + search), ``fr`` and ``fast``,
   split by stage (``detect`` = decode + LSD, ``grid``, ``refine``, ``cues``), on a rendered room
   (:func:`fr_torch.synthetic.render_manhattan_room`, written to a temporary PNG so decoding is
   included) and, when the data root exists, a few YorkUrbanDB images.  The floors are reported
   too: decode + LSD alone, and for the grid the time of its two transcendental passes (atan2 +
   exp) over all G x N x 3 deviations at the in-cache speed measured on this machine.
2. **Throughput** given segments (grid + refinement + cues), images/s, batch 1 ... 1024, on CPU
   and on CUDA when available (timed with ``torch.cuda.synchronize``).
3. **Peak memory** per batch size: on CPU the peak-RSS increase (``VmHWM`` after resetting it,
   ``ru_maxrss`` where /proc is missing) of a fresh subprocess per setting (tracemalloc does not see torch); on CUDA ``torch.cuda.max_memory_allocated``.  With
   ``--stress`` it also checks that a batch of 4096 images x 1000 segments stays bounded (with a
   k=4 grid to keep it short: memory does not depend on k, since the grid is chunked).
4. **Scaling**: time against the number of segments (100 ... 5000) and the grid size k (4 ... 12).
5. **CPU parallelism**: images/s given segments (batch 64) with T intra-op threads vs W
   single-threaded worker processes (:func:`fr_torch.runtime.pipeline.calibrate_segments_sharded`),
   for T, W in 1, 2, 4, 8, cores.
6. **Work outside the search**: ms per image of ``calibrate_segments`` on a large batch with a
   minimal search (k = 2 grid, one start, no sweep or passes, one refinement step): input checks, the
   segment filter, batching, result records, checks, the cues and reliability predictions.  It bounds
   the throughput a device can reach (1000 / ms images/s), per device; it includes tensor work that
   runs on the device (the minimal search, and the ``focal_prior_share`` cue's 81-point lattice per
   image), so on a CPU it is an upper bound of the host's share.
7. **Where the time goes**: a torch profiler table (top ops by self time) of one batch, per device
   (on a GPU per mode), in ``<out>/profile_<device>_<mode>.txt`` and summarised in bench.md.
8. **Contention** (CPU): seconds per photo, one photo per call, given segments and end to end, in
   fresh processes with the commands' thread policy (``FR_THREADS``, default ``auto``): idle, beside
   a busy neighbour (a pure-Python spin loop in a subprocess started and stopped here), as a ratio
   to idle, and two processes side by side (their photos/s together over one alone's)
   (:mod:`fr_eval.contention`; docs/cpu-threads.md).
9. **The grid kernel alone** (on a GPU): stage 1 of 1024 images, eager and with ``--compile``
   compiled, as deviations per second and the fraction of the card's FP32 peak they amount to
   (:data:`FLOPS_PER_DEVIATION`, :data:`GPU_FP32_PEAK`).

Every measurement is written as it is taken: one JSON line per row in ``<out>/bench.jsonl``
(flushed) and one progress line on stderr; bench.json / bench.md / scaling.png at the end.
``--budget-s`` bounds the run: settings not started within the budget are skipped and listed
(default 150 s when a CUDA device is measured, meant to end ``fr bench --device cuda`` in about 3
minutes without ``--compile``: with it, compiling took 16-39 s per mode on an H100 and two runs
went past 3 minutes, results/bench/h100/README.md; the CUDA figures are taken first, with batches 1 ... 16384, 3 repeats
up to 64, 2 up to 4096, then 1).  ``--sections`` picks what to measure (e.g. ``parallel`` alone for
CPU scaling on a large machine); ``--from-jsonl`` writes the report of a run that was cut short from
its rows.  Throughput is drawn in ``<out>/throughput.png``.

``--quick`` is a tiny smoke run (seconds).  The machine (CPU model, cores, torch version, threads,
device, load average) is recorded with the numbers: on a shared machine timings are noisy, so
compare runs only on the same machine and look at the load average.

Threads: single-threaded by default (``--threads 1``).  On a machine shared with other jobs an
OpenMP/MKL parallel region waits for its slowest thread, and a thread that has lost its core
stalls every op (seen here: 10-50x slower with 2 threads under load); ``--threads 0`` keeps
torch's default, ``--threads 2`` uses both cores of an idle 2-core machine.

Run ``fr bench [--quick] [--device cuda] [--out DIR] [--threads T]`` or ``python -m fr_eval.bench``.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from fr_eval import bench_detectors, bench_distortion

from fr_torch.cli.options import add_device_arguments
from fr_torch.runtime.workers import usable_cores

REPO = Path(__file__).resolve().parents[1]
DEFAULT_OUT = REPO / "results" / "bench"
STAGES = ("detect", "grid", "refine", "cues", "total")
SECTIONS = ("device", "latency", "detectors", "parallel", "cpu", "memory", "scaling", "contention",
            "distortion")  # --sections, in running order


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--quick", action="store_true", help="tiny smoke run (CI): a few seconds")
    add_device_arguments(parser, default="auto", device_help="cpu, cuda or auto (cuda when available; CPU is always "
                                                             "measured)")
    parser.add_argument("--out", type=Path, default=DEFAULT_OUT, help=f"output folder (default {DEFAULT_OUT})")
    parser.add_argument("--threads", type=int, default=1,
                        help="torch CPU threads (default 1: on a shared machine multi-threaded torch ops stall "
                             "whenever another process holds a core; 0 = torch's default)")
    parser.add_argument("--repeats", type=int, default=None, help="timed repeats per setting (default 7, quick 2)")
    parser.add_argument("--data-root", default=None, help="dataset root (default: fr_eval.paths.data_root())")
    parser.add_argument("--no-memory", action="store_true", help="skip the memory subprocesses")
    parser.add_argument("--stress", action="store_true",
                        help="also run the bounded-memory check: batch 4096 x 1000 segments (k=4; minutes)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    parser.add_argument("--batches", default=None, metavar="B,B,...",
                        help="CPU batch sizes for throughput and memory (default 1,8,64,256,1024)")
    parser.add_argument("--budget-s", type=float, default=None,
                        help="time budget in seconds: settings not started by then are skipped and listed "
                             "(default 150 with a CUDA device, else none; 0 = none)")
    parser.add_argument("--compile", action="store_true",
                        help="also measure throughput given segments with the search compiled by torch.compile "
                             "(SearchConfig.compile_search; its compilation time is reported beside)")
    parser.add_argument("--sections", default=",".join(SECTIONS), metavar="S,S,...",
                        help="what to measure (default all): device = throughput, outside-search work and "
                             "profile on the --device GPU; latency = end to end per photo; detectors = LSD vs "
                             "torch-lines per photo on the CPU (and JPEG-to-result on a GPU); parallel = CPU "
                             "threads vs worker processes; cpu = CPU throughput, outside-search work and "
                             "profile; memory; scaling = time against segments and grid size; contention = "
                             "per-photo time idle vs beside a busy neighbour vs 2 processes side by side; "
                             "distortion = fR / Fast-fR with --distortion pinhole, division, auto on photos and "
                             "barrel-bent copies (issue 46)")
    parser.add_argument("--from-jsonl", type=Path, default=None, metavar="JSONL",
                        help="measure nothing: write bench.md / bench.json / the figures to --out from the rows of "
                             "an earlier run's bench.jsonl (one that was cut short, say)")
    parser.add_argument("--memory-probe", default=None, help=argparse.SUPPRESS)  # internal: "B,N,k,mode,device"


# --------------------------------------------------------------------------- helpers

def _median_times(fn, repeats: int, warmup: int = 1, sync=None) -> list[float]:
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(repeats):
        if sync:
            sync()
        start = time.perf_counter()
        fn()
        if sync:
            sync()
        times.append(time.perf_counter() - start)
    return times


def _cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def machine_description(device: str) -> dict:
    import torch

    info = {"cpu": _cpu_model(), "cores": os.cpu_count(), "usable_cores": usable_cores(), "torch": torch.__version__,
            "threads": torch.get_num_threads(), "fr_threads": os.environ.get("FR_THREADS", "auto"), "device": device, "python": platform.python_version(),
            "platform": platform.platform()}
    try:
        info["load_average"] = [round(x, 2) for x in os.getloadavg()]
    except OSError:
        pass
    if device.startswith("cuda"):
        try:
            info["gpu"] = torch.cuda.get_device_name(device)
        except (AssertionError, RuntimeError):  # no CUDA here: the record says so instead of failing
            info["gpu"] = "none available"
    return info


def _segments(n: int, seed: int = 0) -> np.ndarray:
    """About n synthetic segments of a 640x480 Manhattan scene (70 % Manhattan, 30 % clutter)."""
    from fr_torch.core.camera import focal_from_hfov, rotation_from_angles
    from fr_torch.synthetic import synthetic_segments

    rng = np.random.default_rng(seed)
    R = rotation_from_angles(*[np.float64(rng.uniform(-20, 20)) for _ in range(3)]).numpy()
    per_family = max(2, int(round(n * 0.7 / 3)))
    seg, _ = synthetic_segments(focal_from_hfov(70.0, 640), R, 640, 480, n_per_family=per_family,
                                clutter_fraction=0.3, seed=seed, min_length_px=10.0, max_length_px=80.0)
    if len(seg) < n:  # pad with jittered copies to reach exactly n
        extra = seg[rng.integers(0, len(seg), n - len(seg))] + rng.normal(0, 0.5, (n - len(seg), 4))
        seg = np.concatenate([seg, extra])
    return seg[:n]


def _estimator(mode: str, device="cpu", k: int | None = None, compile_search: bool = False,
               reliability: bool = True):
    """The estimator of a bench row; ``reliability=False``: no reliability stage (and so, in fR, no
    ``focal_profile_gap`` cue: ``fr batch --no-reliability``)."""
    from fr_torch import FREstimator
    from fr_torch.core.config import SearchConfig

    config = SearchConfig.from_config(compile_search=compile_search, **({"grid_points_per_dim": k} if k else {}))
    return FREstimator(mode=mode, device=device, search_config=config, **({} if reliability else {"reliability": None}))


def _sync(device: str):
    if device.startswith("cuda"):
        import torch

        return torch.cuda.synchronize
    return None


class _Progress:
    """tqdm bar + one JSON line per measurement, flushed at once (``<out>/bench.jsonl``), and a
    time budget: once ``budget_s`` has passed, the remaining settings are skipped (and listed)."""

    def __init__(self, total: int, disable: bool, log_path: Path | None = None, budget_s: float = 0.0):
        from tqdm import tqdm

        self.bar = tqdm(total=total, desc="fr bench", unit="step", disable=disable, file=sys.stderr)
        self.log = open(log_path, "w") if log_path else None
        self.start, self.budget_s, self.skipped = time.perf_counter(), budget_s, []

    def update(self, n: int = 1, section: str | None = None, row: dict | None = None) -> None:
        self.bar.update(n)
        if row is not None and self.log:
            self.log.write(json.dumps({"section": section, **row}) + "\n")
            self.log.flush()
        if row is not None:
            brief = ", ".join(f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}" for k, v in row.items()
                              if not isinstance(v, (dict, list)))
            self.bar.write(f"fr bench [{section}] {brief}", file=sys.stderr)

    def out_of_time(self, what: str) -> bool:
        if self.budget_s and time.perf_counter() - self.start > self.budget_s:
            self.skipped.append(what)
            return True
        return False

    def close(self) -> None:
        self.bar.close()
        if self.log:
            self.log.close()


def _progress(total: int, disable: bool, log_path: Path | None = None, budget_s: float = 0.0) -> _Progress:
    return _Progress(total, disable, log_path, budget_s)


# --------------------------------------------------------------------------- measurements

def _transcendental_ns(device: str = "cpu") -> float:
    """ns per element of atan2 + exp on an in-cache float32 buffer (the grid's floor per deviation)."""
    import torch

    n = 1 << 17
    x, y = torch.rand(n, device=device), torch.rand(n, device=device)
    z = torch.empty(n, device=device)
    ta = statistics.median(_median_times(lambda: torch.atan2(x, y, out=z), 15, 3, _sync(device)))
    te = statistics.median(_median_times(lambda: torch.exp(x, out=z), 15, 3, _sync(device)))
    return (ta + te) / n * 1e9


def end_to_end(images: list[tuple[str, str]], repeats: int, progress, modes=("fast", "fr"),
               compile_search: bool = False) -> list[dict]:
    """Latency of calibrate_images on single images (batch 1), per stage, medians (ms);
    ``compile_search``: also each mode with the compiled search (after its compiling warm-up)."""
    from fr_torch.detectors.registry import get_detector
    from fr_torch.images.convert import to_gray8
    from fr_torch.images.io import load_image

    rows = []
    detector = get_detector("lsd")
    for label, path in images:
        gray = to_gray8(load_image(path))
        decode = statistics.median(_median_times(lambda: load_image(path), repeats))
        lsd = statistics.median(_median_times(lambda: detector(gray), repeats))
        for mode, compiled in [(m, c) for m in modes for c in ((False, True) if compile_search else (False,))]:
            if progress.out_of_time(f"end_to_end {label} {mode}{' compiled' if compiled else ''}"):
                continue
            est = _estimator(mode, compile_search=compiled)
            start = time.perf_counter()
            est.calibrate_images([path])  # warm-up (compiles, the first time in this process)
            warmup_s = time.perf_counter() - start
            runs = []
            for _ in range(repeats):
                start = time.perf_counter()
                [result] = est.calibrate_images([path])
                wall = time.perf_counter() - start
                runs.append(dict(result.runtime_s, wall=wall))
            row = {"image": label, "mode": mode, "search": "compiled" if est.likelihood.compiled else "eager",
                   "segments": result.num_segments,
                   "width": result.width, "height": result.height}
            for key in STAGES + ("wall",):
                row[f"{key}_ms"] = 1000 * statistics.median(r.get(key, 0.0) for r in runs)
            row["decode_ms"], row["lsd_ms"] = 1000 * decode, 1000 * lsd
            row["iterations"] = est.iterations
            if compiled:
                row["compile_s"] = warmup_s
            row["grid_hypotheses"] = est.search.grid_points_per_dim ** 4
            rows.append(row)
            progress.update(1, "end_to_end", row)
    return rows


def throughput(batch_sizes, n_segments: int, device: str, repeats: int, progress, mode: str = "fast",
               compile_search: bool = False, reliability: bool = True) -> list[dict]:
    """Images/s of calibrate_segments (grid + refinement + cues) for each batch size.
    ``compile_search``: with the compiled search kernels; the warm-up call, which compiles them
    (once per process), is reported as ``compile_s``.  ``reliability=False``: without the
    reliability stage (rows marked ``reliability: false``)."""
    est = _estimator(mode, device, compile_search=compile_search, reliability=reliability)
    pool = [_segments(n_segments, seed=i) for i in range(8)]
    start = time.perf_counter()
    est.calibrate_segments(pool[:1], [(640, 480)])  # warm-up
    warmup_s = time.perf_counter() - start
    search = "compiled" if est.likelihood.compiled else "eager"  # eager also after a failed compile
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
        times = _median_times(lambda: est.calibrate_segments(segs, sizes), reps, warmup=1 if batch <= 64 else 0,
                              sync=_sync(device))
        t = statistics.median(times)
        row = {"device": device, "mode": mode, "search": search, "batch": batch, "segments": n_segments, "seconds": t,
               "images_per_s": batch / t, "ms_per_image": 1000 * t / batch, "repeats": reps, "reliability": reliability}
        if compile_search:
            row["compile_s"] = warmup_s
        if device.startswith("cuda"):  # over the timed runs (no extra run: a batch of 16384 takes seconds)
            row["peak_memory_mb"] = torch.cuda.max_memory_allocated() / 2 ** 20
        rows.append(row)
        progress.update(1, "throughput", row)
    return rows


#: Arithmetic per deviation of the measure-b grid kernel, in FLOPs (an FMA = 2): s and t (two 3-term
#: dot products, 10), |s|, |t| (2), atan2 (a division and a degree-9 polynomial with range
#: reduction, about 20), the exponent's scale, offset and clamp (3), exp (about 10) and the
#: mixture's add (1).  A convention, for the fraction of peak below, not a count of instructions.
FLOPS_PER_DEVIATION = 46
#: FP32 (non-tensor-core) peak of GPUs we have measured on, FLOP/s, from the vendor's data sheets
#: (SXM boards, boost clock).
GPU_FP32_PEAK = {"H100": 66.9e12, "H200": 66.9e12}


def grid_kernel(device: str, batch: int, n_segments: int, repeats: int, progress,
                compile_search: bool = False) -> dict | None:
    """Stage 1 alone: the 8^4 grid of ``batch`` images x ``n_segments`` segments scored by
    :func:`fr_torch.core.search.score_grid`, eager or compiled.  Reports deviations per second
    (B x G x N x 3, the nominal count) and, on a GPU of :data:`GPU_FP32_PEAK`, the fraction of its
    FP32 peak that :data:`FLOPS_PER_DEVIATION` per deviation amounts to."""
    import torch

    from fr_torch.core.camera import image_centre
    from fr_torch.core.likelihood import SegmentFeatures
    from fr_torch.core.search import grid_hypotheses, score_grid
    from fr_torch.core.segments import SegmentBatch

    label = f"grid kernel {device} {'compiled' if compile_search else 'eager'}"
    if progress.out_of_time(label):
        return None
    est = _estimator("fast", device, compile_search=compile_search)
    pool = [_segments(n_segments, seed=i) for i in range(8)]
    sizes = [(640, 480)] * batch
    segments = SegmentBatch.from_list([pool[i % len(pool)] for i in range(batch)], sizes, device, torch.float32)
    centre = torch.tensor([image_centre(640, 480)] * batch, dtype=torch.float32, device=device)
    features = SegmentFeatures.from_batch(segments, centre)
    hypotheses = grid_hypotheses(est.search, torch.full((batch,), 640.0, dtype=torch.float64, device=device))
    k = est.search.grid_points_per_dim
    fn = lambda: score_grid(est.likelihood, features, hypotheses, est.search.max_chunk_elements,  # noqa: E731
                            vertical_block=k)
    fn()  # warm-up (compiles, the first time in this process)
    t = statistics.median(_median_times(fn, repeats, warmup=1, sync=_sync(device)))
    deviations = batch * hypotheses.shape[1] * n_segments * 3
    row = {"device": device, "search": "compiled" if est.likelihood.compiled else "eager", "batch": batch,
           "segments": n_segments, "hypotheses": int(hypotheses.shape[1]), "seconds": t,
           "deviations_per_s": deviations / t, "images_per_s": batch / t}
    if device.startswith("cuda"):
        name = torch.cuda.get_device_name(device)
        peak = next((v for key, v in GPU_FP32_PEAK.items() if key in name), None)
        if peak:
            row["fraction_of_fp32_peak"] = deviations * FLOPS_PER_DEVIATION / t / peak
    progress.update(1, "grid_kernel", row)
    return row


def outside_search(batch: int, n_segments: int, device: str, repeats: int, progress) -> dict | None:
    """ms per image of everything but the search: ``calibrate_segments`` on ``batch`` images with a
    minimal search (k = 2, one start, no focal sweep, no passes, one step), default reliability
    stage included."""
    from fr_torch import FREstimator
    from fr_torch.core.config import SearchConfig

    if progress.out_of_time(f"outside-search {device}"):
        return None
    config = SearchConfig.from_config(grid_points_per_dim=2, top_l=1, focal_sweep_points=0, grid_passes=0,
                                      refine_iterations=1)
    est = FREstimator(mode="fast", device=device, search_config=config)
    pool = [_segments(n_segments, seed=i) for i in range(8)]
    segs, sizes = [pool[i % len(pool)] for i in range(batch)], [(640, 480)] * batch
    times = _median_times(lambda: est.calibrate_segments(segs, sizes), repeats, warmup=1, sync=_sync(device))
    ms = 1000 * statistics.median(times) / batch
    row = {"device": device, "batch": batch, "segments": n_segments, "ms_per_image": ms,
           "ceiling_images_per_s": 1000 / ms}
    progress.update(1, "outside_search", row)
    return row


def parallel_scaling(counts, batch: int, n_segments: int, repeats: int, progress, modes=("fast", "fr")) -> list[dict]:
    """CPU images/s given segments with T intra-op threads (one process) and with W single-threaded
    worker processes (:func:`fr_torch.runtime.pipeline.calibrate_segments_sharded`, pool started before timing)."""
    import torch

    from fr_torch.runtime.pipeline import calibrate_segments_sharded, worker_pool

    pool = [_segments(n_segments, seed=i) for i in range(8)]
    segs = [pool[i % len(pool)] for i in range(batch)]
    sizes = [(640, 480)] * batch
    from fr_torch.runtime.device import DevicePolicy

    rows, threads_before = [], torch.get_num_threads()
    for mode in modes:
        est = _estimator(mode, DevicePolicy.resolve("cpu", threads="torch"))  # exactly T threads, whatever the load
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
                    t = statistics.median(_median_times(fn, max(1, min(repeats, 3)), warmup=1))
                finally:
                    torch.set_num_threads(threads_before)
                    if workers is not None:
                        workers.shutdown()
                row = {"mode": mode, "kind": kind, "count": count, "batch": batch, "segments": n_segments,
                       "images_per_s": batch / t, "ms_per_image": 1000 * t / batch}
                rows.append(row)
                progress.update(1, "parallel", row)
    return rows


def profile_table(device: str, batch: int, n_segments: int, out: Path, progress, mode: str = "fast",
                  rows: int = 25) -> dict:
    """torch profiler over one calibrate_segments call: top ops by self time, written to
    ``<out>/profile_<device>_<mode>.txt``; returns the top ops as dicts (ms)."""
    from torch.profiler import ProfilerActivity, profile

    if progress.out_of_time(f"profile {device} {mode}"):
        return {}
    est = _estimator(mode, device)
    pool = [_segments(n_segments, seed=i) for i in range(8)]
    segs, sizes = [pool[i % len(pool)] for i in range(batch)], [(640, 480)] * batch
    est.calibrate_segments(segs[:2], sizes[:2])
    activities = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if device.startswith("cuda") else [])
    sync = _sync(device)
    with profile(activities=activities) as prof:
        start = time.perf_counter()
        est.calibrate_segments(segs, sizes)
        if sync:
            sync()
        wall = time.perf_counter() - start
    sort = "self_cuda_time_total" if device.startswith("cuda") else "self_cpu_time_total"
    averages = prof.key_averages()
    table = averages.table(sort_by=sort, row_limit=rows)
    path = out / f"profile_{device.split(':')[0]}_{mode}.txt"
    path.write_text(f"fr bench profile: device {device}, mode {mode}, batch {batch} x {n_segments} segments, "
                    f"wall {wall:.3f} s (with profiler overhead)\n\n{table}\n")
    key = "self_device_time_total" if device.startswith("cuda") else "self_cpu_time_total"
    top = sorted(averages, key=lambda e: getattr(e, key, 0.0), reverse=True)[:10]
    total = sum(getattr(e, key, 0.0) for e in averages) or 1.0
    result = {"device": device, "mode": mode, "batch": batch, "segments": n_segments, "wall_s": wall,
              "file": path.name, "top_ops": [{"op": e.key, "self_ms": getattr(e, key, 0.0) / 1000,
                                              "share": getattr(e, key, 0.0) / total, "calls": e.count} for e in top]}
    progress.update(1, "profile", {k: v for k, v in result.items() if k != "top_ops"})
    return result


def memory_probe(spec: str) -> dict:
    """Run inside a fresh process: peak RSS increase of one calibrate_segments call (MB)."""
    import torch

    batch, n_seg, k, mode, device = spec.split(",")
    batch, n_seg, k = int(batch), int(n_seg), int(k)
    est = _estimator(mode, device, k)
    pool = [_segments(n_seg, seed=i) for i in range(4)]
    segs = [pool[i % 4] for i in range(batch)]
    # Baseline after imports and inputs, before any search (so library warm-up counts, once).
    # ru_maxrss survives fork + exec (it would report the parent's size), so read VmHWM, reset
    # to the current RSS through /proc/self/clear_refs; ru_maxrss only where /proc is missing.
    before = _reset_peak_rss()
    start = time.perf_counter()
    if device.startswith("cuda"):
        torch.cuda.reset_peak_memory_stats()
    results = est.calibrate_segments(segs, [(640, 480)] * batch)
    seconds = time.perf_counter() - start
    after = _peak_rss()
    out = {"batch": batch, "segments": n_seg, "k": k, "mode": mode, "device": device, "seconds": seconds,
           "rss_before_mb": before / 1024, "peak_rss_mb": after / 1024, "peak_increase_mb": (after - before) / 1024,
           "input_mb": batch * n_seg * 4 * 8 / 2 ** 20, "ok": all(r.ok for r in results)}
    if device.startswith("cuda"):
        out["cuda_peak_mb"] = torch.cuda.max_memory_allocated() / 2 ** 20
    return out


def _proc_status_kb(key: str) -> int | None:
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith(key + ":"):
                return int(line.split()[1])
    except (OSError, ValueError):
        pass
    return None


def _reset_peak_rss() -> float:
    """Reset the peak-RSS mark to the current RSS (Linux); returns the current RSS in KiB."""
    try:
        Path("/proc/self/clear_refs").write_text("5")
    except OSError:
        pass
    current = _proc_status_kb("VmRSS")
    return float(current if current is not None else resource.getrusage(resource.RUSAGE_SELF).ru_maxrss)


def _peak_rss() -> float:
    """Peak RSS in KiB since the last reset (VmHWM), or ru_maxrss where /proc is missing."""
    peak = _proc_status_kb("VmHWM")
    return float(peak if peak is not None else resource.getrusage(resource.RUSAGE_SELF).ru_maxrss)


_PROBE = "import sys; from fr_torch.registry import load_object; sys.exit(load_object('fr_eval.bench:main')())"


def memory(settings, threads: int | None, progress) -> list[dict]:
    rows = []
    for batch, n_seg, k, mode, device in settings:
        if progress.out_of_time(f"memory {device} {batch}x{n_seg}"):
            continue
        # a fresh interpreter; fr_eval through load_object, so a checkout that is not installed works too
        cmd = [sys.executable, "-c", _PROBE, "--memory-probe", f"{batch},{n_seg},{k},{mode},{device}"]
        if threads:
            cmd += ["--threads", str(threads)]
        proc = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True)
        if proc.returncode != 0:
            rows.append({"batch": batch, "segments": n_seg, "k": k, "mode": mode, "device": device, "ok": False,
                         "error": (proc.stderr or proc.stdout).strip().splitlines()[-1:]})
        else:
            rows.append(json.loads(proc.stdout.strip().splitlines()[-1]))
        progress.update(1, "memory", rows[-1])
    return rows


def scaling(segment_counts, grid_sizes, device: str, repeats: int, progress, mode: str = "fast") -> dict:
    """Per-image time (ms, batch 1, given segments) against N segments and against grid size k."""
    out = {"segments": [], "grid": []}
    est = _estimator(mode, device)
    for n in segment_counts:
        if progress.out_of_time(f"scaling segments {n}"):
            continue
        seg = _segments(n, seed=1)
        runs = []
        est.calibrate_segments([seg], [(640, 480)])
        for _ in range(repeats):
            [r] = est.calibrate_segments([seg], [(640, 480)])
            runs.append(r.runtime_s)
        out["segments"].append({"segments": n, **{f"{k}_ms": 1000 * statistics.median(x[k] for x in runs)
                                                  for k in ("grid", "refine", "cues", "total")}})
        progress.update(1, "scaling", out["segments"][-1])
    seg = _segments(500, seed=1)
    for k in grid_sizes:
        if progress.out_of_time(f"scaling k {k}"):
            continue
        est_k = _estimator(mode, device, k)
        est_k.calibrate_segments([seg], [(640, 480)])
        runs = []
        for _ in range(repeats):
            [r] = est_k.calibrate_segments([seg], [(640, 480)])
            runs.append(r.runtime_s)
        out["grid"].append({"k": k, "hypotheses": k ** 4, "segments": 500,
                            **{f"{key}_ms": 1000 * statistics.median(x[key] for x in runs)
                               for key in ("grid", "refine", "cues", "total")}})
        progress.update(1, "scaling", out["grid"][-1])
    return out


# --------------------------------------------------------------------------- report

def _figure(scale: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    for ax, key, xkey, xlabel in ((axes[0], "segments", "segments", "segments per image"),
                                  (axes[1], "grid", "hypotheses", "grid hypotheses k^4")):
        rows = scale[key]
        if not rows:
            continue
        x = [r[xkey] for r in rows]
        for stage in ("grid", "refine", "total"):
            ax.plot(x, [r[f"{stage}_ms"] for r in rows], marker="o", label=stage)
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel(xlabel)
        ax.set_ylabel("ms per image (fast, batch 1)")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend()
    axes[1].set_title("k = " + ", ".join(str(r["k"]) for r in scale["grid"]))
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def _grid_floor_ms(row: dict, ns: float) -> float:
    """The grid floor of an end-to-end row: G x N x 3 deviations at ``ns`` per atan2 + exp."""
    return row["grid_hypotheses"] * row["segments"] * 3 * ns / 1e6


def _latency_lines(report: dict) -> list[str]:
    """bench.md's end-to-end latency table."""
    lines = ["## End-to-end latency per image (CPU, batch 1, ms)", "",
              "| image | mode | search | segments | decode+LSD | grid | refine | cues | total | floor: decode | floor: LSD | grid floor |",
              "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in report["end_to_end"]:
        lines.append(f"| {r['image']} | {r['mode']} | {r.get('search', 'eager')} | {r['segments']} | {r['detect_ms']:.1f} | {r['grid_ms']:.1f} | "
                     f"{r['refine_ms']:.1f} | {r['cues_ms']:.1f} | **{r['wall_ms']:.1f}** | {r['decode_ms']:.1f} | "
                     f"{r['lsd_ms']:.1f} | {_grid_floor_ms(r, report['transcendental_ns']):.1f} |")
    lines += ["", "Grid floor = G x N x 3 deviations x (atan2 + exp ns/element measured in cache: "
              f"{report['transcendental_ns']:.2f} ns), G = the k^4 grid only; the grid column also holds the "
              "focal sweep and the lattice passes.", ""]
    return lines


def _markdown(report: dict) -> str:
    m = report["machine"]
    lines = ["# fR speed benchmark", "",
             f"Machine: {m['cpu']}, {m['cores']} cores, torch {m['torch']}, {m['threads']} threads, "
             f"device {m['device']}" + (f" ({m['gpu']})" if "gpu" in m else "")
             + (f", load average {m.get('load_average')}" if m.get("load_average") else "") + ".",
             f"Command: `{report['command']}`; medians over {report['repeats']} runs after a warm-up "
             f"(GPU rows and large batches fewer: each row's `repeats` in bench.json).", ""]
    if report.get("from_jsonl"):
        lines += [f"Rebuilt from the rows of `{report['from_jsonl']}` (`fr bench --from-jsonl`): what that run "
                  "had measured when it ended.", ""]
    if report["end_to_end"]:
        lines += _latency_lines(report)
    lines += bench_detectors.markdown_lines(report)
    lines += bench_distortion.markdown_lines(report.get("distortion", []))
    lines += ["## Throughput given segments (grid + refinement + cues)", "",
              "| device | mode | search | batch | segments | images/s | ms/image | peak memory (MB) |",
              "|---|---|---|---|---|---|---|---|"]
    mem = {(r["batch"], r["device"]): r for r in report["memory"] if r.get("ok")}
    for r in report["throughput"]:
        peak = r.get("peak_memory_mb")
        search = r.get("search", "eager")  # reports written before --compile have no such column
        if peak is None and r.get("mode", "fast") == "fast" and search == "eager" and (r["batch"], r["device"]) in mem:
            peak = mem[(r["batch"], r["device"])]["peak_increase_mb"]
        mode = r.get("mode", "fast") + ("" if r.get("reliability", True) else ", reliability off")
        lines.append(f"| {r['device']} | {mode} | {search} | {r['batch']} | {r['segments']} | "
                     f"{r['images_per_s']:.1f} | {r['ms_per_image']:.2f} | {'' if peak is None else f'{peak:.0f}'} |")
    compiled = [dict(r, device=r.get("device", "cpu")) for r in report["end_to_end"] + report["throughput"]
                if "compile_s" in r]
    if compiled:
        lines += ["", "search: `eager` = the default; `compiled` = `--compile` (`SearchConfig.compile_search`: "
                  "the grid's scores from one kernel fused by torch.compile, the refinement step compiled "
                  "too); its compilation, once per process and device "
                  "(the first warm-up call), took "
                  + ", ".join(f"{max(r['compile_s'] for r in compiled if r['device'] == d):.1f} s ({d})"
                              for d in dict.fromkeys(r["device"] for r in compiled))
                  + " (less when torch's on-disk compile cache holds an earlier run's kernel)."]
    if report["memory"]:
        lines += ["", "## Peak memory (fresh subprocess per setting; CPU: peak RSS increase over the inputs)", "",
                  "| device | mode | batch | segments | k | peak increase (MB) | peak RSS (MB) | seconds | ok |",
                  "|---|---|---|---|---|---|---|---|---|"]
        for r in report["memory"]:
            if "peak_increase_mb" in r:
                lines.append(f"| {r['device']} | {r['mode']} | {r['batch']} | {r['segments']} | {r['k']} | "
                             f"{r['peak_increase_mb']:.0f} | {r['peak_rss_mb']:.0f} | {r['seconds']:.1f} | {r['ok']} |")
            else:
                lines.append(f"| {r['device']} | {r['mode']} | {r['batch']} | {r['segments']} | {r['k']} | - | - | - | "
                             f"FAILED: {r.get('error')} |")
    if report["scaling"]:
        lines += ["", "## Scaling (fast, batch 1, CPU, ms per image)", "", "| segments | grid | refine | cues | total |",
                  "|---|---|---|---|---|"]
        for r in report["scaling"]["segments"]:
            lines.append(f"| {r['segments']} | {r['grid_ms']:.1f} | {r['refine_ms']:.1f} | {r['cues_ms']:.1f} | {r['total_ms']:.1f} |")
        lines += ["", "| k | hypotheses | grid | refine | total |", "|---|---|---|---|---|"]
        for r in report["scaling"]["grid"]:
            lines.append(f"| {r['k']} | {r['hypotheses']} | {r['grid_ms']:.1f} | {r['refine_ms']:.1f} | {r['total_ms']:.1f} |")
        lines += ["", "![scaling](scaling.png)", ""]
    if report.get("parallel"):
        lines += ["## CPU parallelism (given segments, images/s)", "",
                  "T intra-op threads in one process vs W single-threaded worker processes "
                  "(`fr_torch.runtime.pipeline.calibrate_segments_sharded`); batch "
                  f"{report['parallel'][0]['batch']} x {report['parallel'][0]['segments']} segments.", "",
                  "| mode | kind | count | images/s | ms/image | speed-up vs 1 |", "|---|---|---|---|---|---|"]
        base = {(r["mode"], r["kind"]): r["images_per_s"] for r in report["parallel"] if r["count"] == 1}
        for r in report["parallel"]:
            ref = base.get((r["mode"], r["kind"]))
            speedup = f"{r['images_per_s'] / ref:.2f}x" if ref else ""
            lines.append(f"| {r['mode']} | {r['kind']} | {r['count']} | {r['images_per_s']:.1f} | {r['ms_per_image']:.2f} | "
                         f"{speedup} |")
        lines.append("")
    if report.get("outside_search"):
        lines += ["## Work outside the search (per image)", "",
                  "`calibrate_segments` on a large batch with a minimal search (k = 2, one start, no sweep or passes, one "
                  "step): input checks, segment filter, batching, records, checks, cues (the `focal_prior_share` "
                  "cue scores an 81-point lattice per image: device work, like the minimal search), reliability "
                  "predictions. 1000 / ms bounds the images/s of this device.", "",
                  "| device | batch | segments | ms/image | ceiling (images/s) |", "|---|---|---|---|---|"]
        lines += [f"| {r['device']} | {r['batch']} | {r['segments']} | {r['ms_per_image']:.3f} | "
                  f"{r['ceiling_images_per_s']:.0f} |" for r in report["outside_search"]]
        lines.append("")
    if report.get("grid_kernel"):
        lines += ["## Grid kernel alone (stage 1: 8^4 hypotheses, `score_grid`)", "",
                  f"Deviations = B x G x N x 3 (nominal). Fraction of FP32 peak: {FLOPS_PER_DEVIATION} FLOPs per "
                  "deviation (a convention: s, t, atan2, exp, mixture) against the GPU's data-sheet FP32 peak "
                  f"({', '.join(f'{k} {v / 1e12:.1f} TFLOP/s' for k, v in GPU_FP32_PEAK.items())}).", "",
                  "| device | search | batch | segments | hypotheses | ms | images/s | deviations/s | fraction of FP32 peak |",
                  "|---|---|---|---|---|---|---|---|---|"]
        for r in report["grid_kernel"]:
            fraction = r.get("fraction_of_fp32_peak")
            lines.append(f"| {r['device']} | {r['search']} | {r['batch']} | {r['segments']} | {r['hypotheses']} | "
                         f"{1000 * r['seconds']:.1f} | {r['images_per_s']:.0f} | {r['deviations_per_s']:.3g} | "
                         f"{'' if fraction is None else f'{100 * fraction:.1f} %'} |")
        lines.append("")
    for p in report.get("profiles", []):
        lines += [f"## Where the time goes: {p['device']} {p['mode']}, batch {p['batch']} (torch profiler, "
                  f"full table in `{p['file']}`)", "", "| op | self ms | share | calls |", "|---|---|---|---|"]
        lines += [f"| `{_short_op(o['op'])}` | {o['self_ms']:.1f} | {100 * o['share']:.0f} % | {o['calls']} |"
                  for o in p["top_ops"]]
        lines.append("")
    if report.get("contention"):
        from fr_eval.contention import summary_lines

        lines += ["## Under contention (CPU, seconds per photo, one photo per call)", "",
                  "Fresh processes with the commands' thread policy (`FR_THREADS` = "
                  f"{m.get('fr_threads', 'auto')}): idle; beside a busy neighbour (a pure-Python spin loop in a "
                  "subprocess keeping one core busy); 2 such processes side by side (photos/s of the 2 together "
                  "over one alone's). `segments` = given segments, `images` = decode + LSD + search. "
                  "docs/cpu-threads.md.", ""]
        lines += summary_lines(report["contention"], (2,)) + [""]
    if report.get("skipped"):
        lines += [f"Skipped (time budget {report['budget_s']:.0f} s): " + ", ".join(report["skipped"]) + ".", ""]
    return "\n".join(lines)


def _short_op(name: str, limit: int = 100) -> str:
    """A profiler op name short enough for a table cell: a CUDA kernel's C++ signature is cut to its
    name and template arguments without ``at::native::``, then to ``limit`` characters (the full
    names are in the profile file)."""
    if name.startswith("void "):
        name = name[5:]
    name = name.split(">(", 1)[0].replace("at::native::", "") + (">" if ">(" in name else "")
    return name if len(name) <= limit else name[:limit - 1] + "…"


def write_report(report: dict, out: Path) -> None:
    """bench.json, bench.md and the figures of ``report`` in ``out``: scaling.png (time against
    segments and grid size) when it has the scaling rows, throughput.png when it has throughput rows."""
    written = [out / "bench.md", out / "bench.json"]
    markdown = _markdown(report)
    (out / "bench.json").write_text(json.dumps(report, indent=1))
    (out / "bench.md").write_text(markdown)
    if report.get("scaling"):
        _figure(report["scaling"], out / "scaling.png")
        written.append(out / "scaling.png")
    if report.get("throughput"):
        _throughput_figure(report["throughput"], out / "throughput.png")
        written.append(out / "throughput.png")
    print(markdown)
    print(f"fr bench: wrote {', '.join(map(str, written))}", file=sys.stderr)


def report_from_jsonl(path: Path) -> dict:
    """The report of an earlier run rebuilt from its ``bench.jsonl`` rows (what was measured before
    it ended; the profiles without their top-op tables, which only the full report holds)."""
    rows = [json.loads(line) for line in Path(path).read_text().splitlines() if line.strip()]
    by = {}
    for row in rows:
        by.setdefault(row.pop("section"), []).append(row)
    machine = (by.get("machine") or [{}])[0]
    scale = {"segments": [r for r in by.get("scaling", []) if "k" not in r],
             "grid": [r for r in by.get("scaling", []) if "k" in r]}
    return {"machine": {k: v for k, v in machine.items() if k not in ("command", "repeats", "budget_s")} or
            {"cpu": "not recorded", "cores": "?", "torch": "?", "threads": "?", "device": "?"},
            "command": machine.get("command", f"(rows of {path})"), "quick": False,
            "repeats": machine.get("repeats", "?"),
            "transcendental_ns": (by.get("transcendental") or [{"ns_per_element": float("nan")}])[0]["ns_per_element"],
            "end_to_end": by.get("end_to_end", []), "throughput": by.get("throughput", []),
            "memory": by.get("memory", []), "scaling": scale if scale["segments"] or scale["grid"] else {},
            "parallel": by.get("parallel", []), "outside_search": by.get("outside_search", []),
            "grid_kernel": by.get("grid_kernel", []), "detectors": by.get("detectors", []), "contention": by.get("contention", []),
            "device_end_to_end": by.get("device_end_to_end", []), "profiles": [], "skipped": [],
            "distortion": by.get("distortion", []),
            "budget_s": machine.get("budget_s", 0.0), "sections": [], "from_jsonl": str(path)}


def _throughput_figure(rows: list[dict], path: Path) -> None:
    """Images/s against batch size (log-log), one line per device, mode, search and reliability."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    lines: dict = {}
    for r in rows:
        key = (r["device"], r.get("mode", "fast"), r.get("search", "eager"), r.get("reliability", True))
        lines.setdefault(key, []).append((r["batch"], r["images_per_s"]))
    fig, ax = plt.subplots(figsize=(7, 4.5))
    for (device, mode, search, reliability), points in sorted(lines.items()):
        points.sort()
        label = f"{device} {mode} {search}" + ("" if reliability else ", reliability off")
        ax.plot([b for b, _ in points], [v for _, v in points], marker="o",
                linestyle="-" if search == "eager" else "--", label=label)
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("batch (images searched together)")
    ax.set_ylabel("images/s given 300 segments per image")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def run(args: argparse.Namespace) -> int:
    import torch

    if args.threads and args.threads > 0:
        torch.set_num_threads(args.threads)
    if args.memory_probe:
        print(json.dumps(memory_probe(args.memory_probe)))
        return 0
    if args.from_jsonl:
        out = Path(args.out)
        out.mkdir(parents=True, exist_ok=True)
        write_report(report_from_jsonl(args.from_jsonl), out)
        return 0
    device = args.device
    if device == "auto":
        device = "cuda" if torch.cuda.is_available() else "cpu"
    if device.startswith("cuda") and not torch.cuda.is_available():
        raise ValueError("--device cuda requested but no CUDA device is available")
    quick = args.quick
    repeats = args.repeats or (1 if quick else 7)

    import cv2

    from fr_torch.core.camera import focal_from_hfov, rotation_from_angles
    from fr_torch.synthetic import render_manhattan_room

    tmp = tempfile.TemporaryDirectory()
    R = rotation_from_angles(np.float64(15.0), np.float64(8.0), np.float64(4.0)).numpy()
    rendered = Path(tmp.name) / "room_640x480.png"
    cv2.imwrite(str(rendered), render_manhattan_room(focal_from_hfov(70.0, 640), R, 640, 480))
    images = [("rendered room", str(rendered))]
    if not quick:
        try:
            from fr_eval.paths import data_root

            yud = sorted((data_root(args.data_root) / "yorkurbandb").glob("P*/P*.jpg"))[:3]
            images += [(f"YUD {p.stem}", str(p)) for p in yud]
        except FileNotFoundError:
            pass

    sections = {name.strip() for name in args.sections.split(",") if name.strip()}
    if not sections or sections - set(SECTIONS):
        raise ValueError(f"--sections: choose from {', '.join(SECTIONS)}, got {args.sections!r}")
    batches = [1, 4] if quick else [1, 8, 64, 256, 1024]
    if args.batches:
        batches = [int(b) for b in args.batches.split(",")]
    # CUDA: large batches, capped by the budget; 16384 shows memory stays bounded (issue 14: <= 16 GB).
    device_batches = [1, 4] if quick else [1, 64, 1024, 4096, 16384]
    cores = usable_cores()  # affinity and container quota, as the worker defaults count them
    counts = [1, 2] if quick else sorted({1, 2, min(4, cores), min(8, cores), cores} - {0})
    par_batch = 4 if quick else 64
    n_seg_tp = 50 if quick else 300
    seg_counts = [100] if quick else [100, 300, 1000, 3000, 5000]
    grid_sizes = [4] if quick else [4, 6, 8, 10, 12]
    devices = ["cpu"] + ([device] if device != "cpu" else [])
    gpu = devices[1:] if "device" in sections else []
    mem_settings = [(4, 50, 4, "fast", "cpu")] if quick else (
        [(b, n_seg_tp, 8, "fast", "cpu") for b in batches] + ([(4096, 1000, 4, "fast", "cpu")] if args.stress else [])
        + ([(b, n_seg_tp, 8, "fast", device) for b in batches] + ([(4096, 1000, 8, "fast", device)] if args.stress else [])
           if device != "cpu" else []))
    if args.no_memory or "memory" not in sections:
        mem_settings = []
    modes = ("fast",) if quick else ("fast", "fr")
    contention_kinds = ("segments",) if quick else ("segments", "images")
    tp_runs = 2 if args.compile else 1  # eager, and compiled with --compile
    steps = (("latency" in sections) * tp_runs * len(modes) * len(images)
             + len(gpu) * (tp_runs * len(modes) * len(device_batches) + tp_runs + 1 + len(modes))
             + ("cpu" in sections) * (tp_runs * len(modes) * len(batches) + ("fr" in modes) * len(batches) + 2)
             + len(mem_settings) + ("scaling" in sections) * (len(seg_counts) + len(grid_sizes))
             + ("parallel" in sections) * 2 * len(modes) * len(counts)
             + ("detectors" in sections) * (len(images) + len(devices[1:]) * len(modes) * 3)
             + ("contention" in sections) * len(modes) * len(contention_kinds)
             + ("distortion" in sections) * 2 * len(images) * len(bench_distortion.SETTINGS))
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    budget = args.budget_s if args.budget_s is not None else (150.0 if device.startswith("cuda") else 0.0)
    progress = _progress(steps, args.no_progress, out / "bench.jsonl", budget)
    command = "fr bench " + " ".join(sys.argv[2:] if sys.argv[1:2] == ["bench"] else sys.argv[1:])
    progress.update(0, "machine", dict(machine_description(device), command=command, repeats=repeats, budget_s=budget))

    ns = _transcendental_ns("cpu")
    progress.update(0, "transcendental", {"ns_per_element": ns})
    tp, profiles, outside, e2e, parallel, mem, scale, kernels = [], [], [], [], [], [], {}, []
    detectors, device_e2e = [], []
    jpegs = [path for label, path in images if label.startswith("YUD")] or [images[0][1]]  # same size
    outside_batch = 16 if quick else 1024
    # A GPU figure first (the budget may cut the rest), then CPU latency, throughput, scaling.
    for dev in gpu:
        for mode in modes:
            tp += throughput(device_batches, n_seg_tp, dev, min(repeats, 3), progress, mode)
        for mode in modes if args.compile else ():
            tp += throughput(device_batches, n_seg_tp, dev, min(repeats, 3), progress, mode, compile_search=True)
        kernels += [grid_kernel(dev, outside_batch, n_seg_tp, min(repeats, 3), progress, compiled)
                    for compiled in ((False, True) if args.compile else (False,))]
        outside.append(outside_search(outside_batch, n_seg_tp, dev, min(repeats, 3), progress))
        for mode in modes:
            profiles.append(profile_table(dev, outside_batch, n_seg_tp, out, progress, mode))
    for dev in devices[1:] if "detectors" in sections else ():  # JPEG bytes to results on the GPU
        device_e2e += bench_detectors.device_end_to_end(jpegs, dev, device_batches[:3], min(repeats, 3), progress,
                                                        modes)
    if "latency" in sections:
        e2e = end_to_end(images, repeats, progress, modes, compile_search=args.compile)
    if "detectors" in sections:
        detectors = bench_detectors.detector_rows(images, repeats, progress)
    for row in e2e:
        row["grid_floor_ms"] = _grid_floor_ms(row, ns)
    if "parallel" in sections:
        parallel = parallel_scaling(counts, par_batch, n_seg_tp, repeats, progress, modes)
    if "cpu" in sections:
        profiles.insert(0, profile_table("cpu", par_batch, n_seg_tp, out, progress))
        for mode in modes:
            tp += throughput(batches, n_seg_tp, "cpu", repeats, progress, mode)
        if "fr" in modes:  # fR without the reliability stage, hence without its focal_profile_gap cue
            tp += throughput(batches, n_seg_tp, "cpu", repeats, progress, "fr", reliability=False)
        for mode in modes if args.compile else ():
            tp += throughput(batches, n_seg_tp, "cpu", repeats, progress, mode, compile_search=True)
        outside.insert(0, outside_search(outside_batch, n_seg_tp, "cpu", min(repeats, 3), progress))
    mem = memory(mem_settings, args.threads, progress)
    if "scaling" in sections:
        scale = scaling(seg_counts, grid_sizes, "cpu", repeats, progress)
    contention = []
    if "contention" in sections and not progress.out_of_time("contention"):
        from fr_eval.contention import contention_rows

        contention = contention_rows([path for _, path in images], modes, contention_kinds,
                                     (os.environ.get("FR_THREADS") or "auto",), (2,), passes=1 if quick else 3,
                                     progress=progress)
    distortion = []
    if "distortion" in sections:
        photos = images if quick else images[:2]
        distortion = bench_distortion.distortion_rows(photos + bench_distortion.bent_copies(photos, Path(tmp.name)),
                                                      repeats, progress, _median_times)
    progress.close()
    tmp.cleanup()

    report = {"machine": machine_description(device), "command": command, "quick": quick, "repeats": repeats,
              "transcendental_ns": ns, "end_to_end": e2e, "throughput": tp, "memory": mem, "scaling": scale,
              "parallel": parallel, "outside_search": [r for r in outside if r],
              "grid_kernel": [r for r in kernels if r], "detectors": detectors, "contention": contention, "device_end_to_end": device_e2e,
              "profiles": [p for p in profiles if p], "skipped": progress.skipped,
              "budget_s": budget, "sections": sorted(sections, key=SECTIONS.index), "distortion": distortion}
    write_report(report, out)
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="fr bench", description=__doc__.splitlines()[0])
    add_arguments(parser)
    return run(parser.parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
