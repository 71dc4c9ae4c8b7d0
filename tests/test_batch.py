"""``fr batch``: inputs, Parquet output schema, bad images, resume, the Ray engine and its fault tolerance.

Images are rendered here (30 synthetic rooms, 320 x 240) plus a corrupt file, an empty file and a
missing path.  The Ray tests share one local cluster with 2 CPUs (skipped when Ray is absent).
"""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pandas as pd
import pytest

pq = pytest.importorskip("pyarrow.parquet")  # fr batch needs pyarrow (extra "batch" / "ray")

from fr_torch.batch.inputs import collect_inputs
from fr_torch.batch.jobs import run_batch
from fr_torch.batch.table import records_to_table
from fr_torch.batch.worker import BatchWorker
from fr_torch.cli.batch import estimator_options
from fr_torch.cli.main import build_parser
from fr_torch.core.geometry.conventions import rotation_from_angles
from fr_torch.synthetic import render_manhattan_room
from tests.conftest import checkout_env

N_GOOD = 30


@pytest.fixture(scope="module")
def image_set(tmp_path_factory):
    """Folder with 30 rendered rooms (a third in a sub-folder), a corrupt and an empty image, and a
    CSV manifest (camera id, known focal for two rows, a missing file) over all of them."""
    root = tmp_path_factory.mktemp("batch_images")
    (root / "sub").mkdir()
    rng = np.random.default_rng(5)
    paths = []
    for i in range(N_GOOD):
        rotation = rotation_from_angles(float(rng.uniform(-30, 30)), float(rng.uniform(-10, 10)),
                                        float(rng.uniform(-5, 5))).double().numpy()
        image = render_manhattan_room(float(rng.uniform(200, 350)), rotation, 320, 240, seed=i)
        path = root / ("sub" if i % 3 == 0 else "") / f"room{i:02d}.png"
        cv2.imwrite(str(path), image)
        paths.append(str(path))
    (root / "corrupt.jpg").write_bytes(b"\xff\xd8\xff\xe0 this is not a jpeg" * 10)
    (root / "empty.png").write_bytes(b"")
    bad = [str(root / "corrupt.jpg"), str(root / "empty.png"), str(root / "missing.png")]
    manifest = pd.DataFrame({"image": paths + bad, "camera": [f"cam{i % 4}" for i in range(len(paths) + 3)],
                             "focal_px": [250.0, 300.0] + [None] * (len(paths) + 1)})
    manifest.to_csv(root / "manifest.csv", index=False)
    return {"root": root, "manifest": root / "manifest.csv", "good": paths, "bad": bad}


def _options(**overrides):
    args = build_parser("batch").parse_args(["batch", "x", "--out", "y", "--fast", *overrides.get("argv", [])])
    return estimator_options(args)


def _read(out: Path) -> pd.DataFrame:
    return pd.read_parquet(out).sort_values("image").reset_index(drop=True)


@pytest.fixture(scope="module")
def local_output(image_set, tmp_path_factory):
    """The embedded engine's output on the manifest (the reference for the other tests)."""
    out = tmp_path_factory.mktemp("local") / "out.parquet"
    summary = run_batch([str(image_set["manifest"])], out, _options(), engine="local", workers=1, batch_size=8,
                        progress=False)
    assert summary["processed"] == N_GOOD + 3
    return out


def test_collect_inputs_folder_glob_manifest(image_set, tmp_path):
    root = image_set["root"]
    folder = collect_inputs([str(root)])
    assert {r["image"] for r in folder} == set(image_set["good"]) | set(image_set["bad"][:2])  # recursive
    pattern = collect_inputs([str(root / "sub" / "*.png"), str(root / "sub" / "room00.png")])
    assert len(pattern) == 10 and pattern[0]["image"].endswith("room00.png")  # glob, duplicates once
    rows = collect_inputs([str(image_set["manifest"])])
    assert len(rows) == N_GOOD + 3 and rows[0]["camera"] == "cam0" and rows[0]["focal_px"] == 250.0
    assert rows[2]["focal_px"] is None
    (tmp_path / "list.txt").write_text("# comment\n" + "\n".join(image_set["good"][:3]) + "\n\n")
    pd.DataFrame({"path": image_set["good"][:2]}).to_parquet(tmp_path / "list.parquet")
    assert len(collect_inputs([str(tmp_path / "list.txt"), str(tmp_path / "list.parquet")])) == 3
    with pytest.raises(ValueError, match="no image"):
        collect_inputs([str(tmp_path)])


