"""Shared test fixtures.

Tests that need the real datasets take the ``data_root`` fixture: it points at ``$FR_DATA``
(default: ``../shared/data`` beside the repository).  When the data is missing the test is skipped
on a developer machine but **fails** in CI (``CI=true``), so a broken data set-up never passes
silently.
"""
from __future__ import annotations

import json
import os
import signal
import struct
import subprocess
import sys
import time
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
ROOM_F = 420.0  # focal length (px) of examples/room.png (examples/make_example.py)


def _data_root() -> Path:
    return Path(os.environ.get("FR_DATA", REPO.parent / "shared" / "data"))


def absent(message: str) -> None:
    """Data or weights a test needs are missing: fail in CI (``CI=true``), skip elsewhere."""
    if os.environ.get("CI", "").lower() == "true":
        pytest.fail(message)
    pytest.skip(message)


@pytest.fixture(scope="session")
def data_root() -> Path:
    root = _data_root()
    if not root.is_dir():
        absent(f"dataset root {root} not found (set FR_DATA)")
    return root


@pytest.fixture(scope="session")
def models_root() -> Path:
    """User-supplied model weights: ``$FR_MODELS`` (default ``../shared/models`` beside the
    repository, e.g. ``consac/consac_vp.net``).  Treated like the data: the test fails in CI when
    they are missing and is skipped elsewhere."""
    root = Path(os.environ.get("FR_MODELS", REPO.parent / "shared" / "models"))
    if not (root / "consac" / "consac_vp.net").is_file():
        absent(f"model weights not found under {root} (expected consac/consac_vp.net; set FR_MODELS)")
    return root


@pytest.fixture(scope="module")
def rtsp_server(tmp_path_factory):
    """A real RTSP server on 127.0.0.1 (:class:`fr_eval.datasets.rtsp_stream.RTSPServer`:
    Debian's ``rtsp-server-perl``), started with no publisher, and a clip to publish to it (1 s of
    a 320 x 240 :class:`~fr_eval.datasets.live_stream.SyntheticCamera`, H.264): yields (server,
    clip).  Ended afterwards, publisher and server, none left.  Without ``rtsp-server-perl`` or
    ``ffmpeg`` (``.ci/run`` installs them): fails in CI (``CI=true``), skipped elsewhere."""
    from fr_eval.datasets import rtsp_stream
    from fr_eval.datasets.live_stream import SyntheticCamera

    reason = rtsp_stream.missing()
    if reason:
        absent(reason)
    clip = rtsp_stream.write_clip(tmp_path_factory.mktemp("rtsp") / "clip.mp4",
                                  SyntheticCamera(width=320, height=240), frames=25, fps=25)
    server = rtsp_stream.RTSPServer("cam").start()
    try:
        yield server, clip
    finally:
        processes = [server.server, server.publisher]
        server.close()
    assert all(p is None or p.poll() is not None for p in processes), "an RTSP process was left running"


@pytest.fixture(scope="module")
def rtsp_auth_server(rtsp_server):
    """An RTSP server that checks a password (:class:`fr_eval.datasets.rtsp_stream.AuthRTSPServer`:
    GStreamer's ``rtsp-server``) serving ``rtsp_server``'s clip to user ``viewer`` with password
    ``s3cret``; yields it, ended afterwards.  Without GStreamer's RTSP server (``.ci/run`` installs
    it): fails in CI (``CI=true``), skipped elsewhere."""
    from fr_eval.datasets import rtsp_stream

    reason = rtsp_stream.auth_missing()
    if reason:
        absent(reason)
    with rtsp_stream.AuthRTSPServer(rtsp_server[1], "viewer", "s3cret") as server:
        yield server
    assert server.process.poll() is not None, "the RTSP server was left running"


def require_dataset(root: Path, name: str) -> Path:
    """Path of dataset folder ``name`` under ``root``; fail in CI / skip elsewhere if absent."""
    path = root / name
    if not path.is_dir():
        absent(f"dataset {name!r} not found under {root}")
    return path


