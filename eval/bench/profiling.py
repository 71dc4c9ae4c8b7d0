"""``fr bench``'s profiles: the torch profiler's top ops of one batch, and peak memory measured in a
fresh process per setting."""
from __future__ import annotations

import json
import resource
import subprocess
import sys
import time
from pathlib import Path

from fr_eval.bench.timing import bench_estimator, device_sync, scene_segments
from fr_eval.machine import proc_status_kb
from fr_eval.paths import REPO


def profile_table(device: str, batch: int, n_segments: int, out: Path, progress, mode: str = "fast",
                  rows: int = 25) -> dict:
    """torch profiler over one calibrate_segments call: top ops by self time, written to
    ``<out>/profile_<device>_<mode>.txt``; returns the top ops as dicts (ms)."""
    from torch.profiler import ProfilerActivity, profile

    if progress.out_of_time(f"profile {device} {mode}"):
        return {}
    est = bench_estimator(mode, device)
    pool = [scene_segments(n_segments, seed=i) for i in range(8)]
    segs, sizes = [pool[i % len(pool)] for i in range(batch)], [(640, 480)] * batch
    est.calibrate_segments(segs[:2], sizes[:2])
    activities = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if device.startswith("cuda") else [])
    sync = device_sync(device)
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
    est = bench_estimator(mode, device, k)
    pool = [scene_segments(n_seg, seed=i) for i in range(4)]
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


def _reset_peak_rss() -> float:
    """Reset the peak-RSS mark to the current RSS (Linux); returns the current RSS in KiB."""
    try:
        Path("/proc/self/clear_refs").write_text("5")
    except OSError:
        pass
    current = proc_status_kb("VmRSS")
    return float(current if current is not None else resource.getrusage(resource.RUSAGE_SELF).ru_maxrss)


def _peak_rss() -> float:
    """Peak RSS in KiB since the last reset (VmHWM), or ru_maxrss where /proc is missing."""
    peak = proc_status_kb("VmHWM")
    return float(peak if peak is not None else resource.getrusage(resource.RUSAGE_SELF).ru_maxrss)


_PROBE = "import sys; from fr_torch.registry import load_object; sys.exit(load_object('fr_eval.bench.command:main')())"


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
