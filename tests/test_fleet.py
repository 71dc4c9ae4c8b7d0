"""``fr track`` over a fleet of cameras (:mod:`fr_torch.video.fleet`): the sources file, the turns
(fairness, the rate cap, a stalled or failing camera), and whole runs on synthetic HTTP cameras and
folders: per-camera records with the ``camera`` column, calibration.json, a rerun that appends, the
same records searched in worker processes or in the fleet's own, a stop by SIGTERM.

The turn tests drive :func:`track_fleet` with scripted streams and a stand-in estimator, so what
they check (who is served in which turn) does not depend on time.
"""
from __future__ import annotations

import json
import math
import os
import signal
import subprocess
import sys
import time
from collections import deque
from pathlib import Path

import pandas as pd
import pytest

from fr_eval.bench.track_live import default_stop_signals
from fr_eval.datasets.live_stream import MJPEGServer, SyntheticCamera
from fr_torch.cli.main import main
from fr_torch.core.result import CalibrationResult
from fr_torch.errors import FRInputError
from fr_torch.video.fleet import CameraSpec, FleetCamera, camera_line, camera_specs, track_fleet
from fr_torch.video.fusion import OnlineCalibrator
from fr_torch.video.records import CAMERA_KEY, RECORD_KEYS, TrackOutput
from fr_torch.video.sources import Frame, FrameStream, Reconnect, Source
from fr_torch.video.track import Tracking
from tests.conftest import checkout_env, reap_session, session_left

SMALL = dict(width=320, height=240)
#: Seconds the fork server and resource tracker of the search workers may take to end after fr track.


# ---------------------------------------------------------------------------------- sources file

def test_sources_file_lines_names_and_one_line_errors(tmp_path):
    video = tmp_path / "site3.mp4"
    video.write_bytes(b"")
    listing = tmp_path / "cameras.txt"
    listing.write_text("# the fleet\n\n"
                       "gate rtsp://u:secret@10.0.0.5/stream1 --fov-range 30,60   # a comment\n"
                       f"'{video}' --every=25 --focal 1210 --max-rate 2\n"
                       "http://10.0.0.6/a/stream1\n")
    specs = camera_specs(["http://10.0.0.7/b/stream1"], listing, max_rate=4.0)
    assert [s.name for s in specs] == ["stream1_1", "gate", "site3", "stream1_4"]  # same label: position added
    gate, site = specs[1], specs[2]
    assert gate.fov_range == "30,60" and str(gate.source) == "rtsp://u:***@10.0.0.5/stream1" and gate.max_rate == 4.0
    assert (site.source.kind, site.every, site.focal_px, site.max_rate) == ("file", 25, 1210.0, 2.0)
    assert site.min_interval_s == 0.5 and CameraSpec("x", site.source).min_interval_s == 0.0
    assert camera_line("   # only a comment", "f:1") is None
    # --reconnect per camera, its SECONDS optional; the others get the command's
    for line, give_up in (("a rtsp://x/y --reconnect", math.inf), ("a rtsp://x/y --reconnect 30 --every 2", 30.0),
                          ("a rtsp://x/y --reconnect --every 2", math.inf), ("a rtsp://x/y --reconnect=0", 0.0)):
        assert camera_line(line, "f:1")[2]["reconnect"] == Reconnect(give_up_s=give_up)
    listing.write_text(f"gate rtsp://x/y --reconnect 30\nlobby rtsp://x/z\n'{video}'\n")
    assert [s.reconnect.give_up_s for s in camera_specs([], listing, reconnect=Reconnect(5.0))] == [30.0, 5.0, 5.0]
    for line, message in [("gate", "gate: no such video file"),
                          ("a b c", "expected \\[NAME\\] SOURCE"),
                          ("a rtsp://x/y --zoom 2", "unknown option '--zoom'"),
                          ("a rtsp://x/y --every", "--every needs a value"),
                          ("a rtsp://x/y --every 0", "--every expects an integer >= 1"),
                          ("a rtsp://x/y --focal -3", "--focal expects a number > 0"),
                          ("a rtsp://x/y --fov-range 90,30", "--fov-range"),
                          ("'a rtsp://x/y", "No closing quotation"),
                          ("a/b rtsp://x/y", "camera name 'a/b'"),
                          ("a rtsp://x/y --reconnect=-1", "--reconnect: expected seconds")]:
        with pytest.raises(FRInputError, match=f"^f:1: .*{message}"):
            camera_line(line, "f:1")
    twice = tmp_path / "twice.txt"
    twice.write_text("a rtsp://x/1\na rtsp://x/2\n")
    with pytest.raises(FRInputError, match="two cameras named 'a'"):
        camera_specs([], twice)
    empty = tmp_path / "empty.txt"
    empty.write_text("# nothing\n")
    with pytest.raises(FRInputError, match="no camera in it"):
        camera_specs([], empty)
    with pytest.raises(FRInputError, match="cannot read"):
        camera_specs([], tmp_path / "missing.txt")
    assert main(["track", "--sources", str(twice)]) == 2  # the command: one line, exit status 2


