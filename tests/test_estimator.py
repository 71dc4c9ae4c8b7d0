"""End-to-end recovery of (f, R) from synthetic segments, batching, known focal, determinism."""
import numpy as np
import pytest
import torch

from fr_torch import FREstimator
from fr_torch.core.geometry.camera import Camera
from fr_torch.core.geometry.conventions import focal_from_hfov, horizon_angles, image_centre, rotation_from_angles
from fr_torch.core.geometry.horizon import Horizon
from fr_torch.core.reliability.cues import focal_conditioning
from fr_torch.core.reliability.sanity import LINE_BEND_CUES
from fr_torch.synthetic import synthetic_segments
from tests.conftest import gpu

# Cameras (hfov, pan, pitch, roll) inside the search box; 0.5 px endpoint noise, 30 % clutter.
CAMERAS = [(60.0, 20.0, 12.0, 4.0), (95.0, -33.0, -18.0, -7.0), (75.0, 8.0, 25.0, 9.0)]


def _scene(i, hfov, pan, pitch, roll):
    focal = focal_from_hfov(hfov, 640)
    R = rotation_from_angles(torch.tensor(pan, dtype=torch.float64), pitch, roll).numpy()
    segments, _ = synthetic_segments(focal, R, 640, 480, n_per_family=60, noise_px=0.5, clutter_fraction=0.3, seed=i)
    return segments, focal, R


@pytest.fixture(scope="module")
def scenes():
    return [_scene(i, *cam) for i, cam in enumerate(CAMERAS)]


@pytest.mark.parametrize("mode", ["fr", "fast"])
def test_recovers_synthetic_cameras(scenes, mode):
    results = FREstimator(mode=mode).calibrate_segments([s for s, _, _ in scenes], [(640, 480)] * len(scenes))
    for result, (_, focal, R) in zip(results, scenes):
        truth = horizon_angles(torch.as_tensor(R))
        assert result.ok and result.reliable, result.reason
        assert abs(result.focal_px - focal) / focal < 0.02
        assert abs(result.roll_deg - float(truth["roll_deg"])) < 0.3
        assert abs(result.tilt_deg - float(truth["tilt_deg"])) < 0.3
        assert result.horizon.error(Horizon.from_camera(Camera(640, 480, focal, None, R))) < 0.005
        assert np.allclose(result.rotation @ result.rotation.T, np.eye(3), atol=1e-6)
        assert result.labels.shape == (result.num_segments,)
        assert set(result.cues) == {"min_family_segments", "grid_entropy", "mean_log_likelihood",
                                    "focal_conditioning", "focal_prior_share", "focal_spread",
                                    "focal_profile_spread", "focal_resample_spread", "pitch_resample_spread"} | (
                                        {"focal_profile_gap"} if mode == "fr" else set()) | set(LINE_BEND_CUES)
        # reliable = the shipped promise: both bounds within their limits, the focal one far within
        assert result.error_bound["enforced"] and result.error_bound["focal_pct"] < 5.0
        assert result.error_bound["tilt_deg"] <= 3.0
        if mode == "fr":  # the segments single out the estimate's focal length: by hundreds of nats
            assert result.cues["focal_profile_gap"] > 100.0
        assert 0.0 <= result.cues["focal_prior_share"] < 0.2  # well-constrained views: the segments set f
        expected = float(focal_conditioning(torch.as_tensor(result.rotation)))
        assert result.cues["focal_conditioning"] == pytest.approx(expected, abs=1e-9)
        assert result.cues["min_family_segments"] >= 30


def test_batch_equals_one_by_one_and_is_deterministic(scenes):
    est = FREstimator(mode="fast")
    segments = [s for s, _, _ in scenes]
    batch = est.calibrate_segments(segments, [(640, 480)] * 3)
    for i, seg in enumerate(segments):
        [single] = est.calibrate_segments([seg], [(640, 480)])
        for key in ("focal_px", "roll_deg", "tilt_deg", "pan_deg", "log_likelihood"):
            assert getattr(batch[i], key) == pytest.approx(getattr(single, key), rel=1e-4, abs=1e-3)
    again = est.calibrate_segments(segments, [(640, 480)] * 3)
    assert all(a.focal_px == b.focal_px and np.array_equal(a.rotation, b.rotation) for a, b in zip(batch, again))


