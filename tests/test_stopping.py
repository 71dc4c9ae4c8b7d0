"""Stopping is as safe as running: ``fr batch`` stopped by SIGINT, SIGTERM or SIGKILL of its own
process leaves no process of its pool running (fork server, resource tracker, workers), and a
re-run completes the output with every input exactly once.

Real processes and real signals, bounded in time: each run is its own session, so every process it
started (orphans included: they keep the session) is found in /proc.  The run is stopped while one
batch is deterministically in flight (``FR_BATCH_STALL``: the worker on it sleeps).
"""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

pytest.importorskip("pyarrow.parquet")

from fr_eval.machine import session_processes
from fr_torch.batch.jobs import run_batch
from fr_torch.cli.batch import estimator_options
from fr_torch.cli.main import build_parser, stopped_line
from fr_torch.runtime.workers import (
    Stopped,
    interrupt_exit_status,
    interrupt_on_signals,
    keep_signal_handler,
    stops_held,
)
from fr_torch.synthetic import random_rotation, render_manhattan_room
from tests.conftest import POOL_GONE_S, checkout_env, reap_session, session_left

pytestmark = pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="finds processes in /proc (Linux)")

N_IMAGES = 8
BATCH = 2
STALLED = 4  # the first image of the third batch: two parts are written, then the run waits on it


