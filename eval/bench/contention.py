"""CPU speed under contention: per-photo time idle, beside a busy neighbour, and side by side.

A machine is rarely idle.  This measures fR the way a user's process runs it (a fresh process with
the command's thread settings: :meth:`fr_torch.runtime.device.DevicePolicy.apply_threads`, thread
policy from ``FR_THREADS``) in three conditions:

* **idle**: one process alone;
* **busy**: the same process while a *neighbour* keeps one core busy (a pure-Python spin loop in
  a subprocess this module starts and stops, bounded to :data:`NEIGHBOUR_MAX_S` seconds);
* **side by side**: ``k`` such processes calibrating at the same time.

Probes are long-lived subprocesses (``python -m fr_eval.bench.contention probe``) that load the library
and the photos once, then run one measurement per command read on stdin, so that the side-by-side
processes start their timed work together and the conditions interleave in the same processes.
A measurement is ``passes`` passes over the photos, one photo per call; its figure is the median
over passes of the seconds per photo.  Kinds: ``segments`` (``calibrate_segments`` on LSD
segments detected beforehand) and ``images`` (``calibrate_images`` on the file: decode + LSD +
search).  ``policy`` is the ``FR_THREADS`` value of the probes (``auto``, ``torch``, ``N``).

:func:`command_runs` times whole ``fr calibrate`` commands (start-up included) the same three ways.

``fr bench`` runs :func:`contention_rows` as its ``contention`` section.  For a report::

    python -m fr_eval.bench.contention measure --modes fast,fr --kinds segments,images \\
        --policies auto,torch --side 2 --command-side 2,4 --rounds 3 --passes 3 --images P1.jpg,P2.jpg,...
"""
from __future__ import annotations

import argparse
import json
import os
import signal
import statistics
import subprocess
import sys
import time
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator, Sequence

#: Upper bound on a neighbour's life (seconds): it ends by itself even if its parent dies.
NEIGHBOUR_MAX_S = 600.0
#: Seconds a neighbour spins before the measurement starts (it has its core by then).
NEIGHBOUR_LEAD_S = 0.3
#: Seconds a probe may take to load or to answer one command.
PROBE_TIMEOUT_S = 900.0

_SPIN = ("import time\nend = time.monotonic() + {seconds}\nwhile time.monotonic() < end:\n    pass\n")


@contextmanager
def busy_neighbour(seconds: float = NEIGHBOUR_MAX_S) -> Iterator[subprocess.Popen]:
    """A subprocess that keeps one core busy (pure-Python loop) while the block runs, at most
    ``seconds``; stopped on exit."""
    proc = subprocess.Popen([sys.executable, "-c", _SPIN.format(seconds=float(seconds))])
    try:
        time.sleep(NEIGHBOUR_LEAD_S)
        yield proc
    finally:
        proc.kill()
        proc.wait()


def load_average() -> float | None:
    """The 1-minute load average (None where there is none)."""
    try:
        return round(os.getloadavg()[0], 2)
    except (AttributeError, OSError):
        return None


# --------------------------------------------------------------------------- the probe process

def _probe_main(paths: Sequence[str]) -> int:
    """In a probe process: load the photos, say ``ready``, then answer each JSON command
    ``{"mode", "kind", "passes"}`` with one JSON line ``{"per_photo_s", "passes_s", "threads"}``."""
    import torch

    from fr_torch.detectors.registry import detect_segments
    from fr_torch.images.io import load_image
    from fr_torch.runtime.device import DevicePolicy
    from fr_torch.runtime.estimator import FREstimator

    policy = DevicePolicy.resolve("cpu")
    policy.apply_threads()  # as fr calibrate / track / batch do
    photos = []
    for path in paths:
        image = load_image(path)
        photos.append((path, detect_segments(image), (int(image.shape[1]), int(image.shape[0]))))
    estimators: dict[str, FREstimator] = {}
    print("ready", flush=True)
    for line in sys.stdin:
        command = json.loads(line)
        mode, kind, passes = command["mode"], command["kind"], int(command["passes"])
        est = estimators.get(mode)
        if est is None:
            est = estimators[mode] = FREstimator(mode=mode, device=policy)
        if kind == "segments":
            def call(photo, est=est):
                est.calibrate_segments([photo[1]], [photo[2]])
        else:
            def call(photo, est=est):
                est.calibrate_images([photo[0]])
        for photo in photos[:1] if command.get("warm", True) else ():
            call(photo)  # warm-up: one-time costs and the thread policy's first reading
        used, times = [], []
        for _ in range(passes):
            start = time.perf_counter()
            for photo in photos:
                used.append(policy.search_thread_count() or torch.get_num_threads())
                call(photo)
            times.append((time.perf_counter() - start) / len(photos))
        print(json.dumps({"per_photo_s": statistics.median(times), "passes_s": times,
                          "threads": sorted(set(used))}), flush=True)
    return 0


