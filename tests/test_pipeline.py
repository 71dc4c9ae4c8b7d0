"""The decode/detect pipeline and the sharded search give the in-process results, in input order."""
import multiprocessing
import os
import subprocess
import sys

import cv2
import numpy as np
import pytest

from fr_torch import FREstimator
from fr_torch.core.likelihood.segments import SegmentFilter
from fr_torch.detectors.lsd import LSDDetector
from fr_torch.errors import FRInputError
from fr_torch.runtime import workers as workers_module
from fr_torch.runtime.pipeline import (
    calibrate_paths,
    calibrate_segments_sharded,
    calibrate_stream,
    iter_detections,
)
from fr_torch.synthetic import random_rotation, render_manhattan_room, synthetic_segments


def _same(a, b):
    """The same answer bit for bit: a photo's result does not depend on its batch, the workers or the
    thread count (fr_torch.core.exact)."""
    assert a.image == b.image and a.ok == b.ok and a.reason == b.reason
    if a.ok:
        assert a.focal_px == b.focal_px
        assert np.array_equal(a.rotation, b.rotation)
        assert np.array_equal(a.labels, b.labels)
        assert a.cues == b.cues
        assert a.error_bound == b.error_bound and a.reliable == b.reliable


@pytest.fixture(scope="module")
def folder(tmp_path_factory):
    root = tmp_path_factory.mktemp("images")
    rng = np.random.default_rng(3)
    paths = []
    for i in range(3):
        image = render_manhattan_room(500.0 + 50 * i, random_rotation(rng, pan=(-20, 20), pitch=(-10, 10), roll=(-5, 5)),
                                      320, 240, seed=i)
        paths.append(str(root / f"room{i}.png"))
        cv2.imwrite(paths[-1], image)
    corrupt = root / "corrupt.jpg"
    corrupt.write_bytes(b"\xff\xd8\xff\xe0 not really a jpeg")
    paths.insert(1, str(corrupt))
    paths.append(str(root / "missing.png"))
    return paths


@pytest.mark.parametrize("workers, whole_images", [(0, None), (2, True), (2, False)])
def test_pipeline_equals_in_process_and_keeps_order(folder, workers, whole_images):
    """In-process, whole images in workers (a CPU's default) and detection-only workers (a GPU's)."""
    est = FREstimator(mode="fast")
    reference = est.calibrate_images(folder)
    got = [(chunk, results) for chunk, results in calibrate_paths(est, folder, batch_size=2, workers=workers,
                                                                  whole_images=whole_images)]
    assert [p for chunk, _ in got for p in chunk] == folder
    results = [r for _, batch in got for r in batch]
    assert [r.image for r in results] == folder
    assert not results[1].ok and "corrupt.jpg" in results[1].reason
    assert not results[-1].ok and "no such file" in results[-1].reason
    for a, b in zip(results, reference):
        _same(a, b)
    assert all(r.ok for i, r in enumerate(results) if i not in (1, len(folder) - 1))


@pytest.fixture(scope="module")
def stream_frames(folder):
    """The folder as a stream (the first as an array), 4 times over: 20 frames, more than the 10 a
    stream with workers may read ahead; and their in-process results."""
    frames = [(cv2.imread(p) if i == 0 else p, f"frame{i}") for i, p in enumerate(folder)] * 4
    return frames, FREstimator(mode="fast").calibrate_images([f for f, _ in frames], names=[n for _, n in frames])


@pytest.mark.parametrize("workers, whole_frames", [(0, None), (2, True), (2, False)])
def test_stream_equals_in_process_and_reads_only_what_is_in_flight(stream_frames, workers, whole_frames):
    """A stream of frames (arrays and paths, a bad one among them): in-process, whole frames in
    workers (a CPU's default) and detection-only workers (a GPU's), in order, never read far ahead."""
    est = FREstimator(mode="fast")
    frames, reference = stream_frames
    read = []

    def source():
        for i, frame in enumerate(frames):
            read.append(i)
            yield frame

    results, ahead = [], 0
    for result in calibrate_stream(est, source(), batch_size=2, workers=workers, whole_frames=whole_frames):
        ahead = max(ahead, len(read) - len(results))
        results.append(result)
    assert [r.image for r in results] == [n for _, n in frames]
    for a, b in zip(results, reference):
        _same(a, b)
    assert ahead <= (2 if workers == 0 else 8 + 2) < len(frames)  # a batch; else the bounded queue + a batch


