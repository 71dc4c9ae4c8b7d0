"""``fr track`` on a live source, measured: a long run (soak), stops at random moments, a camera
that pans.  Each runs whole ``fr track`` processes against a synthetic camera served by another
process (:mod:`fr_eval.datasets.live_stream`) and writes its tables and figure to ``--out``
(default ``results/track``)::

    python -m fr_eval.bench.track_live soak --minutes 10 --fps 25      # soak.md, soak.png, soak_*.csv
    python -m fr_eval.bench.track_live stops --trials 20                # stop_trials.md / .csv
    python -m fr_eval.bench.track_live pan --pairs 10                   # pan.md (YorkUrbanDB photos)

**soak**: a fixed camera (640 x 480, hfov 70 deg, image noise, pitch drifting by ``--drift-deg``
over the run) served as HTTP MJPEG at ``--fps``; ``fr track URL --json -`` (fR, real time) reads
it for ``--minutes`` and is then stopped by SIGTERM.  Every second the fr process's resident
memory (VmRSS) is sampled; every record is read from the pipe as it comes and stamped.  Reported:
memory growth after the first minute, the fused focal error and the fused tilt against the
drifting truth after the first minute, the age of each frame when its record was written against
its search time, the pipe's delivery delay, the share of frames dropped.

**stops**: ``--trials`` runs on one output folder (each a new segment), each stopped after a
random delay by SIGTERM, SIGINT, SIGHUP or by killing the stream's server (SIGKILL; the run has
``--reconnect 3``, so it retries and gives up), in a shuffled order with the same count of each.
Checked per trial: the exit status, every line of frames.csv complete and parseable with every
column, this run's records as many as the stop line says, calibration.json valid JSON whose
``run`` says how the run ended, no process of the run's session left.

**pan**: pairs of YorkUrbanDB test photos (one camera), each photo sent ``--repeat`` times with
fresh image noise through a pipe (``fr track - --no-realtime``): the restart must be in the
records within ``--patience`` reliable frames of the switch, and none before it.
"""
from __future__ import annotations

import argparse
import csv
import io
import json
import os
import random
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import cv2
import numpy as np
import pandas as pd

from fr_eval.datasets.live_stream import SyntheticCamera
from fr_eval.machine import machine_description, proc_status_kb, session_processes
from fr_eval.paths import REPO
from fr_eval.scoring.metrics import frame_error_deg
from fr_eval.scoring.plots import save_figure
from fr_torch.core.geometry.conventions import rotation_angles
from fr_torch.video.records import RECORD_KEYS

FR = [sys.executable, "-m", "fr_torch.cli", "track"]
STOPS = ("SIGTERM", "SIGINT", "SIGHUP", "kill source")


def default_stop_signals() -> None:
    """In a child before exec: SIGINT, SIGTERM and SIGHUP with their default actions.  A measurement
    started under ``nohup`` or in a shell's background ignores SIGHUP or SIGINT, its children
    inherit that, and ``fr track`` rightly leaves an ignored signal alone."""
    for signum in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):
        signal.signal(signum, signal.SIG_DFL)


def _env() -> dict[str, str]:
    paths = [str(REPO)] + [p for p in os.environ.get("PYTHONPATH", "").split(os.pathsep) if p]
    return {**os.environ, "PYTHONPATH": os.pathsep.join(paths)}


def start_server(port: int, fps: float, *options: str) -> tuple[subprocess.Popen, float]:
    """The synthetic camera as a process serving ``http://127.0.0.1:PORT/stream.mjpg``, and the Unix
    time of its frame 0 (returns once it listens: it prints both)."""
    server = subprocess.Popen([sys.executable, "-m", "fr_eval.datasets.live_stream", "--port", str(port),
                               "--fps", str(fps), *options], stdout=subprocess.PIPE, text=True, env=_env(),
                              start_new_session=True)
    return server, float(server.stdout.readline().split()[1])


def _stop(process: subprocess.Popen) -> None:
    if process.poll() is None:
        os.killpg(process.pid, signal.SIGKILL)
        process.wait()


# ---------------------------------------------------------------------------------- soak

