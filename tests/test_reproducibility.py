"""One photo, one answer: the same bits in any batch, thread count, CPU kernel set and CPU (its maths
libraries' dispatch), and run after run on a GPU (fr_torch.core.exact, fr_torch.core.exact_math;
results/reproducibility/ measures it on the datasets)."""
import json
import os

import numpy as np
import pytest
import torch

from fr_torch import FREstimator
from fr_torch.core import exact, exact_math
from fr_torch.core.geometry.conventions import rotation_from_angles
from fr_torch.core.search.passes import best_of_start_and_refined, different_solutions, first_near_best
from fr_torch.runtime.device import DevicePolicy
from fr_torch.synthetic import random_rotation, synthetic_segments
from tests.conftest import cpu_kernel_sets, fresh_process_records, gpu


def _photos():
    """Photos of different sizes, segment counts and orientations (portrait among them)."""
    rng = np.random.default_rng(7)
    photos = []
    for i, (width, height, focal, count) in enumerate([(640, 480, 500.0, 40), (480, 640, 420.0, 25),
                                                       (1024, 768, 900.0, 60), (320, 240, 260.0, 15)]):
        segments, _ = synthetic_segments(focal, random_rotation(rng, pan=(-30, 30), pitch=(-15, 15), roll=(-8, 8)),
                                         width, height, n_per_family=count, noise_px=0.5, clutter_fraction=0.2,
                                         seed=i)
        photos.append((segments, (width, height)))
    return photos


def _record(result) -> dict:
    """Every number of a result that must not move (JSON round trip: floats exactly)."""
    return json.loads(json.dumps({key: value for key, value in result.to_json().items() if key != "runtime_s"}))


@pytest.fixture(scope="module")
def estimator():
    return FREstimator(mode="fast")


@pytest.fixture(scope="module")
def reference(estimator):
    photos = _photos()
    return [_record(r) for r in estimator.calibrate_segments([p[0] for p in photos], [p[1] for p in photos])]


@pytest.fixture(scope="module")
def fr_reference():
    photos = _photos()[:2]
    return [_record(r) for r in FREstimator(mode="fr").calibrate_segments([p[0] for p in photos],
                                                                           [p[1] for p in photos])]


@pytest.mark.parametrize("op", [exact_math.exp, exact_math.log, exact_math.atan, exact_math.sin, exact_math.cos,
                                exact_math.sqrt])
def test_the_functions_the_search_uses_round_alike_everywhere_in_a_tensor(op):
    """The premise of fr_torch.core.exact: these functions give an element the same bits wherever it
    sits (vector body or scalar tail of a kernel, any thread's share); torch's atan2 does not."""
    x = torch.rand(1 << 16, dtype=torch.float32) * 5 + 1e-3
    whole = op(x)
    for offset in (1, 3, 17, 1000):
        assert torch.equal(op(x[offset:]), whole[offset:])
        assert torch.equal(op(x[offset:offset + 37]), whole[offset:offset + 37])
    spread = torch.zeros(2 * len(x))
    spread[::2] = x
    assert torch.equal(op(spread[::2]), whole)  # strided: the scalar loop


def test_exact_sum_is_independent_of_order_padding_and_chunks():
    torch.manual_seed(0)
    x = torch.randn(3, 500, 40) * torch.logspace(-3, 3, 40)
    total = exact.exact_sum(x, 1)
    assert torch.equal(exact.exact_sum(x[:, torch.randperm(500)], 1), total)
    assert torch.equal(exact.exact_sum(torch.cat([x, torch.zeros(3, 77, 40)], 1), 1), total)
    assert torch.equal(exact.exact_sum(x[1:2], 1), total[1:2])
    assert torch.allclose(total, x.double().sum(1), rtol=1e-6, atol=1e-6)  # float32 terms: their own precision
    w = torch.rand(3, 500)
    bound = (w.amax(1) * x.abs().amax((1, 2)))[:, None, None]
    weighted = exact.exact_sum(x, 1, bound=bound, weight=w[..., None])
    assert torch.equal(exact.exact_sum(x[:, :250], 1, bound, weight=w[:, :250, None])
                       + exact.exact_sum(x[:, 250:], 1, bound, weight=w[:, 250:, None]), weighted)
    x64 = x.double() * (1 + 1e-9 * torch.rand_like(x.double()))
    assert torch.allclose(exact.exact_sum(x64, 1), x64.sum(1), rtol=1e-14, atol=1e-12)  # float64 precision kept
    grad_input = x64.clone().requires_grad_(True)
    (exact.exact_sum(grad_input, 1) * 2).sum().backward()
    assert torch.equal(grad_input.grad, torch.full_like(x64, 2.0))
    assert torch.isnan(exact.exact_sum(torch.tensor([1.0, float("nan")]), 0))