def test_a_path_and_its_decoded_array_give_the_same_estimate(tmp_path):
    """A colour JPEG calibrated from its path and from ``cv2.imread(path)`` (what ``fr eval`` and
    most users pass): the same grey image, so the same segments and estimate (a grey decode of the
    JPEG differs from BGR -> grey by a level here and there, and LSD follows)."""
    rng = np.random.default_rng(5)
    grey = render_manhattan_room(450.0, random_rotation(rng, pan=(-20, 20), pitch=(-10, 10), roll=(-5, 5)), 640, 480,
                                 seed=5)
    tint = np.clip(grey[..., None].astype(np.float64) * np.array([0.8, 1.0, 1.15]) + rng.normal(0, 6, grey.shape + (3,)),
                   0, 255).astype(np.uint8)
    path = tmp_path / "tinted.jpg"
    cv2.imwrite(str(path), tint, [cv2.IMWRITE_JPEG_QUALITY, 80])
    assert (cv2.imread(str(path), cv2.IMREAD_GRAYSCALE) != cv2.cvtColor(cv2.imread(str(path)), cv2.COLOR_BGR2GRAY)).any()
    est = FREstimator(mode="fast", reliability=None)
    by_path, by_array = est.calibrate_images([str(path), cv2.imread(str(path))], names=["a", "a"])
    assert by_path.ok and by_path.num_segments == by_array.num_segments
    assert np.array_equal(by_path.segments, by_array.segments)
    assert by_path.focal_px == by_array.focal_px


def test_sharded_segments_equal_in_process():
    est = FREstimator(mode="fast")
    rng = np.random.default_rng(0)
    segments = [synthetic_segments(500.0, random_rotation(rng), n_per_family=20, seed=i)[0] for i in range(5)]
    segments[2] = np.full((3, 4), np.nan)  # a bad set stays that set's failure
    sizes = [(640, 480)] * 5
    reference = est.calibrate_segments(segments, sizes)
    sharded = calibrate_segments_sharded(est, segments, sizes, workers=2)
    assert not sharded[2].ok
    for a, b in zip(sharded, reference):
        _same(a, b)


def test_calibrate_detections_works_in_input_pixels():
    """Detections carry working-pixel segments; the caller's focal / principal point and every
    result are in the input's pixels; a bad detection or camera fails only its own image."""
    est = FREstimator(mode="fast", working_long_side=640)
    rng = np.random.default_rng(5)
    big = render_manhattan_room(1000.0, random_rotation(rng, pan=(-25, 25), pitch=(-8, 8), roll=(-4, 4)),
                                1280, 960, seed=7)  # worked on at 640 x 480: scale 2
    images = [big, big, np.zeros((0, 0), np.uint8), big]
    names = ["known", "pp", "empty", "absurd"]
    detections = list(iter_detections(images, names, est.detector, est.segment_filter, working_long_side=640))
    assert detections[0].scale == pytest.approx(2.0) and detections[0].input_size == (1280, 960)
    results = est.calibrate_detections(detections, names, focal_px=[1000.0, None, None, 1e9],
                                       principal_point=[None, (650.0, 470.0), None, None])
    known, pp, empty, absurd = results
    assert (known.width, known.height) == (1280, 960) and known.focal_px == pytest.approx(1000.0)
    assert known.principal_point == (639.5, 479.5)  # the input's centre, exactly
    assert pp.ok and pp.principal_point == pytest.approx((650.0, 470.0))
    assert pp.focal_px == pytest.approx(1000.0, rel=0.1)
    assert not empty.ok and empty.reason
    assert not absurd.ok and "1e+09 px" in absurd.reason and "1280 x 960" in absurd.reason
    # The same as the one-call path, which goes through it.
    _same(pp, est.calibrate_images([big], names=["pp"], principal_point=(650.0, 470.0))[0])
    with pytest.raises(FRInputError):
        est.calibrate_detections(detections, names[:2])


class CrashingDetector(LSDDetector):
    """LSD, except that the process dies (as a native crash would) on a 123-pixel-wide image."""

    name = "tests.test_pipeline:CrashingDetector"  # workers rebuild it from this (the LSD object does not pickle)

    def __call__(self, gray):
        if gray.shape[1] == 123:
            os._exit(3)
        return super().__call__(gray)


@pytest.mark.parametrize("workers", [1, 2])
def test_worker_crash_fails_only_its_image(workers):
    """A worker dying on one image fails that image only; its chunk's other images and the rest of
    the folder are calibrated, in input order (CPU: whole-image workers, chunks of 2 here)."""
    est = FREstimator(mode="fast", detector=CrashingDetector())
    rng = np.random.default_rng(9)
    images = [render_manhattan_room(400.0, random_rotation(rng, pan=(-20, 20), pitch=(-8, 8), roll=(-4, 4)),
                                    320, 240, seed=i) for i in range(6)]
    images[3] = np.zeros((100, 123), np.uint8)
    names = [f"im{i}" for i in range(6)]
    results = [r for _, batch in calibrate_paths(est, images, batch_size=4, workers=workers, names=names)
               for r in batch]
    assert [r.image for r in results] == names
    assert not results[3].ok and "crashed" in results[3].reason and "im3" in results[3].reason
    assert all(r.ok for i, r in enumerate(results) if i != 3)
    detections = list(iter_detections(images, names, est.detector, est.segment_filter, workers=workers))
    assert detections[3].error and "crashed" in detections[3].error
    assert all(d.error is None and len(d.segments) for i, d in enumerate(detections) if i != 3)


