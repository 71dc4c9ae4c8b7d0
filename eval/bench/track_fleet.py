"""``fr track`` over a fleet of live cameras, measured: throughput against one process per
camera, accuracy with a camera that disconnects and returns, a soak, stops at random moments.
Each runs whole ``fr track`` processes against synthetic cameras served over HTTP MJPEG by another
process (:func:`serve`; :mod:`fr_eval.datasets.live_stream`) and writes its tables and figures to
``--out`` (default ``results/track/fleet``)::

    python -m fr_eval.bench.track_fleet throughput --cameras 1,2,4,8,16 --seconds 40   # throughput.md / .csv
    python -m fr_eval.bench.track_fleet accuracy --seconds 75                          # accuracy.md / .csv
    python -m fr_eval.bench.track_fleet soak --cameras 16 --minutes 10                 # soak.md, soak.png, soak_*.csv
    python -m fr_eval.bench.track_fleet stops --trials 20                              # stop_trials.md / .csv
    python -m fr_eval.bench.track_fleet readers --cameras 16 --seconds 20              # reading alone: CPU per frame
    python -m fr_eval.bench.track_fleet serve --cameras 4 --port 18600                 # the cameras alone

The cameras (:func:`fleet_camera`): synthetic rooms of 640 x 480 with image noise, each its own
room, horizontal field of view (50, 62, 74 or 86 deg: four focal lengths), pan, pitch and roll,
all served at ``--fps`` by one process.  Every run is Fast-fR with the reliability stage (``fr
track --fast``) on the same cores as the servers.

**throughput**: for each N of ``--cameras``, N cameras read by one ``fr track URL1 ... URLN`` (the
fleet: one batched search per turn, split over its worker processes; for the N of ``--in-process``
also with ``--workers 0``, searched in the fleet's own process) and then by N ``fr track URLi`` processes (one camera per
process, each searching its newest frame at batch 1).  Once every camera has its first record,
records are counted for ``--seconds``: frames searched per second in all, searches per camera per
second (the least served camera's and the median), the age of a frame at its record, and the
resident memory of all the fr processes.

``--code before=TREE,after=`` runs each N and mode with the ``fr track`` of each checkout in turn
(TREE: e.g. ``git archive`` of an older commit; empty: this one), ``--rounds`` times, the order
reversed every other round: a before / after figure from one run on one machine.

**accuracy**: four cameras of different focal lengths for ``--seconds``; camera 3 stalls (its
server sends nothing) from ``--outage`` seconds, so ``fr track --reconnect`` drops and reopens it.
The fused focal length and tilt of each camera after 60 s against its truth.

**soak**: ``--cameras`` cameras for ``--minutes``, stopped by SIGTERM: resident memory each
second (growth after the first minute) and each camera's longest gap between two records.

**stops**: ``--trials`` runs of a 4-camera fleet (``--reconnect 3``) on one output folder, each
stopped after a random delay by SIGTERM, SIGINT, SIGHUP, or by killing one camera's server (the
fleet goes on without it; it is then stopped by SIGTERM), a shuffled equal count of each.  Checked
per trial: the exit status, every camera's frames.csv complete and parseable, its calibration.json
valid with the records of this run and how its run ended, the stop line's count, no process left.
"""
from __future__ import annotations

import argparse
import itertools
import json
import os
import random
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Iterator

import numpy as np
import pandas as pd

from fr_eval.bench.track_live import FR, _env, _records_check, _stop, default_stop_signals
from fr_eval.datasets.live_stream import MJPEGServer, SyntheticCamera
from fr_eval.machine import machine_description, proc_status_kb, session_cpu_s, session_processes
from fr_eval.paths import REPO
from fr_torch.core.geometry.conventions import rotation_angles
from fr_torch.video.records import CAMERA_KEY, RECORD_KEYS

FLEET_KEYS = (CAMERA_KEY,) + RECORD_KEYS
HFOVS = (50.0, 62.0, 74.0, 86.0)
STOPS = ("SIGTERM", "SIGINT", "SIGHUP", "kill a camera")
#: Seconds the search workers' fork server and resource tracker may take to end after fr track.
POOL_GONE_S = 10.0


def fleet_camera(i: int) -> SyntheticCamera:
    """Camera ``i`` of a fleet (module docstring): its own room and pose, one of four focal lengths."""
    return SyntheticCamera(hfov_deg=HFOVS[i % 4], pan_deg=10.0 + 7.0 * i, pitch_deg=4.0 + i % 5,
                           roll_deg=-2.0 + i % 5, room_seed=i)


class StallingCamera(SyntheticCamera):
    """A camera whose server sends nothing between ``outage[0]`` and ``outage[1]`` (``time.monotonic()``)."""

    outage: tuple[float, float] = (0.0, 0.0)

    def jpeg(self, k: int) -> bytes:
        while self.outage[0] <= time.monotonic() < self.outage[1]:
            time.sleep(0.05)
        return super().jpeg(k)


# ---------------------------------------------------------------------------------- the cameras

