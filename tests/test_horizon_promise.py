"""The horizon promise: its sigma, bound and limit, `horizon_reliable` and its reason in a result's
JSON, the record schema and the batch table."""
from __future__ import annotations

import json
import math

import numpy as np
import pytest

from fr_torch.core.geometry.camera import Camera
from fr_torch.core.reliability.bounds import (
    HORIZON_BOUND_CAP_PCT,
    HorizonPromise,
    ReliabilityPromise,
    focal_sigma_pct,
    horizon_sigma_pct,
)
from fr_torch.core.reliability.model import MODEL_CUE_NAMES, ReliabilityModel
from fr_torch.core.result import JSON_KEYS, NO_HORIZON_PROMISE, CalibrationResult
from fr_torch.runtime.schema import result_record

F, H = 500.0, 480.0
SPREADS = {"focal_profile_spread": 0.04, "focal_resample_spread": 0.01, "pitch_resample_spread": 0.2}


def test_horizon_sigma_terms_in_quadrature():
    pitch = math.radians(0.2)
    # level camera: the focal length does not move the horizon, only the pitch does
    assert horizon_sigma_pct(SPREADS, F, 0.0, H, 0.0) == pytest.approx(100 * F * pitch / H)
    tilt = math.radians(20.0)
    focal = focal_sigma_pct(SPREADS) / 100  # 2 %
    expected = 100 / H * math.hypot(F * pitch / math.cos(tilt) ** 2, F * math.tan(tilt) * focal)
    assert horizon_sigma_pct(SPREADS, F, 20.0, H, 0.0) == pytest.approx(expected)
    assert horizon_sigma_pct(SPREADS, F, -20.0, H, 0.0) == pytest.approx(expected)  # |tan t|
    assert horizon_sigma_pct(SPREADS, F, 20.0, H, 1.0) == pytest.approx(math.hypot(expected, 1.0))  # the floor
    given = horizon_sigma_pct(SPREADS, F, 20.0, H, 0.0, focal_known=True)  # no focal term
    assert given == pytest.approx(100 / H * F * pitch / math.cos(tilt) ** 2)
    # a table (one row per estimate), a missing cue, the cap
    table = {name: np.array([v, v]) for name, v in SPREADS.items()}
    np.testing.assert_allclose(horizon_sigma_pct(table, [F, F], [0.0, 20.0], [H, H], 0.0),
                               [100 * F * pitch / H, expected])
    assert math.isnan(horizon_sigma_pct({"pitch_resample_spread": 0.2}, F, 20.0, H, 0.0))
    assert horizon_sigma_pct({**SPREADS, "pitch_resample_spread": 1000.0}, F, 80.0, H, 0.0) == HORIZON_BOUND_CAP_PCT


def test_horizon_promise_bound_violation_and_config(tmp_path):
    promise = HorizonPromise(limit_pct=5.0, scales={"fr": 3.0}, floor_pct=0.5)
    bound = float(promise.bounds(SPREADS, "fr", F, 0.0, H))
    assert bound == pytest.approx(3.0 * math.hypot(100 * F * math.radians(0.2) / H, 0.5))
    assert promise.violation(bound) is None and bound <= 5.0
    assert math.isnan(promise.bounds(SPREADS, "fast", F, 0.0, H))  # no scale for the mode
    # a batch at once: each row's bound bit for bit, NaN for a missing number, the cap
    rng = np.random.default_rng(3)
    rows = [{name: float(v * rng.uniform(0.1, 30.0)) for name, v in SPREADS.items()} for _ in range(40)]
    focal, tilt = rng.uniform(200.0, 3000.0, 40), rng.uniform(-80.0, 80.0, 40)
    focal[5] = math.nan
    table = {name: np.array([row[name] for row in rows]) for name in SPREADS}
    many = promise.bounds(table, "fr", focal, tilt, np.full(40, H))
    one = [float(promise.bounds(row, "fr", f, t, H)) for row, f, t in zip(rows, focal, tilt)]
    assert np.array_equal(many, np.array(one), equal_nan=True) and math.isnan(many[5])
    assert promise.violation(7.25) == "90 % bound of the horizon 7.2 % of the height > 5 %"
    assert "its cues are missing" in promise.violation(math.nan)
    assert "do not bound the horizon" in promise.violation(HORIZON_BOUND_CAP_PCT)
    for bad in (dict(limit_pct=0.0), dict(floor_pct=-1.0), dict(scales={"fr": 0.0})):
        with pytest.raises(ValueError):
            HorizonPromise(**bad)
    path = tmp_path / "reliability.json"
    path.write_text(json.dumps({"promise": {"scales": {"fr": {"focal_pct": 3, "tilt_deg": 3}}}}))
    assert ReliabilityPromise.from_config(path).horizon is None  # an older config: no horizon promise
    path.write_text(json.dumps({"promise": {"scales": {"fr": {"focal_pct": 3, "tilt_deg": 3}},
                                            "horizon": {"limit_pct": 4, "floor_pct": 0.25, "scales": {"fr": 2.5}}}}))
    loaded = ReliabilityPromise.from_config(path).horizon
    assert loaded == HorizonPromise(limit_pct=4.0, scales={"fr": 2.5}, floor_pct=0.25)


def _training(n=200, seed=0):
    rng = np.random.default_rng(seed)
    cues = np.exp(rng.uniform(-2, 2, (n, len(MODEL_CUE_NAMES))))
    return cues, np.exp(rng.uniform(-2, 1, (n, 3)))