# ---------------------------------------------------------------------------------- turns

class Clock:
    """Turns of a scripted fleet: each search is one turn; ``arrivals[name]`` says in which turns a
    camera's next frame arrives; after ``turns`` turns every stream ends."""

    def __init__(self, turns: int):
        self.turn, self.turns, self.streams, self.batches = 0, turns, [], []

    def calibrate_images(self, images, names, focal_px):
        self.batches.append(list(names))
        self.turn += 1
        for stream in self.streams:
            stream.arrive(self.turn)
        return [CalibrationResult(image=name, width=320, height=240, ok=False, reason="stand-in")
                for name in names]


class ScriptedStream(FrameStream):
    """A live stream whose frames arrive in the turns ``every`` divides (the newest replaces the
    waiting one, as in real time); ``fail``: its reader fails on the first frame instead."""

    live = True

    def __init__(self, name: str, clock: Clock, every: int | None, fail: bool = False):
        super().__init__(Source("stream", f"http://127.0.0.1/{name}"))
        self.name, self.clock, self.every, self.fail = name, clock, every, fail
        self.waiting: deque = deque(maxlen=1)
        clock.streams.append(self)
        self.arrive(0)

    def arrive(self, turn: int) -> None:
        if self.every is not None and turn % self.every == 0 and turn < self.clock.turns:
            self.dropped += len(self.waiting)
            self.waiting.append(Frame(self.arrived, f"{self.name}_{self.arrived}", None, time.monotonic()))
            self.arrived += 1

    def ready(self) -> bool:
        return bool(self.waiting) or self.clock.turn >= self.clock.turns or self.fail

    def __iter__(self):
        while True:
            if self.fail:
                raise FRInputError(f"{self.source}: OpenCV cannot open this stream")
            if self.waiting:
                yield self.waiting.popleft()
            elif self.clock.turn >= self.clock.turns:
                self.end_reason = "the stream ended"
                return


def _fleet(tmp_path, clock: Clock, scripts: dict, max_rate: dict | None = None) -> list[FleetCamera]:
    cameras = []
    for name, (every, fail) in scripts.items():
        stream = ScriptedStream(name, clock, every, fail)
        output = TrackOutput(tmp_path / name, stream.source, {}, "fast", camera=name, log=lambda m: None)
        spec = CameraSpec(name, stream.source, max_rate=(max_rate or {}).get(name))
        cameras.append(FleetCamera(spec, Tracking(stream, OnlineCalibrator(), output, print), clock))
    return cameras


def test_turns_serve_the_least_recently_served_so_a_fast_camera_starves_no_one(tmp_path):
    """One search slot per turn (batch 1): the camera streaming every turn and the one streaming
    every third turn alternate whenever both wait; the slow camera loses no frame."""
    clock = Clock(turns=30)
    lines: list[str] = []
    cameras = _fleet(tmp_path, clock, {"fast": (1, False), "slow": (3, False)})
    track_fleet(cameras, batch_size=1, say=lines.append, idle_s=0.0)
    served = [batch[0].split("_")[0] for batch in clock.batches]
    slow = [i for i, name in enumerate(served) if name == "slow"]
    assert len(slow) == 10 and cameras[1].tracking.stream.dropped == 0  # every slow frame searched
    assert all(served[i - 1] == "fast" for i in slow[1:])  # never twice in a row: the fast one gets its turn
    assert served.count("fast") == len(served) - 10 and len(served) >= 29
    assert [c.run for c in cameras] == ["ended: the stream ended"] * 2
    records = pd.read_csv(tmp_path / "slow" / "frames.csv")
    assert list(records.columns) == [CAMERA_KEY, *RECORD_KEYS] and (records[CAMERA_KEY] == "slow").all()
    assert list(records["frame"]) == list(range(10))