def serve(args) -> int:
    """Serve cameras ``--first`` .. ``--first + --cameras - 1`` on ports ``--port + i``; prints one
    JSON line (their URLs and the Unix time of their frame 0), then serves until killed."""
    servers = []
    now = time.monotonic()
    for i in range(args.first, args.first + args.cameras):
        camera = fleet_camera(i)
        if args.stall is not None and i == args.stall:
            camera = StallingCamera(**{k: getattr(camera, k) for k in ("hfov_deg", "pan_deg", "pitch_deg", "roll_deg",
                                                                        "room_seed")})
            camera.outage = (now + args.outage[0], now + args.outage[1])
        for k in range(4):
            camera.jpeg(k)  # rendered before the first client: serving costs no rendering
        servers.append(MJPEGServer(camera, args.fps, args.port + i - args.first))
    for server in servers:
        server.start()
    print(json.dumps({"urls": [s.url for s in servers],
                      "frame0": [time.time() - (time.monotonic() - s.start_time) for s in servers]}), flush=True)
    try:
        while True:
            time.sleep(3600)
    except KeyboardInterrupt:
        return 0


def start_cameras(count: int, port: int, fps: float, first: int = 0, stall: int | None = None,
                  outage: tuple[float, float] = (0.0, 0.0)) -> tuple[subprocess.Popen, list[str], list[float]]:
    """:func:`serve` as a process: it, the cameras' URLs and the Unix times of their frame 0."""
    command = [sys.executable, "-m", "fr_eval.bench.track_fleet", "serve", "--cameras", str(count), "--port", str(port),
               "--fps", str(fps), "--first", str(first)]
    if stall is not None:
        command += ["--stall", str(stall), "--outage", f"{outage[0]},{outage[1]}"]
    server = subprocess.Popen(command, stdout=subprocess.PIPE, text=True, env=_env(), start_new_session=True)
    started = json.loads(server.stdout.readline())
    return server, started["urls"], started["frame0"]


def code_env(tree: Path | None) -> dict[str, str]:
    """The environment of an ``fr track`` of ``tree`` (a checkout of fR, e.g. an exported older
    commit: its ``fr_torch`` imported first, with this interpreter's packages), or of this checkout
    (None)."""
    env = _env()
    if tree is not None:
        env["PYTHONPATH"] = os.pathsep.join([str(tree), env["PYTHONPATH"]])
    return env


class Run:
    """An ``fr track`` process whose JSON-line records are collected (stamped ``arrived``) as they
    come, and whose resident memory can be sampled.  ``tree``: the checkout whose code it runs
    (:func:`code_env`; None: this one)."""

    def __init__(self, arguments: list[str], out: Path, tree: Path | None = None):
        self.records: list[dict] = []
        self.process = subprocess.Popen(FR + arguments + ["--out", str(out), "--json", "-"], stdout=subprocess.PIPE,
                                        stderr=subprocess.PIPE, text=True, env=code_env(tree), cwd=tree,
                                        start_new_session=True, preexec_fn=default_stop_signals)
        self.stderr = ""
        threading.Thread(target=self._read, daemon=True).start()
        threading.Thread(target=self._read_stderr, daemon=True).start()

    def _read(self) -> None:
        for line in self.process.stdout:
            if line.startswith("{") and '"frame"' in line:
                record = json.loads(line)
                record["arrived"] = time.time()
                self.records.append(record)

    def _read_stderr(self) -> None:
        self.stderr = self.process.stderr.read()

    def cpu_s(self) -> float:
        """CPU seconds (user + system) used so far by the fr track process and every live process it
        started (:func:`fr_eval.machine.session_cpu_s`)."""
        return session_cpu_s(self.process.pid)

    def rss_mb(self) -> float:
        """Resident memory of the fr track process and of every process it started (its search
        workers, their fork server), MB."""
        pids = [self.process.pid] + session_processes(self.process.pid)
        return sum(proc_status_kb("VmRSS", pid) or 0 for pid in pids) / 1024

    def stop(self) -> None:
        if self.process.poll() is None:
            self.process.send_signal(signal.SIGTERM)
        try:
            self.process.wait(timeout=120)
        finally:
            _stop(self.process)


def _clean(folder: Path) -> None:
    if folder.exists():
        subprocess.run(["rm", "-rf", str(folder)], check=True)


def _wait_for_records(runs: list[Run], cameras: int, timeout_s: float) -> float:
    """Wait until every camera has a record; returns when (Unix time)."""
    deadline = time.time() + timeout_s
    while time.time() < deadline:
        seen = {(id(run), r.get(CAMERA_KEY)) for run in runs for r in run.records}
        if len(seen) >= cameras:
            return time.time()
        if any(run.process.poll() is not None for run in runs):
            raise RuntimeError("an fr track process ended: " + " | ".join(run.stderr[-500:] for run in runs))
        time.sleep(0.2)
    raise RuntimeError(f"not every camera had a record within {timeout_s:.0f} s")


# ---------------------------------------------------------------------------------- throughput