def test_hfov_search_range_is_configurable():
    """A zoomed-in camera (hfov 30 deg) lies outside the paper's [50, 130] range: that search stops at
    its edge (flagged unreliable); a user-given range recovers it.  The option works through the
    method spec."""
    from fr_torch.core.settings.config import SearchConfig
    from fr_torch.plugins.interface import get_calibrator

    segments, focal, R = _scene(7, 30.0, 10.0, 6.0, 3.0)
    paper = SearchConfig.from_config().with_fov_range("paper")
    [pinned] = FREstimator(mode="fr", search_config=paper).calibrate_segments([segments], [(640, 480)])
    assert pinned.hfov_deg >= 50.0 - 1e-6
    assert not pinned.reliable and "focal at the edge of the search range" in pinned.reason
    # fr mode: at this focal length (1194 px) Fast-fR's 10 steps stop ~7 % short of the optimum.
    narrow = FREstimator(mode="fr", search_config=SearchConfig.from_config(fov_range=(20.0, 60.0)))
    [result] = narrow.calibrate_segments([segments], [(640, 480)])
    # (tolerance 4 %: the default focal prior pulls clean synthetic scenes ~2.5 % wide)
    assert abs(result.focal_px - focal) / focal < 0.04 and abs(result.hfov_deg - 30.0) < 1.0, result.focal_px
    method = get_calibrator("fr[range=20:60]")
    assert method.name == "fr[range=20:60]"
    est = method.estimator.calibrate_segments([segments], [(640, 480)])[0]
    assert est.focal_px == pytest.approx(result.focal_px)
    with pytest.raises(ValueError, match="min < max"):
        SearchConfig.from_config(fov_range=(60.0, 20.0))
    with pytest.raises(ValueError, match="likelihood config"):
        FREstimator(likelihood="no-such-config")


def test_fast_mode_grid_scores_the_longest_segments(monkeypatch):
    """With ``grid_segments`` set, stage 1 scores each image's longest that many segments (0, all,
    by default in both modes' presets); the other stages always get every segment; negative counts
    are refused."""
    import fr_torch.core.estimator as estimator_module
    import fr_torch.core.search.grid as grid
    import fr_torch.core.search.manhattan as manhattan
    from fr_torch.core.settings.config import SearchConfig

    seen, searching = [], []
    original_score, original_search = grid.score_grid, manhattan.search_manhattan

    def record(model, features, *a, **k):  # stage 1's grids only (the cues' focal profile scores grids too)
        if searching:
            seen.append(features.weight.shape[1])
        return original_score(model, features, *a, **k)

    def search(*a, **k):
        searching.append(True)
        try:
            return original_search(*a, **k)
        finally:
            searching.pop()

    monkeypatch.setattr(grid, "score_grid", record)  # stage 1's grids are all scored in grid.py
    monkeypatch.setattr(estimator_module, "search_manhattan", search)
    segments, _, _ = _scene(3, 70.0, 10.0, 5.0, 2.0)  # 3 x 60 + 30 % clutter
    assert SearchConfig.from_config().resolve("fast").grid_segments == 0  # default: all
    config = SearchConfig.from_config(grid_segments=250)
    assert config.resolve("fast").grid_segments == 250 and config.resolve("fast").refine_iterations == 10
    FREstimator(mode="fast", search_config=config).calibrate_segments([segments], [(640, 480)])
    calls = len(seen)
    FREstimator(mode="fr").calibrate_segments([segments], [(640, 480)])
    assert calls and set(seen[:calls]) == {250}  # set: the longest 250
    assert len(seen) > calls and min(seen[calls:]) > 250  # default: all that the filter kept
    with pytest.raises(ValueError, match="grid_segments must be >= 0"):
        SearchConfig.from_config(grid_segments=-1)
    with pytest.raises(ValueError, match="unknown setting"):
        SearchConfig.from_config(grid_segments_fast=1)

def test_known_focal_searches_rotation_only(scenes):
    segments, focal, R = scenes[1]
    [result] = FREstimator(mode="fast").calibrate_segments([segments], [(640, 480)], focal_px=focal)
    truth = horizon_angles(torch.as_tensor(R))
    assert result.focal_px == pytest.approx(focal)
    assert abs(result.roll_deg - float(truth["roll_deg"])) < 0.3
    assert abs(result.tilt_deg - float(truth["tilt_deg"])) < 0.3


def test_float32_matches_float64_reference(scenes):
    segments = [scenes[0][0]]
    a = FREstimator(mode="fast", dtype=torch.float32).calibrate_segments(segments, [(640, 480)])[0]
    b = FREstimator(mode="fast", dtype=torch.float64).calibrate_segments(segments, [(640, 480)])[0]
    assert a.log_likelihood == pytest.approx(b.log_likelihood, rel=1e-4)
    assert a.focal_px == pytest.approx(b.focal_px, rel=1e-3)
    assert a.roll_deg == pytest.approx(b.roll_deg, abs=0.02)


