"""Shared focal length across photos of one camera (fr_torch.runtime.shared_focal), on synthetic segments."""
import json
import math

import numpy as np
import pytest

from fr_torch import FREstimator
from fr_torch.errors import FRInputError
from fr_torch.runtime.shared_focal import (
    SharedFocalSettings,
    calibrate_shared,
    combine_profiles,
    log_ratio_grid,
)
from fr_torch.synthetic import random_rotation, synthetic_segments
from tests.conftest import ROOM_F

TRUE_F = 600.0


@pytest.fixture(scope="module")
def estimator():
    return FREstimator(mode="fast", reliability=None)


@pytest.fixture(scope="module")
def photos():
    rng = np.random.default_rng(0)
    return [synthetic_segments(TRUE_F, random_rotation(rng), seed=i, n_per_family=30)[0] for i in range(3)]


def test_shared_focal_of_three_photos(estimator, photos):
    shared = calibrate_shared(estimator, segments=photos, image_sizes=[(640, 480)] * 3, names=["a", "b", "c"])
    assert shared.ok and shared.images == shared.images_used == 3
    assert abs(shared.focal_px / TRUE_F - 1) < 0.02
    assert 0 < shared.predicted_error_pct < 10
    assert [r.image for r in shared.results] == ["a", "b", "c"]
    assert all(r.ok and r.focal_px == pytest.approx(shared.focal_px) for r in shared.results)
    record = json.dumps(shared.to_json(), allow_nan=False)
    assert "predicted_error_pct" in record


def test_bad_photos_do_not_drag(estimator, photos):
    clutter = np.random.default_rng(5).uniform(0, 480, (80, 4))  # not Manhattan
    empty = np.zeros((0, 4))
    shared = calibrate_shared(estimator, segments=photos + [clutter, empty], image_sizes=[(640, 480)] * 5)
    assert shared.ok and shared.images == 5 and shared.images_used == 4
    assert abs(shared.focal_px / TRUE_F - 1) < 0.02
    assert not shared.results[-1].ok and "no line segments" in shared.results[-1].reason


def test_group_of_one_and_of_none(estimator, photos):
    [alone] = estimator.calibrate_segments([photos[0]], [(640, 480)])
    one = calibrate_shared(estimator, segments=[photos[0]], image_sizes=[(640, 480)])
    assert one.ok and abs(one.focal_px / alone.focal_px - 1) < 0.02
    none = calibrate_shared(estimator, segments=[np.zeros((0, 4)), np.full((3, 4), np.nan)],
                            image_sizes=[(640, 480)] * 2)
    assert not none.ok and none.focal_px is None and "no photo" in none.reason
    assert [r.ok for r in none.results] == [False, False] and all(r.reason for r in none.results)
    assert json.dumps(none.to_json(), allow_nan=False)


def test_sizes_in_a_group(estimator, photos):
    # a copy at twice the resolution and a portrait photo share f / long side
    double = photos[1] * 2.0
    portrait = synthetic_segments(TRUE_F, random_rotation(np.random.default_rng(9)), 480, 640, seed=9,
                                  n_per_family=40)[0]
    shared = calibrate_shared(estimator, segments=[photos[0], double, portrait],
                              image_sizes=[(640, 480), (1280, 960), (480, 640)])
    assert shared.ok and abs(shared.focal_px / TRUE_F - 1) < 0.02
    assert shared.results[1].focal_px == pytest.approx(2 * shared.focal_px)
    with pytest.raises(FRInputError, match="aspect ratio"):
        calibrate_shared(estimator, segments=[photos[0], photos[1]], image_sizes=[(640, 480), (640, 360)])