@pytest.fixture(scope="module")
def folder(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("stop_images")
    rng = np.random.default_rng(48)
    for i in range(N_IMAGES):
        image = render_manhattan_room(150.0, random_rotation(rng, pan=(-20, 20), pitch=(-10, 10), roll=(-5, 5)),
                                      160, 120, seed=i)
        cv2.imwrite(str(root / f"room{i}.png"), image)
    return root


def _default_sigint() -> None:
    """In the child before exec: SIGINT's default action.  A test run started in the background
    (``pytest &``, ``nohup``) ignores SIGINT, its children inherit that, and ``fr`` rightly leaves an
    ignored SIGINT alone (:func:`fr_torch.runtime.workers.interrupt_on_signals`)."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def _parts(out: Path) -> list[Path]:
    return list(out.glob("part-*.parquet")) if out.is_dir() else []


SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGKILL)


@pytest.fixture(scope="module")
def stopped_runs(folder, tmp_path_factory) -> dict:
    """One ``fr batch`` per signal, the three started together (their start-up -- torch, fork server,
    workers -- is most of a run), each stopped by its signal once it waits on the stalled batch.  The
    signals are sent one run at a time, each run's pool given :data:`POOL_GONE_S` on a quiet machine
    (the other runs wait on their stalled batch meanwhile).  Per signal name: out, stderr_path, pool
    (its processes before the signal), left, returncode, or error (why it was not stopped)."""
    env = checkout_env(FR_BATCH_STALL=f"room{STALLED}.png:180", OMP_NUM_THREADS="1")
    runs = {}
    try:
        for signum in SIGNALS:
            base = tmp_path_factory.mktemp(f"stop_{signum.name}")
            run = runs[signum.name] = {"out": base / "out.parquet", "stderr_path": base / "stderr.txt"}
            command = [sys.executable, "-m", "fr_torch.cli", "batch", str(folder), "--out", str(run["out"]),
                       "--fast", "--batch-size", str(BATCH), "--workers", "2", "--no-progress"]
            with open(run["stderr_path"], "w") as stderr:
                run["process"] = subprocess.Popen(command, env=env, stdout=subprocess.DEVNULL, stderr=stderr,
                                                  start_new_session=True, preexec_fn=_default_sigint)
        deadline = time.monotonic() + 180
        waiting = set(runs)
        while waiting:  # the batches before the stalled one are written
            for name in sorted(waiting):
                run = runs[name]
                if len(_parts(run["out"])) >= STALLED // BATCH:
                    waiting.discard(name)
                elif run["process"].poll() is not None:
                    run["error"] = f"fr batch ended ({run['process'].returncode}): " + run["stderr_path"].read_text()
                    waiting.discard(name)
                elif time.monotonic() > deadline:
                    run["error"] = "no part written in 180 s"
                    waiting.discard(name)
            time.sleep(0.05)
        for signum in SIGNALS:
            run = runs[signum.name]
            if "error" in run:
                continue
            process = run["process"]
            run["pool"] = session_processes(process.pid)
            os.kill(process.pid, signum)
            run["left"] = session_left(process.pid, time.monotonic())
            run["returncode"] = process.wait(timeout=60)
    finally:
        for run in runs.values():
            if "process" in run:
                reap_session(run["process"])
    return runs


@pytest.mark.parametrize("signum", SIGNALS, ids=lambda s: s.name)
def test_stopped_batch_leaves_no_process_and_a_rerun_completes_it(stopped_runs, folder, signum):
    run = stopped_runs[signum.name]
    assert "error" not in run, run.get("error")
    out, stderr_path, left, returncode = run["out"], run["stderr_path"], run["left"], run["returncode"]
    assert len(run["pool"]) >= 3, run["pool"]  # fork server, resource tracker, the workers
    assert not left, f"{len(left)} process(es) of the pool still running {POOL_GONE_S:.0f} s after {signum.name}"
    if signum == signal.SIGKILL:
        assert returncode == -signal.SIGKILL
    else:
        assert returncode == 128 + signum
        lines = stderr_path.read_text().splitlines()
        assert lines == [f"fr batch: stopped by {signum.name}; {STALLED} of {N_IMAGES} images are in {out}; "
                         "the same command again does the rest"]
    assert len(_parts(out)) == STALLED // BATCH  # the batch in flight is not written

    args = build_parser("batch").parse_args(["batch", "x", "--out", "y", "--fast"])
    again = run_batch([str(folder)], out, estimator_options(args), workers=1, batch_size=BATCH, progress=False)
    assert again["skipped"] == STALLED and again["processed"] == N_IMAGES - STALLED
    import pandas as pd

    images = pd.read_parquet(out).image
    assert sorted(images) == sorted(str(p) for p in folder.glob("*.png"))  # every input exactly once
    assert not list(out.glob(".*"))  # no temporary part left


def test_sigterm_raises_like_ctrl_c_and_handlers_come_back():
    """In the main thread SIGTERM raises :class:`Stopped` (a KeyboardInterrupt) inside the block,
    at the end of a :func:`stops_held` block when it arrives in one; the handler before it comes
    back after, also after a library replaced it (as ray.init does)."""
    before = signal.signal(signal.SIGTERM, signal.SIG_DFL)  # earlier tests may have left one (Ray's)
    try:
        _check_sigterm_handling()
    finally:
        signal.signal(signal.SIGTERM, before)


def _check_sigterm_handling():
    before = signal.getsignal(signal.SIGTERM)
    with pytest.raises(KeyboardInterrupt) as caught:
        with interrupt_on_signals():
            os.kill(os.getpid(), signal.SIGTERM)
            time.sleep(5)  # interrupted right away
    assert isinstance(caught.value, Stopped) and caught.value.signum == signal.SIGTERM
    assert signal.getsignal(signal.SIGTERM) is before
    assert interrupt_exit_status(caught.value) == 143 and interrupt_exit_status(KeyboardInterrupt()) == 130
    steps = []
    with pytest.raises(Stopped), interrupt_on_signals():
        with stops_held():
            os.kill(os.getpid(), signal.SIGTERM)
            time.sleep(0.2)
            steps.append("the held step ends")
        steps.append("never")
    assert steps == ["the held step ends"]
    caught.value.add_note("3 of 8 images are in out")
    assert stopped_line("batch", caught.value) == "fr batch: stopped by SIGTERM; 3 of 8 images are in out"
    assert stopped_line("track", KeyboardInterrupt()) == "fr track: stopped by SIGINT"
    with interrupt_on_signals():
        ours = signal.getsignal(signal.SIGTERM)
        with keep_signal_handler():
            signal.signal(signal.SIGTERM, lambda *_: sys.exit(15))
        assert signal.getsignal(signal.SIGTERM) is ours
    assert signal.getsignal(signal.SIGTERM) is before
