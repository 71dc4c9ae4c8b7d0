"""``fr eval --reuse METHODS`` (:mod:`fr_eval.protocols.reuse`): the named methods' rows come from the
output folder's last run, and the outputs are those of a run of every method.

On a fake dataset the tests make (six image-less samples with a camera and labelled vanishing
directions) with oracle-like methods: a run reusing some methods writes byte for byte the files a full
run wrote, even when a reused method would now answer otherwise (it is neither built nor run); every
refusal is one line and exit status 2, before anything is written.  The run times are made
deterministic (``_call`` patched) so that whole files can be compared.
"""
from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from fr_eval.datasets.registry import CalibrationSample
from fr_eval.protocols import eval_command, run_eval, vp_eval
from fr_torch.core.geometry.camera import Camera
from fr_torch.core.geometry.conventions import rotation_from_angles
from fr_torch.registry import plugin
from tests.conftest import REPO, checkout_env
from tests.test_eval import FAKE, OracleCalibrator

SHIFTING = "tests.test_eval_reuse:Shifting"
CUED = "tests.test_eval_reuse:Cued"
FLAKY = "tests.test_eval:make_flaky"
#: What Shifting adds to its roll error (degrees): changed between runs, so a recomputed row would differ.
SHIFT = {"deg": 1.0}
#: The classes of the methods built so far (a reused method is not built).
BUILT: list[str] = []


@plugin("dataset")
def load_fake_vp(root=None, split="test", **_):
    """Six samples without image files: a camera (six FOVs) and its three labelled Manhattan directions."""
    samples = []
    for i in range(6):
        camera = Camera(640, 480, 380.0 + 50 * i, (320.0, 240.0),
                        rotation_from_angles(15.0 * i, -8.0 + 3 * i, 2.0 * i - 5).numpy())
        s = CalibrationSample(name=f"fake_{i}", image_path=None, width=640, height=480, camera=camera, split=split,
                              extra={"vp_directions": camera.rotation.T.copy(), "vp_calibration": camera.K})
        FAKE[s.name] = s
        samples.append(s)
    return samples


class Shifting(OracleCalibrator):
    """The oracle turned by ``SHIFT`` degrees about the optical axis; fails on fake_3; has weights."""

    weights = "shifting.net (sha256 0123abcd)"

    def __init__(self, device="cpu"):
        super().__init__(noise_deg=SHIFT["deg"], fail_on={"fake_3"})
        BUILT.append(type(self).__name__)


class Cued(OracleCalibrator):
    """fR-like: predicted errors, reliability cues, a segment count, a variant of its VPs; ignores intrinsics."""

    uses_intrinsics = False

    def __init__(self, device="cpu"):
        super().__init__(noise_deg=3.0 + SHIFT["deg"], focal_factor=0.9)
        BUILT.append(type(self).__name__)

    def estimate(self, image, meta):
        est = super().estimate(image, meta)
        est.predicted_error = {"roll_deg": 0.5, "tilt_deg": 0.7, "focal_pct": 3.0}
        est.reliable = meta.name != "fake_5"
        est.extra.update(cues={"grid_entropy": 1.5 + len(meta.name) / 7.0}, num_segments=40,
                         vp_variants={"raw": est.camera.vanishing_points[::-1]})
        return est


@pytest.fixture(autouse=True)
def steady_clock(monkeypatch):
    """A run time that depends on the image alone (whole files compare equal); SHIFT and BUILT reset."""
    real = run_eval._call

    def call(method, spec, image, meta):
        return real(method, spec, image, meta)[0], 0.01 * (1 + int(meta.name[-1])) / 3.0

    monkeypatch.setattr(run_eval, "_call", call)
    monkeypatch.setattr(vp_eval, "_call", call)
    SHIFT["deg"] = 1.0
    BUILT.clear()


def fr_eval(*argv: str) -> int:
    return eval_command.main(["--dataset", "tests.test_eval_reuse:load_fake_vp", "--no-progress", *argv])


def same_files(a: Path, b: Path, names) -> None:
    for name in names:
        assert (a / name).read_bytes() == (b / name).read_bytes(), name


def info(folder: Path) -> dict:
    return json.loads((folder / "run_info.json").read_text())


