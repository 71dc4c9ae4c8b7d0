"""GPU batch scoring from JPEG bytes to results, measured stage by stage in one process.

Run by ``tools/gpu_check.sh`` on a CUDA machine (it also runs on a CPU, slowly, for a dry run):

    python tools/gpu_probe.py --images DIR --test-list FILE --out OUT [--batches 256,1024]

Stages (each appends JSON rows to ``OUT/probe.jsonl`` and prints them; a failing stage is a row
with ``error``, the next stage still runs):

* ``pipeline``: files on disk to results through :func:`fr_torch.runtime.pipeline.calibrate_paths`
  (the path of ``calibrate_images``, ``fr calibrate``, ``fr batch``: decode, detect and search on
  the device, a reader thread one batch ahead), 4 batches per row; ``pipeline_profile`` profiles it;
* ``reliability_cost``: the same path with the reliability stage off and on;
* ``decode``: ``decode_jpeg_batch`` (torchvision ``decode_jpeg`` on the device) of B JPEGs;
* ``detect``: ``torch-lines`` ``detect_batch`` on the decoded (B, 1, H, W) batch;
* ``e2e``: :func:`fr_torch.runtime.device_pipeline.calibrate_decoded` from bytes, per mode, with
  the split of its time (decode, detect, the device -> host hop, the search call);
* ``given``: the search alone, given the same segments (``calibrate_segments``);
* ``profile``: ``torch.profiler`` over one end-to-end Fast-fR batch (tables in OUT);
* ``accuracy``: the images named in ``--test-list`` through the device path, one JSON record per
  image and mode in ``OUT/accuracy_<device>.json`` (scored against ground truth elsewhere).

Images/s are batch / median wall seconds of ``--repeats`` timed runs after one warm-up, with the
device synchronised around each run.
"""
from __future__ import annotations

import argparse
import json
import statistics
import time
import traceback
from pathlib import Path

import numpy as np
import torch


def _sync(device: str) -> None:
    if device.startswith("cuda"):
        torch.cuda.synchronize()


def _profiled(fn, device: str, out: Path, stem: str, title: str):
    """Run ``fn`` once under ``torch.profiler`` (CPU, and CUDA on a CUDA device) and write the 30
    operators with the most self time to ``out/STEM_cpu.txt`` (and ``STEM_cuda.txt``), headed by
    ``title`` and the wall seconds.  Returns (wall seconds, the profiler's key averages)."""
    from torch.profiler import ProfilerActivity, profile

    cuda = device.startswith("cuda")
    with profile(activities=[ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if cuda else [])) as prof:
        _sync(device)
        start = time.perf_counter()
        fn()
        _sync(device)
        wall = time.perf_counter() - start
    averages = prof.key_averages()
    for unit in ("cuda", "cpu") if cuda else ("cpu",):
        (out / f"{stem}_{unit}.txt").write_text(f"{title}, wall {wall:.3f} s (with profiler)\n\n"
                                               f"{averages.table(sort_by=f'self_{unit}_time_total', row_limit=30)}\n")
    return wall, averages


def _timed(fn, device: str, repeats: int) -> tuple[float, object]:
    """(median wall seconds of ``repeats`` runs after one warm-up, the last run's value)."""
    value = fn()
    seconds = []
    for _ in range(max(1, repeats)):
        _sync(device)
        start = time.perf_counter()
        value = fn()
        _sync(device)
        seconds.append(time.perf_counter() - start)
    return statistics.median(seconds), value