def test_exact_index_sum_and_the_angle():
    torch.manual_seed(1)
    values, index = torch.randn(1000, 3), torch.randint(0, 7, (1000,))
    total = exact.exact_index_sum(values, index, 7)
    order = torch.randperm(1000)
    assert torch.equal(exact.exact_index_sum(values[order], index[order], 7), total)
    assert torch.allclose(total, torch.zeros(7, 3, dtype=torch.float64).index_add_(0, index, values.double()), atol=1e-5)
    s, t = torch.randn(10000), torch.randn(10000)
    assert torch.allclose(exact.angle_of(s, t), torch.atan2(s.abs(), t.abs()), atol=3e-7)
    assert torch.allclose(exact.atan2(s, t), torch.atan2(s, t), atol=3e-7)
    assert exact.angle_of(torch.zeros(1), torch.zeros(1)).item() == 0.0


def test_ties_go_to_the_earlier_candidate_and_two_answers_are_flagged():
    scores = torch.tensor([[1.0, 3.0, 3.0 + 1e-9, 2.0]], dtype=torch.float64)
    assert first_near_best(scores, torch.tensor([1e-6])).item() == 1
    assert first_near_best(scores, torch.tensor([0.0])).item() == 2
    a = torch.tensor([10.0, 5.0, 1.0, 500.0], dtype=torch.float64)
    assert not different_solutions(a, a + torch.tensor([89.9, 0.2, 0.0, 2.0], dtype=torch.float64))  # pan mod 90
    assert different_solutions(a, a * torch.tensor([1.0, 1.0, 1.0, 1.05], dtype=torch.float64))
    starts = a.expand(1, 2, 4)
    refined = torch.stack([a, a * torch.tensor([1.0, 1.0, 1.0, 1.2], dtype=torch.float64)])[None]
    _, _, tied = best_of_start_and_refined(starts, torch.tensor([[0.0, 0.0]]), refined,
                                           torch.tensor([[10.0, 10.0 - 1e-9]], dtype=torch.float64),
                                           torch.tensor([1e-6], dtype=torch.float64))
    assert tied.tolist() == [True]
    _, _, tied = best_of_start_and_refined(starts, torch.tensor([[0.0, 0.0]]), refined,
                                           torch.tensor([[10.0, 9.0]], dtype=torch.float64),
                                           torch.tensor([1e-6], dtype=torch.float64))
    assert tied.tolist() == [False]


def test_a_photo_gets_one_answer_alone_and_in_any_batch(estimator, reference):
    """Fuzz-style: each photo alone, twice in one mixed batch, in reverse order, with 1 and 2 threads."""
    photos = _photos()
    for i, (segments, size) in enumerate(photos):
        [alone] = estimator.calibrate_segments([segments], [size], names=[f"image{i}"])
        assert _record(alone) == reference[i]
    mixed = [photos[2], photos[0], photos[2], photos[3], photos[1]]
    got = estimator.calibrate_segments([p[0] for p in mixed], [p[1] for p in mixed])
    for result, j in zip(got, (2, 0, 2, 3, 1)):
        record = _record(result)
        assert dict(record, image=None) == dict(reference[j], image=None)
    threads = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        one_thread = estimator.calibrate_segments([p[0] for p in photos], [p[1] for p in photos])
    finally:
        torch.set_num_threads(threads)
    assert [_record(r) for r in one_thread] == reference