def test_local_output_schema_bad_images_and_carried_columns(image_set, local_output):
    frame = _read(local_output)
    assert len(frame) == N_GOOD + 3 and frame.image.is_unique
    good = frame[frame.image.isin(image_set["good"])]
    assert good.ok.all() and good.reliable.mean() > 0.8
    failed = frame[frame.image.isin(image_set["bad"])]
    assert not failed.ok.any() and failed.reason.str.len().gt(0).all()
    assert failed.focal_px.isna().all()  # null, the camera fields are absent
    assert {"camera", "known_focal_px"} <= set(frame.columns)
    known = frame.set_index("image").loc[image_set["good"][:2]]
    assert np.allclose(known.focal_px, [250.0, 300.0]) and np.allclose(known.known_focal_px, [250.0, 300.0])
    assert frame.set_index("image").loc[image_set["good"][5], "camera"] == "cam1"
    schema = pq.read_schema(next(local_output.glob("part-*.parquet")))
    # No fixed-size lists: pyarrow < 26 cannot read a null one back (a failed image's row)
    assert not any("fixed_size" in str(field.type) for field in schema)
    assert str(schema.field("rotation").type) == "list<element: list<element: double>>"
    assert failed.rotation.isna().all() and failed.principal_point.isna().all()
    assert all(len(pp) == 2 for pp in good.principal_point)
    rotation = np.stack([np.stack(r) for r in good.rotation])
    assert np.allclose(rotation @ rotation.transpose(0, 2, 1), np.eye(3), atol=1e-5)
    # the same fields as `fr calibrate`'s JSON
    [result] = BatchWorker(_options()).estimator.calibrate_images([image_set["good"][3]])
    assert set(result.to_json()) <= set(frame.columns)


def test_resume_after_interrupted_run(image_set, local_output, tmp_path):
    """A run killed mid-job (hard exit on one image) keeps its finished batches; a re-run completes
    the output with every image exactly once, and a third run has nothing to do."""
    out = tmp_path / "out.parquet"
    env = checkout_env(FR_BATCH_CRASH=f"room20.png:{tmp_path / 'marker'}")
    command = [sys.executable, "-m", "fr_torch.cli", "batch", str(image_set["manifest"]), "--out", str(out),
               "--fast", "--batch-size", "8", "--workers", "1", "--no-progress"]
    crashed = subprocess.run(command, env=env, capture_output=True, text=True, timeout=120)
    assert crashed.returncode == 1, crashed.stderr
    partial = _read(out)
    assert 0 < len(partial) < N_GOOD + 3 and partial.image.is_unique
    resumed = run_batch([str(image_set["manifest"])], out, _options(), workers=1, batch_size=8, progress=False)
    assert resumed["skipped"] == len(partial) and resumed["processed"] == N_GOOD + 3 - len(partial)
    frame = _read(out)
    reference = _read(local_output)
    assert list(frame.image) == list(reference.image)
    assert np.allclose(frame.focal_px, reference.focal_px, equal_nan=True)
    again = run_batch([str(image_set["manifest"])], out, _options(), workers=1, batch_size=8, progress=False)
    assert again["processed"] == 0 and again["skipped"] == N_GOOD + 3
    assert not list(out.glob(".*"))  # no temp files left