def test_combination_is_robust():
    settings = SharedFocalSettings()
    grid = log_ratio_grid((30.0, 120.0), 48)
    truth = grid[20] + 0.3 * (grid[1] - grid[0])

    def peaked(centre, width=0.3):
        return -((grid - centre) / width) ** 2 * 1000.0  # objective units; W = 1000

    lengths = np.full(6, 1000.0)
    good = [peaked(truth) for _ in range(4)]
    flat = np.zeros(len(grid))  # a photo that does not constrain f
    wrong = peaked(grid[40], 0.05)  # a confidently wrong one
    out = combine_profiles(grid, np.array(good + [flat, wrong]), lengths, None, settings)
    assert abs(out.log_ratio - truth) < 0.01
    assert out.used.all()
    # without usable photos: nan, no exception; with only a prior: the prior's centre
    empty = combine_profiles(grid, np.full((2, len(grid)), -np.inf), np.zeros(2), None, settings)
    assert math.isnan(empty.log_ratio) and not empty.used.any()
    only_prior = combine_profiles(grid, np.full((1, len(grid)), -np.inf), np.zeros(1), None, settings,
                                  prior=(grid[10], 0.1))
    assert only_prior.log_ratio == pytest.approx(grid[10], abs=1e-6)
    # a photo predicted to be badly wrong weighs less
    weighted = combine_profiles(grid, np.array([peaked(grid[15]), peaked(grid[25])]), lengths[:2],
                                np.array([2.0, 40.0]), SharedFocalSettings(error_scale_pct=10.0))
    assert weighted.log_ratio < 0.5 * (grid[15] + grid[25])


def test_cli_shared_focal(tmp_path, capsys):
    import shutil
    from pathlib import Path

    from fr_torch.cli.main import main

    room = Path(__file__).resolve().parents[1] / "examples" / "room.png"  # rendered with f = ROOM_F
    paths = [str(shutil.copy(room, tmp_path / f"view{i}.png")) for i in range(2)]
    code = main(["calibrate", *paths, "--shared-focal", "--fast", "--no-reliability", "--workers", "0"])
    out = capsys.readouterr()
    assert code == 0, out.err
    records = [json.loads(line) for line in out.out.splitlines()]
    assert len(records) == 2 and records[0]["shared_focal"] == records[1]["shared_focal"]
    assert abs(records[0]["shared_focal"]["focal_px"] / ROOM_F - 1) < 0.04
    assert records[0]["focal_px"] == pytest.approx(records[1]["focal_px"])
    assert records[0]["focal_prior"] is None
    assert records[0]["shared_focal"]["principal_point"] is None  # two photos: too few to estimate it
    assert main(["calibrate", *paths, "--shared-focal", "--focal", "500"]) == 2


def test_batch_shared_focal_by(shared_focal_local_batch):
    """``fr batch --shared-focal-by`` on the local engine: checked in the fixture
    (:func:`tests.conftest.shared_focal_batch_on_local_engine`)."""
    manifest, options, table = shared_focal_local_batch
    assert len(table) == 4


def test_shared_principal_point(estimator):
    """Photos of a camera whose principal point is off the image centre: the group recovers it (and f);
    a given principal point or ``estimate_principal_point=False`` keeps the centre."""
    rng = np.random.default_rng(3)
    truth = (340.0, 228.0)  # 20 px right of and 12 px above the centre of 640 x 480
    photos = [synthetic_segments(TRUE_F, random_rotation(rng), seed=20 + i, n_per_family=40,
                                 principal_point=truth)[0] for i in range(6)]
    clutter = np.random.default_rng(8).uniform(0, 480, (150, 4))  # a non-Manhattan photo must not drag it
    shared = calibrate_shared(estimator, segments=photos + [clutter], image_sizes=[(640, 480)] * 7)
    assert shared.ok and shared.principal_point is not None
    assert np.hypot(*(np.subtract(shared.principal_point, truth))) < 6.0
    assert all(0 < s < 10.0 for s in shared.principal_point_sigma_px)  # a clear maximum: a finite 1-sigma (px)
    assert abs(shared.focal_px / TRUE_F - 1) < 0.02
    assert all(r.principal_point == pytest.approx(shared.principal_point) for r in shared.results if r.ok)
    assert json.loads(json.dumps(shared.to_json()))["principal_point"] == pytest.approx(list(shared.principal_point))
    given = calibrate_shared(estimator, segments=photos, image_sizes=[(640, 480)] * 6, principal_point=(320, 240))
    assert given.principal_point is None and given.results[0].principal_point == pytest.approx((320, 240))
    few = calibrate_shared(estimator, segments=photos[:3], image_sizes=[(640, 480)] * 3)
    assert few.principal_point is None  # fewer than SharedFocalSettings.pp_min_images photos


