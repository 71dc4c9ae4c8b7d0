"""``fr track`` on live sources: images split from a pipe, the real-time slot, a local HTTP MJPEG
stream (reading, dropping, reconnecting), a camera that pans, a stop by SIGHUP and a resumed run.

The live sources are local and synthetic (:mod:`fr_eval.datasets.live_stream`): an MJPEG server
thread on 127.0.0.1 and frames written to a file read as standard input.  No assertion is about
time: what dropping and stopping must keep is checked on the records themselves.
"""
from __future__ import annotations

import io
import itertools
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import pandas as pd
import pytest
from fr_eval.bench.track_live import default_stop_signals
from fr_eval.datasets.live_stream import MJPEGServer, SyntheticCamera
from fr_eval.machine import session_processes

from fr_torch.cli.main import main
from fr_torch.images.io import decode_image_bytes, read_image
from fr_torch.images.stream import split_images
from fr_torch.output import dumps
from fr_torch.video.fusion import OnlineCalibrator
from fr_torch.video.records import RECORD_KEYS
from fr_torch.video.sources import LiveFrames, Reconnect, Source
from tests.conftest import checkout_env

SMALL = dict(width=320, height=240)  # the size of the synthetic frames: reliable rooms, quick searches


def _records(out: Path) -> pd.DataFrame:
    table = pd.read_csv(out / "frames.csv")
    assert list(table.columns) == list(RECORD_KEYS)
    return table


def _check_drops(table: pd.DataFrame) -> None:
    """A live segment's frame indices count every frame read, so each gap is the record's drops."""
    for _, segment in table.groupby("segment"):
        frames = segment["frame"].to_numpy()
        assert (np.diff(frames) > 0).all(), frames
        np.testing.assert_array_equal(np.diff(frames) - 1, segment["dropped"].to_numpy()[1:])


# ---------------------------------------------------------------------------------- pieces

def test_split_images_walks_each_format_and_skips_garbage():
    camera = SyntheticCamera(**SMALL, noise_variants=1)
    image = cv2.imdecode(np.frombuffer(camera.jpeg(0), np.uint8), cv2.IMREAD_COLOR)
    baseline = cv2.imencode(".jpg", image)[1].tobytes()
    # an APP1 segment holding a thumbnail's own SOI ... EOI, which must not end the image
    thumbnail = b"\xff\xd8\xff\xd9"
    app1 = b"\xff\xe1" + (len(thumbnail) + 8).to_bytes(2, "big") + b"Exif\x00\x00" + thumbnail
    with_exif = baseline[:2] + app1 + baseline[2:]
    progressive = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_PROGRESSIVE, 1])[1].tobytes()
    png = cv2.imencode(".png", image)[1].tobytes()
    ppm = cv2.imencode(".ppm", image)[1].tobytes()
    pgm = cv2.imencode(".pgm", cv2.cvtColor(image, cv2.COLOR_BGR2GRAY))[1].tobytes()
    bmp = cv2.imencode(".bmp", image)[1].tobytes()
    images = [ppm, pgm, bmp, with_exif, progressive, png, baseline]
    # after bytes of no image, the split resumes at the next JPEG or PNG signature
    data = b"".join(images[:4]) + b"not an image" + b"".join(images[4:]) + png[:100]
    stream = io.BytesIO(data)
    skipped: list[int] = []
    parts = list(split_images(lambda n: stream.read(min(n, 777)), on_skip=skipped.append, chunk_size=777))
    assert parts == images
    assert skipped == [len(b"not an image"), 100]  # the garbage, then the image cut at the end
    decoded, size = decode_image_bytes(with_exif, "frame")
    assert size == (320, 240) and np.array_equal(decoded, cv2.imdecode(np.frombuffer(baseline, np.uint8),
                                                                         cv2.IMREAD_COLOR))


def test_decode_image_bytes_matches_the_file_reader(tmp_path):
    camera = SyntheticCamera(**SMALL, noise_variants=1)
    path = tmp_path / "frame.jpg"
    path.write_bytes(camera.jpeg(0))
    from_file, file_size = read_image(path)
    from_bytes, size = decode_image_bytes(camera.jpeg(0), "frame")
    assert size == file_size and np.array_equal(from_file, from_bytes)
    with pytest.raises(Exception, match="frame: not a readable image"):
        decode_image_bytes(b"\xff\xd8\xff\xe0junk", "frame")