def test_local_worker_processes_match_in_process_and_survive_a_crash(image_set, local_output, tmp_path, monkeypatch):
    """The local engine's worker processes give the in-process rows, even when a worker dies on an
    image once (the injected crash): its batch is retried image by image and the run goes on
    (an image that kills its worker every time fails alone: tests/test_pipeline.py)."""
    monkeypatch.setenv("FR_BATCH_CRASH", f"room20.png:{tmp_path / 'marker'}")
    out = tmp_path / "out.parquet"
    summary = run_batch([str(image_set["manifest"])], out, _options(), workers=2, batch_size=8, progress=False)
    assert (tmp_path / "marker").exists()  # the crash happened
    assert summary["processed"] == N_GOOD + 3 and summary["failed"] == 3  # the 3 bad files
    assert len(list(out.glob("part-*.parquet"))) == 5  # 33 rows in batches of 8, regrouped after the retry
    frame, reference = _read(out), _read(local_output)
    assert list(frame.image) == list(reference.image) and list(frame.camera) == list(reference.camera)
    assert list(frame.ok) == list(reference.ok)
    assert np.allclose(frame.focal_px, reference.focal_px, rtol=1e-5, equal_nan=True)


def test_rows_per_part_gathers_batches_and_cli_summary(image_set, tmp_path, capsys):
    from fr_torch.cli.main import main

    (tmp_path / "list.txt").write_text("\n".join(image_set["good"][:3] + image_set["bad"]))
    out = tmp_path / "out.parquet"
    assert main(["batch", str(tmp_path / "list.txt"), "--out", str(out), "--fast", "--batch-size", "2", "--workers", "1",
                 "--rows-per-part", "100", "--no-progress", "--no-reliability"]) == 0
    assert len(list(out.glob("part-*.parquet"))) == 1 and len(pd.read_parquet(out)) == 6
    assert "6 processed (3 failed: " in capsys.readouterr().err
    assert main(["batch", str(tmp_path / "nothing*.png"), "--out", str(out)]) == 2  # one-line error


# ------------------------------------------------------------------------------------------ Ray


@pytest.fixture(scope="module")
def ray_cluster():
    ray = pytest.importorskip("ray")
    pytest.importorskip("ray.data")
    started = not ray.is_initialized()
    if started:
        ray.init(num_cpus=2, include_dashboard=False, logging_level="ERROR")
    yield ray
    if started:
        ray.shutdown()


def _assert_same_rows(frame: pd.DataFrame, reference: pd.DataFrame) -> None:
    assert list(frame.columns) == list(reference.columns)
    assert list(frame.image) == list(reference.image)
    for column in ("ok", "reliable", "num_segments", "camera", "width", "height"):
        assert list(frame[column]) == list(reference[column]), column
    for column in ("focal_px", "roll_deg", "tilt_deg", "pan_deg", "known_focal_px"):
        assert np.allclose(frame[column], reference[column], rtol=1e-4, atol=1e-3, equal_nan=True), column


def test_ray_engine_matches_embedded_despite_worker_crash(image_set, local_output, ray_cluster, tmp_path,
                                                        monkeypatch):
    """Ray Data, 2 actors: an actor that dies (os._exit) on one image is restarted by Ray and its batch
    retried; the output has every input exactly once, with the same rows as the embedded engine."""
    marker = tmp_path / "marker"
    monkeypatch.setenv("FR_BATCH_CRASH", f"room07.png:{marker}")
    out = tmp_path / "ray.parquet"
    summary = run_batch([str(image_set["manifest"])], out, _options(), engine="ray", workers=2, batch_size=4,
                        progress=False)
    assert marker.exists()  # the crash happened
    frame = _read(out)
    assert summary["processed"] == N_GOOD + 3 and summary["failed"] == 3
    assert len(frame) == N_GOOD + 3 and frame.image.is_unique
    _assert_same_rows(frame, _read(local_output))
    assert ray_cluster.data.read_parquet(str(out)).count() == N_GOOD + 3  # readable by Ray in one line


def test_batch_shared_focal_by_on_ray_equals_local(ray_cluster, shared_focal_local_batch, tmp_path):
    """The Ray engine searches each group in one actor and gives the local engine's rows."""
    manifest, options, local = shared_focal_local_batch
    summary = run_batch([str(manifest)], tmp_path / "ray_out", options, engine="ray", workers=2,
                        progress=False, shared_focal_by="camera")
    assert summary["processed"] == 4 and summary["failed"] == 1
    remote = pd.read_parquet(tmp_path / "ray_out").set_index("image").loc[local.index]
    assert list(remote.ok) == list(local.ok) and list(remote.shared_focal_ok) == list(local.shared_focal_ok)
    assert list(remote.columns) == list(local.columns)
    assert remote.focal_px.fillna(-1).tolist() == pytest.approx(local.focal_px.fillna(-1).tolist(), rel=1e-6)