@gpu
def test_cuda_equals_cpu(scenes):
    segments = [s for s, _, _ in scenes]
    cpu = FREstimator(mode="fast").calibrate_segments(segments, [(640, 480)] * 3)
    cuda = FREstimator(mode="fast", device="cuda").calibrate_segments(segments, [(640, 480)] * 3)
    for a, b in zip(cpu, cuda):
        assert a.focal_px == pytest.approx(b.focal_px, rel=1e-4)
        assert a.log_likelihood == pytest.approx(b.log_likelihood, rel=1e-4)


def test_focal_conditioning_geometry():
    """0 when every VP is on the principal point or at infinity, sqrt(1/2) for two horizontal VPs at
    45 deg, independent of column order and sign; batched over leading dimensions."""
    def rot(pan_deg=0.0, pitch_deg=0.0):
        return rotation_from_angles(pan_deg, pitch_deg, 0.0)

    assert float(focal_conditioning(torch.eye(3, dtype=torch.float64))) == pytest.approx(0.0, abs=1e-12)
    assert float(focal_conditioning(rot(pan_deg=45.0))) == pytest.approx(0.5 ** 0.5, abs=1e-9)
    # a camera panned square to a wall and pitched 1 deg: nearly degenerate
    assert float(focal_conditioning(rot(pitch_deg=1.0))) < 0.03
    R = rot(pan_deg=30.0, pitch_deg=-12.0)
    value = float(focal_conditioning(R))
    assert 0.3 < value <= 3 ** 0.5 / 2
    shuffled = R[:, [2, 0, 1]] * torch.tensor([1.0, -1.0, -1.0], dtype=torch.float64)
    assert float(focal_conditioning(shuffled)) == pytest.approx(value, abs=1e-12)
    batch = torch.stack([torch.stack([R, torch.eye(3, dtype=torch.float64)])] * 2)  # (2, 2, 3, 3)
    out = focal_conditioning(batch)
    assert out.shape == (2, 2) and float(out[1, 0]) == pytest.approx(value) and float(out[1, 1]) == 0.0


def test_focal_prior_share_says_when_the_prior_sets_f():
    """A view with finite, well-spread VPs has its f set by the segments (share near 0); a camera
    square to a wall (one horizontal VP on the principal point, the others at infinity) leaves f to
    the prior (share near 1); without a prior, or with the focal length given, the share is 0.
    The cue matches a direct evaluation of :func:`fr_torch.core.reliability.cues.focal_prior_share`."""
    from dataclasses import replace

    from fr_torch.core.likelihood.mixture import MixtureLikelihood
    from fr_torch.core.reliability.cues import focal_prior_share

    focal = focal_from_hfov(70.0, 640)
    views = {"oblique": rotation_from_angles(torch.tensor(30.0, dtype=torch.float64), 15.0, 3.0).numpy(),
             "square to a wall": rotation_from_angles(torch.tensor(0.0, dtype=torch.float64), 0.0, 0.0).numpy()}
    segments = [synthetic_segments(focal, R, 640, 480, n_per_family=60, noise_px=0.5, clutter_fraction=0.2,
                                   seed=3)[0] for R in views.values()]
    est = FREstimator(mode="fast", reliability=None)
    oblique, square = est.calibrate_segments(segments, [(640, 480)] * 2)
    assert oblique.cues["focal_prior_share"] < 0.1
    assert square.cues["focal_prior_share"] > 0.5
    # the objective peaks sharply along f for the oblique view, hardly for the one square to a wall
    assert 0.0 < oblique.cues["focal_spread"] < square.cues["focal_spread"] / 3
    [given] = est.calibrate_segments(segments[:1], [(640, 480)], focal_px=focal)
    assert given.cues["focal_prior_share"] == 0.0 and given.cues["focal_spread"] == 0.0

    from fr_torch.core.geometry.params import angles_from_search_rotation
    from fr_torch.core.likelihood.measures import SegmentFeatures
    from fr_torch.core.likelihood.segments import SegmentBatch

    batch = SegmentBatch.from_list([oblique.segments], [(640, 480)])
    features = SegmentFeatures.from_batch(batch, torch.tensor([image_centre(640, 480)]))
    angles = angles_from_search_rotation(torch.as_tensor(oblique.rotation)[None])
    params = torch.cat([angles, torch.tensor([[oblique.focal_px]], dtype=torch.float64)], -1)
    direct = focal_prior_share(est.likelihood, features, params)
    assert float(direct[0]) == pytest.approx(oblique.cues["focal_prior_share"], rel=1e-6, abs=1e-9)
    no_prior = MixtureLikelihood(replace(est.likelihood.params, focal_prior_weight=0.0))
    assert float(focal_prior_share(no_prior, features, params)[0]) == 0.0
    # a flat-topped prior whose band holds the estimate sets none of f there
    flat = MixtureLikelihood(replace(est.likelihood.params, focal_prior_hfov_deg=oblique.hfov_deg,
                                     focal_prior_flat_halfwidth=0.3))
    assert float(focal_prior_share(flat, features, params)[0]) == 0.0


