"""The reliability stage under the leave-one-dataset-out protocol, and the promise ``reliable`` ships with.

Usage (after ``python -m fr_eval.protocols.lodo run`` -- or ``run --stage reliability``, the runs this
module reads)::

    python -m fr_eval.protocols.lodo_reliability table     # results/cross_dataset/reliability_f10_t3.{md,csv}
    python -m fr_eval.protocols.lodo_reliability figure    # results/reliability/risk_coverage.png
    python -m fr_eval.protocols.lodo_reliability promise --write  # the conformal scales -> configs/reliability.json

Records: per-image cues and absolute errors from the LODO cache (:mod:`fr_eval.protocols.lodo`):
the train splits of :data:`~fr_eval.protocols.lodo.RELIABILITY_TRAIN` under the shipped estimator
(NYU-VP every 2nd photo) and each reported dataset under its held-out setting.

Bounds (``--bounds``): a bound is ``scale x sigma`` per error (focal %, tilt deg).

* ``spreads`` (what ``reliable`` ships with): sigma from the estimate's own spreads
  (:data:`fr_torch.core.reliability.bounds.SIGMAS`); no model is fitted.
* ``knn`` (the KNN's bounds, for comparison): sigma = the KNN's predicted error
  (:class:`fr_torch.core.reliability.model.ReliabilityModel`, the shipped cue set of the mode, floored at
  0.5 % / 0.1 deg), the model fitted on the calibration records (for a family's scale: without
  that family).

Scales: each family of the calibration records (YUD with its crops, ZInD-fR, NYU-VP) gives the
split-conformal quantile of actual / sigma at the coverage (90 %); ``worst`` keeps the largest
(shipped), ``pooled`` one quantile over all of them.  For a reported dataset the calibration
records are the other families' train records; for the shipped promise, every family's.

Reported per dataset (limits T_f, T_t; "good" = within both, a photo without a known vertical by
its focal error alone): precision (of the photos flagged reliable, the share good), recall (of the
good photos, the share flagged), coverage (the share flagged), AURC / oracle (the area under focal
MAE vs share kept, photos ordered by the focal bound, over that of the order by the actual error;
:func:`fr_eval.scoring.metrics.aurc`), Spearman rho of each bound with its error, and the share of
photos within each bound.
"""
from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path
from typing import Sequence

import numpy as np
import pandas as pd
from scipy.stats import spearmanr

from fr_eval.paths import REPO, cache_root
from fr_eval.protocols.lodo import (
    RELIABILITY_TRAIN,
    REPORTED,
    SHIPPED,
    family_of,
    prediction_path,
    setting_name,
)
from fr_eval.scoring.metrics import aurc
from fr_eval.scoring.plots import risk_coverage_panel, save_figure
from fr_torch.core.reliability.bounds import (
    DEFAULT_COVERAGE,
    DEFAULT_LIMITS,
    PROMISE_TARGETS,
    SIGMAS,
    conformal_scale,
    worst_group_scale,
)
from fr_torch.core.reliability.cues import SPREAD_CUE_NAMES
from fr_torch.core.reliability.model import ERROR_COLUMNS, ReliabilityModel, model_cue_names
from fr_torch.output import write_text_atomic

TARGET_INDEX = {"roll_deg": 0, "tilt_deg": 1, "focal_pct": 2}
ERROR_OF = {"focal_pct": "focal_err_pct", "tilt_deg": "tilt_err_deg"}
SCALE_RULES = ("worst", "pooled")
BOUND_KINDS = ("spreads", "knn")
#: Floors of a KNN prediction before the ratio (focal %, tilt deg)
KNN_FLOOR = {"focal_pct": 0.5, "tilt_deg": 0.1}
MODE_LABEL = {"fr": "fR", "fast": "Fast-fR"}
METHOD_OF_MODE = {"fr": "fr", "fast": "fast-fr"}