class Log:
    def __init__(self, path: Path):
        self.file = path.open("a")

    def __call__(self, stage: str, **row) -> None:
        row = {"stage": stage, **row}
        line = json.dumps(row, default=float)
        print(line, flush=True)
        self.file.write(line + "\n")
        self.file.flush()


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--images", required=True, help="folder of same-size JPEGs")
    parser.add_argument("--test-list", default=None, help="names (file stems) scored for accuracy, one per line")
    parser.add_argument("--out", required=True)
    parser.add_argument("--device", default="cuda")
    parser.add_argument("--batches", default="256,1024")
    parser.add_argument("--modes", default="fast,fr")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--searchers", default="1,2", help="pipeline stage: search threads to compare (eager)")
    parser.add_argument("--stages", default="pipeline,reliability_cost,pipeline_profile,decode,detect,e2e,given,profile,"
                                            "accuracy")
    args = parser.parse_args(argv)

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    log = Log(out / "probe.jsonl")
    device = args.device
    stages = set(args.stages.split(","))
    batches = [int(b) for b in args.batches.split(",")]
    modes = args.modes.split(",")
    searcher_counts = [int(n) for n in args.searchers.split(",")]

    from fr_torch.detectors.tensor_lines import TensorLinesDetector, decode_jpeg_batch
    from fr_torch.runtime.device_pipeline import as_numpy_lists, calibrate_decoded
    from fr_torch.runtime.estimator import FREstimator

    info = {"torch": torch.__version__, "device": device}
    if device.startswith("cuda"):
        info.update(gpu=torch.cuda.get_device_name(device), sms=torch.cuda.get_device_properties(device).multi_processor_count)
    try:
        import torchvision

        info["torchvision"] = torchvision.__version__
    except Exception as exc:  # noqa: BLE001
        info["torchvision"] = f"unavailable: {exc}"
    log("info", **info)

    paths = sorted(Path(args.images).rglob("*.jpg"))
    data = {p.stem: p.read_bytes() for p in paths}
    pool = list(data.values())

    def payload(batch: int) -> list[bytes]:
        return [pool[i % len(pool)] for i in range(batch)]

    def decode(batch_bytes) -> torch.Tensor:
        try:
            return torch.stack(decode_jpeg_batch(batch_bytes, device=device))
        except RuntimeError:
            if device != "cpu":
                raise
            import cv2  # a CPU dry run without a working torchvision

            return torch.from_numpy(np.stack([cv2.imdecode(np.frombuffer(b, np.uint8), cv2.IMREAD_GRAYSCALE)
                                              for b in batch_bytes]))[:, None]

    detector = TensorLinesDetector(device=device)

    def stage(name: str, fn) -> None:
        if name not in stages:
            return
        try:
            fn()
        except Exception as exc:  # noqa: BLE001 - a failed stage is a row; the next stage runs
            log(name, error=f"{type(exc).__name__}: {exc}", traceback=traceback.format_exc()[-2000:])

    def run_decode():
        for batch in batches:
            data_b = payload(batch)
            t, images = _timed(lambda: decode(data_b), device, args.repeats)
            log("decode", batch=batch, seconds=t, images_per_s=batch / t, shape=list(images.shape))

    def run_detect():
        for batch in batches:
            images = decode(payload(batch))
            if device.startswith("cuda"):
                torch.cuda.reset_peak_memory_stats()
            t, (segments, mask) = _timed(lambda: detector.detect_batch(images), device, args.repeats)
            counts = mask.sum(1).float()
            row = dict(batch=batch, seconds=t, images_per_s=batch / t, segments_mean=float(counts.mean()),
                       segments_min=int(counts.min()), padded=int(mask.shape[1]))
            if device.startswith("cuda"):
                row["peak_gb"] = torch.cuda.max_memory_allocated() / 1e9
            log("detect", **row)

    estimators = {}

    def estimator(mode: str):
        if mode not in estimators:
            estimators[mode] = FREstimator(mode=mode, device=device)
        return estimators[mode]

    def e2e_rows():
        for mode in modes:
            est = estimator(mode)
            start = time.perf_counter()
            calibrate_decoded(est, detector, decode(payload(64)))  # warm-up
            _sync(device)
            log("warmup", mode=mode, seconds=time.perf_counter() - start)
            for batch in batches:
                data_b = payload(batch)
                t, results = _timed(lambda: calibrate_decoded(est, detector, decode(data_b)), device, args.repeats)
                # the split of one run's time
                _sync(device)
                t0 = time.perf_counter()
                images = decode(data_b)
                _sync(device)
                t1 = time.perf_counter()
                segments, mask = detector.detect_batch(images)
                _sync(device)
                t2 = time.perf_counter()
                lists = as_numpy_lists(segments, mask)
                t3 = time.perf_counter()
                est.calibrate_segments(lists, [(images.shape[-1], images.shape[-2])] * batch)
                _sync(device)
                t4 = time.perf_counter()
                log("e2e", mode=mode, batch=batch, seconds=t, images_per_s=batch / t,
                    ok_share=float(np.mean([r.ok for r in results])),
                    reliable_share=float(np.mean([bool(r.reliable) for r in results])),
                    split_s={"decode": t1 - t0, "detect": t2 - t1, "to_host": t3 - t2, "search_call": t4 - t3})
                sizes = [(images.shape[-1], images.shape[-2])] * batch
                tg, _ = _timed(lambda: est.calibrate_segments(lists, sizes), device, args.repeats)
                log("given", mode=mode, batch=batch, seconds=tg, images_per_s=batch / tg,
                    segments_mean=float(np.mean([len(x) for x in lists])))

    def run_profile():
        est = estimator("fast")
        batch = max(batches)
        data_b = payload(batch)
        calibrate_decoded(est, detector, decode(data_b))
        wall, averages = _profiled(lambda: calibrate_decoded(est, detector, decode(data_b)), device, out,
                                   f"profile_e2e_fast_{batch}", f"end to end Fast-fR, batch {batch}, {device}")
        gpu_total = sum(getattr(e, "self_device_time_total", 0.0) for e in averages) / 1e6
        log("profile", batch=batch, wall_s=wall, device_busy_s=gpu_total)

    def run_accuracy():
        if not args.test_list:
            return
        names = [n.strip() for n in Path(args.test_list).read_text().split() if n.strip()]
        records = []
        from fr_torch.runtime.pipeline import calibrate_paths

        files = {p.stem: str(p) for p in paths}
        for mode in modes:
            est = estimator(mode)
            results = [r for _, chunk in calibrate_paths(est, [files[n] for n in names], 64) for r in chunk]
            for name, r in zip(names, results):
                records.append({"mode": mode, **r.to_json(), "image": name})
        path = out / f"accuracy_{device.split(':')[0]}.json"
        path.write_text(json.dumps(records))
        log("accuracy", images=len(names), file=path.name)

    def run_pipeline():
        """Files on disk to results through calibrate_paths (the path of calibrate_images, fr
        calibrate and fr batch on a GPU), over 4 batches of the largest size."""
        from fr_torch.runtime import device_pipeline
        from fr_torch.runtime.pipeline import calibrate_paths

        files = [str(p) for p in paths]
        default_searchers = device_pipeline.SEARCH_THREADS
        for mode, searchers in [(mode, n) for mode in modes for n in searcher_counts]:
            device_pipeline.SEARCH_THREADS = searchers
            try:
                est = estimator(mode)
                for batch in batches:
                    todo = [files[i % len(files)] for i in range(4 * batch)]
                    list(calibrate_paths(est, todo[:batch], batch))  # warm-up at this batch size
                    _sync(device)
                    start = time.perf_counter()
                    results = [r for _, chunk in calibrate_paths(est, todo, batch) for r in chunk]
                    _sync(device)
                    wall = time.perf_counter() - start
                    log("pipeline", mode=mode, searchers=searchers, batch=batch, images=len(todo),
                        seconds=wall, images_per_s=len(todo) / wall, ok_share=float(np.mean([r.ok for r in results])),
                        reliable_share=float(np.mean([bool(r.reliable) for r in results])),
                        detect_ms=1000 * float(np.median([r.runtime_s.get("detect", 0.0) for r in results])))
            finally:
                device_pipeline.SEARCH_THREADS = default_searchers

    def run_pipeline_profile():
        from fr_torch.runtime.pipeline import calibrate_paths

        est = estimator("fast")
        batch = max(batches)
        files = [str(p) for p in paths]
        todo = [files[i % len(files)] for i in range(2 * batch)]
        list(calibrate_paths(est, todo[:batch], batch))
        wall, averages = _profiled(lambda: list(calibrate_paths(est, todo, batch)), device, out,
                                   f"profile_pipeline_fast_{batch}",
                                   f"calibrate_paths Fast-fR, 2 batches of {batch}, {device}")
        log("pipeline_profile", batch=batch, images=len(todo), wall_s=wall,
            device_busy_s=sum(getattr(e, "self_device_time_total", 0.0) for e in averages) / 1e6)

    def run_reliability_cost():
        """The reliability stage's share on the device (issue 44's spreads): the same files with
        the stage off and on, batch = the largest, 2 batches each, median of ``--repeats``."""
        from fr_torch.runtime.pipeline import calibrate_paths

        files = [str(p) for p in paths]
        batch = max(batches)
        todo = [files[i % len(files)] for i in range(2 * batch)]
        for mode in modes:
            for reliability in (None, "default"):
                est = FREstimator(mode=mode, device=device, reliability=reliability)
                t, _ = _timed(lambda: list(calibrate_paths(est, todo, batch)), device, args.repeats)
                log("reliability_cost", mode=mode, reliability=reliability or "off", batch=batch, images=len(todo),
                    seconds=t, images_per_s=len(todo) / t)

    stage("pipeline", run_pipeline)
    stage("reliability_cost", run_reliability_cost)
    stage("pipeline_profile", run_pipeline_profile)
    stage("decode", run_decode)
    stage("detect", run_detect)
    stage("e2e", e2e_rows)
    stage("profile", run_profile)
    stage("accuracy", run_accuracy)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
