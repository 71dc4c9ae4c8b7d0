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
   (:mod:`fr_eval.bench.contention`; docs/cpu-threads.md).
9. **The grid kernel alone** (on a GPU): stage 1 of 1024 images, as deviations per second and the fraction of the card's FP32 peak they amount to
   (:data:`fr_eval.bench.gpu.FLOPS_PER_DEVIATION`, :data:`fr_eval.bench.gpu.GPU_FP32_PEAK`).

Every measurement is written as it is taken: one JSON line per row in ``<out>/bench.jsonl``
(flushed) and one progress line on stderr; bench.json / bench.md / scaling.png at the end.
``--budget-s`` bounds the run: settings not started within the budget are skipped and listed
(default 150 s when a CUDA device is measured, meant to end ``fr bench --device cuda`` in about 3
minutes; the CUDA figures are taken first: JPEG files to
results through the GPU path (section ``detectors``), then the search given segments with batches
1 ... 4096 (16384 with ``--stress``), 3 repeats up to 64, 2 up to 4096, then 1).  ``--sections`` picks what to measure (e.g. ``parallel`` alone for
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

The sections live in the modules beside this one: :mod:`fr_eval.bench.search` (latency, throughput,
work outside the search, scaling), :mod:`fr_eval.bench.gpu` (the grid kernel), :mod:`fr_eval.bench.parallel`,
:mod:`fr_eval.bench.profiling` (profiler tables, peak memory), :mod:`fr_eval.bench.detectors`,
:mod:`fr_eval.bench.contention`, :mod:`fr_eval.bench.cold` (a new process's first search); :mod:`fr_eval.bench.report` writes bench.md / bench.json / the figures.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
from pathlib import Path

import numpy as np

from fr_eval.bench import cold as bench_cold
from fr_eval.bench import detectors as bench_detectors
from fr_eval.bench import distortion as bench_distortion
from fr_eval.bench.gpu import grid_kernel
from fr_eval.bench.parallel import parallel_scaling
from fr_eval.bench.profiling import memory, memory_probe, profile_table
from fr_eval.bench.report import grid_floor_ms, report_from_jsonl, write_report
from fr_eval.bench.search import end_to_end, outside_search, scaling, throughput, transcendental_ns
from fr_eval.bench.timing import Progress
from fr_eval.machine import machine_description
from fr_eval.paths import REPO
from fr_torch.cli.options import add_device_arguments
from fr_torch.runtime.workers import usable_cores

DEFAULT_OUT = REPO / "results" / "bench"
#: Batch sizes of the GPU rows from JPEG files to results (section ``detectors``).
DEVICE_E2E_BATCHES = (1, 256, 1024)
SECTIONS = ("device", "latency", "cold", "detectors", "parallel", "cpu", "memory", "scaling", "contention",
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
                        help="also run the bounded-memory checks: batch 4096 x 1000 segments (k=4; minutes) and, on "
                             "a GPU, batches of 16384")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    parser.add_argument("--batches", default=None, metavar="B,B,...",
                        help="CPU batch sizes for throughput and memory (default 1,8,64,256,1024)")
    parser.add_argument("--budget-s", type=float, default=None,
                        help="time budget in seconds: settings not started by then are skipped and listed "
                             "(default 150 with a CUDA device, else none; 0 = none)")
    parser.add_argument("--sections", default=",".join(SECTIONS), metavar="S,S,...",
                        help="what to measure (default all): device = throughput, outside-search work and "
                             "profile on the --device GPU; latency = end to end per photo; cold = a new process's first "
                             "search against its second (fr calibrate); detectors = LSD vs "
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

    from fr_torch.core.geometry.conventions import focal_from_hfov, rotation_from_angles
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
    # CUDA: large batches; 16384 (--stress) shows memory stays bounded (issue 14: <= 16 GB).
    device_batches = [1, 4] if quick else [1, 64, 1024, 4096] + ([16384] if args.stress else [])
    e2e_batches = [1, 4] if quick else list(DEVICE_E2E_BATCHES)
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
    steps = (("latency" in sections) * len(modes) * len(images) + ("cold" in sections) * len(modes)
             + len(gpu) * (len(modes) * len(device_batches) + 2 + len(modes))
             + ("cpu" in sections) * (len(modes) * len(batches) + ("fr" in modes) * len(batches) + 2)
             + len(mem_settings) + ("scaling" in sections) * (len(seg_counts) + len(grid_sizes))
             + ("parallel" in sections) * 2 * len(modes) * len(counts)
             + ("detectors" in sections) * (len(images) + len(devices[1:]) * len(modes) * 3)
             + ("contention" in sections) * len(modes) * len(contention_kinds)
             + ("distortion" in sections) * 2 * len(images[:1] if quick else images[:2])
             * sum(mode in modes for mode, _ in bench_distortion.SETTINGS))
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    budget = args.budget_s if args.budget_s is not None else (150.0 if device.startswith("cuda") else 0.0)
    progress = Progress(steps, args.no_progress, out / "bench.jsonl", budget)
    command = "fr bench " + " ".join(sys.argv[2:] if sys.argv[1:2] == ["bench"] else sys.argv[1:])
    progress.update(0, "machine", dict(machine_description(device), command=command, repeats=repeats, budget_s=budget))

    ns = transcendental_ns("cpu")
    progress.update(0, "transcendental", {"ns_per_element": ns})
    tp, profiles, outside, e2e, parallel, mem, scale, kernels = [], [], [], [], [], [], {}, []
    detectors, device_e2e = [], []
    jpegs = [path for label, path in images if label.startswith("YUD")] or [images[0][1]]  # same size
    outside_batch = 16 if quick else 1024
    # GPU figures first (the budget may cut the rest): files to results, then the search given
    # segments; then CPU latency, throughput, scaling.
    for dev in devices[1:] if "detectors" in sections else ():  # JPEG files to results on the GPU
        device_e2e += bench_detectors.device_end_to_end(jpegs, dev, e2e_batches, min(repeats, 3), progress,
                                                        modes)
    for dev in gpu:
        for mode in modes:
            tp += throughput(device_batches, n_seg_tp, dev, min(repeats, 3), progress, mode)
        kernels.append(grid_kernel(dev, outside_batch, n_seg_tp, min(repeats, 3), progress))
        outside.append(outside_search(outside_batch, n_seg_tp, dev, min(repeats, 3), progress))
        for mode in modes:
            profiles.append(profile_table(dev, outside_batch, n_seg_tp, out, progress, mode))
    if "latency" in sections:
        e2e = end_to_end(images, repeats, progress, modes)
    cold = []
    if "cold" in sections:  # a YUD photo where there is one
        cold = bench_cold.cold_rows(images[min(1, len(images) - 1)], modes, 2 if quick else 5, progress)
    if "detectors" in sections:
        detectors = bench_detectors.detector_rows(images, repeats, progress)
    for row in e2e:
        row["grid_floor_ms"] = grid_floor_ms(row, ns)
        row["full_grid_floor_ms"] = grid_floor_ms(row, ns, scored=False)
    if "parallel" in sections:
        parallel = parallel_scaling(counts, par_batch, n_seg_tp, repeats, progress, modes)
    if "cpu" in sections:
        profiles.insert(0, profile_table("cpu", par_batch, n_seg_tp, out, progress))
        for mode in modes:
            tp += throughput(batches, n_seg_tp, "cpu", repeats, progress, mode)
        if "fr" in modes:  # fR without the reliability stage, hence without its focal_profile_gap cue
            tp += throughput(batches, n_seg_tp, "cpu", repeats, progress, "fr", reliability=False)
        outside.insert(0, outside_search(outside_batch, n_seg_tp, "cpu", min(repeats, 3), progress))
    mem = memory(mem_settings, args.threads, progress)
    if "scaling" in sections:
        scale = scaling(seg_counts, grid_sizes, "cpu", repeats, progress)
    contention = []
    if "contention" in sections and not progress.out_of_time("contention"):
        from fr_eval.bench.contention import contention_rows

        contention = contention_rows([path for _, path in images], modes, contention_kinds,
                                     (os.environ.get("FR_THREADS") or "auto",), (2,), passes=1 if quick else 3,
                                     progress=progress)
    distortion = []
    if "distortion" in sections:
        photos = images[:1] if quick else images[:2]
        distortion = bench_distortion.distortion_rows(photos + bench_distortion.bent_copies(photos, Path(tmp.name)),
                                                      repeats, progress,
                                                      bench_distortion.QUICK_BATCH if quick else bench_distortion.BATCH,
                                                      modes=modes)
    progress.close()
    tmp.cleanup()

    report = {"machine": machine_description(device), "command": command, "quick": quick, "repeats": repeats,
              "transcendental_ns": ns, "end_to_end": e2e, "cold_start": cold, "throughput": tp, "memory": mem, "scaling": scale,
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