def records_from_predictions(table: pd.DataFrame, dataset: str, mode: str) -> pd.DataFrame:
    """``fr eval`` prediction rows -> records of the estimates (failures left out): the KNN's cues
    and the spread cues (by name), the error columns, ``reliable`` (the estimator's flag),
    ``pred_err_focal_pct`` (the KNN's prediction, NaN without one), ``group`` (one per photo: a YUD
    crop shares its photo's) and ``dataset``."""
    ok = table[~table["failed"].astype(bool)]
    names = list(dict.fromkeys(model_cue_names(mode) + SPREAD_CUE_NAMES))
    out = pd.DataFrame({name: pd.to_numeric(ok.get(f"cue_{name}"), errors="coerce") for name in names})
    for column in ERROR_COLUMNS:
        out[column] = pd.to_numeric(ok[column], errors="coerce").to_numpy()
    out["reliable"] = ok["reliable"].astype(str).str.lower().eq("true").to_numpy()
    out["pred_err_focal_pct"] = pd.to_numeric(ok["pred_err_focal_pct"], errors="coerce").to_numpy()
    out["group"] = [f"{family_of(dataset)}:{name}" for name in ok["image"]]
    out["dataset"] = dataset
    return out.reset_index(drop=True)


def _run(cache: Path, setting: str, dataset: str, split: str, mode: str) -> pd.DataFrame:
    path = prediction_path(cache, setting, dataset, split, METHOD_OF_MODE[mode])
    if not path.is_file():
        raise FileNotFoundError(f"{path} is missing: run `python -m fr_eval.protocols.lodo run --stage reliability`")
    return records_from_predictions(pd.read_csv(path), dataset, mode)


def train_records(dataset: str, mode: str, cache: Path) -> pd.DataFrame:
    """Train-split records of the shipped estimator on ``dataset`` (module docstring)."""
    return _run(cache, SHIPPED, dataset, "train", mode)


def held_out_records(dataset: str, split: str, mode: str, cache: Path) -> pd.DataFrame:
    """The reported dataset's records under its held-out setting (estimates and cues)."""
    return _run(cache, setting_name(family_of(dataset)), dataset, split, mode)


def fit_model(records: pd.DataFrame, mode: str) -> ReliabilityModel:
    """The KNN error model of ``mode``'s shipped cue set fitted on ``records``."""
    names = model_cue_names(mode)
    return ReliabilityModel.fit(records[list(names)].to_numpy(), records[list(ERROR_COLUMNS)].to_numpy(),
                                groups=records["group"].to_numpy(), cue_names=names, meta={"mode": mode})


def sigmas(records: pd.DataFrame, kind: str = "spreads", model: ReliabilityModel | None = None) -> dict[str, np.ndarray]:
    """target -> (n,) error scale of each record: the spreads' (``spreads``) or ``model``'s floored
    prediction (``knn``)."""
    if kind == "spreads":
        return {target: np.asarray(SIGMAS[target](records), np.float64) for target in PROMISE_TARGETS}
    predicted = model.predict(records[list(model.cue_names)].to_numpy())
    return {target: np.maximum(predicted[:, TARGET_INDEX[target]], KNN_FLOOR[target]) for target in PROMISE_TARGETS}


def family_scales(records: pd.DataFrame, mode: str, coverage: float = DEFAULT_COVERAGE, rule: str = "worst",
                  kind: str = "spreads") -> dict[str, tuple[float, dict[str, float]]]:
    """Conformal scales per target over the families of ``records`` (module docstring): target ->
    (the scale the rule gives, {family: its own scale}).  ``knn``: each family predicted by a model
    fitted without it (with one family: 5 folds grouped by photo)."""
    families = records["dataset"].map(family_of).to_numpy()
    if kind == "spreads":
        parts = [(records, families)]
    else:
        if len(set(families.tolist())) > 1:
            folds = [(families != f, families == f) for f in dict.fromkeys(families.tolist())]
        else:
            from sklearn.model_selection import GroupKFold
            index = np.arange(len(records))
            folds = [(np.isin(index, a), np.isin(index, b))
                     for a, b in GroupKFold(n_splits=5).split(records, groups=records["group"].to_numpy())]
        parts = [(records[inside], families[inside]) for _, inside in folds]
        models = [fit_model(records[train], mode) for train, _ in folds]
    scale_of = {}
    for target in PROMISE_TARGETS:
        sigma, actual, groups = [], [], []
        for j, (part, part_families) in enumerate(parts):
            sigma.append(sigmas(part, kind, None if kind == "spreads" else models[j])[target])
            actual.append(part[ERROR_OF[target]].to_numpy(np.float64))
            groups.append(part_families)
        sigma, actual, groups = np.concatenate(sigma), np.concatenate(actual), np.concatenate(groups)
        worst, per = worst_group_scale(sigma, actual, groups, coverage)
        scale_of[target] = (conformal_scale(sigma, actual, coverage) if rule == "pooled" else worst, per)
    return scale_of