#: Seconds a stopped command's worker pool (fork server, resource tracker, workers) has to end.
POOL_GONE_S = 10.0


def session_left(pid: int, since: float) -> list[int]:
    """The processes of the session led by ``pid`` still running :data:`POOL_GONE_S` seconds after
    ``since`` (``time.monotonic()``), or as soon as none is (returns [])."""
    from fr_eval.machine import session_processes

    while (left := session_processes(pid)) and time.monotonic() - since < POOL_GONE_S:
        time.sleep(0.05)
    return left


def reap_session(process) -> None:
    """Kill every process of ``process``'s session and ``process`` itself (a Popen): a failed test
    leaves nothing behind."""
    from fr_eval.machine import session_processes

    for pid in session_processes(process.pid):
        os.kill(pid, signal.SIGKILL)
    if process.poll() is None:
        process.kill()
        process.wait()


def checkout_env(**extra: str) -> dict[str, str]:
    """This process's environment for a subprocess that imports the checkout: ``REPO`` first on
    ``PYTHONPATH``, whatever was there kept (packages made importable that way, e.g. carried
    wheels), plus ``extra`` variables."""
    paths = [str(REPO)] + [p for p in os.environ.get("PYTHONPATH", "").split(os.pathsep) if p]
    return {**os.environ, "PYTHONPATH": os.pathsep.join(paths), **extra}


#: What a fresh process calibrates (:func:`fresh_process_records`): the photos of
#: tests/test_reproducibility.py (Fast-fR, and the first two with fR), the scenes of
#: tests/test_families.py (extra families) and one scene with fR; then whether the fused kernels ran
#: and whether torch's compiler was imported.
_FRESH_PROCESS_CODE = """
import json, sys
from fr_torch import FREstimator
from fr_torch.core.likelihood import native
from fr_torch.core.geometry.conventions import rotation_from_angles
from fr_torch.core.settings.config import SearchConfig
from fr_torch.synthetic import synthetic_segments
from tests.test_reproducibility import _photos, _record
p = _photos()
photos = FREstimator(mode='fast').calibrate_segments([x[0] for x in p], [x[1] for x in p])
from tests.test_families import _families_scenes
f = _families_scenes()
families = FREstimator(mode='fast', search_config=SearchConfig.from_config(families='auto')).calibrate_segments(
    [x[0] for x in f], [x[1] for x in f])
scene, _ = synthetic_segments(500.0, rotation_from_angles(10.0, 5.0, 2.0).numpy(), 640, 480, n_per_family=30, seed=0)
[fr] = FREstimator(mode='fr').calibrate_segments([scene], [(640, 480)])
fr_photos = FREstimator(mode='fr').calibrate_segments([x[0] for x in p[:2]], [x[1] for x in p[:2]])
print(json.dumps({'photos': [_record(x) for x in photos], 'families': [_record(x) for x in families],
                  'fr_photos': [_record(x) for x in fr_photos],
                  'fr_ok': [fr.ok, fr.reason], 'native': native.available(),
                  'dynamo_imported': 'torch._dynamo' in sys.modules}))
"""


def cpu_kernel_sets() -> list[str]:
    """torch CPU kernel sets (``ATEN_CPU_CAPABILITY``) this machine can run: default, and avx2,
    avx512 where the CPU has them."""
    flags = open("/proc/cpuinfo").read().split() if os.path.exists("/proc/cpuinfo") else []
    return ["default"] + (["avx2"] if "avx2" in flags else []) + (["avx512"] if "avx512f" in flags else [])