class CrashingFilter(SegmentFilter):
    """The default segment filter, except that a worker process dies (as when the kernel kills it
    for memory) on a set of exactly 7 segments; in the test's own process it never crashes."""

    def many(self, segment_list, sizes):
        if multiprocessing.parent_process() is not None and any(len(s) == 7 for s in segment_list):
            os._exit(3)
        return super().many(segment_list, sizes)


def test_sharded_segments_survive_a_worker_crash():
    """A worker dying on one segment set fails that image only; the others come back as in process."""
    est = FREstimator(mode="fast", segment_filter=CrashingFilter())
    rng = np.random.default_rng(4)
    segments = [synthetic_segments(500.0, random_rotation(rng), n_per_family=20, seed=i)[0] for i in range(5)]
    segments[3] = segments[3][:7]
    sizes = [(640, 480)] * 5
    sharded = calibrate_segments_sharded(est, segments, sizes, workers=2, names=[f"s{i}" for i in range(5)])
    assert [r.image for r in sharded] == [f"s{i}" for i in range(5)]
    assert not sharded[3].ok and "crashed" in sharded[3].reason and "s3" in sharded[3].reason
    reference = est.calibrate_segments([s for i, s in enumerate(segments) if i != 3], sizes[:4],
                                       names=[f"s{i}" for i in range(5) if i != 3])
    for a, b in zip([r for i, r in enumerate(sharded) if i != 3], reference):
        _same(a, b)


def test_shutting_down_a_broken_pool_never_waits_for_a_worker():
    """A broken pool is joined after its workers are killed: a worker that is still alive (here one
    busy for minutes, as a worker that escaped the pool's own termination would wait forever) does
    not hang the shutdown."""
    import threading
    import time
    from concurrent.futures import ProcessPoolExecutor

    from fr_torch.runtime.pipeline import _shutdown
    from fr_torch.runtime.workers import context

    pool = ProcessPoolExecutor(1, mp_context=context())
    pool.submit(time.sleep, 0).result()  # the worker is up
    pool.submit(time.sleep, 300)
    time.sleep(0.5)  # ... and busy
    worker = next(iter(pool._processes.values()))
    stopped = threading.Event()
    threading.Thread(target=lambda: (_shutdown(pool, kill=True), stopped.set()), daemon=True).start()
    finished = stopped.wait(60)
    if not finished:
        worker.kill()  # lets the pool's threads end, so that this failure does not hang the interpreter's exit
    assert finished, "shutting down a broken pool waited for its worker"
    worker.join(10)
    assert not worker.is_alive()


def _crash_on_minus_one(chunk):
    """A pool task: item -1 kills its worker (as a native crash would); other items come back doubled."""
    if -1 in chunk:
        os._exit(3)
    return [2 * item for item in chunk]


def test_a_worker_started_while_the_pool_breaks_is_not_left_running(monkeypatch):
    """On Python < 3.14 a worker that ``submit`` is still starting while the pool's manager thread
    terminates the broken pool escapes that termination: it waits for work forever (a fresh-clone CI
    run hung joining one).  Here every worker start is slowed down, so the second worker starts after
    the first one's crash has been handled; the map must still finish, fail only the crashing item
    and leave no worker running."""
    import threading
    import time
    from concurrent.futures import process as futures_process

    from fr_torch.runtime.pipeline import ordered_pool_map

    started = {}
    spawn = futures_process.ProcessPoolExecutor._spawn_process

    def slow_spawn(pool):
        time.sleep(0.5)
        spawn(pool)
        started.update(pool._processes)

    monkeypatch.setattr(futures_process.ProcessPoolExecutor, "_spawn_process", slow_spawn)
    out = {}
    worker = threading.Thread(target=lambda: out.update(results=list(ordered_pool_map(
        _crash_on_minus_one, [-1, 1, 2], chunk_size=1, workers=2, initializer=None, initargs=(),
        on_crash=lambda item: f"crashed on {item}"))), daemon=True)
    worker.start()
    worker.join(120)
    for process in started.values():  # the last pool's workers stop on their own, right after the map
        process.join(10)
    running = [p for p in started.values() if p.is_alive()]
    for process in running:  # so that a failure here does not hang the interpreter's exit
        process.kill()
    assert out.get("results") == ["crashed on -1", 2, 4]
    assert not running, f"{len(running)} worker(s) left running"