def soak(args) -> None:
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    frames = int(args.minutes * 60 * args.fps)
    camera = SyntheticCamera(drift_deg=args.drift_deg, drift_frames=frames)
    server, frame0 = start_server(args.port, args.fps, "--drift-deg", str(args.drift_deg), "--drift-frames", str(frames))
    folder = out / "soak_run"
    if folder.exists():
        for path in folder.iterdir():
            path.unlink()
    command = FR + [f"http://127.0.0.1:{args.port}/stream.mjpg", "--out", str(folder), "--json", "-", *args.extra]
    started = time.time()
    process = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True, env=_env(),
                               start_new_session=True, preexec_fn=default_stop_signals)
    records: list[dict] = []

    def read_records():
        for line in process.stdout:
            record = json.loads(line)
            record["arrived"] = time.time()
            records.append(record)

    reader = threading.Thread(target=read_records, daemon=True)
    reader.start()
    memory = []
    try:
        while time.time() - started < args.minutes * 60 + args.startup_s:
            rss = proc_status_kb("VmRSS", process.pid)
            if rss is None:
                break
            memory.append({"t_s": round(time.time() - started, 2), "rss_mb": rss / 1024})
            time.sleep(1.0)
        process.send_signal(signal.SIGTERM)
        process.wait(timeout=120)
    finally:
        _stop(process)
        _stop(server)
    reader.join(10)
    summary = json.loads((folder / "calibration.json").read_text())
    table = pd.DataFrame(records)
    table["t_s"] = table["time"] - started  # both clocks: seconds since the process started
    # the server's frame: fr track counts frames from its connection, the server from its start
    table["server_frame"] = ((table["time"] - table["age_s"] - frame0) * args.fps).round().astype(int)
    truth = [camera.truth(int(k)) for k in table["server_frame"]]
    table["true_tilt_deg"] = [rotation_angles(c.rotation)["tilt_deg"] for c in truth]
    table["fused_focal_err_pct"] = 100 * (table["fused_focal_px"] - camera.focal_px) / camera.focal_px
    table["fused_tilt_err_deg"] = table["fused_tilt_deg"] - table["true_tilt_deg"]
    table["delivery_s"] = table["arrived"] - table["time"]
    table["wait_s"] = table["age_s"] - table["runtime_s_total"]
    memory = pd.DataFrame(memory)
    columns = ["t_s", "frame", "server_frame", "status", "age_s", "runtime_s_total", "wait_s", "delivery_s", "dropped_share",
               "focal_px", "fused_focal_px", "fused_focal_err_pct", "tilt_deg", "fused_tilt_deg", "true_tilt_deg",
               "fused_tilt_err_deg"]
    table[columns].to_csv(out / "soak_records.csv", index=False, float_format="%.5g")
    memory.to_csv(out / "soak_memory.csv", index=False, float_format="%.4g")
    _soak_report(table, memory, summary, camera, args, out, command)