def test_the_search_takes_one_path_at_every_thread_count(monkeypatch):
    """``FR_THREADS=auto`` gives every search call the threads the load leaves it, so a command's
    thread count changes with the load, call by call: the search must cut its work into the same
    chunks at 1 and 2 threads (results/decisions/60.md), not only give the same bits."""
    from fr_torch.core.likelihood.mixture import MixtureLikelihood

    chunks = []
    objective = MixtureLikelihood.objective

    def recording(self, features, rotation, focal, *args, **kwargs):
        chunks.append((tuple(features.weight.shape), tuple(rotation.shape[:2])))
        return objective(self, features, rotation, focal, *args, **kwargs)

    monkeypatch.setattr(MixtureLikelihood, "objective", recording)
    estimator = FREstimator(mode="fast", device=DevicePolicy.resolve("cpu", threads="torch"))  # torch's count
    photos = _photos()
    paths, records = {}, {}
    threads = torch.get_num_threads()
    try:
        for count in (1, 2):
            torch.set_num_threads(count)
            chunks.clear()
            results = estimator.calibrate_segments([p[0] for p in photos], [p[1] for p in photos])
            paths[count], records[count] = list(chunks), [_record(r) for r in results]
    finally:
        torch.set_num_threads(threads)
    assert paths[1], "the grid was not scored through MixtureLikelihood.objective"
    assert paths[2] == paths[1]
    assert records[2] == records[1]


@pytest.mark.parametrize("kernels", cpu_kernel_sets())
def test_every_cpu_kernel_set_gives_the_same_bits(reference, fr_reference, kernels):
    """The photos searched in a process with another ATEN_CPU_CAPABILITY, and with the maths libraries
    pinned to what an older CPU runs (tests/conftest.py, EMULATED_CPUS: oneMKL's COMPATIBLE or AVX2
    branch, numpy without AVX-512 or AVX2): bit for bit the same records in both modes (CI machines
    differ in their CPUs; this is what a new one must reproduce)."""
    records = fresh_process_records(kernels)
    assert records["photos"] == reference
    assert records["fr_photos"] == fr_reference


def test_the_mkl_branch_is_named():
    """oneMKL picks its code branch by CPU, and its branches round torch's ``exp`` / ``log`` / ``atan``
    ... differently; the search takes those from fr_torch.core.exact_math, and the machine record
    names the branch (the pinned one where ``MKL_CBWR`` pins it) so that any difference left
    elsewhere can be traced."""
    import subprocess
    import sys

    from fr_torch.core.likelihood.native import MKL_BRANCHES, mkl_branch

    here = mkl_branch()
    assert here is None or here in MKL_BRANCHES.values()
    if here is not None:
        code = "from fr_torch.core.likelihood.native import mkl_branch; print(mkl_branch())"
        pinned = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                                env={**os.environ, "MKL_CBWR": "COMPATIBLE"}).stdout.strip()
        assert pinned == "COMPATIBLE"


def test_the_torch_path_gives_the_fused_kernels_bits(reference, fr_reference):
    """FR_NATIVE=0, what a machine without a C compiler runs: the torch path of every score and
    gradient (with oneMKL on its COMPATIBLE branch), bit for bit the records of this process (whose
    fused kernels of fr_torch.core.likelihood.native run when this machine can build them)."""
    torch_path = fresh_process_records("torch-path")
    assert not torch_path["native"]
    assert torch_path["photos"] == reference
    assert torch_path["fr_photos"] == fr_reference


def test_the_fused_kernels_check_themselves_against_the_torch_path():
    """Where the kernels build (a C compiler), their first-use check passed; the
    grid's scores and the refinement's gradient equal the torch path's on a scene bit for bit."""
    from fr_torch.core.geometry.conventions import image_centre, vanishing_points
    from fr_torch.core.geometry.params import rotations
    from fr_torch.core.likelihood.measures import SegmentFeatures
    from fr_torch.core.likelihood.mixture import MixtureLikelihood, kernels_match_torch, native
    from fr_torch.core.likelihood.objective import measure_b_objective_and_grad, objective_b_nograd, vp_major

    if not native.available():
        pytest.skip(f"fused kernels unavailable here ({native._state.get('error', 'FR_NATIVE=0')})")
    assert kernels_match_torch()
    segments, size = _photos()[0]
    features = SegmentFeatures.from_endpoints(torch.as_tensor(segments, dtype=torch.float32)[None], None,
                                              torch.tensor([image_centre(*size)]))
    generator = torch.Generator().manual_seed(3)
    params = torch.cat([torch.rand(1, 96, 3, generator=generator) * 90 - 45,
                        200 + 800 * torch.rand(1, 96, 1, generator=generator)], -1)
    flat = vp_major(vanishing_points(params[..., 3], features.principal_point[:, None], rotations(params)))
    constants = MixtureLikelihood()._b_constants(features.weight)
    args = (features.line_along, features.weight, flat)
    for block in (1, 3):
        assert torch.equal(objective_b_nograd(*args, *constants, vertical_block=block),
                           objective_b_nograd(*args, *constants, vertical_block=block, fused=False))
    grad_out = torch.tensor([[-1e-3]])
    for fused, torch_path in zip(measure_b_objective_and_grad(*args, constants, grad_out),
                                 measure_b_objective_and_grad(*args, constants, grad_out, fused=False)):
        assert torch.equal(fused, torch_path)