def _result(spreads, tilt=0.0, reliable=True, reason=""):
    r = CalibrationResult(image="x", width=640, height=480, ok=True, reliable=reliable, reason=reason,
                          camera=Camera.from_angles(640, 480, F, roll_deg=0.0, tilt_deg=tilt))
    r.cues = {**dict(zip(MODEL_CUE_NAMES, np.ones(len(MODEL_CUE_NAMES)))), **spreads}
    return r


def _model(tmp_path, horizon: bool = True):
    cues, errors = _training()
    ReliabilityModel.fit(cues, errors, meta={"mode": "fast"}).save(tmp_path / "reliability_fast.npz")
    promise = {"coverage": 0.9, "limits": {"focal_pct": 10.0, "tilt_deg": 3.0},
               "scales": {"fast": {"focal_pct": 2.0, "tilt_deg": 2.0}}}
    if horizon:
        promise["horizon"] = {"limit_pct": 5.0, "floor_pct": 0.5, "scales": {"fast": 3.0}}
    (tmp_path / "reliability.json").write_text(json.dumps({"thresholds": {}, "promise": promise}))
    return ReliabilityModel.load_default("fast", config_dir=tmp_path)


def test_horizon_reliable_beside_the_focal_tilt_promise(tmp_path):
    """A horizon can be trusted where the focal length cannot (a level camera whose f the lines
    leave open); a failed sanity check or a wide horizon bound says why in `horizon_reason`."""
    model = _model(tmp_path)
    open_focal = _result({"focal_profile_spread": 1.0, "focal_resample_spread": 1.0, "pitch_resample_spread": 0.1})
    wide = _result({**SPREADS, "pitch_resample_spread": 3.0}, tilt=10.0)
    insane = _result(SPREADS, reliable=False, reason="too few segments (12 < 30)")
    model.annotate_many([open_focal, wide, insane], mode="fast")
    assert not open_focal.reliable and "do not bound the focal" in open_focal.reason
    assert open_focal.horizon_reliable and open_focal.horizon_reason == ""
    record = json.loads(json.dumps(result_record(open_focal)))
    assert record["horizon_reliable"] is True and record["horizon"]["bound_pct"] == open_focal.error_bound["horizon_pct"]
    assert record["horizon"]["unbounded"] is False  # the focal bound is open, the horizon's is not
    assert record["error_bound"]["limits"]["horizon_pct"] == 5.0
    assert not wide.horizon_reliable and wide.horizon_reason.startswith("outside the horizon promise: 90 % bound")
    assert not insane.horizon_reliable and insane.horizon_reason == "too few segments (12 < 30)"
    assert list(record)[:8] == list(JSON_KEYS[:8])


def test_without_a_horizon_promise_the_reason_says_so(tmp_path):
    model = _model(tmp_path, horizon=False)
    r = _result(SPREADS)
    model.annotate_many([r], mode="fast")
    out = r.to_json()
    assert out["horizon_reliable"] is False and out["horizon_reason"] == NO_HORIZON_PROMISE
    assert "horizon_pct" not in r.error_bound and r.horizon.bound_pct is not None  # the derived bound
    failed = CalibrationResult(image="y", width=640, height=480, ok=False, reason="no segments")
    out = failed.to_json()
    assert out["horizon_reliable"] is False and out["horizon_reason"] == "no segments"


def test_batch_rows_carry_the_horizon_promise(tmp_path):
    from fr_torch.batch.table import records_to_table

    model = _model(tmp_path)
    r = _result(SPREADS)
    model.annotate_many([r], mode="fast")
    failed = CalibrationResult(image="y", width=640, height=480, ok=False, reason="no segments")
    table = records_to_table([r.to_json(), failed.to_json()], [{}, {}]).to_pylist()
    assert [row["horizon_reliable"] for row in table] == [True, False]
    assert table[1]["horizon_reason"] == "no segments"
    assert table[0]["error_bound"]["horizon_pct"] == pytest.approx(r.error_bound["horizon_pct"])
    assert table[0]["error_bound"]["limits"]["horizon_pct"] == 5.0


def test_the_focal_tilt_route(tmp_path):
    """With ``or_focal_tilt`` the horizon is trusted where the focal / tilt promise holds, whatever its
    own bound; without it, only by its own bound."""
    wide_but_kept = {"focal_profile_spread": 0.01, "focal_resample_spread": 0.004, "pitch_resample_spread": 1.0}
    for route in (False, True):
        model = _model(tmp_path)
        config = json.loads((tmp_path / "reliability.json").read_text())
        config["promise"]["horizon"] |= {"or_focal_tilt": route, "scales": {"fast": 30.0}}
        (tmp_path / "reliability.json").write_text(json.dumps(config))
        model = ReliabilityModel.load_default("fast", config_dir=tmp_path)
        r = _result(wide_but_kept)
        model.annotate_many([r], mode="fast")
        assert r.reliable and r.error_bound["horizon_pct"] > 5.0  # the focal / tilt promise holds
        assert r.horizon_reliable is route
        assert route or r.horizon_reason.startswith("outside the horizon promise: 90 % bound of the horizon")
    promise = HorizonPromise(scales={"fr": 3.0}, or_focal_tilt=True)
    assert promise.violation(7.0).endswith("and the focal / tilt promise does not hold")
    assert promise.violation(7.0, focal_tilt_kept=True) is None