def _soak_report(table, memory, summary, camera, args, out: Path, command) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    settled = float(table["t_s"].iloc[0]) + 60  # one minute after the first record
    after = table[table["t_s"] >= settled]
    minute = memory[memory["t_s"] >= settled]
    growth = float(minute["rss_mb"].max() - minute["rss_mb"].iloc[0]) if len(minute) else float("nan")
    fig, axes = plt.subplots(4, 1, figsize=(9, 10), sharex=False)
    axes[0].plot(memory["t_s"] / 60, memory["rss_mb"], color="tab:blue")
    axes[0].set_ylabel("fr track RSS (MB)")
    axes[1].plot(table["t_s"] / 60, table["age_s"], ".", ms=2, color="tab:red", label="age of the frame at its record")
    axes[1].plot(table["t_s"] / 60, table["runtime_s_total"], ".", ms=2, color="tab:grey", label="its detection + search")
    axes[1].set_ylabel("seconds")
    axes[1].legend(fontsize=8, loc="upper right")
    axes[2].plot(table["t_s"] / 60, table["fused_focal_err_pct"], "-", color="tab:red", label="fused")
    axes[2].plot(table["t_s"] / 60, 100 * (table["focal_px"] - camera.focal_px) / camera.focal_px, ".", ms=2,
                 color="tab:grey", label="per frame")
    axes[2].axhspan(-1, 1, color="tab:green", alpha=0.1)
    axes[2].set_ylabel("focal error (%)")
    axes[2].legend(fontsize=8, loc="upper right")
    axes[3].plot(table["t_s"] / 60, table["tilt_deg"], ".", ms=2, color="tab:grey", label="per frame")
    axes[3].plot(table["t_s"] / 60, table["fused_tilt_deg"], "-", color="tab:red", label="fused")
    axes[3].plot(table["t_s"] / 60, table["true_tilt_deg"], "--", color="k", label="truth (drifting)")
    axes[3].set_ylabel("tilt (deg)")
    axes[3].legend(fontsize=8, loc="upper left")
    for ax in axes:
        ax.axvline(settled / 60, color="k", lw=0.8, ls=":")
        ax.grid(alpha=0.3)
    axes[-1].set_xlabel("minutes since fr track started (dotted: one minute after its first record)")
    save_figure(fig, out / "soak.png", f"fr track soak: {args.minutes:g} min of a {args.fps:g} fps HTTP MJPEG stream")

    def q(series, p):
        return float(np.nanpercentile(series, p))

    machine = machine_description("cpu")
    rows = [
        ("records", f"{len(table)} over {(table['t_s'].iloc[-1] - table['t_s'].iloc[0]) / 60:.1f} min "
                    f"({len(table) / (table['t_s'].iloc[-1] - table['t_s'].iloc[0]):.2f} frames/s processed; first "
                    f"record {table['t_s'].iloc[0]:.1f} s after the start)"),
        ("frames arrived / dropped", f"{summary['frames_arrived']} / {summary['frames_dropped']} "
                                     f"(dropped share {summary['dropped_share']:.3f})"),
        ("RSS 1 min after the first record, max after it, growth",
         f"{minute['rss_mb'].iloc[0]:.0f} MB, {minute['rss_mb'].max():.0f} MB, **{growth:.1f} MB**"),
        ("fused focal error after 1 min: mean, max |.|",
         f"{after['fused_focal_err_pct'].mean():+.2f} %, **{after['fused_focal_err_pct'].abs().max():.2f} %**"),
        ("per-frame focal error after 1 min: median |.|",
         f"{(100 * (after['focal_px'] - camera.focal_px) / camera.focal_px).abs().median():.2f} %"),
        ("fused tilt - truth after 1 min: mean, max |.| (drift over the run)",
         f"{after['fused_tilt_err_deg'].mean():+.3f} deg, {after['fused_tilt_err_deg'].abs().max():.3f} deg "
         f"({table['true_tilt_deg'].iloc[-1] - table['true_tilt_deg'].iloc[0]:+.3f} deg)"),
        ("detection + search per frame: median, p95", f"{table['runtime_s_total'].median():.3f} s, {q(table['runtime_s_total'], 95):.3f} s"),
        ("age of a frame at its record: median, p95, max",
         f"{table['age_s'].median():.3f} s, {q(table['age_s'], 95):.3f} s, {table['age_s'].max():.3f} s"),
        ("age - search (waiting for the search + fusion + write): median, p95, max",
         f"{table['wait_s'].median():.3f} s, {q(table['wait_s'], 95):.3f} s, {table['wait_s'].max():.3f} s"),
        ("records whose age - search exceeds their search time", f"{int((table['wait_s'] > table['runtime_s_total']).sum())}"),
        ("pipe delivery (record written -> read by the consumer): median, max",
         f"{1000 * table['delivery_s'].median():.1f} ms, {1000 * table['delivery_s'].max():.1f} ms"),
        ("statuses", ", ".join(f"{k} {v}" for k, v in table["status"].value_counts().items())),
    ]
    text = [f"# `fr track` soak: {args.minutes:g} minutes of a live stream", "",
            f"Command: `python -m fr_eval.bench.track_live soak --minutes {args.minutes:g} --fps {args.fps:g} "
            f"--drift-deg {args.drift_deg:g}` (runs `{' '.join(command[2:])}`, stopped by SIGTERM at the end).",
            f"Camera: synthetic room 640 x 480, hfov 70 deg (f = {camera.focal_px:.1f} px), Gaussian noise sigma 3, "
            f"JPEG q90, pitch {camera.pitch_deg:g} -> {camera.pitch_deg + args.drift_deg:g} deg over the run, "
            f"served by `python -m fr_eval.datasets.live_stream` on 127.0.0.1 (another process, same cores).",
            f"Machine: {machine['cpu']}, {machine['usable_cores']} usable cores, torch {machine['torch']}, load average "
            f"at the end {os.getloadavg()[0]:.2f} (shared with other work: ages and search times are pessimistic).",
            "", "| measure | value |", "| --- | --- |"] + [f"| {a} | {b} |" for a, b in rows] + [
            "", "![soak](soak.png)", "",
            "Files: `soak_records.csv` (every record, with the truth), `soak_memory.csv` (RSS each second), "
            "`soak_run/` (the run's own frames.csv, calibration.json, track.png)."]
    (out / "soak.md").write_text("\n".join(text) + "\n")
    print("\n".join(text))