def test_the_fused_refinement_reproduces_the_torch_loop():
    """Where the kernels build, fR's 100-step refinement of a photo's starts runs as one kernel call
    (fr_torch.core.search.refine.refine_fused) whose answer is the torch loop's bit for bit, alone
    and in a batch split over two threads."""
    from fr_torch.core.geometry.conventions import image_centre
    from fr_torch.core.likelihood.measures import SegmentFeatures
    from fr_torch.core.likelihood.mixture import LikelihoodParams, MixtureLikelihood, native
    from fr_torch.core.search.refine import _refine_slice, refine_kernel_matches_torch

    if not native.available():
        pytest.skip(f"fused kernels unavailable here ({native._state.get('error', 'FR_NATIVE=0')})")
    assert native.available("refine")  # its first-use check passed
    assert refine_kernel_matches_torch()
    segments, size = _photos()[0]
    features = SegmentFeatures.from_endpoints(torch.as_tensor(segments, dtype=torch.float32)[None], None,
                                              torch.tensor([image_centre(*size)]))
    likelihood = MixtureLikelihood(LikelihoodParams(focal_prior_weight=0.3, focal_prior_flat_halfwidth=0.2))
    generator = torch.Generator().manual_seed(66)
    lower, upper = torch.tensor([[0.0, -45.0, -45.0, 150.0]]), torch.tensor([[90.0, 45.0, 45.0, 1500.0]])
    starts = lower[:, None] + torch.rand(1, 8, 4, generator=generator) * (upper - lower)[:, None]
    expected = _refine_slice(likelihood, features, starts, lower, upper, 100, False, periodic_pan=True, fused=False)
    got = _refine_slice(likelihood, features, starts, lower, upper, 100, False, periodic_pan=True)
    assert all(torch.equal(a, b) for a, b in zip(expected, got))
    twice = features.take_images(torch.tensor([0, 0]))
    threads = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        batch = _refine_slice(likelihood, twice, starts.repeat(2, 1, 1), lower.repeat(2, 1), upper.repeat(2, 1), 100,
                              False, periodic_pan=True)
    finally:
        torch.set_num_threads(threads)
    assert all(torch.equal(a[0], b[0]) and torch.equal(a[0], b[1]) for a, b in zip(expected, batch))


def test_the_fused_division_refinement_reproduces_the_torch_loop():
    """Where the kernels build, fR's 100-step refinement with the division model's k (each start's
    segments undistorted with its own k, the prior on k) runs as one kernel call whose answer is the
    torch loop's bit for bit: a bent photo alone on one and on two threads, and twice in a batch
    split over two threads."""
    from fr_torch.core.geometry.conventions import image_centre
    from fr_torch.core.likelihood.measures import SegmentFeatures
    from fr_torch.core.likelihood.mixture import LikelihoodParams, MixtureLikelihood, native
    from fr_torch.core.search.lens import SegmentGeometry
    from fr_torch.core.search.refine import _refine_slice, refine_kernel_matches_torch
    from fr_torch.synthetic import distorted_segments

    if not native.available():
        pytest.skip(f"fused kernels unavailable here ({native._state.get('error', 'FR_NATIVE=0')})")
    assert native.available("refine_lens")  # its first-use check passed
    assert refine_kernel_matches_torch(SegmentGeometry.from_features)
    rng = np.random.default_rng(66)
    segments, labels = synthetic_segments(450.0, random_rotation(rng, pan=(-30, 30), pitch=(-15, 15), roll=(-8, 8)),
                                          seed=66)
    segments, _ = distorted_segments(segments, labels, -0.3, 640, 480)
    endpoints, size = torch.as_tensor(segments, dtype=torch.float32)[None], torch.tensor([[640.0, 480.0]])
    features = SegmentFeatures.from_endpoints(endpoints, None, torch.tensor([image_centre(640, 480)]))
    likelihood = MixtureLikelihood(LikelihoodParams(focal_prior_weight=0.3, focal_prior_flat_halfwidth=0.2))
    generator = torch.Generator().manual_seed(66)
    lower = torch.tensor([[0.0, -45.0, -45.0, 150.0, -0.6]])
    upper = torch.tensor([[90.0, 45.0, 45.0, 1500.0, 0.2]])
    starts = lower[:, None] + torch.rand(1, 8, 5, generator=generator) * (upper - lower)[:, None]

    def refined(threads, images=1, fused=True):
        batch = features.take_images(torch.zeros(images, dtype=torch.long))
        geometry = SegmentGeometry.from_features(batch, endpoints.repeat(images, 1, 1), size.repeat(images, 1),
                                                 k_prior_weight=3.0)
        previous = torch.get_num_threads()
        torch.set_num_threads(threads)
        try:
            return _refine_slice(likelihood, batch, starts.repeat(images, 1, 1), lower.repeat(images, 1),
                                 upper.repeat(images, 1), 100, False, periodic_pan=True, geometry=geometry, fused=fused)
        finally:
            torch.set_num_threads(previous)

    expected = refined(1, fused=False)
    assert expected[0][..., 4].min() < -0.1  # the refinement found the bend
    for got in (refined(1), refined(2)):
        assert all(torch.equal(a, b) for a, b in zip(expected, got))
    batch = refined(2, images=2)
    assert all(torch.equal(a[0], b[0]) and torch.equal(a[0], b[1]) for a, b in zip(expected, batch))


