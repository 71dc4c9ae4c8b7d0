"""Running fR as operators do: no secret of a URL in any output, one schema in every record, stderr
as a log, live metrics.

* the URL corpus (:data:`CORPUS`): user parts and credential parameters, HTTP and RTSP, with and
  without a port, percent-encoded, several parameters, a fragment; every secret in it is a unique
  word, looked for (and its decoded form) in stdout, stderr, every file under ``--out``, the JSON
  lines and the metrics page of a 4-camera fleet, of one source, of ``fr calibrate`` and ``fr batch``;
* the same photo through ``fr calibrate --json``, ``fr batch`` and ``fr track``: the same fields
  (:data:`fr_torch.runtime.schema.FLAT_COLUMNS`), the same values, the search's settings;
* the fleet's stderr (not a terminal): no ``\\r``, every line ``fr track: NAME: ...``, an outage one
  line and its end one line, a per-camera ``--reconnect``, a folder in a ``--reconnect`` fleet;
* the metrics page, scraped while the fleet runs, and its values against calibration.json.
"""
from __future__ import annotations

import json
import socket
import threading
import time
import urllib.request
from pathlib import Path
from urllib.parse import unquote

import numpy as np
import pandas as pd
import pyarrow.parquet as pq
import pytest
from fr_eval.datasets.live_stream import MJPEGServer, SyntheticCamera
from prometheus_client.parser import text_string_to_metric_families

from fr_torch.cli.main import main
from fr_torch.redaction import MASK, redact_text, redact_url
from fr_torch.runtime.schema import ALL_CUES, FLAT_COLUMNS, complete, flat_record
from fr_torch.video.fusion import OnlineCalibrator
from fr_torch.video.metrics import MetricsAddress, TrackCollector
from fr_torch.video.records import TrackOutput
from fr_torch.video.sources import Frame, FrameStream, Source
from fr_torch.video.track import Tracking

SMALL = dict(width=320, height=240)
ROOM = Path(__file__).resolve().parents[1] / "examples" / "room.png"

#: URL forms (PORT: a camera's port) and the secrets each holds; what each must show instead.
CORPUS = (
    ("http://admin:Hunter2pw@127.0.0.1:PORT/video.mjpg", ("Hunter2pw",),
     "http://admin:***@127.0.0.1:PORT/video.mjpg"),
    ("http://127.0.0.1:PORT/videostream.cgi?user=admin&pwd=QsPwd77", ("QsPwd77",),
     "http://127.0.0.1:PORT/videostream.cgi?user=admin&pwd=***"),
    ("http://127.0.0.1:PORT/s.mjpg?channel=1&Password=Enc%74oded9&SIG=SiGnAtUrE4#auth=Fr4gment",
     ("Enc%74oded9", "Enctoded9", "SiGnAtUrE4", "Fr4gment"),
     "http://127.0.0.1:PORT/s.mjpg?channel=1&Password=***&SIG=***#auth=***"),
    ("rtsp://viewer:p%40ssRtsp5@127.0.0.1:9/live?token=RtSpTok3n&api_key=K3yValue", ("p%40ssRtsp5", "p@ssRtsp5",
     "RtSpTok3n", "K3yValue"), "rtsp://viewer:***@127.0.0.1:9/live?token=***&api_key=***"),
    ("rtsp://cam.local/stream1?access_token=BearerX1;secret=Semi2", ("BearerX1", "Semi2"),
     "rtsp://cam.local/stream1?access_token=***;secret=***"),
    ("https://a:b/c@host.example/x?X-Amz-Signature=AwsSig6&X-Amz-Credential=AwsCred8", ("b/c", "AwsSig6", "AwsCred8"),
     "https://a:***@host.example/x?X-Amz-Signature=***&X-Amz-Credential=***"),
    ("rtsp://UserTok9@127.0.0.1:9/h264", ("UserTok9",), "rtsp://***@127.0.0.1:9/h264"),
)
SECRETS = tuple(secret for _, secrets, _ in CORPUS for secret in secrets if secret != "b/c")


def _url(form: str, port: int | str) -> str:
    return form.replace("PORT", str(port))


