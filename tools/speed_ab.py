"""Two checkouts timed in one run, interleaved: per-stage latency and throughput given segments.

``python tools/speed_ab.py --before <checkout> --after <checkout> [--rounds 3] [--threads 2]``: each
round runs, for each checkout in turn, one process that times (a) the search per photo at batch 1 on
4 YUD train photos (LSD segments, detected once and cached in ``--cache``; the ``runtime_s`` stages
grid / refine / cues / total, wall and process CPU time; median of 2 passes) in Fast-fR and fR, and
(b) images/s given 300 synthetic segments at batch 1 and 64 (``fr_eval.bench.timing``); then prints
the medians over rounds, before -> after, as Markdown.  Each process imports the library and the
harness (``fr_eval``) of its own checkout.  Interleaving keeps a shared machine's load
out of the ratios; the load average at each start is reported beside them.  ``--distortion division``:
the same figures with the division model's lens search (``FREstimator(distortion="division")``).
"""
from __future__ import annotations

import argparse
import collections
import json
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

HERE = Path(__file__).resolve().parent


def measure(threads: int, what: str, cache: Path, distortion: str | None = None) -> dict:
    """One process's figures (run inside the checkout being timed); ``distortion``: the estimator's
    lens setting (None: pinhole)."""
    import time

    import numpy as np
    import torch

    torch.set_num_threads(threads)
    from fr_torch import FREstimator

    out = {}
    if what == "latency":
        sys.path.insert(0, str(HERE))
        from bit_identity import segment_sets

        segments, sizes = segment_sets(cache, 8, 4)
        segments, sizes = segments[:4], sizes[:4]
        for mode in ("fast", "fr"):
            estimator = FREstimator(mode=mode, distortion=distortion)
            estimator.calibrate_segments(segments[:1], sizes[:1])
            rows = []
            for _ in range(2):
                for seg, size in zip(segments, sizes):
                    cpu, wall = time.process_time(), time.perf_counter()
                    [result] = estimator.calibrate_segments([seg], [size])
                    rows.append(dict(result.runtime_s, wall=time.perf_counter() - wall,
                                     cpu=time.process_time() - cpu))
            out[mode] = {k: 1e3 * statistics.median(r[k] for r in rows) for k in ("grid", "refine", "cues", "total",
                                                                                  "wall", "cpu")}
    else:
        from fr_eval.bench.timing import bench_estimator, scene_segments

        pool = [scene_segments(300, seed=i) for i in range(8)]
        for mode in ("fast", "fr"):
            estimator = bench_estimator(mode, "cpu", distortion=distortion)
            for batch in (1, 64):
                segs, sizes = [pool[i % 8] for i in range(batch)], [(640, 480)] * batch
                estimator.calibrate_segments(segs[:2], sizes[:2])
                walls, cpus = [], []
                for _ in range(5 if batch == 1 else 1):
                    cpu, wall = time.process_time(), time.perf_counter()
                    estimator.calibrate_segments(segs, sizes)
                    walls.append(time.perf_counter() - wall)
                    cpus.append(time.process_time() - cpu)
                out[f"{mode} batch {batch}"] = {"images/s": batch / float(np.median(walls)),
                                                "CPU ms/image": 1e3 * float(np.median(cpus)) / batch}
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--before", required=True)
    parser.add_argument("--after", required=True)
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--cache", type=Path, default=Path("/tmp/fr_speed_ab.segments.npz"))
    parser.add_argument("--distortion", choices=("pinhole", "division"), default="pinhole")
    parser.add_argument("--measure", help=argparse.SUPPRESS)  # internal: one process's figures
    args = parser.parse_args()
    if args.measure:
        distortion = None if args.distortion == "pinhole" else args.distortion
        print(json.dumps(measure(args.threads, args.measure, args.cache, distortion)))
        return
    figures = collections.defaultdict(lambda: collections.defaultdict(list))
    loads = []
    links = tempfile.TemporaryDirectory()  # each checkout's harness under its installed names
    for name, checkout in (("before", args.before), ("after", args.after)):
        folder = Path(links.name) / name
        folder.mkdir()
        (folder / "fr_eval").symlink_to(Path(checkout).resolve() / "eval")
        (folder / "fr_baselines").symlink_to(Path(checkout).resolve() / "baselines")
    for _ in range(args.rounds):
        for what in ("latency", "throughput"):
            for name, checkout in (("before", args.before), ("after", args.after)):
                loads.append(os.getloadavg()[0])
                env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(Path(checkout).resolve()),
                                                                   str(Path(links.name) / name),
                                                                   os.environ.get("PYTHONPATH", "")]))
                done = subprocess.run([sys.executable, __file__, "--before", args.before, "--after", args.after,
                                       "--threads", str(args.threads), "--cache", str(args.cache),
                                       "--distortion", args.distortion, "--measure", what],
                                      capture_output=True, text=True, env=env, check=True)
                for row, values in json.loads(done.stdout.strip().splitlines()[-1]).items():
                    for key, value in values.items():
                        figures[(row, key)][name].append(value)
    print(f"{args.rounds} rounds, {args.threads} threads, {args.distortion}, "
          f"load average {min(loads):.1f}-{max(loads):.1f}\n")
    print("| | measure | before | after | ratio |\n| --- | --- | --- | --- | --- |")
    for (row, key), values in figures.items():
        before, after = statistics.median(values["before"]), statistics.median(values["after"])
        ratio = after / before if key == "images/s" else before / after
        print(f"| {row} | {key} | {before:.1f} | {after:.1f} | {ratio:.2f}x |")


if __name__ == "__main__":
    main()