def test_device_policy_defaults():
    """Worker and batch defaults follow from the device and the usable cores (no GPU needed: a
    CUDA policy is built by hand)."""
    import torch

    from fr_torch.runtime import device as device_module
    from fr_torch.runtime.device import DevicePolicy

    cpu, gpu = DevicePolicy(torch.device("cpu"), 16), DevicePolicy(torch.device("cuda", 0), 16)
    assert cpu.default_workers(1000) == device_module.MAX_DEFAULT_WORKERS
    assert cpu.default_workers(100) == 3  # one per 32 images
    assert cpu.default_workers(40) == 0  # a pool does not pay
    assert gpu.default_workers(100) == 15  # detection on every other core, for the device
    assert gpu.default_workers(1) == 0
    assert DevicePolicy(torch.device("cuda", 0), 64).default_workers(10_000) == device_module.MAX_DEFAULT_DETECTION_WORKERS
    assert DevicePolicy(torch.device("cpu"), 1).default_workers(1000) == 0
    assert DevicePolicy(torch.device("cuda", 0), 1).default_workers(1000) == 0
    assert cpu.default_batch_size == 16 and gpu.default_batch_size == 256
    assert cpu.whole_image_workers and not gpu.whole_image_workers
    assert DevicePolicy.resolve("cpu").device == torch.device("cpu") and DevicePolicy.resolve(cpu) is cpu
    assert DevicePolicy.parse("cuda:1").device == torch.device("cuda", 1)  # planning for a remote node
    with pytest.raises(ValueError, match="unknown device"):
        DevicePolicy.parse("tpu-9")


def test_cgroup_cpu_quota(tmp_path):
    """A container's CPU quota caps the cores the defaults count (cgroup v2 and v1 files)."""
    assert workers_module.cgroup_cpu_limit(tmp_path) is None  # no cgroup files
    (tmp_path / "cpu.max").write_text("max 100000\n")
    assert workers_module.cgroup_cpu_limit(tmp_path) is None
    (tmp_path / "cpu.max").write_text("250000 100000\n")
    assert workers_module.cgroup_cpu_limit(tmp_path) == pytest.approx(2.5)
    v1 = tmp_path / "v1"
    (v1 / "cpu").mkdir(parents=True)
    (v1 / "cpu" / "cpu.cfs_quota_us").write_text("-1\n")
    (v1 / "cpu" / "cpu.cfs_period_us").write_text("100000\n")
    assert workers_module.cgroup_cpu_limit(v1) is None
    (v1 / "cpu" / "cpu.cfs_quota_us").write_text("400000\n")
    assert workers_module.cgroup_cpu_limit(v1) == pytest.approx(4.0)
    assert 1 <= workers_module.usable_cores() <= (os.cpu_count() or 1)


def test_threads_fit_the_usable_cores(monkeypatch):
    import torch

    before, before_cv = torch.get_num_threads(), cv2.getNumThreads()
    from fr_torch.runtime.device import DevicePolicy

    try:
        DevicePolicy(torch.device("cpu"), 1).apply_threads()
        assert torch.get_num_threads() == 1 and cv2.getNumThreads() <= 1
    finally:
        torch.set_num_threads(before)
        cv2.setNumThreads(before_cv)


def test_importing_the_library_and_its_command_line_loads_no_torch():
    """``import fr_torch`` and ``fr_torch.cli`` are light, so ``fr`` can start its workers' server
    while it loads torch; the public names still load on use."""
    code = ("import sys, fr_torch, fr_torch.cli, fr_torch.runtime.workers; assert 'torch' not in sys.modules; "
            "from fr_torch import FREstimator, Camera; assert 'torch' in sys.modules; print(sorted(fr_torch.__all__))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert "FREstimator" in out.stdout


def test_what_workers_cannot_receive_is_a_one_line_error():
    class Local(LSDDetector):
        name = "no-such-detector"

    est = FREstimator(mode="fast", detector=Local())
    with pytest.raises(FRInputError, match="cannot be sent to worker processes"):
        list(calibrate_paths(est, [np.zeros((50, 50), np.uint8)] * 3, workers=2))
    est = FREstimator(mode="fast", reliability=None)
    est.reliability = lambda results, mode: None  # a user's object that does not pickle
    with pytest.raises(FRInputError, match="estimator cannot be sent to worker processes"):
        list(calibrate_paths(est, [np.zeros((50, 50), np.uint8)] * 3, workers=2))