def test_redact_url_hides_every_secret_of_the_corpus_and_keeps_the_rest():
    for url, secrets, shown in CORPUS:
        assert redact_url(url) == shown
        assert not any(secret in redact_url(url) for secret in secrets if secret != "b/c")
    assert redact_url("/data/site3.mp4") == "/data/site3.mp4" and redact_url("0") == "0"
    assert redact_url("rtsp://10.0.0.7/stream1?channel=2") == "rtsp://10.0.0.7/stream1?channel=2"
    assert redact_url("http://admin@10.0.0.7/x") == "http://***@10.0.0.7/x"  # a user part alone may be a token
    text = "error: cannot open 'rtsp://u:pw1@h/x?pwd=pw2' nor http://h/y?auth=pw3."
    assert redact_text(text) == f"error: cannot open 'rtsp://u:{MASK}@h/x?pwd={MASK}' nor http://h/y?auth={MASK}."


def _free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


def _leaks(texts: dict[str, bytes]) -> list[str]:
    """``where: secret`` for each secret (or its decoded form) found in ``texts``."""
    found = []
    for where, data in texts.items():
        for secret in SECRETS + tuple(unquote(s) for s in SECRETS):
            if secret.encode() in data:
                found.append(f"{where}: {secret}")
    return found


def _files(folder: Path) -> dict[str, bytes]:
    return {str(path): path.read_bytes() for path in folder.rglob("*") if path.is_file()}


class Scraper(threading.Thread):
    """Scrapes ``url`` every 0.1 s until stopped; ``pages`` keeps every page read."""

    def __init__(self, url: str):
        super().__init__(daemon=True)
        self.url, self.pages, self.stop = url, [], threading.Event()

    def run(self) -> None:
        while not self.stop.wait(0.1):
            try:
                with urllib.request.urlopen(self.url, timeout=2) as response:
                    self.pages.append(response.read().decode())
            except OSError:
                pass