def parse_code(text: str) -> list[tuple[str, Path | None]]:
    """``--code LABEL=TREE,...`` as (label, tree) pairs; an empty TREE (or no option) is this checkout."""
    if not text:
        return [("", None)]
    pairs = [item.partition("=") for item in text.split(",")]
    return [(label, Path(tree).resolve() if tree else None) for label, _, tree in pairs]


def _interleaved(rounds: int, counts: list[int], modes: list[str], codes: list) -> Iterator[tuple]:
    """(round, N, mode, code) of each run: every code run after run for the same N and mode, in the
    given order in odd rounds and reversed in even ones (A B, B A: a drift of the machine's load
    favours neither)."""
    for round_ in range(1, rounds + 1):
        for n, mode in itertools.product(counts, modes):
            for code in (codes if round_ % 2 else codes[::-1]):
                yield round_, n, mode, code


def throughput(args) -> None:
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    counts = [int(n) for n in args.cameras.split(",")]
    in_process = [int(n) for n in args.in_process.split(",") if n]
    codes = parse_code(args.code)
    server, urls, _ = start_cameras(max(counts), args.port, args.fps)
    rows = []
    try:
        for round_, n, mode, (code, tree) in _interleaved(args.rounds, counts, args.modes.split(","), codes):
            if mode == "fleet" and n == 1:  # one camera: the same command as one process
                continue
            for mode in (mode,) + (("fleet, --workers 0",) if mode == "fleet" and n in in_process else ()):
                folder = Path(args.work) / (f"throughput_{mode.split(',')[0]}{'_0' if ',' in mode else ''}_{n}"
                                            + (f"_{code}" if code else ""))
                _clean(folder)
                if mode.startswith("fleet"):
                    workers = ["--workers", "0"] if "--workers 0" in mode else []
                    runs = [Run(urls[:n] + ["--fast", *workers, *args.extra], folder, tree)]
                else:
                    runs = [Run([url, "--fast", *args.extra], folder / f"camera{i}", tree)
                            for i, url in enumerate(urls[:n])]
                try:
                    start = _wait_for_records(runs, n, args.startup_s)
                    load_start = os.getloadavg()[0]
                    cpu_start = sum(run.cpu_s() for run in runs)
                    rss = []
                    while time.time() < start + args.seconds:
                        rss.append(sum(run.rss_mb() for run in runs))
                        time.sleep(1.0)
                    end = time.time()
                    cpu = sum(run.cpu_s() for run in runs) - cpu_start
                    load = os.getloadavg()[0]
                finally:
                    for run in runs:
                        run.stop()
                per_camera = []
                ages, runtimes = [], []
                for i, run in enumerate(runs):
                    window = [r for r in run.records if start <= r["time"] < end]
                    ages += [r["age_s"] for r in window]
                    runtimes += [r["runtime_s_total"] for r in window if r["runtime_s_total"] is not None]
                    if mode.startswith("fleet"):
                        per_camera += [sum(r[CAMERA_KEY] == name for r in window)
                                       for name in sorted({r[CAMERA_KEY] for r in run.records})]
                    else:
                        per_camera.append(len(window))
                seconds = end - start
                rates = np.array(per_camera) / seconds
                rows.append({"round": round_, "code": code, "cameras": n, "mode": mode, "seconds": round(seconds, 1),
                             "records": int(sum(per_camera)),
                             "frames_per_s": round(sum(per_camera) / seconds, 3),
                             "per_camera_min_per_s": round(float(rates.min()), 3),
                             "per_camera_median_per_s": round(float(np.median(rates)), 3),
                             "age_median_s": round(float(np.median(ages)), 3),
                             "age_p95_s": round(float(np.percentile(ages, 95)), 3),
                             "runtime_median_s": round(float(np.median(runtimes)), 3),
                             "cpu_s_per_frame": round(cpu / max(1, sum(per_camera)), 3),
                             "rss_mb": round(float(np.median(rss)), 0), "load_start": round(load_start, 2),
                             "load_avg": round(load, 2)})
                print(rows[-1], flush=True)
                pd.DataFrame(rows).to_csv(out / "throughput.csv", index=False)
    finally:
        _stop(server)
    _throughput_report(pd.DataFrame(rows), args, out)


def _shown(value, digits: int = 3) -> str:
    return "" if value is None or pd.isna(value) else f"{value:.{digits}f}"