#: What the maths libraries run on other CPUs, pinned on this one: with the kernel set of an older CPU
#: its oneMKL branch (``MKL_CBWR``: the vector maths behind torch's ``exp`` / ``log`` / ...), its
#: numpy SIMD level (``NPY_DISABLE_CPU_FEATURES``) and OpenBLAS's kernels (``OPENBLAS_CORETYPE``), so
#: that a result depending on the CPU shows here.
EMULATED_CPUS = {
    "default": {"MKL_CBWR": "COMPATIBLE", "NPY_DISABLE_CPU_FEATURES": "X86_V3 X86_V4 AVX512_ICL AVX512_SPR",
                "OPENBLAS_CORETYPE": "Prescott"},
    "avx2": {"MKL_CBWR": "AVX2", "NPY_DISABLE_CPU_FEATURES": "X86_V4 AVX512_ICL AVX512_SPR"},
    "torch-path": {"MKL_CBWR": "COMPATIBLE"},
}


#: The fresh processes, by name: one per CPU kernel set (one thread), and ``torch-path`` (FR_NATIVE=0,
#: one thread: the torch path of every score and gradient, what a machine without a C compiler runs);
#: each with :data:`EMULATED_CPUS`' libraries where it names some.
def _fresh_process_env(name: str) -> dict[str, str]:
    if name == "torch-path":
        return checkout_env(FR_NATIVE="0", FR_THREADS="1", **EMULATED_CPUS[name])
    return checkout_env(ATEN_CPU_CAPABILITY=name, FR_THREADS="1", **EMULATED_CPUS.get(name, {}))


_fresh_processes: dict[str, subprocess.Popen] = {}
_fresh_records: dict[str, dict] = {}


#: The tests that read :func:`fresh_process_records`: when one of them is collected, the fresh
#: processes start as soon as collection ends and run beside the tests before it.
FRESH_PROCESS_TESTS = {"test_every_cpu_kernel_set_gives_the_same_bits", "test_the_torch_path_gives_the_fused_kernels_bits",
                       "test_the_families_give_the_same_bits_under_every_kernel_set",
                       "test_calibrating_does_not_import_the_compiler"}


def start_fresh_processes() -> None:
    """Start the fresh processes of :func:`fresh_process_records` (once per session)."""
    if not _fresh_processes:
        for each in [*cpu_kernel_sets(), "torch-path"]:
            _fresh_processes[each] = subprocess.Popen([sys.executable, "-c", _FRESH_PROCESS_CODE], cwd=REPO,
                                                      env=_fresh_process_env(each), stdout=subprocess.PIPE,
                                                      stderr=subprocess.PIPE, text=True)


def pytest_collection_finish(session):
    if any(getattr(item, "originalname", item.name) in FRESH_PROCESS_TESTS for item in session.items):
        start_fresh_processes()


def fresh_process_records(name: str) -> dict:
    """The JSON of one fresh process (:data:`_FRESH_PROCESS_CODE`): ``photos``, ``families``
    (:func:`tests.test_families._families_scenes` with ``families=auto``), ``fr_photos`` (fR, the first
    two photos) (records, ``runtime_s`` left out), ``fr_ok``, ``native``, ``dynamo_imported``.  ``name``: a
    kernel set of :func:`cpu_kernel_sets` or ``torch-path``.  All of them start together (each is one
    thread: they share the cores), when collection ends (:func:`pytest_collection_finish`) or else at
    the first call; each runs once per session, and every check that compares across kernel sets or
    paths reads its part."""
    start_fresh_processes()
    if name not in _fresh_records:
        process = _fresh_processes[name]
        try:
            stdout, stderr = process.communicate(timeout=600)
        except subprocess.TimeoutExpired:
            process.kill()
            stdout, stderr = process.communicate()
        assert process.returncode == 0, f"{name}: {stderr[-3000:]}"
        _fresh_records[name] = json.loads(stdout.strip().splitlines()[-1])
    return _fresh_records[name]


def pytest_sessionfinish(session, exitstatus):
    """Fresh processes that no test waited for (a run of some tests only) do not outlive the session."""
    for process in _fresh_processes.values():
        if process.poll() is None:
            process.kill()
        process.communicate()