def set_info(folder: Path, **changes) -> None:
    data = {k: v for k, v in {**info(folder), **changes}.items() if v is not None}
    (folder / "run_info.json").write_text(json.dumps(data))


CAMERA = ("--methods", f"{CUED},{SHIFTING},{FLAKY}")
CAMERA_FILES = ("predictions.csv", "summary.csv", "summary.md", "summary.tex", "summary_common.csv", "by_fov.csv")


def test_camera_task_reuse_writes_what_the_full_run_wrote(tmp_path):
    full, again, third = tmp_path / "full", tmp_path / "again", tmp_path / "third"
    assert fr_eval(*CAMERA, "--out", str(full), "--no-plots") == 0
    assert BUILT == ["Cued", "Shifting"] and info(full)["weights"] == {SHIFTING: Shifting.weights}
    shutil.copytree(full, again)
    set_info(again, date="2000-01-01 00:00:00")
    SHIFT["deg"] = 6.0  # a fresh run of Cued or Shifting would now differ
    BUILT.clear()
    assert fr_eval(*CAMERA, "--out", str(again), "--reuse", f"{SHIFTING},{CUED}") == 0
    assert BUILT == []  # neither built nor run
    same_files(full, again, CAMERA_FILES)
    assert info(again)["reused"] == {CUED: "2000-01-01 00:00:00", SHIFTING: "2000-01-01 00:00:00"}
    assert info(again)["weights"] == {SHIFTING: Shifting.weights}
    assert (again / "hist_tests.test_eval_reuse_Shifting.png").is_file()  # figures drawn from the reused rows
    # Reusing from a run that reused: the date of the run that computed the rows is kept; Shifting now runs.
    shutil.copytree(again, third)
    assert fr_eval(*CAMERA, "--out", str(third), "--reuse", CUED, "--no-plots") == 0
    assert BUILT == ["Shifting"] and info(third)["reused"] == {CUED: "2000-01-01 00:00:00"}
    old, new = pd.read_csv(full / "predictions.csv"), pd.read_csv(third / "predictions.csv")
    assert list(new.columns) == list(old.columns) and new["image"].tolist() == old["image"].tolist()
    pd.testing.assert_frame_equal(new[new.method == CUED], old[old.method == CUED])
    assert not np.allclose(new[new.method == SHIFTING]["roll_err_deg"].fillna(0),
                           old[old.method == SHIFTING]["roll_err_deg"].fillna(0))


def test_weights_caption_of_a_run_that_did_not_record_them(tmp_path):
    """A run_info.json from before ``weights`` was recorded: the caption's sentence in summary.md."""
    from fr_eval.protocols.reuse import PreviousRun

    (tmp_path / "summary.md").write_text("# t\n\n| a |\nMean ± SE. Settings: x = 1; y. Weights: ctrlc = gsv.onnx "
                                         "(sha256 ab), exported from c.pth (sha256 cd); consac = c.net (sha256 ef).\n")
    previous = PreviousRun(folder=tmp_path, info={"date": "d"}, rows=pd.DataFrame(), methods=("consac", "ctrlc", "x"))
    assert run_eval.reused_weights(previous) == {"consac": "c.net (sha256 ef)",
                                                 "ctrlc": "gsv.onnx (sha256 ab), exported from c.pth (sha256 cd)"}
    previous.info["weights"] = {"ctrlc": "new.onnx", "other": "o"}
    assert run_eval.reused_weights(previous) == {"ctrlc": "new.onnx"}


@pytest.fixture(scope="module")
def camera_run(tmp_path_factory):
    """A finished camera-task run of CUED, SHIFTING, FLAKY."""
    out = tmp_path_factory.mktemp("camera") / "run"
    assert fr_eval(*CAMERA, "--out", str(out), "--no-plots") == 0
    return out


def _drop_a_row(out: Path) -> None:
    rows = pd.read_csv(out / "predictions.csv")
    rows.drop(index=rows.index[(rows.method == SHIFTING) & (rows.image == "fake_4")]).to_csv(
        out / "predictions.csv", index=False)