def test_a_fleet_keeps_its_secrets_logs_a_line_per_event_and_serves_metrics(tmp_path, capsys):
    """Four cameras (three HTTP ones whose URLs carry secrets, one dropping and reconnecting with
    its own --reconnect, and a folder in a --reconnect fleet) and an RTSP camera nobody serves
    (--reconnect 0: it ends alone at once): no secret anywhere, a log without \\r, metrics."""
    folder = tmp_path / "archive"
    folder.mkdir()
    wide = SyntheticCamera(**SMALL, hfov_deg=70)
    for k in range(3):
        (folder / f"f{k}.jpg").write_bytes(wide.jpeg(k))
    out, jsonl, port = tmp_path / "out", tmp_path / "records.jsonl", _free_port()
    with MJPEGServer(SyntheticCamera(**SMALL), fps=25) as door, \
            MJPEGServer(SyntheticCamera(**SMALL, hfov_deg=55, room_seed=2), fps=25, drop_after=2) as gate, \
            MJPEGServer(SyntheticCamera(**SMALL, hfov_deg=60, room_seed=3), fps=25) as lobby:
        ports = {name: server.url.split(":")[2].split("/")[0] for name, server in
                 (("door", door), ("gate", gate), ("lobby", lobby))}
        listing = tmp_path / "cameras.txt"
        listing.write_text(f"door  '{_url(CORPUS[0][0], ports['door'])}'\n"
                           f"gate  '{_url(CORPUS[1][0], ports['gate'])}'  --reconnect 20\n"
                           f"lobby '{_url(CORPUS[2][0], ports['lobby'])}'\n"
                           f"archive {folder}\n"
                           f"nobody '{CORPUS[3][0]}' --reconnect 0\n")
        scraper = Scraper(f"http://127.0.0.1:{port}/metrics")
        scraper.start()
        try:
            code = main(["track", "--sources", str(listing), "--out", str(out), "--fast", "--max-frames", "3",
                         "--workers", "0", "--reconnect", "5", "--json", str(jsonl), "--metrics", f"127.0.0.1:{port}"])
        finally:
            scraper.stop.set()
            scraper.join()
        assert gate.connections >= 2
    captured = capsys.readouterr()
    assert code == 1  # "nobody" has no calibration
    outputs = {"stdout": captured.out.encode(), "stderr": captured.err.encode(), **_files(out),
               "--json": jsonl.read_bytes(),
               **{f"metrics page {i}": page.encode() for i, page in enumerate(scraper.pages)}}
    assert not _leaks(outputs)
    # the log: no carriage return, one line per event, each naming its camera
    err = captured.err
    assert "\r" not in err
    names = ("door", "gate", "lobby", "archive", "nobody")
    assert all(line.startswith("fr track: ") for line in err.splitlines()), err
    gate_lines = [line for line in err.splitlines() if "(--reconnect)" in line or "reconnected after" in line]
    assert gate_lines and all(line.startswith("fr track: gate: ") for line in gate_lines), err
    assert all(("reconnecting in" in line) == (i % 2 == 0) for i, line in enumerate(gate_lines)), gate_lines
    assert "127.0.0.1:" + ports["gate"] not in err  # lines name the camera, not its URL
    summaries = {json.loads(line)["camera"]: json.loads(line) for line in captured.out.splitlines()}
    assert set(summaries) == set(names)
    assert summaries["archive"]["run"] == "ended: --max-frames" and summaries["nobody"]["run"].startswith("error: ")
    nobody = json.loads((out / "nobody" / "calibration.json").read_text())
    assert nobody["source"] == CORPUS[3][2] and nobody["settings"]["reconnect_give_up_s"] is None
    gate_summary = json.loads((out / "gate" / "calibration.json").read_text())
    assert gate_summary["settings"]["reconnect_give_up_s"] == 20.0 and gate_summary["source"].endswith("pwd=***")
    assert json.loads((out / "archive" / "calibration.json").read_text())["settings"]["reconnect_give_up_s"] is None
    # the metrics, scraped while the fleet ran: every camera by its name, never a URL
    assert scraper.pages, "the metrics page never answered"
    samples = [s for page in scraper.pages for family in text_string_to_metric_families(page) for s in family.samples]
    assert {s.labels["camera"] for s in samples} == set(names)
    assert all("//" not in value for s in samples for value in s.labels.values())
    searched = {s.labels["camera"]: s.value for s in samples if s.name == "fr_track_frames_searched_total"}
    assert all(value <= 3 for value in searched.values())
    # one source, its URL's secrets in the query and fragment
    with MJPEGServer(SyntheticCamera(**SMALL), fps=25) as lobby:
        one = tmp_path / "one"
        url = _url(CORPUS[2][0], lobby.url.split(":")[2].split("/")[0])
        assert main(["track", url, "--out", str(one), "--fast", "--max-frames", "2", "--json", "-"]) == 0
    captured = capsys.readouterr()
    assert not _leaks({"stdout": captured.out.encode(), "stderr": captured.err.encode(), **_files(one)})
    assert "\r" not in captured.err


def test_fr_calibrate_and_fr_batch_never_print_or_write_a_urls_secret(tmp_path, capsys):
    urls = [_url(form, 9) for form, _, _ in CORPUS]
    listing = tmp_path / "calibration.json"
    assert main(["calibrate", *urls, "--fast", "--json", str(listing)]) == 1
    captured = capsys.readouterr()
    assert not _leaks({"stdout": captured.out.encode(), "stderr": captured.err.encode(), **_files(tmp_path)})
    assert [record["image"] for record in json.loads(listing.read_text())] == [_url(shown, 9) for _, _, shown in CORPUS]
    # fr batch reads URLs through fsspec (here without its HTTP filesystem: a one-line error, redacted)
    for url in urls[1:4]:
        assert main(["batch", url, "--out", str(tmp_path / "table"), "--fast", "--workers", "1"]) == 2
        captured = capsys.readouterr()
        assert len(captured.err.splitlines()) == 1 and redact_url(url) in captured.err
        assert not _leaks({"stdout": captured.out.encode(), "stderr": captured.err.encode(), **_files(tmp_path)})