def has_cuda() -> bool:
    import torch

    return torch.cuda.is_available()


gpu = pytest.mark.skipif(not has_cuda(), reason="needs a CUDA device")


def pytest_collection_modifyitems(config, items):
    """``@pytest.mark.slow`` tests run only with ``FR_SLOW=1`` or when ``-m`` selects them."""
    if os.environ.get("FR_SLOW") == "1" or "slow" in (config.getoption("-m") or ""):
        return
    skip = pytest.mark.skip(reason="slow: set FR_SLOW=1 or use -m slow")
    for item in items:
        if "slow" in item.keywords:
            item.add_marker(skip)


def with_exif_orientation(jpeg: bytes, orientation: int, big_endian: bool = False) -> bytes:
    """``jpeg`` (bytes) with an APP1 Exif segment right after SOI whose IFD0 holds only the
    Orientation tag (0x0112); little-endian TIFF ("II") unless ``big_endian`` ("MM")."""
    order = ">" if big_endian else "<"
    tiff = (b"MM" if big_endian else b"II") + struct.pack(order + "HIH", 42, 8, 1)
    tiff += struct.pack(order + "HHIHHI", 0x0112, 3, 1, orientation, 0, 0)
    body = b"Exif\x00\x00" + tiff
    return jpeg[:2] + b"\xff\xe1" + struct.pack(">H", len(body) + 2) + body + jpeg[2:]


@pytest.fixture(scope="session")
def shared_focal_local_batch(tmp_path_factory):
    """:func:`shared_focal_batch_on_local_engine` once per session (tests/test_shared_focal.py checks it,
    tests/test_batch.py compares the Ray engine's rows with it)."""
    return shared_focal_batch_on_local_engine(tmp_path_factory.mktemp("shared_focal_batch"))


def shared_focal_batch_on_local_engine(tmp_path: Path):
    """``fr batch --shared-focal-by`` on the local engine over three copies of ``examples/room.png`` and a
    missing file, checked; returns (manifest, options, output table by image)."""
    import shutil

    import pandas as pd

    from fr_torch.batch.jobs import run_batch

    room = REPO / "examples" / "room.png"
    a, b, c = (shutil.copy(room, tmp_path / f"{name}.png") for name in ("a", "b", "c"))
    manifest = tmp_path / "m.csv"
    pd.DataFrame({"image": [str(a), str(tmp_path / "missing.png"), str(b), str(c)],
                  "camera": ["c1", "c1", "c1", ""]}).to_csv(manifest, index=False)
    options = {"estimator": {"mode": "fast"}, "principal_point": None, "focal_px": None, "reliability": False}
    with pytest.raises(ValueError, match="no such manifest column"):
        run_batch([str(manifest)], tmp_path / "bad_out", options, progress=False, shared_focal_by="cam")
    summary = run_batch([str(manifest)], tmp_path / "out", options, progress=False, shared_focal_by="camera")
    assert summary["processed"] == 4 and summary["failed"] == 1
    table = pd.read_parquet(tmp_path / "out").set_index("image")
    group = table.loc[[str(a), str(b)]]
    assert group["shared_focal_ok"].all() and (group["shared_focal_images_used"] == 2).all()
    assert group["focal_px"].iloc[0] == pytest.approx(group["focal_px"].iloc[1])
    assert abs(group["shared_focal_px"].iloc[0] / ROOM_F - 1) < 0.04
    missing = table.loc[str(tmp_path / "missing.png")]
    assert not missing["ok"] and missing["shared_focal_ok"]  # its group has a value; it keeps its failure
    single = table.loc[str(c)]  # an empty group value: a group of one
    assert single["ok"] and single["shared_focal_images_used"] == 1
    assert table["shared_pp_x"].isna().all()  # groups of fewer than 5 photos keep the image centre
    return manifest, options, table