@gpu
def test_gpu_runs_repeat_and_match_the_cpu(reference):
    """On a GPU: two runs give the same bits; the CPU's answers within 1e-4 relative, no other basin."""
    photos = _photos()
    device = FREstimator(mode="fast", device="cuda")
    first = device.calibrate_segments([p[0] for p in photos], [p[1] for p in photos])
    second = device.calibrate_segments([p[0] for p in photos], [p[1] for p in photos])
    assert [_record(r) for r in first] == [_record(r) for r in second]
    for result, cpu in zip(first, reference):
        assert result.focal_px == pytest.approx(cpu["focal_px"], rel=1e-4)
        assert np.allclose(result.rotation, cpu["rotation"], atol=1e-4)


def test_rotation_builder_is_exact_per_entry():
    """The VPs and rotations the search builds are the same bits for one hypothesis in any batch."""
    angles = torch.tensor([[10.0, 5.0, 2.0], [-20.0, 3.0, -1.0], [40.0, -30.0, 14.0]], dtype=torch.float64)
    whole = rotation_from_angles(angles[:, 0], angles[:, 1], angles[:, 2])
    assert torch.equal(rotation_from_angles(angles[1:, 0], angles[1:, 1], angles[1:, 2]), whole[1:])


def test_check_tables_holds_a_regenerated_table_to_its_tolerance():
    """eval/reproduce.sh --check: numbers within rtol pass, beyond it fail; timings are not compared."""
    import pandas as pd

    from fr_eval.protocols.check_tables import compare

    committed = pd.DataFrame({"method": ["fr", "fr"], "focal_err_pct": [3.25, 4.5], "runtime_s": [0.1, 0.2]})
    assert compare(committed, committed.assign(runtime_s=[9.0, 9.0]), 1e-6, 1e-9)[0]
    assert compare(committed, committed.assign(focal_err_pct=[3.25 * (1 + 1e-8), 4.5]), 1e-6, 1e-9)[0]
    assert not compare(committed, committed.assign(focal_err_pct=[3.26, 4.5]), 1e-6, 1e-9)[0]
    assert not compare(committed, committed.assign(method=["fr", "fast-fr"]), 1e-6, 1e-9)[0]


def test_check_tables_moves_are_counted_in_committed_standard_errors():
    """check_tables --moves: each summary mean's move in units of its committed SE; timings and
    unmoved means left out."""
    import pandas as pd

    from fr_eval.protocols.check_tables import standard_error_moves

    committed = pd.DataFrame({"method": ["fr", "fast-fr"], "focal_err_pct_mean": [3.0, 5.0],
                              "focal_err_pct_se": [0.5, 1.0], "runtime_s_mean": [0.1, 0.2], "runtime_s_se": [0.01, 0.01]})
    current = committed.assign(focal_err_pct_mean=[3.75, 5.0], runtime_s_mean=[9.0, 9.0])
    (move,) = standard_error_moves(committed, current)
    assert (move["method"], move["metric"], move["se_moved"]) == ("fr", "focal_err_pct", 1.5)