def test_source_parse_and_reconnect_policy(tmp_path):
    assert Source.parse("-").kind == "stdin" and Source.parse("-").live
    stream = Source.parse("rtsp://user:secret@cam.example:554/live/main")
    assert stream.kind == "stream" and str(stream) == "rtsp://user:***@cam.example:554/live/main"
    assert stream.label == "main"
    assert Source.parse("0") == Source("camera", "0") and Source.parse("0").label == "camera0"
    assert Source.parse(str(tmp_path)).kind == "folder" and not Source.parse(str(tmp_path)).live
    with pytest.raises(FileNotFoundError):
        Source.parse(str(tmp_path / "missing.mp4"))
    assert not Reconnect.parse(None).enabled and Reconnect.parse("inf").give_up_s == float("inf")
    waits = Reconnect.parse("60").waits()
    assert [next(waits) for _ in range(8)] == [0.5, 1, 2, 4, 8, 16, 30, 30]
    for bad in ("-1", "nan", "soon"):
        with pytest.raises(Exception, match="--reconnect"):
            Reconnect.parse(bad)


def test_realtime_keeps_the_newest_frame_and_counts_the_rest():
    image = np.zeros((4, 4), np.uint8)
    for realtime, expected in ((True, [4]), (False, [0, 1, 2, 3, 4])):
        frames = LiveFrames(Source("stdin", "-"), realtime=realtime, stdin_fd=-1)
        for _ in range(5):  # five frames arrive while the search is busy
            frames._put(image)
        frames._ended = True  # the source ends: the reader thread is never started
        taken = [(f.index, f.dropped) for f in frames._take()]
        assert [index for index, _ in taken] == expected
        assert frames.arrived == 5 and frames.dropped == 5 - len(expected)
        assert sum(dropped for _, dropped in taken) == frames.dropped
        assert frames.dropped_share == pytest.approx(frames.dropped / 5)


class GarbledCamera(SyntheticCamera):
    """A camera whose every fourth frame (k = 2 mod 4) is bytes that start as a JPEG and cannot be decoded."""

    def jpeg(self, k: int) -> bytes:
        return b"\xff\xd8\xff\xe0 no image" if k % 4 == 2 else super().jpeg(k)


