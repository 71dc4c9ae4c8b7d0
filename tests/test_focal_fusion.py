"""fr_eval.protocols.focal_fusion (one camera's focal estimates fused with and without predicted-error weights) and
the cue-set comparison of fr train-reliability."""
from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from fr_eval.protocols import focal_fusion
from fr_torch.core.reliability.model import ERROR_COLUMNS, FR_MODEL_CUE_NAMES


def test_fused_focal_error_weights_follow_predicted_errors():
    focal = np.array([500.0, 500.0, 800.0])
    assert focal_fusion.fused_focal_error_pct(np.full(4, 510.0), None, 500.0) == pytest.approx(2.0)
    unweighted = focal_fusion.fused_focal_error_pct(focal, None, 500.0)
    trusted = focal_fusion.fused_focal_error_pct(focal, np.array([2.0, 2.0, 60.0]), 500.0)
    assert unweighted > 10.0 and trusted < 0.5 < unweighted  # the frame predicted bad barely counts
    # fr track's floor on sigma (1 %): predictions below it weigh the same
    assert focal_fusion.fused_focal_error_pct(focal, np.array([0.01, 0.1, 60.0]), 500.0) == pytest.approx(
        focal_fusion.fused_focal_error_pct(focal, np.array([0.1, 0.01, 60.0]), 500.0))


def _records(n, seed):
    rng = np.random.default_rng(seed)
    frame = pd.DataFrame({"min_family_segments": rng.integers(3, 80, n).astype(float),
                          "grid_entropy": rng.uniform(1e-4, 2.0, n), "mean_log_likelihood": rng.normal(0, 0.5, n),
                          "focal_conditioning": rng.uniform(0.001, 0.7, n),
                          "focal_prior_share": np.exp(rng.uniform(np.log(3e-3), 0.0, n)),
                          "focal_profile_gap": rng.uniform(-200.0, 5000.0, n),
                          "focal_spread": np.exp(rng.uniform(np.log(0.05), np.log(2.0), n))})
    frame[list(ERROR_COLUMNS)] = np.abs(rng.normal(size=(n, 3))) * [0.3, 0.8, 5.0]
    frame["ok"], frame["group"] = True, [f"g{i % 20}" for i in range(n)]
    return frame


def test_fuse_reads_records_and_checks_one_camera(tmp_path):
    from fr_torch.core.reliability.model import ReliabilityModel

    for source in ReliabilityModel.load_default("fr").meta["training_data"]:  # the shipped model's sources
        _records(60, seed=len(source)).to_csv(tmp_path / f"{source}_train_fr.csv", index=False)
    rng = np.random.default_rng(1)
    n = 12
    predictions = pd.DataFrame({"method": "fr", "failed": False, "reliable": [True] * (n - 1) + [False],
                                "gt_focal_px": 675.0, "est_focal_px": 675.0 * (1 + 0.03 * rng.normal(size=n))})
    for name in FR_MODEL_CUE_NAMES:
        predictions[f"cue_{name}"] = _records(n, seed=2)[name]
    table = focal_fusion.fuse(predictions, tmp_path)
    assert list(table["method"]) == ["fr"] and int(table["frames"].iloc[0]) == n - 1  # unreliable frame left out
    assert np.isfinite(table[["unweighted", "paper cues", "shipped model"]].to_numpy(float)).all()
    predictions.loc[0, "gt_focal_px"] = 700.0
    with pytest.raises(ValueError, match="one true focal length"):
        focal_fusion.fuse(predictions, tmp_path)


def test_compare_cue_sets_writes_table_and_figure(tmp_path):
    from fr_eval.protocols.reliability_train import CUE_SETS, compare_cue_sets

    train = pd.concat([_records(60, seed=1).assign(source="yud", name=[f"y{i}" for i in range(60)]),
                       _records(80, seed=2).assign(source="zind-fr", name=[f"z{i}" for i in range(80)])],
                      ignore_index=True)
    train["group"] = [f"{s}:{i % 25}" for i, s in enumerate(train["source"])]
    test = _records(40, seed=3)
    table = compare_cue_sets(train, test, tmp_path, "fr")
    assert list(table["cues"]) == list(CUE_SETS)
    assert np.isfinite(table.drop(columns="cues").to_numpy(float)).all()
    text = (tmp_path / "cues_fr.md").read_text()
    assert "oof yud rho" in text and "oof zind-fr rho" in text and "cues_fr.png" in text
    assert (tmp_path / "cues_fr.png").stat().st_size > 0 and (tmp_path / "cues_fr.csv").is_file()


def test_fast_records_without_the_profile_gap(tmp_path):
    """Fast-fR does not compute focal_profile_gap: its records leave the column empty; cue sets with
    it are left out of the comparison, and asking for it is a one-line error, not an empty fit."""
    from fr_eval.protocols.reliability_train import CUE_SETS, compare_cue_sets, usable
    from fr_torch.core.reliability.model import MODEL_CUE_NAMES, model_cue_names

    train = pd.concat([_records(60, seed=1).assign(source="yud", name=[f"y{i}" for i in range(60)]),
                       _records(80, seed=2).assign(source="zind-fr", name=[f"z{i}" for i in range(80)])],
                      ignore_index=True)
    train["group"] = [f"{s}:{i % 25}" for i, s in enumerate(train["source"])]
    train["focal_profile_gap"] = np.nan
    test = _records(40, seed=3).assign(focal_profile_gap=np.nan)
    assert len(usable(train, model_cue_names("fast"))) == len(train) and model_cue_names("fast") == MODEL_CUE_NAMES
    with pytest.raises(ValueError, match="focal_profile_gap"):
        usable(train, model_cue_names("fr"))
    table = compare_cue_sets(train, test, tmp_path, "fast")
    assert list(table["cues"]) == [name for name, cues in CUE_SETS.items() if "focal_profile_gap" not in cues]