# ---------------------------------------------------------------------------------- stops

def _records_check(path: Path, keys: tuple[str, ...] = RECORD_KEYS) -> tuple[int, bool, str]:
    """(records, every line complete and parseable with every column, a problem); ``keys``: the
    columns (a fleet camera's start with ``camera``)."""
    if not path.exists():
        return 0, True, "no frames.csv"
    data = path.read_bytes()
    if data and not data.endswith(b"\n"):
        return 0, False, "last line cut short"
    rows = list(csv.reader(io.StringIO(data.decode("utf-8"))))
    if not rows or rows[0] != list(keys):
        return 0, False, "header"
    bad = [i for i, row in enumerate(rows[1:]) if len(row) != len(keys)]
    try:
        pd.read_csv(path)
    except Exception as exc:  # noqa: BLE001 (what a reader of the file would meet)
        return 0, False, f"pandas: {exc}"
    return len(rows) - 1, not bad, f"rows with other column counts: {bad[:3]}" if bad else ""


def stops(args) -> None:
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    folder = out / "stop_trials_run"
    if folder.exists():
        for path in folder.iterdir():
            path.unlink()
    rng = random.Random(args.seed)
    kinds = [STOPS[i % len(STOPS)] for i in range(args.trials)]
    rng.shuffle(kinds)
    rows = []
    for trial, kind in enumerate(kinds):
        delay = rng.uniform(args.min_delay, args.max_delay)
        server, _ = start_server(args.port, args.fps)
        before, _, _ = _records_check(folder / "frames.csv")
        command = FR + [f"http://127.0.0.1:{args.port}/stream.mjpg", "--out", str(folder), "--reconnect", "3",
                        *args.extra]
        process = subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                                   env=_env(), start_new_session=True, preexec_fn=default_stop_signals)
        time.sleep(delay)
        stopped = time.monotonic()
        if kind == "kill source":
            os.killpg(server.pid, signal.SIGKILL)
            server.wait()
        else:
            process.send_signal(getattr(signal, kind))
        try:
            _, stderr = process.communicate(timeout=120)
            exit_s = time.monotonic() - stopped
        except subprocess.TimeoutExpired:  # a failed trial: recorded, and the run killed
            _stop(process)
            stderr, exit_s = process.stderr.read() + "\n(no exit 120 s after the stop: killed)", float("nan")
        finally:
            _stop(process)
            _stop(server)
        time.sleep(0.2)
        left = session_processes(process.pid)
        records, parseable, problem = _records_check(folder / "frames.csv")
        lines = [line for line in stderr.replace("\r", "\n").splitlines() if line.startswith("fr track")]
        stop_line = next((line for line in lines if "stopped by" in line), "")
        said = int(stop_line.split("; ")[1].split()[0]) if "frames of this run" in stop_line else None
        try:
            summary = json.loads((folder / "calibration.json").read_text())
            valid, run = True, summary.get("run", "")
            segment = summary["segments"][-1]
            processed = segment["frames_processed"]
        except (OSError, ValueError, KeyError, IndexError) as exc:
            valid, run, processed = (folder / "calibration.json").exists() is False, f"({exc})", None
        expected_exit = 0 if kind == "kill source" else 128 + getattr(signal, kind)
        rows.append({"trial": trial + 1, "stop": kind, "after_s": round(delay, 2), "exit": process.returncode,
                     "expected_exit": expected_exit, "exit_s": round(exit_s, 2), "records_this_run": records - before,
                     "stop_line_says": said, "calibration_says": processed, "frames_csv_ok": parseable,
                     "calibration_json_ok": valid, "run": run, "processes_left": len(left),
                     "traceback": "Traceback" in stderr, "problem": problem})
        print(rows[-1], flush=True)
    table = pd.DataFrame(rows)
    table.to_csv(out / "stop_trials.csv", index=False)
    ok = ((table["exit"] == table["expected_exit"]) & table["frames_csv_ok"] & table["calibration_json_ok"]
          & (table["processes_left"] == 0) & ~table["traceback"]
          & ((table["stop_line_says"].isna()) | (table["stop_line_says"] == table["records_this_run"]))
          & ((table["calibration_says"].isna()) | (table["calibration_says"] == table["records_this_run"])))
    machine = machine_description("cpu")
    text = ["# `fr track`: stops at random moments", "",
            f"Command: `python -m fr_eval.bench.track_live stops --trials {args.trials} --seed {args.seed}` "
            f"(each trial: `fr track URL --out stop_trials_run --reconnect 3{''.join(' ' + e for e in args.extra)}` on a "
            f"{args.fps:g} fps synthetic HTTP MJPEG stream served by another process, stopped "
            f"{args.min_delay:g}-{args.max_delay:g} s after its start, uniformly at random; the process starts in "
            f"about 4 s, so a few stops land before the first record). All trials append to one output folder.",
            f"Machine: {machine['cpu']}, {machine['usable_cores']} usable cores (shared with other work).", "",
            f"**{int(ok.sum())} of {len(table)} trials** pass every check (exit status, frames.csv complete and "
            "parseable, records = what the stop line and calibration.json say, calibration.json valid, no process "
            "left, no traceback).", "",
            "| trial | stop | after (s) | exit | exit took (s) | records this run | stop line says | "
            "calibration.json says | frames.csv ok | calibration.json ok | run | processes left |",
            "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    for row in rows:
        text.append(f"| {row['trial']} | {row['stop']} | {row['after_s']:.1f} | {row['exit']} | {row['exit_s']:.1f} | "
                    f"{row['records_this_run']} | {'' if row['stop_line_says'] is None else row['stop_line_says']} | "
                    f"{'' if row['calibration_says'] is None else row['calibration_says']} | {row['frames_csv_ok']} | "
                    f"{row['calibration_json_ok']} | {row['run']} | {row['processes_left']} |")
    (out / "stop_trials.md").write_text("\n".join(text) + "\n")
    print("\n".join(text))


# ---------------------------------------------------------------------------------- pan

def pan(args) -> None:
    from fr_eval.datasets.yud import load_yud
    from fr_torch.runtime.estimator import FREstimator

    samples = load_yud(split="test")
    mode = "fast" if "--fast" in args.extra else "fr"
    results = FREstimator(mode=mode, reliability="default").calibrate_images([str(s.image_path) for s in samples])
    usable = [s for s, r in zip(samples, results) if r.ok and r.reliable]  # a camera must be seen to move
    rng = np.random.default_rng(args.seed)
    rows = []
    for p in range(min(args.pairs, len(usable) // 2)):
        a, b = usable[2 * p], usable[2 * p + 1]
        difference = frame_error_deg(a.rotation, b.rotation)
        stream = bytearray()
        for sample, count in ((a, args.repeat), (b, args.repeat)):
            image = cv2.imread(str(sample.image_path), cv2.IMREAD_COLOR).astype(np.float64)
            for _ in range(count):
                noisy = np.clip(image + rng.normal(0, 2.0, image.shape), 0, 255).astype(np.uint8)
                stream += cv2.imencode(".jpg", noisy, [cv2.IMWRITE_JPEG_QUALITY, 92])[1].tobytes()
        folder = Path(args.out) / "pan_run" / f"{a.name}_{b.name}"
        if folder.exists():
            for path in folder.iterdir():
                path.unlink()
        subprocess.run(FR + ["-", "--out", str(folder), "--no-realtime", "--patience", str(args.patience),
                             *args.extra], input=bytes(stream), stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                       env=_env(), check=False)
        table = pd.read_csv(folder / "frames.csv")
        before, after = table[table["frame"] < args.repeat], table[table["frame"] >= args.repeat]
        restarts = list(after.loc[after["restarted"], "frame"])
        reliable_until = int(after.loc[:after.index[after["restarted"]][0], "reliable"].sum()) if restarts else None
        reliable_after = int(after["reliable"].sum())
        first_reliable = after[after["reliable"]].head(1)
        rows.append({"pair": f"{a.name} -> {b.name}", "gt_rotation_change_deg": round(difference, 2),
                     "reliable_before": int(before["reliable"].sum()), "reliable_after": reliable_after,
                     # the first reliable frame of the new view against the old fusion (units of --change-k;
                     # above 1 it disagrees)
                     "disagreement": None if first_reliable.empty else round(float(first_reliable["disagreement"].iloc[0]), 2),
                     "restarts_before_switch": int(before["restarted"].sum()),
                     "restart_at_frame": restarts[0] if restarts else None,
                     "reliable_frames_to_restart": reliable_until,
                     "within_patience": None if reliable_after == 0 else
                     reliable_until is not None and reliable_until <= args.patience})
        print(rows[-1], flush=True)
    table = pd.DataFrame(rows)
    table.to_csv(Path(args.out) / "pan.csv", index=False)
    text = ["# `fr track`: a camera that pans mid-stream (YorkUrbanDB)", "",
            f"Command: `python -m fr_eval.bench.track_live pan --pairs {args.pairs} --repeat {args.repeat} "
            f"--patience {args.patience}{''.join(' ' + e for e in args.extra)}`: consecutive pairs of the {len(usable)} YUD test "
            f"photos (of 51; one camera, f = 674.9 px) whose {mode} estimate is reliable (a move can only be seen "
            f"on reliable frames), each photo sent {args.repeat} times with fresh Gaussian noise (sigma 2) as "
            "JPEGs through a pipe into `fr track - --no-realtime`; the switch is at frame "
            f"{args.repeat}. `gt rotation change`: the ground-truth rotation difference, modulo the Manhattan "
            "symmetries.", "",
            f"**{sum(r['within_patience'] is True for r in rows)} of {sum(r['within_patience'] is not None for r in rows)}"
            f"** pairs with a reliable frame after the switch restart within --patience ({args.patience}) reliable "
            f"frames of it ({sum(r['within_patience'] is None for r in rows)} without one: n/a); restarts before the "
            f"switch: {int(table['restarts_before_switch'].sum())}.  `disagreement`: the first reliable frame after "
            "the switch against the fusion so far, in units of --change-k (above 1 it disagrees; below, the change "
            "is within the predicted errors and is not a move the fusion can see).", "",
            "| pair | gt rotation change (deg) | reliable before / after | disagreement | restart at frame "
            "| reliable frames to it | within patience |", "| --- | --- | --- | --- | --- | --- | --- |"]

    def shown(value) -> str:
        return "n/a" if value is None else str(value)

    for row in rows:
        text.append(f"| {row['pair']} | {row['gt_rotation_change_deg']:.1f} | {row['reliable_before']} / "
                    f"{row['reliable_after']} | {shown(row['disagreement'])} | {shown(row['restart_at_frame'])} | "
                    f"{shown(row['reliable_frames_to_restart'])} | {shown(row['within_patience'])} |")
    (Path(args.out) / "pan.md").write_text("\n".join(text) + "\n")
    print("\n".join(text))


def main(argv: list[str] | None = None) -> int:
    common = argparse.ArgumentParser(add_help=False)
    common.add_argument("--out", default=str(REPO / "results" / "track"))
    common.add_argument("--port", type=int, default=18554)
    common.add_argument("--fps", type=float, default=25.0)
    common.add_argument("--seed", type=int, default=53)
    parser = argparse.ArgumentParser(prog="python -m fr_eval.bench.track_live", description=__doc__.split("\n")[0])
    sub = parser.add_subparsers(dest="what", required=True)
    s = sub.add_parser("soak", parents=[common])
    s.add_argument("--minutes", type=float, default=10.0)
    s.add_argument("--drift-deg", type=float, default=0.5)
    s.add_argument("--startup-s", type=float, default=5.0, help="seconds added to --minutes for the start-up")
    s.add_argument("extra", nargs="*", help="more fr track options (after --)")
    s.set_defaults(run=soak)
    t = sub.add_parser("stops", parents=[common])
    t.add_argument("--trials", type=int, default=20)
    t.add_argument("--min-delay", type=float, default=3.0)
    t.add_argument("--max-delay", type=float, default=15.0)
    t.add_argument("extra", nargs="*")
    t.set_defaults(run=stops)
    p = sub.add_parser("pan", parents=[common])
    p.add_argument("--pairs", type=int, default=10)
    p.add_argument("--repeat", type=int, default=6)
    p.add_argument("--patience", type=int, default=2)
    p.add_argument("extra", nargs="*")
    p.set_defaults(run=pan)
    args = parser.parse_args(argv)
    args.run(args)
    return 0


if __name__ == "__main__":
    sys.exit(main())