def _oblique_and_square():
    """(f, [R oblique, R square to a wall], their segments): a 70-degree camera panned 30 deg and pitched 15,
    and one looking square at a wall (its vanishing points at the centre and at infinity)."""
    focal = focal_from_hfov(70.0, 640)
    views = [rotation_from_angles(torch.tensor(30.0, dtype=torch.float64), 15.0, 3.0).numpy(),
             rotation_from_angles(torch.tensor(0.0, dtype=torch.float64), 0.0, 0.0).numpy()]
    segments = [synthetic_segments(focal, R, 640, 480, n_per_family=60, noise_px=0.5, clutter_fraction=0.2,
                                   seed=3)[0] for R in views]
    return focal, views, segments


def test_focal_profile_gap_sign_and_scale(monkeypatch):
    """``focal_profile_gap``: large at a well-determined estimate, small where the lines say little
    about f (camera square to a wall), negative at an estimate a clearly different focal length
    beats, 0 for a given focal length (fR only; Fast-fR does not compute it)."""
    from fr_torch.core.geometry.params import angles_from_search_rotation
    from fr_torch.core.geometry.params import rotations as hypothesis_rotations
    from fr_torch.core.likelihood.measures import SegmentFeatures
    from fr_torch.core.likelihood.segments import SegmentBatch
    from fr_torch.core.reliability.cues import focal_profile_gap

    focal, views, segments = _oblique_and_square()
    est = FREstimator(mode="fr", reliability=None, profile_gap=True)
    oblique, square = est.calibrate_segments(segments, [(640, 480)] * 2)
    assert oblique.cues["focal_profile_gap"] > 300.0 > abs(square.cues["focal_profile_gap"])
    [given] = est.calibrate_segments(segments[:1], [(640, 480)], focal_px=focal)
    assert given.cues["focal_profile_gap"] == 0.0
    [fast] = FREstimator(mode="fast", reliability=None).calibrate_segments(segments[:1], [(640, 480)])
    assert "focal_profile_gap" not in fast.cues

    # An estimate 40 % too long, scored where it is: the profile at 0.7 x finds the true basin.
    features = SegmentFeatures.from_batch(SegmentBatch.from_list([oblique.segments], [(640, 480)]),
                                          torch.tensor([image_centre(640, 480)]))
    angles = angles_from_search_rotation(torch.as_tensor(oblique.rotation)[None])
    wrong = torch.cat([angles, torch.tensor([[1.4 * oblique.focal_px]], dtype=torch.float64)], -1)
    wrong_score = est.likelihood.objective(features, hypothesis_rotations(wrong)[:, None].float(),
                                           wrong[:, None, 3].float())[:, 0]
    gap = focal_profile_gap(est.likelihood, features, wrong, wrong_score, est.search, 10)
    assert gap.shape == (1,) and float(gap[0]) < -300.0
    right = focal_profile_gap(est.likelihood, features, torch.cat([angles, torch.tensor([[oblique.focal_px]],
                              dtype=torch.float64)], -1), torch.tensor([oblique.log_likelihood]), est.search, 10)
    assert float(right[0]) == pytest.approx(oblique.cues["focal_profile_gap"], rel=1e-4)
    # profiled in slices of images (bounded copies): the same gaps as one slice
    both = SegmentFeatures.from_batch(SegmentBatch.from_list([oblique.segments] * 2, [(640, 480)] * 2),
                                      torch.tensor([image_centre(640, 480)] * 2))
    args = (est.likelihood, both, wrong.expand(2, 4), wrong_score.expand(2), est.search, 10)
    together = focal_profile_gap(*args)
    monkeypatch.setattr("fr_torch.core.reliability.cues.PROFILE_CHUNK_IMAGES", 1)
    torch.testing.assert_close(focal_profile_gap(*args), together)
    assert float(together[0]) == pytest.approx(float(gap[0]), rel=1e-4)
    # only focal lengths inside the range are searched: an estimate at the wide edge (ratios < 1 out)
    # batched with one in the middle gives each the gap it gets alone; none inside -> 0
    edge = wrong.clone()
    edge[0, 3] = focal_from_hfov(est.search.fov_range.max_deg, 640)
    edge_score = est.likelihood.objective(features, hypothesis_rotations(edge)[:, None].float(),
                                          edge[:, None, 3].float())[:, 0]
    alone = focal_profile_gap(est.likelihood, features, edge, edge_score, est.search, 10)
    mixed = focal_profile_gap(est.likelihood, both, torch.cat([edge, wrong]), torch.cat([edge_score, wrong_score]),
                              est.search, 10)
    torch.testing.assert_close(mixed, torch.cat([alone, gap]))
    narrow = est.search.with_fov_range((66.0, 68.0))  # f x 0.7 and x 0.8 give 71.1 and 64.0 deg
    assert float(focal_profile_gap(est.likelihood, features, wrong, wrong_score, narrow, 10)[0]) == 0.0