def test_records_with_missing_or_malformed_arrays_become_nulls():
    """A record whose arrays are absent, non-finite or of the wrong shape is stored with nulls there
    (never a wrong-shaped row, never a failed part) and reads back."""
    good = {"image": "a.png", "ok": True, "focal_px": 500.0, "principal_point": [320.0, 240.0],
            "rotation": np.eye(3).tolist(), "vanishing_points": np.eye(3).tolist(),
            "horizon": {"line": [0.0, 1.0, -240.0], "left_y": 240.0, "right_y": 240.0, "bound_pct": 2.5}}
    odd = {"image": "b.png", "ok": True, "focal_px": float("nan"), "principal_point": [],
           "rotation": [[1.0, 0.0], [0.0, 1.0]], "vanishing_points": [[float("inf")] * 3] * 3,
           "horizon": {"line": [0.0, 1.0], "left_y": None, "right_y": float("nan"), "bound_pct": None}}
    table = records_to_table([good, odd, {"image": "c.png", "ok": False}], [{}, {}, {}])
    rows = table.to_pylist()
    assert rows[0]["principal_point"] == [320.0, 240.0] and rows[0]["rotation"] == np.eye(3).tolist()
    assert all(rows[i][key] is None for i in (1, 2) for key in ("principal_point", "rotation", "vanishing_points"))
    assert rows[1]["focal_px"] is None
    assert rows[0]["horizon"] == dict(good["horizon"], unbounded=False) and rows[2]["horizon"] is None
    assert rows[1]["horizon"] == {"line": None, "left_y": None, "right_y": None, "bound_pct": None, "unbounded": False}


def test_pipelined_rows_match_per_batch_rows_and_survive_a_search_error(image_set, monkeypatch):
    """The local engine's GPU path (workers decode and detect, this process searches) gives the rows
    of the per-batch path -- here on a CPU estimator, bad files included -- and a search that raises
    mid-way loses no row: the rest goes through the per-batch path."""
    import pyarrow as pa

    rows = collect_inputs([str(image_set["manifest"])])[21:]  # 9 good rooms, then corrupt, empty, missing
    worker = BatchWorker(_options())
    reference = pa.concat_tables([worker.calibrate_rows(rows[i:i + 4]) for i in range(0, len(rows), 4)]).to_pandas()
    piped = pa.concat_tables(list(worker.calibrate_rows_pipelined(rows, 4, 2))).to_pandas()
    assert list(piped.image) == list(reference.image) and list(piped.ok) == list(reference.ok)
    assert np.allclose(piped.focal_px, reference.focal_px, rtol=1e-4, equal_nan=True)
    assert list(piped.reason[~piped.ok]) == list(reference.reason[~reference.ok])
    calls = {"n": 0}
    search = worker.estimator.calibrate_detections

    def flaky(*args, **kwargs):
        calls["n"] += 1
        if calls["n"] == 2:
            raise RuntimeError("device lost")
        return search(*args, **kwargs)

    monkeypatch.setattr(worker.estimator, "calibrate_detections", flaky)
    recovered = pa.concat_tables(list(worker.calibrate_rows_pipelined(rows, 4, 2))).to_pandas()
    assert list(recovered.image) == list(reference.image)
    assert np.allclose(recovered.focal_px, reference.focal_px, rtol=1e-4, equal_nan=True)


def test_unusable_device_is_one_line_before_any_work(image_set, tmp_path, capsys):
    from fr_torch.cli.main import main

    out = tmp_path / "out.parquet"
    assert main(["batch", str(image_set["manifest"]), "--out", str(out), "--device", "tpu", "--no-progress"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "unknown device 'tpu'" in err and not out.exists()