class Probe:
    """A probe subprocess (see the module docstring) with ``FR_THREADS=policy``."""

    def __init__(self, paths: Sequence[str], policy: str):
        env = dict(os.environ, FR_THREADS=str(policy))
        self.proc = subprocess.Popen([sys.executable, "-m", "fr_eval.bench.contention", "probe", "--images",
                                      ",".join(paths)], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                     text=True, env=env)

    def wait_ready(self) -> None:
        line = self.proc.stdout.readline()
        if line.strip() != "ready":
            raise RuntimeError(f"contention probe failed to start (exit {self.proc.poll()})")

    def send(self, mode: str, kind: str, passes: int) -> None:
        self.proc.stdin.write(json.dumps({"mode": mode, "kind": kind, "passes": passes}) + "\n")
        self.proc.stdin.flush()

    def receive(self) -> dict:
        line = self.proc.stdout.readline()
        if not line:
            raise RuntimeError(f"contention probe died (exit {self.proc.poll()})")
        return json.loads(line)

    def close(self) -> None:
        if self.proc.poll() is None:
            self.proc.stdin.close()
            try:
                self.proc.wait(timeout=30)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()


def _run_together(probes: Sequence[Probe], mode: str, kind: str, passes: int) -> list[dict]:
    for probe in probes:
        probe.send(mode, kind, passes)
    return [probe.receive() for probe in probes]


def contention_rows(paths: Sequence[str], modes: Sequence[str] = ("fast", "fr"),
                    kinds: Sequence[str] = ("segments", "images"), policies: Sequence[str] = ("auto",),
                    side_counts: Sequence[int] = (2,), passes: int = 3, rounds: int = 1,
                    progress=None) -> list[dict]:
    """One row per (mode, kind, policy, round): seconds per photo idle, beside a busy neighbour
    (and the ratio to idle), and side by side (each of ``k`` processes; ``side{k}_throughput`` =
    the photos per second of the ``k`` together over those of one alone).  Conditions interleave
    within a round; every policy has its own probes, started once."""
    width = max([1, *side_counts])
    probes = {policy: [Probe(paths, policy) for _ in range(width)] for policy in policies}
    rows = []
    try:
        for group in probes.values():
            for probe in group:
                probe.wait_ready()
        for round_index in range(rounds):
            for mode in modes:
                for kind in kinds:
                    for policy, group in probes.items():
                        row = {"mode": mode, "kind": kind, "policy": policy, "round": round_index,
                               "photos": len(paths), "passes": passes, "load_before": load_average()}
                        [idle] = _run_together(group[:1], mode, kind, passes)
                        row["idle_s"], row["idle_threads"] = idle["per_photo_s"], idle["threads"]
                        with busy_neighbour():
                            [busy] = _run_together(group[:1], mode, kind, passes)
                        row["busy_s"], row["busy_threads"] = busy["per_photo_s"], busy["threads"]
                        row["busy_ratio"] = row["busy_s"] / row["idle_s"]
                        for k in side_counts:
                            side = _run_together(group[:k], mode, kind, passes)
                            each = [s["per_photo_s"] for s in side]
                            row[f"side{k}_s"] = statistics.mean(each)
                            row[f"side{k}_throughput"] = sum(row["idle_s"] / s for s in each)
                            row[f"side{k}_threads"] = sorted({t for s in side for t in s["threads"]})
                        row["load_after"] = load_average()
                        rows.append(row)
                        if progress is not None:
                            progress.update(1, "contention", row)
    finally:
        for group in probes.values():
            for probe in group:
                probe.close()
    return rows


# --------------------------------------------------------------------------- whole commands

def _fr_command(paths: Sequence[str], mode: str) -> list[str]:
    return [sys.executable, "-m", "fr_torch.cli", "calibrate", "--no-progress",
            *(["--fast"] if mode == "fast" else []), *paths]


def _time_commands(commands: Sequence[list[str]], env: dict) -> list[float]:
    """Wall seconds of each command, all started together."""
    start = time.perf_counter()
    procs = [subprocess.Popen(c, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, env=env) for c in commands]
    walls = [0.0] * len(procs)
    pending = set(range(len(procs)))
    try:
        while pending:
            for i in list(pending):
                if procs[i].poll() is not None:
                    walls[i] = time.perf_counter() - start
                    pending.discard(i)
                    if procs[i].returncode != 0:
                        raise RuntimeError(f"fr calibrate failed: {procs[i].stderr.read().strip()[-300:]}")
            time.sleep(0.01)
    finally:
        for proc in procs:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
    return walls


