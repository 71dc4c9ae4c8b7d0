"""``fr track`` against real RTSP servers on loopback (:mod:`fr_eval.datasets.rtsp_stream`): the
``rtsp_server`` fixture, Debian's ``rtsp-server-perl`` fed by ffmpeg with a synthetic clip, and
``rtsp_auth_server``, GStreamer's ``rtsp-server`` serving the clip to user ``viewer`` with password
``s3cret`` only.

``fr track`` runs as a process of its own, as a user would, its stderr in a file: what the terminal
would show.  The password of the URL (``s3cret``) must appear nowhere fR writes (rtsp-server-perl
does no authentication: there the credentials are only carried in the URL; GStreamer's server
checks them).  OpenCV's and FFmpeg's own lines (``[tcp @ 0x...]``, ``[rtsp @ 0x...]``, ``[
WARN:...] VIDEOIO(FFMPEG)``) must not reach stderr, and each of fR's lines names the source once.
No assertion is about time.
"""
from __future__ import annotations

import itertools
import json
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import pandas as pd
import pytest
from fr_eval.datasets.rtsp_stream import READER_ENV, free_port
from fr_eval.machine import session_processes

from fr_torch.errors import FRInputError
from fr_torch.video.sources import LiveFrames, Source
from tests.conftest import checkout_env

PASSWORD = "s3cret"
FOREIGN = re.compile(r"\[\w+ @ 0x[0-9a-f]+\]|VIDEOIO|\[ ?(WARN|ERROR|INFO)|OPENCV:FFMPEG")


def _start(url: str, out: Path, *options: str) -> tuple[subprocess.Popen, Path, Path]:
    """``fr track url --out out --fast options`` as a process of its own session; its stdout and
    stderr go to files beside ``out``."""
    stdout, stderr = out.with_suffix(".stdout"), out.with_suffix(".stderr")
    command = [sys.executable, "-m", "fr_torch.cli", "track", url, "--out", str(out), "--fast", *options]
    with open(stdout, "w") as o, open(stderr, "w") as e:
        process = subprocess.Popen(command, env=checkout_env(**READER_ENV), stdin=subprocess.DEVNULL, stdout=o,
                                   stderr=e, start_new_session=True)
    return process, stdout, stderr


def _finish(process: subprocess.Popen, timeout: float = 180) -> int:
    try:
        returncode = process.wait(timeout)
    finally:
        if process.poll() is None:
            process.kill()
            process.wait()
    assert not session_processes(process.pid), "fr track left a process"
    return returncode


def _lines(path: Path) -> list[str]:
    """The terminal's lines: tqdm's redraws (``\\r``) split like line ends, blanks dropped."""
    return [line.strip() for line in re.split(r"[\r\n]", path.read_text()) if line.strip()]


def _check_terminal(lines: list[str], source: str) -> None:
    """No OpenCV / FFmpeg line, no password, and each line that names the source names it once."""
    for line in lines:
        assert not FOREIGN.search(line), line
        assert PASSWORD not in line, line
        if "127.0.0.1" in line:
            assert line.count(source) == 1 and line.count("127.0.0.1") == 1, line


def _check_no_password(out: Path) -> None:
    for path in out.iterdir():
        if path.suffix != ".png":
            assert PASSWORD not in path.read_text(), path


def test_failing_rtsp_sources_give_one_line_each_naming_them_once(rtsp_server, rtsp_auth_server, tmp_path):
    """A mount nothing publishes to (the server answers 404), a wrong password (401) and, for
    HTTP, a port nothing listens on (connection refused): one retry line, then the error line,
    each naming the source once, a password hidden; nothing of OpenCV or FFmpeg."""
    server, _ = rtsp_server
    server.stop_publisher()
    urls = {"not_found": server.url("viewer", PASSWORD),
            "refused": f"http://viewer:{PASSWORD}@127.0.0.1:{free_port()}/stream.mjpg",
            "unauthorized": rtsp_auth_server.url("viewer", "wrong-" + PASSWORD)}
    runs = {case: _start(url, tmp_path / case, "--reconnect", "1.2") for case, url in urls.items()}
    for case, (process, stdout, stderr) in runs.items():
        assert _finish(process) == 2, stderr.read_text()
        source = re.sub(r"(?<=viewer:)[^@]+", "***", urls[case])
        lines = _lines(stderr)
        _check_terminal(lines, source)
        assert f"fr track: {source}: OpenCV cannot open this stream; reconnecting in 0.5 s (--reconnect)" in lines
        assert re.fullmatch(rf"fr track: error: {re.escape(source)}: OpenCV cannot open this stream; no frame for "
                            r"\d+ s: gave up reconnecting \(--reconnect\)", lines[-1]), lines[-1]
        assert PASSWORD not in stdout.read_text()
        _check_no_password(tmp_path / case)
        summary = json.loads((tmp_path / case / "calibration.json").read_text())
        assert summary["source"] == source and summary["run"].startswith(f"error: FRInputError: {source}: ")