def test_batch_focal_prior(tmp_path):
    """fr batch --focal-prior: each photo without a known focal length is searched with the prior,
    the prior columns say which prior (or why none); with --focal it is a one-line usage error."""
    import shutil
    from pathlib import Path

    import pandas as pd

    from fr_torch.batch.jobs import run_batch
    from fr_torch.cli.main import main
    from fr_torch.runtime.focal_prior import parse_focal_prior

    room = Path(__file__).resolve().parents[1] / "examples" / "room.png"
    a, b = (shutil.copy(room, tmp_path / f"{name}.png") for name in ("a", "b"))
    manifest = tmp_path / "m.csv"
    pd.DataFrame({"image": [str(a), str(b), str(tmp_path / "missing.png")],
                  "focal_px": [None, 450.0, None]}).to_csv(manifest, index=False)
    options = {"estimator": {"mode": "fast"}, "principal_point": None, "focal_px": None, "reliability": False,
               "focal_prior": parse_focal_prior(f"{ROOM_F * 1.1:.1f},5")}
    summary = run_batch([str(manifest)], tmp_path / "out", options, progress=False)
    assert summary["processed"] == 3 and summary["failed"] == 1
    table = pd.read_parquet(tmp_path / "out").set_index("image")
    with_prior, known = table.loc[str(a)], table.loc[str(b)]
    assert with_prior["focal_prior_source"] == "user" and with_prior["focal_prior_px"] == pytest.approx(ROOM_F * 1.1)
    assert with_prior["focal_prior_sigma_pct"] == 5.0 and with_prior["ok"]
    assert known["focal_px"] == pytest.approx(450.0) and pd.isna(known["focal_prior_px"])
    assert known["focal_prior_reason"] == "focal length given"
    options["focal_prior"] = parse_focal_prior("exif")  # a PNG has no EXIF: no prior, and why
    run_batch([str(a)], tmp_path / "out_exif", options, progress=False)
    row = pd.read_parquet(tmp_path / "out_exif").iloc[0]
    assert pd.isna(row["focal_prior_px"]) and row["focal_prior_reason"] and row["ok"]
    assert main(["batch", str(a), "--out", str(tmp_path / "bad"), "--focal", "500", "--focal-prior", "400"]) == 2


def test_a_flat_principal_point_is_the_centre_with_an_open_bound(monkeypatch):
    """Scores that do not single out a principal point (flat, or curving the wrong way) keep the image
    centre and say so (an infinite 1-sigma), instead of a point the last bits would pick."""
    from types import SimpleNamespace

    from fr_torch.runtime import shared_focal

    photos = [SimpleNamespace(width=640, height=480)] * 5
    settings = shared_focal.SharedFocalSettings()
    axis = np.asarray(settings.pp_offsets)
    grid = np.stack(np.meshgrid(axis, axis, indexing="xy"), -1).reshape(-1, 2)
    for surface in (np.zeros(len(grid)), 1e3 * (grid ** 2).sum(1), -1e-3 * (grid ** 2).sum(1)):
        monkeypatch.setattr(shared_focal, "principal_point_scores",
                            lambda *args, s=surface: (np.tile(s, (5, 1)), np.full(5, 1000.0)))
        fit = shared_focal.shared_principal_point(None, photos, settings)
        assert fit.flat and fit.offset == (0.0, 0.0) and fit.sigma == (np.inf, np.inf)
    peaked = -2e4 * ((grid - [0.01, -0.005]) ** 2).sum(1)  # tempered by beta / W = 0.03: within the floor
    monkeypatch.setattr(shared_focal, "principal_point_scores", lambda *args: (np.tile(peaked, (5, 1)), np.full(5, 1e3)))
    fit = shared_focal.shared_principal_point(None, photos, settings)
    assert not fit.flat and fit.offset == pytest.approx((0.01, -0.005), abs=1e-3) and max(fit.sigma) < 0.04