def command_runs(paths: Sequence[str], modes: Sequence[str] = ("fast", "fr"), policies: Sequence[str] = ("auto",),
                 side_counts: Sequence[int] = (2, 4), rounds: int = 1, progress=None) -> list[dict]:
    """Whole ``fr calibrate`` commands on ``paths`` (start-up included, after one untimed run):
    seconds per photo alone, beside a busy neighbour, and for ``k`` commands side by side
    (``side{k}_throughput``: photos per second of the ``k`` together over those of one alone).
    One row per (mode, policy, round)."""
    rows = []
    # Warm-up: the first run after a pause reads the library's files from disk (0.5-0.7 s more).
    _time_commands([_fr_command(paths[:1], modes[0])], dict(os.environ))
    for round_index in range(rounds):
        for mode in modes:
            for policy in policies:
                env = dict(os.environ, FR_THREADS=str(policy))
                command = _fr_command(paths, mode)
                row = {"mode": mode, "kind": "fr calibrate", "policy": policy, "round": round_index,
                       "photos": len(paths), "load_before": load_average()}
                [idle] = _time_commands([command], env)
                row["idle_s"] = idle / len(paths)
                with busy_neighbour():
                    [busy] = _time_commands([command], env)
                row["busy_s"] = busy / len(paths)
                row["busy_ratio"] = row["busy_s"] / row["idle_s"]
                for k in side_counts:
                    walls = _time_commands([command] * k, env)
                    row[f"side{k}_s"] = statistics.mean(walls) / len(paths)
                    row[f"side{k}_throughput"] = k * idle / max(walls)
                row["load_after"] = load_average()
                rows.append(row)
                if progress is not None:
                    progress.update(1, "contention", row)
    return rows


# --------------------------------------------------------------------------- report

def summary_lines(rows: Sequence[dict], side_counts: Sequence[int]) -> list[str]:
    """A Markdown table of ``rows`` (medians over rounds per mode, kind and policy)."""
    groups: dict = {}
    for r in rows:
        groups.setdefault((r["mode"], r["kind"], r["policy"]), []).append(r)
    header = ("| mode | kind | FR_THREADS | idle s/photo | busy neighbour s/photo | busy / idle | "
              + " | ".join(f"{k} side by side s/photo (each) | {k} together / one alone" for k in side_counts)
              + " | rounds | load avg |")
    lines = [header, "|" + "---|" * (header.count("|") - 1)]

    def med(group, key):
        values = [r[key] for r in group if key in r]
        return statistics.median(values) if values else float("nan")

    for (mode, kind, policy), group in groups.items():
        loads = [r["load_before"] for r in group if r.get("load_before") is not None]
        cells = [mode, kind, policy, f"{med(group, 'idle_s'):.3f}", f"{med(group, 'busy_s'):.3f}",
                 f"**{med(group, 'busy_ratio'):.2f}x**"]
        for k in side_counts:
            cells += [f"{med(group, f'side{k}_s'):.3f}", f"**{med(group, f'side{k}_throughput'):.2f}x**"]
        cells += [str(len(group)), f"{min(loads):.1f}-{max(loads):.1f}" if loads else "?"]
        lines.append("| " + " | ".join(cells) + " |")
    return lines


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m fr_eval.bench.contention", description=__doc__.splitlines()[0])
    parser.add_argument("action", choices=("measure", "probe"))
    parser.add_argument("--images", required=True, help="comma-separated photo paths")
    parser.add_argument("--modes", default="fast,fr")
    parser.add_argument("--kinds", default="segments,images,command",
                        help="segments, images (in a probe process) and/or command (whole fr calibrate runs)")
    parser.add_argument("--policies", default="auto", help="FR_THREADS values to compare, e.g. auto,torch")
    parser.add_argument("--side", default="2", help="numbers of processes side by side, e.g. 2,4")
    parser.add_argument("--command-side", default=None, help="the same for whole commands (default --side)")
    parser.add_argument("--passes", type=int, default=3)
    parser.add_argument("--rounds", type=int, default=1)
    parser.add_argument("--json", type=Path, default=None, help="also write the rows to this JSON file")
    args = parser.parse_args(argv)
    paths = [p for p in args.images.split(",") if p]
    if args.action == "probe":
        return _probe_main(paths)
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(143))  # stop the probes and the neighbour too
    split = lambda text: [v for v in text.split(",") if v]  # noqa: E731
    modes, kinds, policies = split(args.modes), split(args.kinds), split(args.policies)
    side = [int(v) for v in split(args.side)]
    command_side = [int(v) for v in split(args.command_side)] if args.command_side else side

    class _Print:
        def update(self, n, section, row):
            print(json.dumps(row), file=sys.stderr, flush=True)

    rows = []
    probe_kinds = [k for k in kinds if k != "command"]
    for round_index in range(args.rounds):  # probes and commands interleave round by round
        if probe_kinds:
            for row in contention_rows(paths, modes, probe_kinds, policies, side, args.passes, 1, _Print()):
                rows.append(dict(row, round=round_index))
        if "command" in kinds:
            for row in command_runs(paths, modes, policies, command_side, 1, _Print()):
                rows.append(dict(row, round=round_index))
        if args.json:
            args.json.write_text(json.dumps(rows, indent=1))
    if probe_kinds:
        print("\n".join(summary_lines([r for r in rows if r["kind"] != "fr calibrate"], side)) + "\n")
    if "command" in kinds:
        print("\n".join(summary_lines([r for r in rows if r["kind"] == "fr calibrate"], command_side)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