def test_rtsp_stream_is_read_and_reconnected_after_the_publisher_goes(rtsp_server, tmp_path):
    """The camera (the publisher) goes away mid-run and comes back: ``--reconnect`` opens the
    stream again and frames after the gap are recorded, with the reconnection counted."""
    server, clip = rtsp_server
    server.publish(clip)
    url = server.url("viewer", PASSWORD)
    source = url.replace(PASSWORD, "***")
    out = tmp_path / "out"
    process, stdout, stderr = _start(url, out, "--reconnect", "60", "--stream-timeout", "0.5",
                                     "--json", str(tmp_path / "records.jsonl"))
    try:
        def wait_for(what, condition, timeout=120.0):
            deadline = time.monotonic() + timeout
            while not condition():
                assert process.poll() is None, stderr.read_text()
                assert time.monotonic() < deadline, f"{what}: not in {timeout:.0f} s: {stderr.read_text()}"
                time.sleep(0.05)

        def records() -> pd.DataFrame:
            path = out / "frames.csv"
            return pd.read_csv(path) if path.exists() and len(path.read_text().splitlines()) > 1 else pd.DataFrame()

        wait_for("a record", lambda: len(records()) >= 1)
        server.stop_publisher()
        wait_for("a retry", lambda: "reconnecting in" in stderr.read_text())
        server.publish(clip)
        wait_for("a record after the reconnection", lambda: len(records()) > 0 and records()["reconnects"].max() >= 1)
        process.send_signal(signal.SIGTERM)
    finally:
        returncode = _finish(process)
    assert returncode == 128 + signal.SIGTERM, stderr.read_text()
    table = pd.read_csv(out / "frames.csv")
    assert (table["frame"].diff().dropna() > 0).all()  # the count of frames read goes on over the gap
    after = table[table["reconnects"] >= 1]
    assert len(after) >= 1 and after["ok"].all() and after.index[0] >= 1  # records before and after the gap
    lines = _lines(stderr)
    _check_terminal(lines, source)
    assert any(line.startswith(f"fr track: {source}: reconnected after ") for line in lines), lines
    assert lines[-1].startswith("fr track: stopped by SIGTERM; ")
    assert PASSWORD not in stdout.read_text()
    _check_no_password(out)
    assert PASSWORD not in (tmp_path / "records.jsonl").read_text()
    summary = json.loads((out / "calibration.json").read_text())
    assert summary["source"] == source and summary["run"] == "stopped by SIGTERM"
    assert summary["calibration"]["focal_px"] > 0


def test_rtsp_credentials_are_checked_by_the_server_and_never_shown(rtsp_auth_server, capfd):
    """The right password reads the stream (FFmpeg answers the server's 401 with it); none is
    refused by the server with one error naming the source.  No output of this process (OpenCV's
    and FFmpeg's included) shows the password.  ``fr track`` with a wrong one: the failing
    sources' test."""
    server = rtsp_auth_server
    logs: list[str] = []
    with LiveFrames(Source.parse(server.url("viewer", PASSWORD)), realtime=False, log=logs.append) as frames:
        images = [frame.image for frame in itertools.islice(iter(frames), 3)]
    assert len(images) == 3 and images[0].shape == (240, 320, 3)
    source = Source.parse(server.url())
    with pytest.raises(FRInputError) as refused:
        list(LiveFrames(source, log=logs.append))
    assert str(refused.value) == f"{source}: OpenCV cannot open this stream"
    captured = capfd.readouterr()
    assert all(PASSWORD not in text for text in (captured.out, captured.err, *logs))
