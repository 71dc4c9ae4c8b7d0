"""Folder end to end: wall time of whole ``fr calibrate`` processes on the YorkUrbanDB photos.

    python -m fr_eval.bench.folder --copies 1,3 --workers 0,1,2,default --rounds 2 \\
        --out results/bench/pipeline.md

For every number of copies of the 102 photos (a folder of 102 x c paths), mode and ``--workers``
setting, runs ``fr calibrate [--fast] --workers W PATHS...`` as a new process (start-up, model
loading, decode, LSD, search and JSON output included), ``--rounds`` times one after the other,
and reports seconds per round and images/s from their mean.  ``default`` leaves ``--workers``
unset (:meth:`fr_torch.runtime.device.DevicePolicy.default_workers`).  Also checks that every setting gives the same
focal lengths as in-process (``--workers 0``).  ``--device cuda`` times ``fr calibrate --device
cuda`` (workers then decode and detect while the process searches on the GPU; results/bench/h100);
``--extra`` passes more options (``--fast``).  Run it on an idle machine.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

from fr_eval.machine import machine_description
from fr_eval.paths import data_root
from fr_torch.cli.options import add_device_arguments
from fr_torch.runtime.device import DevicePolicy
from fr_torch.runtime.workers import usable_cores

MODES = {"fast": ["--fast"], "fr": []}


def _run(paths: list[str], mode: str, workers: str, device: str = "cpu",
         extra: tuple[str, ...] = ()) -> tuple[float, list[float | None]]:
    command = [sys.executable, "-m", "fr_torch.cli", "calibrate", *MODES[mode], "--device", device, *extra, *paths]
    if workers != "default":
        command += ["--workers", workers]
    start = time.perf_counter()
    out = subprocess.run(command, capture_output=True, text=True)
    seconds = time.perf_counter() - start
    if out.returncode not in (0, 1):  # 1 = some image failed (reported in its record)
        raise RuntimeError(f"{' '.join(command[:6])} ...: exit {out.returncode}: {out.stderr.strip()[-300:]}")
    focal = [json.loads(line).get("focal_px") for line in out.stdout.splitlines() if line.startswith("{")]
    return seconds, focal


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--copies", default="1,3", help="folder sizes, in copies of the 102 photos")
    parser.add_argument("--workers", default="0,1,2,default", help="--workers settings (default = unset)")
    parser.add_argument("--modes", default="fast,fr")
    parser.add_argument("--rounds", type=int, default=2)
    parser.add_argument("--data-root", default=None)
    add_device_arguments(parser, device_help="fr calibrate's --device (cpu or cuda)")
    parser.add_argument("--extra", default="", help="more fr calibrate options, e.g. '--fast'")
    parser.add_argument("--out", type=Path, default=None, help="write the Markdown table here")
    args = parser.parse_args(argv)
    photos = sorted(str(p) for p in (data_root(args.data_root) / "yorkurbandb").glob("*/*.jpg"))
    if not photos:
        raise SystemExit("no YorkUrbanDB photos found under the data root")
    rows = []
    for copies in (int(c) for c in args.copies.split(",")):
        paths = photos * copies
        for mode in args.modes.split(","):
            reference = None
            for workers in args.workers.split(","):
                runs = []
                for _ in range(args.rounds):
                    seconds, focal = _run(paths, mode, workers, args.device, tuple(args.extra.split()))
                    runs.append(seconds)
                    reference = reference if reference is not None else focal
                    same = focal == reference
                shown = workers if workers != "default" else f"default ({DevicePolicy.parse(args.device).default_workers(len(paths))})"
                row = {"images": len(paths), "mode": mode, "workers": shown, "seconds": runs,
                       "images_per_s": len(paths) / (sum(runs) / len(runs)), "same_as_in_process": same}
                rows.append(row)
                print(json.dumps(row), flush=True)
    load = os.getloadavg() if hasattr(os, "getloadavg") else None
    machine = machine_description(args.device)  # the CPU, and the GPU of a CUDA run
    lines = [
        f"# Folder end to end (`fr calibrate --device {args.device}` on YorkUrbanDB photos, {usable_cores()} cores)", "",
        "Command: `python -m fr_eval.bench.folder " + " ".join(argv if argv is not None else sys.argv[1:]) + "`.",
        "Wall time of each whole `fr calibrate [--fast] [--workers W] PATHS...` process (start-up, model loading,",
        "decode, LSD, search, JSON output), 640×480 JPEGs, the 102 photos repeated to make larger folders;",
        f"rounds one after the other, seconds per round, images/s from their mean. Machine: {machine['cpu']},",
        f"{usable_cores()} usable cores{', ' + machine['gpu'] if 'gpu' in machine else ''}, load average after the run "
        f"{tuple(round(v, 2) for v in load) if load else 'n/a'}.",
        "W = 0: in-process (intra-op threads); W > 0 on a CPU: whole-image worker processes, one thread each; "
        "W > 0 on a GPU: decode + detection workers feeding the search in this process.",
        "", "| images | mode | workers W | seconds | images/s | focal lengths = in-process |", "|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['images']} | {r['mode']} | {r['workers']} | {' / '.join(f'{s:.2f}' for s in r['seconds'])} "
                     f"| {r['images_per_s']:.1f} | {'yes' if r['same_as_in_process'] else 'NO'} |")
    text = "\n".join(lines) + "\n"
    print(text)
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