REFUSALS = {
    "no run_info.json": ((), lambda out: (out / "run_info.json").unlink(), "run_info.json not found"),
    "no per-image file": ((), lambda out: (out / "predictions.csv").unlink(), "predictions.csv not found"),
    "other dataset": (("--dataset", "tests.test_eval:load_fake"), None, "dataset"),
    "other limit": (("--limit", "3"), None, "limit"),
    "other principal point": (("--pp", "calibrated"), None, "pp"),
    "known focal": (("--known-focal",), None, "known_focal"),
    "other FOV range": (("--fov-range", "40,100"), None, "fov_range_deg"),
    "other task": (("--task", "horizon"), lambda out: shutil.copy(out / "predictions.csv",
                                                                    out / "horizon_errors.csv"), "task"),
    "not a method of this run": (("--reuse", "tests.test_eval:OracleCalibrator"), None, "not among"),
    "no rows": (("--methods", f"{CUED},tests.test_eval:OracleCalibrator", "--reuse",
                 "tests.test_eval:OracleCalibrator"), None, "no rows"),
    "an image without a row": ((), _drop_a_row, "lacks"),
}


@pytest.mark.parametrize("case", REFUSALS)
def test_refusals_are_one_line_and_write_nothing(case, camera_run, tmp_path, capsys):
    argv, damage, expected = REFUSALS[case]
    out = tmp_path / "run"
    shutil.copytree(camera_run, out)
    if damage is not None:
        damage(out)
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    capsys.readouterr()
    assert fr_eval(*CAMERA, "--out", str(out), "--reuse", SHIFTING, *argv) == 2  # a later option wins
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and err.startswith("error: --reuse:") and expected in err, err
    assert BUILT == [] and {p.name: p.read_bytes() for p in out.iterdir()} == before


def test_refusal_from_the_command_line(tmp_path):
    done = subprocess.run([sys.executable, "-m", "fr_torch.cli", "eval", "--dataset", "tests.test_eval_reuse:load_fake_vp",
                           "--methods", SHIFTING, "--reuse", SHIFTING, "--out", str(tmp_path)],
                          capture_output=True, text=True, cwd=REPO, env=checkout_env(), timeout=120)
    assert done.returncode == 2 and len(done.stderr.strip().splitlines()) == 1, done.stderr
    assert "run_info.json not found" in done.stderr and "Traceback" not in done.stderr


VP = ("--task", "vp", "--methods", f"{SHIFTING},{CUED}")


def test_vp_task_reuse_takes_rows_variants_and_time_per_image(tmp_path, capsys):
    full, again = tmp_path / "full", tmp_path / "again"
    assert fr_eval(*VP, "--out", str(full)) == 0
    assert {"tests.test_eval_reuse:Cued (raw)"} < set(pd.read_csv(full / "vp_errors.csv")["method"])
    shutil.copytree(full, again)
    SHIFT["deg"] = 6.0
    BUILT.clear()
    assert fr_eval(*VP, "--out", str(again), "--reuse", CUED) == 0
    assert BUILT == ["Shifting"]
    SHIFT["deg"] = 1.0  # Shifting, run again, answers as in the full run
    BUILT.clear()
    assert fr_eval(*VP, "--out", str(again), "--reuse", CUED) == 0
    same_files(full, again, ("vp_errors.csv", "vp_summary.csv", "vp_summary.md", "vp_summary.tex"))
    assert info(again)["reused"] == {CUED: info(full)["date"]}
    capsys.readouterr()
    assert fr_eval(*VP, "--out", str(again), "--reuse", CUED, "--intrinsics", "unknown") == 2
    assert "intrinsics" in capsys.readouterr().err
    (again / "vp_summary.csv").unlink()
    assert fr_eval(*VP, "--out", str(again), "--reuse", CUED) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "vp_summary.csv is missing" in err


def test_horizon_task_reuse(tmp_path):
    full, again = tmp_path / "full", tmp_path / "again"
    methods = ("--task", "horizon", "--methods", f"{SHIFTING},{FLAKY},{CUED}", "--no-plots")
    assert fr_eval(*methods, "--out", str(full)) == 0
    shutil.copytree(full, again)
    SHIFT["deg"] = 6.0
    BUILT.clear()
    assert fr_eval(*methods, "--out", str(again), "--reuse", f"{SHIFTING},{CUED}") == 0
    assert BUILT == []
    same_files(full, again, ("horizon_errors.csv", "horizon_summary.csv", "horizon_summary.md", "horizon_summary.tex"))
    assert info(again)["reused"] == {SHIFTING: info(full)["date"], CUED: info(full)["date"]}