def test_fr_batch_names_each_failed_file_and_resumes_by_the_rows_names(tmp_path, capsys):
    (tmp_path / "broken.jpg").write_bytes(b"not a jpeg")
    out = tmp_path / "table"
    command = ["batch", str(tmp_path / "broken.jpg"), str(tmp_path / "missing.png"), "--out", str(out), "--fast",
               "--workers", "1"]
    assert main(command) == 0
    err = capsys.readouterr().err
    assert "\r" not in err and err.count("fr batch: failed: ") == 2
    assert f"(2 failed: {tmp_path / 'broken.jpg'}, {tmp_path / 'missing.png'})" in err
    assert main(command) == 0
    assert "2 already done" in capsys.readouterr().err


def _flat(record: dict) -> dict:
    return flat_record(complete(dict(record)))


def test_calibrate_batch_and_track_carry_the_same_fields_for_the_same_photo(tmp_path, capsys):
    options = ["--fast", "--pitch-range=-30,30"]
    listing = tmp_path / "calibrate.json"
    assert main(["calibrate", str(ROOM), *options, "--json", str(listing)]) == 0
    capsys.readouterr()
    [calibrate] = json.loads(listing.read_text())
    assert main(["batch", str(ROOM), "--out", str(tmp_path / "table"), *options, "--workers", "1"]) == 0
    row = pd.read_parquet(tmp_path / "table").iloc[0].to_dict()
    row = json.loads(pd.Series(row).to_json())  # nested arrays -> lists, as a reader gets them
    frames = tmp_path / "frames"
    frames.mkdir()
    (frames / ROOM.name).write_bytes(ROOM.read_bytes())
    assert main(["track", str(frames), "--out", str(tmp_path / "track"), *options]) == 0
    capsys.readouterr()
    record = pd.read_csv(tmp_path / "track" / "frames.csv").iloc[0].to_dict()
    summary = json.loads((tmp_path / "track" / "calibration.json").read_text())

    # the same fields: calibrate's and batch's records flatten to the CSV's estimate columns
    assert set(calibrate) - {"ranked_vanishing_points"} == {key for key in row if key != "ranked_vanishing_points"}
    assert FLAT_COLUMNS == tuple(_flat(calibrate)) == tuple(_flat(row))
    assert set(FLAT_COLUMNS) <= set(record)
    # the same values
    flat_calibrate, flat_row = _flat(calibrate), _flat(row)
    for column in FLAT_COLUMNS:
        values = [flat_calibrate[column], flat_row[column], record[column]]
        if column in ("image", "reason") or column.startswith("runtime_s"):
            continue
        if isinstance(values[0], float) or isinstance(values[2], float):
            numbers = [np.nan if v is None or v == "" else float(v) for v in values]
            np.testing.assert_allclose(numbers, numbers[0], rtol=1e-6, atol=1e-9, err_msg=column)
        else:
            assert values[0] == values[1] == values[2] or (values[0] is None and pd.isna(values[2])), (column, values)
    assert calibrate["model"] == "manhattan" and record["model"] == calibrate["model"]
    # the fused calibration: the principal point, the horizon with its bound, the search's range in the settings
    fused = summary["calibration"]
    assert fused["principal_point"] == calibrate["principal_point"]
    assert set(fused["horizon"]) == {"line", "left_y", "right_y", "bound_pct", "unbounded"}
    assert summary["settings"]["pitch_range_deg"] == [-30.0, 30.0]


def test_a_bound_that_says_nothing_is_null_and_flagged():
    bounded = {"ok": True, "tilt_deg": 5.0, "cues": {},
               "horizon": {"line": [0, 1, -100], "left_y": 100.0, "right_y": 100.0, "bound_pct": 3.0},
               "error_bound": {"coverage": 0.9, "focal_pct": 4.0, "tilt_deg": 1.0, "limits": {}, "enforced": True}}
    record = complete(json.loads(json.dumps(bounded)))
    assert record["horizon"]["bound_pct"] == 3.0 and record["horizon"]["unbounded"] is False
    assert record["error_bound"]["unbounded"] == {"focal_pct": False, "tilt_deg": False}
    assert set(record["cues"]) == set(ALL_CUES) and all(v is None for v in record["cues"].values())
    cases = (({"focal_pct": 975.8, "tilt_deg": 1.0}, 40.0),  # a focal bound that says nothing
             ({"focal_pct": 4.0, "tilt_deg": 89.0}, 975.8),  # a tilt within its bound reaching 89 deg
             ({"focal_pct": 4.0, "tilt_deg": 2.0}, 1000.0))  # the core's cap
    for bound, horizon_bound in cases:
        record = json.loads(json.dumps(bounded))
        record["error_bound"].update(bound)
        record["horizon"]["bound_pct"] = horizon_bound
        record = complete(record)
        assert record["horizon"]["bound_pct"] is None and record["horizon"]["unbounded"] is True
        assert record["error_bound"]["focal_pct"] == (None if bound["focal_pct"] > 100 else bound["focal_pct"])
        assert complete(json.loads(json.dumps(record))) == record  # a record in the schema stays as it is