def evaluate(records: pd.DataFrame, bounds: dict[str, np.ndarray], limits: dict,
             flagged: np.ndarray | None = None) -> dict:
    """Promise and ranking figures of ``bounds`` (target -> (n,)) for records with actual errors
    (module docstring).  ``flagged`` (n,) bool: the photos called reliable (None: those whose bounds
    are within the limits)."""
    focal = records["focal_err_pct"].to_numpy(np.float64)
    tilt = records["tilt_err_deg"].to_numpy(np.float64)
    has_tilt = np.isfinite(tilt)  # NYU-VP photos without a known vertical have a focal error only
    bound_f, bound_t = bounds["focal_pct"], bounds["tilt_deg"]
    if flagged is None:
        flagged = (bound_f <= limits["focal_pct"]) & (bound_t <= limits["tilt_deg"])
    flagged = np.asarray(flagged, bool)
    good = (focal <= limits["focal_pct"]) & (~has_tilt | (tilt <= limits["tilt_deg"]))
    share = lambda mask: 100 * float(mask.mean()) if mask.size else math.nan  # noqa: E731
    oracle = aurc(focal, focal)
    return {"n": len(records), "good_pct": share(good), "reliable_n": int(flagged.sum()), "coverage_pct": share(flagged),
            "precision_pct": share(good[flagged]), "recall_pct": share(flagged[good]),
            "aurc": aurc(bound_f, focal), "aurc_oracle": oracle, "aurc_ratio": aurc(bound_f, focal) / oracle,
            "rho_focal": float(spearmanr(bound_f, focal, nan_policy="omit").statistic),
            "rho_tilt": float(spearmanr(bound_t[has_tilt], tilt[has_tilt], nan_policy="omit").statistic),
            "focal_mae": float(np.nanmean(focal)),
            "reliable_focal_mae": float(np.nanmean(focal[flagged])) if flagged.any() else math.nan,
            "bound_holds_focal": share(focal <= bound_f), "bound_holds_tilt": share((tilt <= bound_t)[has_tilt])}


def held_out_bounds(cache: Path, mode: str, dataset: str, split: str, coverage: float, rule: str, kind: str,
                    train: dict[str, pd.DataFrame]) -> tuple[pd.DataFrame, dict[str, np.ndarray], dict]:
    """(the reported dataset's records, their bounds, the scales) with everything fitted without its
    family."""
    family = family_of(dataset)
    calibration = pd.concat([r for d, r in train.items() if family_of(d) != family], ignore_index=True)
    scales = family_scales(calibration, mode, coverage, rule, kind)
    test = held_out_records(dataset, split, mode, cache)
    model = fit_model(calibration, mode) if kind == "knn" else None
    sigma = sigmas(test, kind, model)
    return test, {t: scales[t][0] * sigma[t] for t in PROMISE_TARGETS}, scales


def lodo_table(cache: Path, limits: dict, coverage: float, modes: Sequence[str] = ("fr", "fast"),
               rule: str = "worst", kind: str = "spreads") -> pd.DataFrame:
    """One row per (mode, reported dataset): bounds calibrated without the dataset's family, judged on
    its held-out predictions (module docstring)."""
    rows = []
    for mode in modes:
        train = {d: train_records(d, mode, cache) for d in RELIABILITY_TRAIN}
        for dataset, split in REPORTED:
            test, bounds, scales = held_out_bounds(cache, mode, dataset, split, coverage, rule, kind, train)
            row = {"mode": mode, "dataset": dataset, "split": split, "bounds": kind,
                   "scale_focal": scales["focal_pct"][0], "scale_tilt": scales["tilt_deg"][0],
                   **evaluate(test, bounds, limits)}
            rows.append(row)
            print(f"{mode} {dataset}: precision {row['precision_pct']:.0f} % recall {row['recall_pct']:.0f} % "
                  f"coverage {row['coverage_pct']:.0f} % AURC/oracle {row['aurc_ratio']:.2f}", file=sys.stderr)
    return pd.DataFrame(rows)


