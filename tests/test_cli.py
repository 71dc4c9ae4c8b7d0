"""The ``fr calibrate`` command end to end on the bundled rendered example."""
import json
import subprocess
import sys

import pytest

from tests.conftest import REPO

EXAMPLE = REPO / "examples" / "room.png"
# Ground truth of examples/room.png (examples/make_example.py): f = 420 px, roll 4, pitch 8 deg.
TRUE_FOCAL, TRUE_ROLL, TRUE_TILT = 420.0, 4.0, 8.0246


class Runs:
    """``fr`` commands started together (each is mostly torch's import: side by side they share the
    cores); :meth:`result` waits for one."""

    def __init__(self, commands: dict):
        self.processes = {name: subprocess.Popen([sys.executable, "-m", "fr_torch.cli", *map(str, args)],
                                                 stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=REPO)
                          for name, args in commands.items()}
        self.results = {}

    def result(self, name: str) -> subprocess.CompletedProcess:
        if name not in self.results:
            process = self.processes[name]
            stdout, stderr = process.communicate(timeout=300)
            self.results[name] = subprocess.CompletedProcess(process.args, process.returncode, stdout, stderr)
        return self.results[name]

    def close(self) -> None:
        for process in self.processes.values():
            if process.poll() is None:
                process.kill()
            process.communicate()


@pytest.fixture(scope="module", autouse=True)
def runs(tmp_path_factory):
    """The module's ``fr calibrate`` processes, started before its first test: over a missing file, a
    file that is no image and the example (with --overlay and --json); fR without reliability."""
    folder = tmp_path_factory.mktemp("cli")
    (folder / "bad.jpg").write_text("nope")
    started = Runs({"bad_inputs": ["calibrate", folder / "missing.jpg", folder / "bad.jpg", EXAMPLE, "--fast",
                                   "--overlay", folder / "ov", "--json", folder / "out.json"],
                    "no_reliability": ["calibrate", EXAMPLE, "--no-reliability"]})
    started.folder = folder
    try:
        yield started
    finally:
        started.close()


def test_a_reader_that_closes_the_pipe_early_loses_no_overlay(tmp_path):
    """``fr calibrate ... | head -c 1``: fr stops quietly when its stdout closes, with the overlay written
    first (the record of an image is printed after its files)."""
    command = [sys.executable, "-m", "fr_torch.cli", "calibrate", str(EXAMPLE), "--fast", "--overlay", str(tmp_path / "ov")]
    producer = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, cwd=REPO)
    assert producer.stdout.read(1) == b"{"
    producer.stdout.close()  # the reader is gone before the rest of the record
    assert producer.wait(timeout=300) in (0, 141)
    assert b"Traceback" not in producer.stderr.read()
    assert (tmp_path / "ov" / "room_fr.png").stat().st_size > 1000


def test_calibrate_writes_json_and_overlay_and_bad_inputs_give_one_line_errors(runs, capsys):
    """One ``fr calibrate --fast`` over a missing file, a file that is no image and the example: the
    example's record (every field, the right camera), its overlay and --json file; the bad inputs
    fail alone with one-line messages and a non-zero exit status.  A bad option: a one-line error,
    exit status 2 (in this process; the command line's own start-up is the subprocess above)."""
    tmp_path = runs.folder
    out = runs.result("bad_inputs")
    assert out.returncode != 0
    assert "Traceback" not in out.stderr
    assert "no such file" in out.stderr and "not a readable image" in out.stderr
    records = [json.loads(line) for line in out.stdout.strip().splitlines()]
    assert [r["ok"] for r in records] == [False, False, True]
    record = records[2]
    for key in ("image", "width", "height", "focal_px", "hfov_deg", "rotation", "vertical_axis", "roll_deg",
                "tilt_deg", "pitch_deg", "pan_deg", "vanishing_points", "num_segments", "cues", "reliable"):
        assert key in record
    assert abs(record["focal_px"] - TRUE_FOCAL) / TRUE_FOCAL < 0.03
    assert abs(record["roll_deg"] - TRUE_ROLL) < 0.5 and abs(record["tilt_deg"] - TRUE_TILT) < 0.5
    assert len(record["rotation"]) == 3 and record["vertical_axis"] == 1
    written = [r for r in json.loads((tmp_path / "out.json").read_text()) if r["ok"]]
    assert [r["focal_px"] for r in written] == [record["focal_px"]]
    assert (tmp_path / "ov" / "room_fr.png").stat().st_size > 1000

    from fr_torch.cli.main import main

    try:
        status = main(["calibrate", str(EXAMPLE), "--focal", "-5"])
    except SystemExit as stop:
        status = stop.code
    err = capsys.readouterr().err
    assert status == 2 and "--focal" in err and err.strip().count("\n") == 0


def test_calibrate_without_reliability_skips_the_profile_gap(runs):
    """``--no-reliability``: no predicted errors, and fR skips the cue only the model needs."""
    out = runs.result("no_reliability")
    assert out.returncode == 0, out.stderr
    record = json.loads(out.stdout.strip().splitlines()[0])
    assert record["predicted_error"] is None and record["cues"]["focal_profile_gap"] is None  # not computed: null
    assert "focal_prior_share" in record["cues"] and record["reliable"] is True
    assert abs(record["focal_px"] - TRUE_FOCAL) / TRUE_FOCAL < 0.03