def test_a_stalled_or_failing_camera_neither_stops_nor_slows_the_others(tmp_path):
    """Every turn searches one frame of each camera that has one: the stalled camera (no frame)
    is skipped, the failing one ends alone with one line, the others are served every turn."""
    clock = Clock(turns=12)
    lines: list[str] = []
    cameras = _fleet(tmp_path, clock, {"a": (1, False), "stalled": (None, False), "broken": (1, True),
                                       "b": (1, False)})
    track_fleet(cameras, batch_size=8, say=lines.append, idle_s=0.0)
    assert all(sorted(name.split("_")[0] for name in batch) == ["a", "b"] for batch in clock.batches)
    assert len(clock.batches) == 12
    runs = {c.spec.name: c.run for c in cameras}
    assert runs["broken"] == "error: http://127.0.0.1/broken: OpenCV cannot open this stream"
    assert runs["a"] == runs["b"] == runs["stalled"] == "ended: the stream ended"
    assert lines[0] == "fr track: broken: error: http://127.0.0.1/broken: OpenCV cannot open this stream"
    summary = json.loads((tmp_path / "broken" / "calibration.json").read_text())
    assert summary["run"].startswith("error: ") and summary["camera"] == "broken" and summary["frames_processed"] == 0


def test_the_rate_cap_spaces_a_cameras_searches(tmp_path):
    """A camera capped at 5 frames per second is not served again within 0.2 s (the turns here
    take microseconds); the uncapped one is served every turn."""
    clock = Clock(turns=20)
    cameras = _fleet(tmp_path, clock, {"capped": (1, False), "free": (1, False)}, max_rate={"capped": 5.0})
    track_fleet(cameras, batch_size=8, say=lambda m: None, idle_s=0.0)
    served = [name.split("_")[0] for batch in clock.batches for name in batch]
    assert served.count("free") == 20 and served.count("capped") <= 2  # the first turn, then maybe the end


# ---------------------------------------------------------------------------------- fr track, a fleet

def _records(folder: Path) -> pd.DataFrame:
    table = pd.read_csv(folder / "frames.csv")
    assert list(table.columns) == [CAMERA_KEY, *RECORD_KEYS]
    assert (table[CAMERA_KEY] == folder.name).all()
    return table


def test_a_fleet_of_two_http_cameras_and_a_folder_then_a_rerun_appends(tmp_path, capsys):
    narrow = SyntheticCamera(**SMALL, hfov_deg=50, room_seed=3)
    wide = SyntheticCamera(**SMALL, hfov_deg=70)
    folder = tmp_path / "frames"
    folder.mkdir()
    for k in range(3):
        (folder / f"f{k}.jpg").write_bytes(wide.jpeg(k))
    out, jsonl = tmp_path / "out", tmp_path / "records.jsonl"
    with MJPEGServer(narrow, fps=25) as a, MJPEGServer(wide, fps=25) as b:
        listing = tmp_path / "cameras.txt"
        listing.write_text(f"narrow {a.url} --fov-range 40,80\n"
                           f"known {b.url} --focal {wide.focal_px}\n"
                           f"{folder}\n")
        command = ["track", "--sources", str(listing), "--out", str(out), "--fast", "--max-frames", "3",
                   "--json", str(jsonl)]
        assert main(command) == 0
        captured = capsys.readouterr()
        summaries = [json.loads(line) for line in captured.out.splitlines()]
        assert [s["camera"] for s in summaries] == ["narrow", "known", "frames"]
        assert all(s["run"] == "ended: --max-frames" and s["frames_processed"] == 3 for s in summaries)
        for name, camera in (("narrow", narrow), ("known", wide), ("frames", wide)):
            table = _records(out / name)
            assert len(table) == 3 and (table["segment"] == 0).all()
            summary = json.loads((out / name / "calibration.json").read_text())
            assert summary["camera"] == name and summary["run"] == "ended: --max-frames"
            assert summary["calibration"]["focal_px"] == pytest.approx(camera.focal_px, rel=0.05)
            assert (out / name / "track.png").stat().st_size > 0
        known = _records(out / "known")["focal_px"]
        assert known.to_numpy() == pytest.approx([wide.focal_px] * 3, rel=1e-6)  # known: not searched
        assert json.loads((out / "narrow" / "calibration.json").read_text())["settings"]["fov_range"] == "40,80"
        assert list(_records(out / "frames")["frame"]) == [0, 1, 2]
        lines = [json.loads(line) for line in jsonl.read_text().splitlines()]
        assert len(lines) == 9 and list(lines[0]) == [CAMERA_KEY, *RECORD_KEYS]
        # the same command again: each camera appends a segment; the folder had no frame left
        assert main(command) == 0
    for name in ("narrow", "known"):
        table = _records(out / name)
        assert list(table["segment"]) == [0, 0, 0, 1, 1, 1]
        assert table["status"].iloc[3] != "started"  # the fusion continued
    assert len(_records(out / "frames")) == 3
    assert "frames: " in capsys.readouterr().err