class _Frames(FrameStream):
    live = True

    def __init__(self):
        super().__init__(Source("stream", "rtsp://u:Hunter2pw@127.0.0.1/x?token=RtSpTok3n"))
        self.arrived, self.dropped, self.reconnects = 7, 2, 1


def test_the_metrics_equal_calibration_json(tmp_path):
    from fr_torch.runtime.estimator import FREstimator

    camera = SyntheticCamera(**SMALL)
    images = [camera.jpeg(k) for k in range(2)]
    results = FREstimator(mode="fast", reliability="default").calibrate_images([_decode(image) for image in images])
    stream = _Frames()
    output = TrackOutput(tmp_path / "gate", stream.source, {}, "fast", camera="gate", log=lambda m: None)
    tracking = Tracking(stream, OnlineCalibrator(), output, lambda m: None)
    tracking.begin()
    for k, result in enumerate(results):
        tracking.fuse(Frame(k, f"gate_{k}", None, time.monotonic()), result)
    tracking.finish("ended: test")
    summary = json.loads(output.calibration_path.read_text())
    assert summary["calibration"] is not None
    values = {metric.name: metric.samples[0].value for metric in TrackCollector(lambda: [("gate", tracking)]).collect()}
    fused = summary["calibration"]
    assert values["fr_track_focal_px"] == fused["focal_px"] and values["fr_track_tilt_deg"] == fused["tilt_deg"]
    assert values["fr_track_roll_deg"] == fused["roll_deg"]
    assert values["fr_track_focal_sigma_pct"] == fused["sigma"]["focal_pct"]
    assert values["fr_track_tilt_sigma_deg"] == fused["sigma"]["tilt_deg"]
    assert values["fr_track_frames_searched"] == summary["frames_processed"] == 2
    assert values["fr_track_frames_accepted"] == summary["frames_accepted"]
    assert values["fr_track_frames_read"] == summary["frames_arrived"] == 7
    assert values["fr_track_frames_dropped"] == summary["frames_dropped"] == 2
    assert values["fr_track_reconnects"] == summary["segments"][-1]["reconnects"] == 1
    assert values["fr_track_up"] == 0.0 and values["fr_track_calibrated"] == 1.0
    assert (fused["horizon"]["bound_pct"] is None) == ("fr_track_horizon_bound_pct" not in values)


def _decode(data: bytes):
    import cv2

    return cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)


def test_metrics_address_defaults_to_this_machine_and_bad_values_are_one_line():
    assert MetricsAddress.parse("9464") == MetricsAddress("127.0.0.1", 9464)
    assert MetricsAddress.parse("0.0.0.0:9464") == MetricsAddress("0.0.0.0", 9464)
    assert MetricsAddress.parse("[::1]:0") == MetricsAddress("::1", 0)
    for bad in ("", "host", "host:99999", ":80", "1.2.3.4:-1"):
        with pytest.raises(ValueError, match="--metrics"):
            MetricsAddress.parse(bad)


def test_an_unknown_option_shows_the_commands_usage(capsys):
    with pytest.raises(SystemExit) as stop:
        main(["track", "x.mp4", "--no-such-option"])
    err = capsys.readouterr().err
    assert stop.value.code == 2 and err.startswith("usage: fr track ") and "--no-such-option" in err
    assert "--no-progress" in main.__globals__["build_parser"]("track").command_parsers["track"].format_usage()