def test_profile_gap_follows_the_reliability_model():
    """The gap costs a quarter of fR's time: computed when the reliability model uses it (fR's
    shipped model) or when asked, skipped with reliability off; turning it off under a model that
    needs it is a one-line error."""
    from fr_torch.errors import FRInputError

    segments = [synthetic_segments(500.0, rotation_from_angles(torch.tensor(30.0, dtype=torch.float64), 15.0,
                                                               3.0).numpy(), 640, 480, seed=4)[0]]
    [plain] = FREstimator(mode="fr", reliability=None).calibrate_segments(segments, [(640, 480)])
    assert "focal_profile_gap" not in plain.cues and plain.predicted_error is None
    [shipped] = FREstimator(mode="fr").calibrate_segments(segments, [(640, 480)])
    assert shipped.cues["focal_profile_gap"] > 100.0 and shipped.predicted_error is not None
    assert plain.focal_px == pytest.approx(shipped.focal_px, rel=1e-9)
    with pytest.raises(FRInputError, match="focal_profile_gap"):
        FREstimator(mode="fr", profile_gap=False)
    assert FREstimator(mode="fast", profile_gap=False).profile_gap is False


def test_spread_cues_measure_how_well_the_segments_fix_the_camera():
    """The spreads the bounds of `reliable` rest on: small where the segments pin f down, large where
    they leave it to the prior (a camera square to a wall), at their maximum at an estimate a nearby
    focal length beats; a given focal length has no focal spread but a pitch spread; computed when
    the reliability stage holds a promise or when asked, skipped otherwise."""
    from fr_torch.core.geometry.params import angles_from_search_rotation
    from fr_torch.core.likelihood.measures import SegmentFeatures
    from fr_torch.core.likelihood.segments import SegmentBatch
    from fr_torch.core.reliability.cues import MAX_SPREAD, SPREAD_FOCAL_RATIOS, focal_profile, focal_profile_spread

    focal, views, segments = _oblique_and_square()
    est = FREstimator(mode="fast", reliability=None, spreads=True)
    oblique, square = est.calibrate_segments(segments, [(640, 480)] * 2)
    names = ("focal_profile_spread", "focal_resample_spread", "pitch_resample_spread")
    assert all(0.0 < oblique.cues[n] < 0.05 for n in names[:2]) and 0.0 < oblique.cues[names[2]] < 0.5
    assert square.cues["focal_profile_spread"] > 5 * oblique.cues["focal_profile_spread"]
    [given] = est.calibrate_segments(segments[:1], [(640, 480)], focal_px=focal)
    assert given.cues["focal_profile_spread"] == given.cues["focal_resample_spread"] == 0.0
    assert 0.0 < given.cues["pitch_resample_spread"] < 0.5
    [plain] = FREstimator(mode="fast", reliability=None).calibrate_segments(segments[:1], [(640, 480)])
    assert not set(names) & set(plain.cues) and plain.focal_px == pytest.approx(oblique.focal_px, rel=1e-9)
    # at an estimate 40 % too long, f x 0.87 explains the segments better: no spread says it is right
    features = SegmentFeatures.from_batch(SegmentBatch.from_list([segments[0]], [(640, 480)]),
                                          torch.tensor([image_centre(640, 480)]))
    wrong = torch.cat([angles_from_search_rotation(torch.as_tensor(views[0])[None]),
                       torch.tensor([[1.4 * focal]], dtype=torch.float64)], -1)
    profile = focal_profile(est.likelihood, features, wrong, est.search, 10, SPREAD_FOCAL_RATIOS)
    assert float(focal_profile_spread(est.likelihood, features, wrong, est.search, profile)[0]) == MAX_SPREAD