def test_a_fleet_records_the_same_searched_in_workers_or_in_its_process(tmp_path, capsys):
    """Five folders of frames: each turn split over 2 worker processes (shards of 2 and 3 frames) or
    searched in the fleet's own process as one batch of 5, every camera's records are the same
    (but for the times): a frame's estimate depends on the frame alone."""
    for i in range(5):
        folder = tmp_path / f"cam{i}"
        folder.mkdir()
        camera = SyntheticCamera(**SMALL, hfov_deg=50 + 8 * i, room_seed=i)
        for k in range(3):
            (folder / f"f{k}.jpg").write_bytes(camera.jpeg(k))
    folders = [str(tmp_path / f"cam{i}") for i in range(5)]
    for workers in ("2", "0"):
        assert main(["track", *folders, "--fast", "--workers", workers, "--out", str(tmp_path / f"out{workers}")]) == 0
    capsys.readouterr()
    timed = ["time", "age_s"] + [c for c in RECORD_KEYS if c.startswith("runtime_s")]
    for i in range(5):
        pooled, alone = (_records(tmp_path / f"out{w}" / f"cam{i}").drop(columns=timed) for w in ("2", "0"))
        assert len(pooled) == 3
        pd.testing.assert_frame_equal(pooled, alone)


def test_sigterm_stops_a_fleet_with_every_record_on_disk_and_no_process_left(tmp_path):
    """Two cameras, searched by worker processes (the default on a CPU): after SIGTERM every record
    is on disk, every calibration.json says so, and no process of the run is left."""
    out = tmp_path / "out"
    stderr_path, stdout_path = tmp_path / "stderr.txt", tmp_path / "stdout.txt"
    with MJPEGServer(SyntheticCamera(**SMALL), fps=25) as a, \
            MJPEGServer(SyntheticCamera(**SMALL, hfov_deg=55, room_seed=2), fps=25) as b:
        command = [sys.executable, "-m", "fr_torch.cli", "track", a.url, b.url, "--out", str(out), "--fast"]
        with open(stderr_path, "w") as stderr, open(stdout_path, "w") as stdout:
            process = subprocess.Popen(command, env=checkout_env(), stdout=stdout, stderr=stderr,
                                       start_new_session=True, preexec_fn=default_stop_signals)
        try:
            deadline = time.monotonic() + 120
            files = [out / "stream_1" / "frames.csv", out / "stream_2" / "frames.csv"]
            while not all(f.exists() and len(f.read_text().splitlines()) >= 3 for f in files):
                assert process.poll() is None, stderr_path.read_text()
                assert time.monotonic() < deadline, "no records in 120 s"
                time.sleep(0.05)
            os.kill(process.pid, signal.SIGTERM)
            returncode = process.wait(timeout=60)
            # the fork server and resource tracker end once the workers are gone
            left = session_left(process.pid, time.monotonic())
        finally:
            reap_session(process)
    assert returncode == 128 + signal.SIGTERM and not left
    assert "\r" not in stderr_path.read_text()  # a file is no terminal: no progress bar
    last = stderr_path.read_text().splitlines()[-1]
    assert last.startswith("fr track: stopped by SIGTERM; ") and "(2 cameras)" in last
    written = int(last.split("; ")[1].split()[0])
    total = 0
    for name in ("stream_1", "stream_2"):
        table = _records(out / name)
        total += len(table)
        summary = json.loads((out / name / "calibration.json").read_text())
        assert summary["run"] == "stopped by SIGTERM" and summary["frames_processed"] == len(table)
    assert total == written
    # each camera's summary line, as at the end of a run
    summaries = [json.loads(line) for line in stdout_path.read_text().splitlines()]
    assert [(s["camera"], s["run"]) for s in summaries] == [("stream_1", "stopped by SIGTERM"),
                                                             ("stream_2", "stopped by SIGTERM")]
