"""``fr export-ctrlc`` on the real CTRL-C code, then the exported file through ``fr eval``.

The network is CTRL-C's own (imported from its checkout, ``$FR_CTRLC_SOURCE`` or
``../shared/ctrlc_source``) in a small-width config (ResNet-18, one encoder / decoder layer,
width 64) with random weights so that it runs on two CPU cores: the same code path as the full
model.  Random weights make the numbers meaningless: these tests check shapes, finiteness and
ONNX-vs-PyTorch agreement only, never accuracy.  Needs the ``ctrlc`` extra (torchvision, yacs);
without it or without the CTRL-C source the tests are skipped here and fail in CI.
"""
from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from tests.conftest import REPO, absent, checkout_env, require_dataset

SMALL = ["MODELS.BACKBONE", "resnet18", "MODELS.TRANSFORMER.ENC_LAYERS", "1", "MODELS.TRANSFORMER.DEC_LAYERS", "1",
         "MODELS.TRANSFORMER.HIDDEN_DIM", "64", "MODELS.TRANSFORMER.DIM_FEEDFORWARD", "128",
         "MODELS.TRANSFORMER.NHEADS", "2"]


@pytest.fixture(scope="module")
def ctrlc_source() -> Path:
    source = Path(os.environ.get("FR_CTRLC_SOURCE", REPO.parent / "shared" / "ctrlc_source"))
    if not (source / "models" / "ctrlc.py").is_file():
        absent(f"CTRL-C source not found at {source} (set FR_CTRLC_SOURCE)")
    from fr_baselines.export_ctrlc_onnx import ExportError, import_torchvision

    try:
        import_torchvision()
        import onnx  # noqa: F401
        import yacs  # noqa: F401
    except (ExportError, ImportError) as exc:
        absent(f"the ctrlc extra is not installed: {exc}")
    return source


def _fr(*args: str, cwd: Path) -> subprocess.CompletedProcess:
    env = checkout_env()
    return subprocess.run([sys.executable, "-m", "fr_torch.cli", *args], cwd=cwd, env=env, capture_output=True,
                          text=True, timeout=900)


@pytest.fixture(scope="module")
def small_onnx(ctrlc_source, data_root, tmp_path_factory) -> Path:
    yud = require_dataset(data_root, "yorkurbandb")
    image = sorted(yud.glob("P*/P*.jpg"))[0]
    out = tmp_path_factory.mktemp("ctrlc") / "ctrlc_small_random.onnx"
    result = _fr("export-ctrlc", "--random-weights", "--ctrlc-source", str(ctrlc_source), "--out", str(out),
                 "--check-image", str(image), "--opts", *SMALL, cwd=out.parent)
    assert result.returncode == 0, result.stderr[-3000:]
    assert "max |ONNX - PyTorch|" in result.stdout and "RANDOM" not in result.stdout
    return out


def test_export_agrees_and_records_provenance(small_onnx):
    import onnxruntime as ort

    from fr_baselines.ctrlc import CTRLC

    session = ort.InferenceSession(str(small_onnx), providers=["CPUExecutionProvider"])
    meta = session.get_modelmeta().custom_metadata_map
    assert meta["random_weights"] == "true" and meta["ctrlc_checkpoint"] == ""
    assert float(meta["onnx_vs_torch_max_abs_diff"]) <= 1e-4
    assert [i.shape for i in session.get_inputs()] == [[1, 3, 512, 512], [1, 512, 3], [1, 512, 1]]
    weights = CTRLC(onnx_path=small_onnx).weights
    assert small_onnx.name in weights and "sha256" in weights and "RANDOM WEIGHTS" in weights


def test_exported_ctrlc_in_fr_eval(small_onnx, data_root, tmp_path, monkeypatch):
    """The random-weight export through the ctrlc adapter in ``fr eval`` on three YUD images:
    refused by default (n/a), and with FR_CTRLC_ALLOW_RANDOM=1 every image gets finite numbers and
    the caption names the weights and says they are random."""
    from fr_baselines.ctrlc import CTRLC
    from fr_torch.plugins.interface import ImageMeta

    monkeypatch.delenv("FR_CTRLC_ALLOW_RANDOM", raising=False)
    refused = CTRLC(onnx_path=small_onnx).estimate(np.zeros((480, 640, 3), np.uint8), ImageMeta(name="x"))
    assert not refused.ok and refused.reason.startswith("n/a (not supplied: ") and "random weights" in refused.reason
    monkeypatch.setenv("FR_CTRLC_ALLOW_RANDOM", "1")
    monkeypatch.chdir(tmp_path)
    from fr_torch.cli.main import main  # in this process: the command's own start-up is small_onnx's export

    assert main(["eval", "--dataset", "yud", "--limit", "3", "--methods", "ctrlc", "--ctrlc-onnx", str(small_onnx),
                 "--data-root", str(data_root), "--out", str(tmp_path), "--no-plots", "--group-by", "none"]) == 0
    rows = pd.read_csv(tmp_path / "predictions.csv")
    assert len(rows) == 3 and not rows["failed"].astype(bool).any(), rows.get("reason")
    for column in ("est_hfov_deg", "est_roll_deg", "est_tilt_deg", "roll_err_deg", "fov_err_pct"):
        assert np.isfinite(rows[column].to_numpy(float)).all(), column
    caption = (tmp_path / "summary.md").read_text()
    assert "ctrlc = ctrlc_small_random.onnx (sha256 " in caption and "RANDOM WEIGHTS" in caption


def test_export_errors_are_one_line(tmp_path, capsys):
    """In this process (``fr export-ctrlc`` itself runs as a subprocess in ``small_onnx``): a folder
    that is not a CTRL-C checkout and a missing checkpoint are one-line errors, exit status 2."""
    import torch

    from fr_torch.cli.main import main

    with torch.random.fork_rng(devices=[]):  # the command seeds torch before it looks at the source
        assert main(["export-ctrlc", "--random-weights", "--ctrlc-source", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert "not a CTRL-C checkout" in err and err.count("\n") == 1
    assert main(["export-ctrlc", "--checkpoint", str(tmp_path / "none.pth"), "--ctrlc-source", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert "not found" in err and err.count("\n") == 1