def _throughput_report(table: pd.DataFrame, args, out: Path) -> None:
    for column, default in (("round", 1), ("code", ""), ("load_start", np.nan)):  # a table of an older run
        if column not in table:
            table[column] = default
    table["code"] = table["code"].fillna("")
    machine = machine_description("cpu")
    code = f" --code {args.code}" if getattr(args, "code", "") else ""
    text = ["# `fr track` over a fleet: throughput by number of cameras", "",
            f"Command: `python -m fr_eval.bench.track_fleet throughput --cameras {args.cameras} --seconds "
            f"{args.seconds:g} --fps {args.fps:g} --modes {args.modes} --rounds {args.rounds}{code}`. For each N: "
            "`fr track URL1 ... URLN --fast --json -` (one "
            "process, one batched search per turn, split over its worker processes), then N processes `fr track "
            "URLi --fast --json -` (one camera each, batch 1; `fleet, --workers 0`: the fleet searching in its own "
            f"process, among its reader threads), both on the same N synthetic cameras (640 x 480, {args.fps:g} frames/s, HTTP MJPEG, "
            "served by one other process on the same cores). Records counted over the window that starts when every "
            "camera has its first record. `code`: whose `fr track` ran (`--code LABEL=TREE`: a checkout's fr_torch; "
            "the codes interleaved, run after run).",
            f"Machine: {machine['cpu']}, {machine['usable_cores']} usable cores, torch {machine['torch']}; "
            "shared with other work (`load`: 1-minute load average at the start and the end of each window).", "",
            "| round | code | cameras | mode | frames searched / s | per camera / s (least served, median) | age at "
            "record (median, p95) s | detection + search per frame (median) s | CPU s per frame searched | RSS of all "
            "fr processes (MB) | load (start, end) |",
            "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    for _, row in table.iterrows():
        text.append(f"| {row['round']} | {row['code']} | {row['cameras']} | {row['mode']} | {row['frames_per_s']:.2f} | "
                    f"{row['per_camera_min_per_s']:.2f}, {row['per_camera_median_per_s']:.2f} | "
                    f"{row['age_median_s']:.2f}, {row['age_p95_s']:.2f} | {row['runtime_median_s']:.3f} | "
                    f"{_shown(row.get('cpu_s_per_frame'))} | {row['rss_mb']:.0f} | {_shown(row['load_start'], 1)}, "
                    f"{row['load_avg']:.1f} |")
    fleet, separate = table[table["mode"] == "fleet"], table[table["mode"] == "separate"]
    text += ["", "Fleet against one process per camera (frames searched per second, the same N and round; "
             "`fleet code / separate code`):", ""]
    for (round_, n), fleets in fleet.groupby(["round", "cameras"]):
        for _, f in fleets.iterrows():
            for _, o in separate[(separate["round"] == round_) & (separate["cameras"] == n)].iterrows():
                text.append(f"- round {round_}, {n} cameras, {f['code'] or 'fleet'} / {o['code'] or 'separate'}: "
                            f"{f['frames_per_s']:.2f} / {o['frames_per_s']:.2f} = "
                            f"**{f['frames_per_s'] / o['frames_per_s']:.2f} x**; memory {f['rss_mb']:.0f} MB against "
                            f"{o['rss_mb']:.0f} MB")
    text.append("")
    for label, runs in fleet.groupby("code"):
        served = runs[runs["per_camera_min_per_s"] >= 1.0]
        most = int(served["cameras"].max()) if len(served) else 0
        text.append(f"Most cameras of this table served at >= 1 search per camera per second by one fleet"
                    f"{f' ({label})' if label else ''}: **{most}**.")
    (out / "throughput.md").write_text("\n".join(text) + "\n")
    print("\n".join(text))


# ---------------------------------------------------------------------------------- readers

def readers(args) -> None:
    """The cost of reading alone: ``--cameras`` cameras read in this process as a fleet reads them
    (:class:`fr_torch.video.sources.LiveFrames`, real time, no frame taken, nothing searched) for
    ``--seconds`` after ``--warmup-s``; prints one JSON line: the fr_torch that read, frames read,
    this process's CPU in cores and in milliseconds per frame read, the load average.  For another
    checkout's readers run it in that checkout's folder with ``PYTHONPATH`` set to it (``-m`` puts
    the current folder first on the path)."""
    import fr_torch
    from fr_torch.video.sources import LiveFrames, Source, quiet_video_logs

    quiet_video_logs()
    server, urls, _ = start_cameras(args.cameras, args.port, args.fps)
    streams = [LiveFrames(Source.parse(url)) for url in urls]
    try:
        for stream in streams:
            stream.start()
        time.sleep(args.warmup_s)
        cpu, read, wall = time.process_time(), sum(s.arrived for s in streams), time.monotonic()
        time.sleep(args.seconds)
        cpu, read, wall = (time.process_time() - cpu, sum(s.arrived for s in streams) - read,
                           time.monotonic() - wall)
    finally:
        for stream in streams:
            stream.close()
        _stop(server)
    print(json.dumps({"fr_torch": str(Path(fr_torch.__file__).parent), "cameras": args.cameras,
                      "frames_read": read, "cores": round(cpu / wall, 3),
                      "cpu_ms_per_frame": round(1000 * cpu / max(1, read), 3), "load": round(os.getloadavg()[0], 2)}))


# ---------------------------------------------------------------------------------- accuracy

def accuracy(args) -> None:
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    outage = tuple(float(v) for v in args.outage.split(","))
    server, urls, frame0 = start_cameras(4, args.port, args.fps, stall=3, outage=outage)
    folder = Path(args.work) / "accuracy_run"
    _clean(folder)
    started = time.time()
    run = Run(urls + ["--fast", "--reconnect", *args.extra], folder)
    try:
        while time.time() < started + args.seconds and run.process.poll() is None:
            time.sleep(0.5)
    finally:
        run.stop()
        _stop(server)
    records = pd.DataFrame(run.records)
    records["t_s"] = records["time"] - started
    rows = []
    names = sorted(records[CAMERA_KEY].unique())
    for i, name in enumerate(names):
        camera = fleet_camera(i)
        truth_tilt = rotation_angles(camera.truth(0).rotation)["tilt_deg"]
        mine = records[records[CAMERA_KEY] == name]
        after = mine[mine["t_s"] >= args.settle_s]
        summary = json.loads((folder / name / "calibration.json").read_text())
        times = mine["time"].to_numpy()
        rows.append({"camera": name, "hfov_deg": camera.hfov_deg, "true_focal_px": round(camera.focal_px, 2),
                     "true_tilt_deg": round(truth_tilt, 3), "records": len(mine), "records_after": len(after),
                     "fused_focal_px": round(float(after["fused_focal_px"].iloc[-1]), 2),
                     "focal_err_pct_last": round(float(100 * (after["fused_focal_px"].iloc[-1] / camera.focal_px - 1)), 3),
                     "focal_err_pct_max_after": round(float((100 * (after["fused_focal_px"] / camera.focal_px - 1)).abs().max()), 3),
                     "tilt_err_deg_last": round(float(after["fused_tilt_deg"].iloc[-1] - truth_tilt), 3),
                     "tilt_err_deg_max_after": round(float((after["fused_tilt_deg"] - truth_tilt).abs().max()), 3),
                     "reconnects": int(summary["segments"][-1]["reconnects"]),
                     "longest_gap_s": round(float(np.diff(times).max()), 1) if len(times) > 1 else None,
                     "statuses": ", ".join(f"{k} {v}" for k, v in mine["status"].value_counts().items())})
        print(rows[-1], flush=True)
    table = pd.DataFrame(rows)
    table.to_csv(out / "accuracy.csv", index=False)
    ok = (table["focal_err_pct_max_after"] <= 1.0) & (table["tilt_err_deg_max_after"] <= 0.1)
    machine = machine_description("cpu")
    text = ["# `fr track` over a fleet: four cameras, one disconnecting and returning", "",
            f"Command: `python -m fr_eval.bench.track_fleet accuracy --seconds {args.seconds:g} --outage {args.outage} "
            f"--settle-s {args.settle_s:g}` (runs `fr track URL1 URL2 URL3 URL4 --fast --reconnect --json -`, "
            "stopped by SIGTERM at the end). Four synthetic cameras (640 x 480, image noise, each its own room and "
            f"pose; hfov {', '.join(f'{h:g}' for h in HFOVS)} deg) at {args.fps:g} frames/s; the server of the fourth "
            f"sends nothing from {outage[0]:g} s to {outage[1]:g} s after it started, so `fr track` drops it after "
            "--stream-timeout (5 s) and reconnects. Errors of the fused state against the truth in every record "
            f"written from {args.settle_s:g} s after `fr track` started.",
            f"Machine: {machine['cpu']}, {machine['usable_cores']} usable cores, shared with other work (load average "
            f"at the end {os.getloadavg()[0]:.1f}).", "",
            f"**{int(ok.sum())} of {len(table)}** cameras: fused focal length within 1 % and tilt within 0.1 deg of the "
            f"truth in every record after {args.settle_s:g} s.", "",
            "| camera | hfov (deg) | true f (px) | records (after settle) | fused f, last (px) | focal err last / max "
            "after (%) | tilt err last / max after (deg) | reconnects | longest gap (s) | statuses |",
            "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    for r in rows:
        text.append(f"| {r['camera']} | {r['hfov_deg']:g} | {r['true_focal_px']:.1f} | {r['records']} ({r['records_after']}) "
                    f"| {r['fused_focal_px']:.1f} | {r['focal_err_pct_last']:+.3f} / {r['focal_err_pct_max_after']:.3f} | "
                    f"{r['tilt_err_deg_last']:+.3f} / {r['tilt_err_deg_max_after']:.3f} | {r['reconnects']} | "
                    f"{r['longest_gap_s']} | {r['statuses']} |")
    (out / "accuracy.md").write_text("\n".join(text) + "\n")
    print("\n".join(text))


# ---------------------------------------------------------------------------------- soak

def soak(args) -> None:
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    server, urls, _ = start_cameras(args.cameras, args.port, args.fps)
    folder = Path(args.work) / "soak_run"
    _clean(folder)
    started = time.time()
    run = Run(urls + ["--fast", *args.extra], folder)
    memory = []
    try:
        while time.time() < started + args.minutes * 60 + args.startup_s and run.process.poll() is None:
            memory.append({"t_s": round(time.time() - started, 2), "rss_mb": run.rss_mb()})
            time.sleep(1.0)
    finally:
        run.stop()
        _stop(server)
    records = pd.DataFrame(run.records)
    records["t_s"] = records["time"] - started
    memory = pd.DataFrame(memory)
    records[["t_s", CAMERA_KEY, "frame", "status", "age_s", "runtime_s_total", "fused_focal_px", "fused_tilt_deg"]].to_csv(
        out / "soak_records.csv", index=False, float_format="%.5g")
    memory.to_csv(out / "soak_memory.csv", index=False, float_format="%.4g")
    _soak_report(records, memory, args, out, folder)


def _soak_report(records: pd.DataFrame, memory: pd.DataFrame, args, out: Path, folder: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from fr_eval.scoring.plots import save_figure

    first = float(records["t_s"].min())
    settled = first + 60
    minute = memory[memory["t_s"] >= settled]
    growth = float(minute["rss_mb"].max() - minute["rss_mb"].iloc[0]) if len(minute) else float("nan")
    names = sorted(records[CAMERA_KEY].unique())
    gaps, rates = {}, {}
    for name in names:
        times = np.sort(records.loc[records[CAMERA_KEY] == name, "t_s"].to_numpy())
        gaps[name] = float(np.diff(np.concatenate([[first], times])).max())  # from the first record of the fleet
        rates[name] = (len(times) - 1) / (times[-1] - times[0]) if len(times) > 1 else 0.0
    fig, axes = plt.subplots(3, 1, figsize=(9, 9))
    axes[0].plot(memory["t_s"] / 60, memory["rss_mb"], color="tab:blue")
    axes[0].axvline(settled / 60, color="k", lw=0.8, ls=":")
    axes[0].set_ylabel("fr track RSS (MB)")
    axes[0].set_xlabel("minutes since fr track started (dotted: one minute after the first record)")
    for name in names:
        t = records.loc[records[CAMERA_KEY] == name, "t_s"].to_numpy()
        axes[1].plot(t[1:] / 60, np.diff(t), ".", ms=2)
    axes[1].set_ylabel("seconds between a camera's records")
    axes[1].set_xlabel("minutes (one colour per camera)")
    axes[2].bar(range(len(names)), [gaps[n] for n in names], color="tab:red", label="longest gap")
    axes[2].bar(range(len(names)), [1 / rates[n] if rates[n] else 0 for n in names], color="tab:grey",
                label="mean interval")
    axes[2].axhline(5, color="k", lw=0.8, ls="--")
    axes[2].set_xticks(range(len(names)), names, rotation=60, fontsize=7)
    axes[2].set_ylabel("seconds")
    axes[2].legend(fontsize=8)
    for ax in axes:
        ax.grid(alpha=0.3)
    save_figure(fig, out / "soak.png", f"fr track fleet soak: {args.cameras} cameras, {args.minutes:g} min, "
                                       f"{args.fps:g} fps HTTP MJPEG each (Fast-fR)")
    summaries = {n: json.loads((folder / n / "calibration.json").read_text()) for n in names}
    machine = machine_description("cpu")
    span = float(records["t_s"].max()) - first
    rows = [("records", f"{len(records)} over {span / 60:.1f} min ({len(records) / span:.2f} frames/s in all; first "
                        f"record {first:.1f} s after the start)"),
            ("searches per camera per second: least, median, most",
             f"{min(rates.values()):.3f}, {np.median(list(rates.values())):.3f}, {max(rates.values()):.3f}"),
            ("RSS 1 min after the first record, max after it, growth",
             f"{minute['rss_mb'].iloc[0]:.0f} MB, {minute['rss_mb'].max():.0f} MB, **{growth:.1f} MB**"),
            ("longest gap between two records of a camera: max over cameras (camera)",
             f"**{max(gaps.values()):.2f} s** ({max(gaps, key=gaps.get)})"),
            ("age of a frame at its record: median, p95, max",
             f"{records['age_s'].median():.2f} s, {np.percentile(records['age_s'], 95):.2f} s, {records['age_s'].max():.2f} s"),
            ("runs in calibration.json", ", ".join(sorted({s['run'] for s in summaries.values()}))),
            ("statuses", ", ".join(f"{k} {v}" for k, v in records["status"].value_counts().items()))]
    text = [f"# `fr track` over a fleet: soak of {args.cameras} cameras for {args.minutes:g} minutes", "",
            f"Command: `python -m fr_eval.bench.track_fleet soak --cameras {args.cameras} --minutes {args.minutes:g} "
            f"--fps {args.fps:g}` (runs `fr track URL1 ... URL{args.cameras} --fast --json -`, stopped by SIGTERM at "
            "the end; the cameras are served by another process on the same cores).",
            f"Machine: {machine['cpu']}, {machine['usable_cores']} usable cores, torch {machine['torch']}, shared with "
            f"other work (load average at the end {os.getloadavg()[0]:.1f}).", "",
            "| measure | value |", "| --- | --- |"] + [f"| {a} | {b} |" for a, b in rows] + [
            "", "![soak](soak.png)", "",
            "Files: `soak_records.csv` (every record: time, camera, frame, status, age, search time, fused focal and "
            "tilt), `soak_memory.csv` (RSS each second)."]
    (out / "soak.md").write_text("\n".join(text) + "\n")
    print("\n".join(text))


# ---------------------------------------------------------------------------------- stops

def _camera_checks(folder: Path, before: dict[str, int]) -> tuple[dict, list[str]]:
    """Per camera: (records this run, frames.csv ok, calibration.json ok, its run, what it says)."""
    found, problems = {}, []
    for camera in sorted(p for p in folder.iterdir() if p.is_dir()):
        records, parseable, problem = _records_check(camera / "frames.csv", FLEET_KEYS)
        if problem:
            problems.append(f"{camera.name}: {problem}")
        try:
            summary = json.loads((camera / "calibration.json").read_text())
            valid, run, says = True, summary.get("run", ""), summary["segments"][-1]["frames_processed"]
        except (OSError, ValueError, KeyError, IndexError) as exc:
            valid, run, says = False, f"({exc})", None
        found[camera.name] = {"records": records - before.get(camera.name, 0), "csv_ok": parseable, "json_ok": valid,
                              "run": run, "says": says}
    return found, problems


def stops(args) -> None:
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    folder = Path(args.work) / "stop_trials_run"
    _clean(folder)
    rng = random.Random(args.seed)
    kinds = [STOPS[i % len(STOPS)] for i in range(args.trials)]
    rng.shuffle(kinds)
    others, urls, _ = start_cameras(3, args.port, args.fps)
    rows = []
    try:
        for trial, kind in enumerate(kinds):
            delay = rng.uniform(args.min_delay, args.max_delay)
            victim, victim_urls, _ = start_cameras(1, args.port + 10, args.fps, first=3)
            before = {} if not folder.exists() else {k: v["records"] for k, v in _camera_checks(folder, {})[0].items()}
            command = FR + urls + victim_urls + ["--out", str(folder), "--reconnect", "3", "--fast", *args.extra]
            process = subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                                       env=_env(), start_new_session=True, preexec_fn=default_stop_signals)
            time.sleep(delay)
            stopped = time.monotonic()
            signum = signal.SIGTERM if kind == "kill a camera" else getattr(signal, kind)
            if kind == "kill a camera":
                os.killpg(victim.pid, signal.SIGKILL)
                victim.wait()
                time.sleep(args.after_kill_s)  # the fleet goes on without it; then it is stopped
                stopped = time.monotonic()
            alive_at_stop = process.poll() is None
            process.send_signal(signum)
            try:
                _, stderr = process.communicate(timeout=120)
                exit_s = time.monotonic() - stopped
            except subprocess.TimeoutExpired:
                _stop(process)
                stderr, exit_s = process.stderr.read() + "\n(no exit 120 s after the stop: killed)", float("nan")
            finally:
                _stop(process)
                _stop(victim)
            gone_by = time.monotonic() + POOL_GONE_S  # the workers' fork server and resource tracker end after them
            while (left := session_processes(process.pid)) and time.monotonic() < gone_by:
                time.sleep(0.05)
            cameras, problems = _camera_checks(folder, before)
            lines = [line for line in stderr.replace("\r", "\n").splitlines() if line.startswith("fr track")]
            stop_line = next((line for line in lines if "stopped by" in line), "")
            said = int(stop_line.split("; ")[1].split()[0]) if "frames of this run" in stop_line else None
            total = sum(c["records"] for c in cameras.values())
            expected_runs = {name: f"stopped by {signal.Signals(signum).name}" for name in cameras}
            victim_name = sorted(cameras)[-1] if cameras else ""
            runs_ok = all(c["run"] == expected_runs[n] or (kind == "kill a camera" and n == victim_name
                                                           and c["run"].startswith("ended: "))
                          for n, c in cameras.items()) if alive_at_stop else True
            rows.append({"trial": trial + 1, "stop": kind, "after_s": round(delay, 2), "exit": process.returncode,
                         "expected_exit": 128 + signum, "exit_s": round(exit_s, 2), "records_this_run": total,
                         "stop_line_says": said,
                         "calibration_says": sum(c["says"] or 0 for c in cameras.values()) if cameras else None,
                         "frames_csv_ok": all(c["csv_ok"] for c in cameras.values()),
                         "calibration_json_ok": all(c["json_ok"] for c in cameras.values()),
                         "runs_ok": runs_ok, "runs": "; ".join(f"{n}: {c['run']}" for n, c in cameras.items()),
                         "processes_left": len(left), "traceback": "Traceback" in stderr,
                         "problem": "; ".join(problems)})
            print(rows[-1], flush=True)
    finally:
        _stop(others)
    _stops_report(pd.DataFrame(rows), args, out)


def _stops_report(table: pd.DataFrame, args, out: Path) -> None:
    table.to_csv(out / "stop_trials.csv", index=False)
    ok = ((table["exit"] == table["expected_exit"]) & table["frames_csv_ok"] & table["calibration_json_ok"]
          & table["runs_ok"] & (table["processes_left"] == 0) & ~table["traceback"]
          & (table["stop_line_says"].isna() | (table["stop_line_says"] == table["records_this_run"]))
          & (table["calibration_says"].isna() | (table["calibration_says"] == table["records_this_run"])))
    machine = machine_description("cpu")
    text = ["# `fr track` over a fleet: stops at random moments", "",
            f"Command: `python -m fr_eval.bench.track_fleet stops --trials {len(table)} --seed {args.seed}` (each trial: "
            "`fr track URL1 URL2 URL3 URL4 --out stop_trials_run --reconnect 3 --fast` on four synthetic "
            f"{args.fps:g} frames/s HTTP MJPEG cameras, stopped {args.min_delay:g}-{args.max_delay:g} s after its start, "
            "uniformly at random; `kill a camera`: the fourth camera's server is killed (SIGKILL) then, the fleet goes "
            f"on without it for {args.after_kill_s:g} s (the camera gives up after --reconnect 3) and is stopped by "
            "SIGTERM). All trials append to one output folder; the process starts in about 5 s, so a few stops land "
            "before the first record.",
            f"Machine: {machine['cpu']}, {machine['usable_cores']} usable cores (shared with other work).", "",
            f"**{int(ok.sum())} of {len(table)} trials** pass every check (exit status, every camera's frames.csv "
            "complete and parseable, records = what the stop line and the calibration.json files say, every "
            "calibration.json valid with how its camera's run ended, no process left, no traceback).", "",
            "| trial | stop | after (s) | exit | exit took (s) | records this run | stop line says | "
            "calibration.json says | frames.csv ok | calibration.json ok | runs | processes left |",
            "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    for _, row in table.iterrows():
        said = "" if pd.isna(row["stop_line_says"]) else int(row["stop_line_says"])
        says = "" if pd.isna(row["calibration_says"]) else int(row["calibration_says"])
        text.append(f"| {row['trial']} | {row['stop']} | {row['after_s']:.1f} | {row['exit']} | {row['exit_s']:.1f} | "
                    f"{row['records_this_run']} | {said} | {says} | {row['frames_csv_ok']} | {row['calibration_json_ok']} | "
                    f"{row['runs']} | {row['processes_left']} |")
    (out / "stop_trials.md").write_text("\n".join(text) + "\n")
    print("\n".join(text))


def main(argv: list[str] | None = None) -> int:
    common = argparse.ArgumentParser(add_help=False)
    common.add_argument("--out", default=str(REPO / "results" / "track" / "fleet"))
    common.add_argument("--work", default=str(REPO / "results" / "track" / "fleet"),
                        help="where the runs' own output folders go (*_run, throughput_*: not committed)")
    common.add_argument("--port", type=int, default=18600)
    common.add_argument("--fps", type=float, default=25.0)
    common.add_argument("--seed", type=int, default=61)
    parser = argparse.ArgumentParser(prog="python -m fr_eval.bench.track_fleet", description=__doc__.split("\n")[0])
    sub = parser.add_subparsers(dest="what", required=True)
    s = sub.add_parser("serve", parents=[common])
    s.add_argument("--cameras", type=int, default=4)
    s.add_argument("--first", type=int, default=0)
    s.add_argument("--stall", type=int, default=None)
    s.add_argument("--outage", type=lambda v: tuple(float(x) for x in v.split(",")), default=(0.0, 0.0))
    s.set_defaults(run=serve)
    t = sub.add_parser("throughput", parents=[common])
    t.add_argument("--cameras", default="1,2,4,8,16")
    t.add_argument("--seconds", type=float, default=40.0)
    t.add_argument("--in-process", default="16", help="N for which the fleet is also run with --workers 0")
    t.add_argument("--modes", default="fleet,separate", help="fleet, separate or both")
    t.add_argument("--rounds", type=int, default=1, help="the whole comparison this many times (noise)")
    t.add_argument("--code", default="", help="LABEL=TREE,...: whose fr track to run, interleaved (TREE: a "
                   "checkout, e.g. `git archive` of an older commit; empty: this one)")
    t.add_argument("--startup-s", type=float, default=240.0)
    t.add_argument("extra", nargs="*", help="more fr track options (after --)")
    t.set_defaults(run=throughput)
    r = sub.add_parser("readers", parents=[common])
    r.add_argument("--cameras", type=int, default=16)
    r.add_argument("--seconds", type=float, default=20.0)
    r.add_argument("--warmup-s", type=float, default=3.0)
    r.set_defaults(run=readers)
    a = sub.add_parser("accuracy", parents=[common])
    a.add_argument("--seconds", type=float, default=75.0)
    a.add_argument("--outage", default="25,37", help="START,END seconds after the servers start: camera 3 stalls")
    a.add_argument("--settle-s", type=float, default=60.0)
    a.add_argument("extra", nargs="*")
    a.set_defaults(run=accuracy)
    k = sub.add_parser("soak", parents=[common])
    k.add_argument("--cameras", type=int, default=16)
    k.add_argument("--minutes", type=float, default=10.0)
    k.add_argument("--startup-s", type=float, default=10.0)
    k.add_argument("extra", nargs="*")
    k.set_defaults(run=soak)
    p = sub.add_parser("stops", parents=[common])
    p.add_argument("--trials", type=int, default=20)
    p.add_argument("--min-delay", type=float, default=3.0)
    p.add_argument("--max-delay", type=float, default=15.0)
    p.add_argument("--after-kill-s", type=float, default=6.0)
    p.add_argument("extra", nargs="*")
    p.set_defaults(run=stops)
    args = parser.parse_args(argv)
    return int(args.run(args) or 0)


if __name__ == "__main__":
    sys.exit(main())
