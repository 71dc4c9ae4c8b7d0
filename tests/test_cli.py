"""The ``fr calibrate`` command end to end on the bundled rendered example."""
import json
import subprocess
import sys

from tests.conftest import REPO

EXAMPLE = REPO / "examples" / "room.png"
# Ground truth of examples/room.png (examples/make_example.py): f = 420 px, roll 4, pitch 8 deg.
TRUE_FOCAL, TRUE_ROLL, TRUE_TILT = 420.0, 4.0, 8.0246


def fr(*args, cwd=REPO):
    return subprocess.run([sys.executable, "-m", "fr_torch.cli", *map(str, args)], capture_output=True, text=True,
                          cwd=cwd, timeout=300)


def test_calibrate_example_writes_json_and_overlay(tmp_path):
    out = fr("calibrate", EXAMPLE, "--fast", "--overlay", tmp_path / "ov", "--json", tmp_path / "out.json")
    assert out.returncode == 0, out.stderr
    record = json.loads(out.stdout.strip().splitlines()[0])
    for key in ("image", "width", "height", "focal_px", "hfov_deg", "rotation", "vertical_axis", "roll_deg",
                "tilt_deg", "pitch_deg", "pan_deg", "vanishing_points", "num_segments", "cues", "reliable"):
        assert key in record
    assert abs(record["focal_px"] - TRUE_FOCAL) / TRUE_FOCAL < 0.03
    assert abs(record["roll_deg"] - TRUE_ROLL) < 0.5 and abs(record["tilt_deg"] - TRUE_TILT) < 0.5
    assert len(record["rotation"]) == 3 and record["vertical_axis"] == 1
    assert json.loads((tmp_path / "out.json").read_text())[0]["focal_px"] == record["focal_px"]
    assert (tmp_path / "ov" / "room_fr.png").stat().st_size > 1000


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


def test_bad_inputs_give_one_line_errors(tmp_path):
    (tmp_path / "bad.jpg").write_text("nope")
    out = fr("calibrate", tmp_path / "missing.jpg", tmp_path / "bad.jpg", EXAMPLE, "--fast")
    assert out.returncode != 0
    assert "Traceback" not in out.stderr
    assert "no such file" in out.stderr and "not a readable image" in out.stderr
    records = [json.loads(line) for line in out.stdout.strip().splitlines()]
    assert [r["ok"] for r in records] == [False, False, True]
    bad_option = fr("calibrate", EXAMPLE, "--focal", "-5")
    assert bad_option.returncode == 2 and "Traceback" not in bad_option.stderr and "--focal" in bad_option.stderr


def test_calibrate_without_reliability_skips_the_profile_gap():
    """``--no-reliability``: no predicted errors, and fR skips the cue only the model needs."""
    out = fr("calibrate", EXAMPLE, "--no-reliability")
    assert out.returncode == 0, out.stderr
    record = json.loads(out.stdout.strip().splitlines()[0])
    assert record["predicted_error"] is None and record["cues"]["focal_profile_gap"] is None  # not computed: null
    assert "focal_prior_share" in record["cues"] and record["reliable"] is True
    assert abs(record["focal_px"] - TRUE_FOCAL) / TRUE_FOCAL < 0.03