def markdown(table: pd.DataFrame, limits: dict, coverage: float) -> str:
    lines = [f"Promise: {round(100 * coverage)} % bounds, focal <= {limits['focal_pct']:g} %, "
             f"tilt <= {limits['tilt_deg']:g}°.", "",
             "| mode | held-out dataset | n | within both | reliable (coverage) | precision | recall | "
             "AURC / oracle | ρ focal | ρ tilt | focal MAE reliable / all | within bound (focal, tilt) | "
             "scales (focal, tilt) |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in table.itertuples():
        precision = "—" if math.isnan(r.precision_pct) else f"{r.precision_pct:.0f} %"
        reliable_mae = "—" if math.isnan(r.reliable_focal_mae) else f"{r.reliable_focal_mae:.2f}"
        lines.append(f"| {MODE_LABEL[r.mode]} | {r.dataset} {r.split} | {r.n} | {r.good_pct:.0f} % | "
                     f"{r.reliable_n} ({r.coverage_pct:.0f} %) | {precision} | {r.recall_pct:.0f} % | "
                     f"{r.aurc:.2f} / {r.aurc_oracle:.2f} = {r.aurc_ratio:.2f} | {r.rho_focal:.2f} | {r.rho_tilt:.2f} | "
                     f"{reliable_mae} / {r.focal_mae:.2f} | {r.bound_holds_focal:.0f} %, {r.bound_holds_tilt:.0f} % | "
                     f"{r.scale_focal:.2f}, {r.scale_tilt:.2f} |")
    return "\n".join(lines)


def risk_coverage_figure(cache: Path, path: Path, coverage: float = DEFAULT_COVERAGE,
                         modes: Sequence[str] = ("fr", "fast")) -> Path:
    """Focal MAE of the photos kept vs the share kept, per mode (rows) and held-out dataset (columns):
    ordered by the spreads' focal bound (shipped), by the KNN's bound, and by the actual error
    (oracle); the dashed line is all photos' MAE."""
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(len(modes), len(REPORTED), figsize=(3.4 * len(REPORTED), 3.0 * len(modes)),
                             squeeze=False)
    for i, mode in enumerate(modes):
        train = {d: train_records(d, mode, cache) for d in RELIABILITY_TRAIN}
        for j, (dataset, split) in enumerate(REPORTED):
            ax = axes[i, j]
            curves = {}
            for kind, label in (("spreads", "focal bound (spreads)"), ("knn", "issue 35 KNN bound")):
                test, bounds, _ = held_out_bounds(cache, mode, dataset, split, coverage, "worst", kind, train)
                curves[label] = bounds["focal_pct"]
            focal = test["focal_err_pct"].to_numpy(np.float64)
            ax.axhline(float(np.nanmean(focal)), color="grey", lw=0.8, ls="--")
            risk_coverage_panel(ax, [(label, score, focal, style) for (label, score), style
                                     in zip(curves.items(), ("C0-", "C1--"))] + [("oracle", focal, focal, "k:")],
                                f"{MODE_LABEL[mode]}, {dataset} {split}", j == 0, legend_size=6)
    return save_figure(fig, path, "Risk-coverage, held out: photos kept in the order of their predicted focal bound "
                                  "(AURC / oracle in brackets)")


def shipped_promise(cache: Path, limits: dict, coverage: float, validated_detectors: Sequence[str] = ()) -> dict:
    """The ``promise`` block for configs/reliability.json: scales per mode from every family's train
    records (the largest per-family quantile); ``validated_detectors`` kept as given (the detectors
    besides the model's own that the promise was measured on: :mod:`fr_eval.protocols.detector_reliability`,
    to be rerun after a refit)."""
    scales, detail = {}, {}
    for mode in ("fr", "fast"):
        records = pd.concat([train_records(d, mode, cache) for d in RELIABILITY_TRAIN], ignore_index=True)
        fitted = family_scales(records, mode, coverage)
        scales[mode] = {t: round(fitted[t][0], 3) for t in PROMISE_TARGETS}
        detail[mode] = {t: {k: round(v, 3) for k, v in fitted[t][1].items()} for t in PROMISE_TARGETS}
    return {"coverage": coverage, "limits": limits, "enforce": True, "scales": scales, "per_family_scales": detail,
            "validated_detectors": list(validated_detectors),
            "doc": "error_bound = scale x sigma, a 90 % bound; sigma from the estimate's own spreads (focal: "
                   "100 sqrt(focal_profile_spread x focal_resample_spread) %, tilt: hypot(pitch_resample_spread, "
                   "0.5) deg; fr_torch.core.reliability.bounds); reliable = every bound within its limit (enforce "
                   "false: reported only, reliable keeps the thresholds); scales: split-conformal quantiles of "
                   "actual / sigma per dataset family (YUD + crops, ZInD-fR, NYU-VP; train splits), the largest "
                   "kept (python -m fr_eval.protocols.lodo_reliability promise --write; docs/reliability.md); "
                   "validated_detectors: line detectors besides the models' own (LSD) whose segments the promise "
                   "was measured to hold for (python -m fr_eval.protocols.detector_reliability table; "
                   "results/decisions/45.md)"}


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m fr_eval.protocols.lodo_reliability",
                                     description=__doc__.split("\n")[0])
    parser.add_argument("action", choices=("table", "figure", "promise"))
    parser.add_argument("--cache", default=str(cache_root() / "lodo"))
    parser.add_argument("--focal-limit", type=float, default=DEFAULT_LIMITS["focal_pct"], help="T_f, percent")
    parser.add_argument("--tilt-limit", type=float, default=DEFAULT_LIMITS["tilt_deg"], help="T_t, degrees")
    parser.add_argument("--coverage", type=float, default=DEFAULT_COVERAGE)
    parser.add_argument("--scale-rule", choices=SCALE_RULES, default="worst",
                        help="table: conformal scale = the largest per-family quantile (worst, shipped) or one "
                             "quantile over all calibration photos (pooled)")
    parser.add_argument("--bounds", choices=BOUND_KINDS, default="spreads",
                        help="table: the shipped bounds (spreads) or the KNN's bounds (knn, for comparison)")
    parser.add_argument("--out", default=str(REPO / "results" / "cross_dataset"))
    parser.add_argument("--figure", default=str(REPO / "results" / "reliability" / "risk_coverage.png"))
    parser.add_argument("--write", action="store_true", help="promise: write it into configs/reliability.json")
    args = parser.parse_args(argv)
    limits = {"focal_pct": args.focal_limit, "tilt_deg": args.tilt_limit}
    cache = Path(args.cache)
    if args.action == "table":
        table = lodo_table(cache, limits, args.coverage, rule=args.scale_rule, kind=args.bounds)
        out = Path(args.out)
        out.mkdir(parents=True, exist_ok=True)
        stem = (f"reliability_f{args.focal_limit:g}_t{args.tilt_limit:g}"
                + ("" if args.scale_rule == "worst" else f"_{args.scale_rule}")
                + ("" if args.bounds == "spreads" else f"_{args.bounds}"))
        table.to_csv(out / f"{stem}.csv", index=False)
        text = markdown(table, limits, args.coverage)
        (out / f"{stem}.md").write_text(text + "\n")
        print(text)
        return 0
    if args.action == "figure":
        print(risk_coverage_figure(cache, Path(args.figure), args.coverage))
        return 0
    path = REPO / "configs" / "reliability.json"
    config = json.loads(path.read_text())
    block = shipped_promise(cache, limits, args.coverage, config.get("promise", {}).get("validated_detectors", ()))
    if args.write:
        config["promise"] = block
        write_text_atomic(path, json.dumps(config, indent=1) + "\n")  # searches running now read it whole
    print(json.dumps(block, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