def _wait_for(condition, what: str, timeout_s: float = 60.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not condition():
        assert time.monotonic() < deadline, f"no {what} within {timeout_s:.0f} s"
        time.sleep(0.02)


def test_an_mjpeg_stream_is_decoded_only_for_the_frames_taken(monkeypatch):
    import fr_torch.video.sources as sources

    decoded = []
    monkeypatch.setattr(sources, "decode_image_bytes", lambda data, name: decoded.append(name)
                        or decode_image_bytes(data, name))
    camera = SyntheticCamera(**SMALL, noise_variants=1)  # every frame the same JPEG
    with MJPEGServer(camera, fps=50) as server, LiveFrames(Source.parse(server.url)) as frames:
        taken = iter(frames)
        first = next(taken)
        _wait_for(lambda: frames.arrived >= first.index + 11, "10 more frames")
        with frames._condition:  # the newest frame waits as the camera sent it, undecoded
            assert frames._waiting[0][1] == camera.jpeg(0)
        second = next(taken)
    assert len(decoded) == 2 and second.dropped >= 9  # 11 frames or more read, 2 decoded
    # decoded as `fr calibrate` decodes the same JPEG saved to a file
    for frame in (first, second):
        assert np.array_equal(frame.image, decode_image_bytes(camera.jpeg(0), "frame")[0])


@pytest.mark.parametrize("fourcc, suffix, encoded", [("MJPG", ".avi", True), ("mp4v", ".mp4", False)])
def test_a_stream_is_kept_encoded_only_when_each_frame_is_a_jpeg(tmp_path, fourcc, suffix, encoded):
    """OpenCV's FFmpeg back end opens a file as it opens a URL: Motion JPEG frames stay JPEG bytes,
    MPEG-4 (each frame predicted from the ones before) is decoded as it is read."""
    path = str(tmp_path / f"clip{suffix}")
    writer = cv2.VideoWriter(path, cv2.VideoWriter_fourcc(*fourcc), 5.0, (320, 240))
    assert writer.isOpened()
    camera = SyntheticCamera(**SMALL, noise_variants=2)
    for k in range(3):
        writer.write(cv2.imdecode(np.frombuffer(camera.jpeg(k), np.uint8), cv2.IMREAD_COLOR))
    writer.release()
    frames = LiveFrames(Source("stream", path))
    read = list(frames._capture())
    assert len(read) == 3 and all(isinstance(item, bytes) == encoded for item in read)
    if encoded:  # each is a whole JPEG of the frame
        assert all(decode_image_bytes(item, "frame")[0].shape == (240, 320, 3) for item in read)


def test_an_mjpeg_frame_that_cannot_be_decoded_is_skipped_not_the_stream():
    lines: list[str] = []
    with MJPEGServer(GarbledCamera(**SMALL, noise_variants=1), fps=50) as server, \
            LiveFrames(Source.parse(server.url), realtime=False, log=lines.append, name="cam") as frames:
        taken = list(itertools.islice(frames, 12))
    good = decode_image_bytes(SyntheticCamera(**SMALL, noise_variants=1).jpeg(0), "frame")[0]
    assert all(np.array_equal(frame.image, good) for frame in taken)
    assert frames.skipped >= 3 and frames.reconnects == 0 and frames.dropped == 0
    assert sum(frame.dropped for frame in taken) == 0  # a skipped frame is no drop
    assert lines and all(line.startswith("fr track: cam: skipping frame ") for line in lines), lines


def test_fusion_checkpoint_continues_exactly_and_history_is_bounded(fast_results):
    first, second = OnlineCalibrator(history_length=3), OnlineCalibrator(history_length=3)
    results = fast_results
    for i, result in enumerate(results[:4]):
        first.update(result, i)
    second.restore(json.loads(dumps(first.checkpoint())))  # through JSON, as calibration.json holds it
    for i, result in enumerate(results[4:], start=4):
        a, b = first.update(result, i), second.update(result, i)
        assert (a.status, a.epoch, a.n_fused) == (b.status, b.epoch, b.n_fused)
        assert a.focal_px == pytest.approx(b.focal_px, rel=1e-12)
        np.testing.assert_allclose(a.rotation, b.rotation, atol=1e-12)
    assert len(first.history) == 3 and first.history[-1].frame == len(results) - 1
    with pytest.raises(ValueError, match="not a fusion checkpoint"):
        OnlineCalibrator().restore({"m": "nonsense"})


@pytest.fixture(scope="module")
def fast_results():
    """Fast-fR results of 6 frames of one room, the camera panning after frame 3."""
    from fr_torch.runtime.estimator import FREstimator

    camera = SyntheticCamera(**SMALL, pan_after=3, noise_variants=2)
    frames = [cv2.imdecode(np.frombuffer(camera.jpeg(k), np.uint8), cv2.IMREAD_COLOR) for k in range(6)]
    return FREstimator(mode="fast", reliability="default").calibrate_images(frames)


# ---------------------------------------------------------------------------------- fr track, live

def test_fr_track_reconnects_a_dropped_stream_and_gives_up(tmp_path, capsys):
    out = tmp_path / "out"
    with MJPEGServer(SyntheticCamera(**SMALL), fps=50, drop_after=4) as server:
        assert main(["track", server.url, "--out", str(out), "--fast", "--max-frames", "5", "--reconnect", "10"]) == 0
        assert server.connections >= 2
    table = _records(out)
    assert table["reconnects"].iloc[-1] >= 1
    _check_drops(table)  # frame indices keep counting over the reconnections
    err = capsys.readouterr().err
    # one line when the stream drops, one when it is back: never a line per retry
    events = [line for line in err.splitlines() if "(--reconnect)" in line or "reconnected after" in line]
    assert "the stream ended; reconnecting in 0.5 s (--reconnect)" in events[0] and len(events) >= 2
    assert all(("reconnecting in" in line) == (i % 2 == 0) for i, line in enumerate(events)), events
    assert all("reconnected after" in line for line in events[1::2]), events
    # nothing listens there: the first connection fails, one retry, then a one-line error
    closed = f"http://127.0.0.1:{server.url.split(':')[2].split('/')[0]}/stream.mjpg"
    assert main(["track", closed, "--out", str(tmp_path / "none"), "--fast", "--reconnect", "0.8"]) == 2
    assert "gave up reconnecting (--reconnect)" in capsys.readouterr().err.splitlines()[-1]


def test_fr_track_stdin_pipe_finds_the_pan_and_skips_a_bad_frame(tmp_path, monkeypatch, capsys):
    camera = SyntheticCamera(**SMALL, pan_after=3)
    frames = tmp_path / "frames.bin"  # what `ffmpeg ... -f image2pipe -` would write
    frames.write_bytes(b"".join(camera.jpeg(k) for k in range(3)) + b"\xff\xd8\xff\xd9"
                       + b"".join(camera.jpeg(k) for k in range(3, 6)))
    out = tmp_path / "out"
    with open(frames, "rb") as stdin:
        monkeypatch.setattr(sys, "stdin", stdin)
        assert main(["track", "-", "--out", str(out), "--fast", "--no-realtime", "--patience", "2"]) == 0
    err = capsys.readouterr().err
    assert "skipping frame 3: stdin_000003: not a readable image" in err
    table = _records(out)
    assert list(table["frame"]) == [0, 1, 2, 4, 5, 6] and not table["dropped"].any()
    # the camera pans from frame 4 on (the bad image is frame 3): the restart comes within
    # --patience reliable frames of it, and the frames after it are fused
    after = table[table["frame"] >= 4]
    restart = after.index[after["restarted"]]
    assert len(restart) == 1 and not table.loc[:3, "restarted"].any(), table[["frame", "status", "reliable"]]
    assert after.loc[:restart[0], "reliable"].sum() <= 2
    assert table.loc[restart[0]:, "status"].isin(["restarted", "fused"]).all()


def test_sighup_stops_a_live_run_that_a_rerun_appends_to(tmp_path):
    """A real process on an HTTP stream stopped by SIGHUP keeps every record; the same command
    again (here in-process, with JSON lines) appends a segment and continues the fusion."""
    out, jsonl = tmp_path / "out", tmp_path / "records.jsonl"
    stderr_path = tmp_path / "stderr.txt"
    with MJPEGServer(SyntheticCamera(**SMALL), fps=50) as server:
        command = [sys.executable, "-m", "fr_torch.cli", "track", server.url, "--out", str(out), "--fast"]
        with open(stderr_path, "w") as stderr:
            process = subprocess.Popen(command, env=checkout_env(), stdout=subprocess.DEVNULL, stderr=stderr,
                                       start_new_session=True, preexec_fn=default_stop_signals)
        try:
            deadline = time.monotonic() + 120
            while not (out / "frames.csv").exists() or len((out / "frames.csv").read_text().splitlines()) < 2:
                assert process.poll() is None, stderr_path.read_text()
                assert time.monotonic() < deadline, "no record in 120 s"
                time.sleep(0.05)
            os.kill(process.pid, signal.SIGHUP)
            returncode = process.wait(timeout=60)
            left = session_processes(process.pid)
        finally:
            if process.poll() is None:
                process.kill()
                process.wait()
        assert returncode == 128 + signal.SIGHUP and not left
        last = stderr_path.read_text().replace("\r", "\n").splitlines()[-1]
        assert last.startswith("fr track: stopped by SIGHUP; ")
        written = int(last.split("; ")[1].split()[0])  # "...; N frames of this run are in ..."
        table = _records(out)
        assert len(table) == written >= 1
        summary = json.loads((out / "calibration.json").read_text())
        assert summary["run"] == "stopped by SIGHUP" and summary["frames_processed"] == written
        assert summary["fusion"]["n"] >= 1 and summary["calibration"]["focal_px"] > 0
        # the same command again: a new segment, the frames counted from 0, the fusion continued
        code = main(["track", server.url, "--out", str(out), "--fast", "--max-frames", "3", "--json", str(jsonl)])
    assert code == 0
    table = _records(out)
    assert list(table["segment"]) == [0] * written + [1] * 3 and (table["age_s"] > 0).all()
    assert table["status"].iloc[written] != "started"  # a fresh fusion would start again
    _check_drops(table)
    lines = [json.loads(line) for line in jsonl.read_text().splitlines()]
    assert [r["frame"] for r in lines] == list(table["frame"].iloc[written:]) and list(lines[0]) == list(RECORD_KEYS)
    summary = json.loads((out / "calibration.json").read_text())
    assert summary["frames_processed"] == written + 3 and summary["live"] and summary["settings"]["realtime"]
    assert [s["run"] for s in summary["segments"]] == ["stopped by SIGHUP", "ended: --max-frames"]
    assert summary["segments"][1]["frames_dropped"] >= table["dropped"].iloc[written:].sum()
    assert summary["calibration"]["focal_px"] == pytest.approx(SyntheticCamera(**SMALL).focal_px, rel=0.05)
    assert (out / "track.png").stat().st_size > 0


@pytest.mark.skipif(not hasattr(signal, "SIGUSR1"), reason="SIGUSR1 asks for the figure")
def test_sigusr1_asks_for_the_figure_and_its_handler_comes_back():
    from fr_torch.video.track import plot_requests

    before = signal.getsignal(signal.SIGUSR1)
    with plot_requests() as requested:
        assert not requested()
        os.kill(os.getpid(), signal.SIGUSR1)
        time.sleep(0.01)  # the handler runs in the main thread between bytecodes
        assert requested() and not requested()
    assert signal.getsignal(signal.SIGUSR1) == before
