"""The reliability stage under the leave-one-dataset-out protocol, and the promise ``reliable`` ships with.

Usage (after ``python -m fr_eval.protocols.lodo run``, whose cached predictions it reads)::

    python -m fr_eval.protocols.lodo_reliability table            # results/cross_dataset/reliability.{md,csv}
    python -m fr_eval.protocols.lodo_reliability promise --write  # the conformal scales -> configs/reliability.json

Training records (cues and absolute errors of the shipped estimator on train splits): YUD, the YUD
crops and ZInD-fR from ``results/reliability/records/<dataset>_train_<mode>.csv`` (``fr
train-reliability``), NYU-VP train from the LODO cache (``shipped/nyu-vp_train_<method>.csv``: every
2nd train photo, 500).

For each reported dataset (its family left out, :mod:`fr_eval.protocols.lodo`): the KNN error model
(:class:`fr_torch.core.reliability.ReliabilityModel`, the shipped cue set of the mode) is fitted on the
other families' train records; its conformal scales (:mod:`fr_torch.core.reliability_bounds`) come from
predicting each of those families with a model fitted without it (largest per-family quantile); the
held-out dataset's images (estimated under its held-out setting) are then predicted and flagged.
Reported per dataset: Spearman rho of predicted vs actual focal and tilt error, the focal MAE of the
quarter predicted best over that of all images, the share flagged ``reliable`` and, of those, the
share within the limits (focal, tilt, both): the promise's coverage.
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
from fr_eval.protocols.lodo import REPORTED, family_of, setting_name
from fr_eval.paths import REPO, cache_root
from scipy.stats import spearmanr

from fr_torch.core.reliability import ERROR_COLUMNS, ReliabilityModel, model_cue_names
from fr_torch.core.reliability_bounds import (
    DEFAULT_COVERAGE,
    DEFAULT_LIMITS,
    PREDICTION_FLOOR,
    PROMISE_TARGETS,
    ReliabilityPromise,
    conformal_scale,
    worst_group_scale,
)

RECORDS = REPO / "results" / "reliability" / "records"
TARGET_INDEX = {"roll_deg": 0, "tilt_deg": 1, "focal_pct": 2}
METHOD_OF_MODE = {"fr": "fr", "fast": "fast-fr"}
TRAIN_DATASETS = ("yud", "yud-crop-400x300", "yud-crop-480x360", "zind-fr", "nyu-vp")


def _from_predictions(table: pd.DataFrame, dataset: str, names: Sequence[str]) -> pd.DataFrame:
    """``fr eval`` prediction rows -> record columns (cue names, error columns, group, dataset)."""
    ok = table[~table["failed"].astype(bool)].copy()
    out = pd.DataFrame({name: pd.to_numeric(ok.get(f"cue_{name}"), errors="coerce") for name in names})
    for column in ERROR_COLUMNS:
        out[column] = pd.to_numeric(ok[column], errors="coerce").to_numpy()
    out["group"] = [f"{dataset}:{name}" for name in ok["image"]]
    out["dataset"] = dataset
    return out.reset_index(drop=True)


def train_records(dataset: str, mode: str, cache: Path) -> pd.DataFrame:
    """Train-split records of the shipped estimator on ``dataset`` (module docstring)."""
    names = model_cue_names(mode)
    if dataset == "nyu-vp":
        return _from_predictions(pd.read_csv(cache / "shipped" / f"nyu-vp_train_{METHOD_OF_MODE[mode]}.csv"),
                                 dataset, names)
    table = pd.read_csv(RECORDS / f"{dataset}_train_{mode}.csv")
    table = table[table["ok"].astype(bool)]
    out = table[list(names) + list(ERROR_COLUMNS)].reset_index(drop=True)
    out["group"] = table["group"].astype(str).to_numpy()
    out["dataset"] = dataset
    return out


def held_out_records(dataset: str, split: str, mode: str, cache: Path) -> pd.DataFrame:
    """The reported dataset's records under its held-out setting (estimates and cues)."""
    path = cache / setting_name(family_of(dataset)) / f"{dataset}_{split}_{METHOD_OF_MODE[mode]}.csv"
    return _from_predictions(pd.read_csv(path), dataset, model_cue_names(mode))


def fit_model(records: pd.DataFrame, mode: str) -> ReliabilityModel:
    names = model_cue_names(mode)
    return ReliabilityModel.fit(records[list(names)].to_numpy(), records[list(ERROR_COLUMNS)].to_numpy(),
                                groups=records["group"].to_numpy(), cue_names=names, meta={"mode": mode})


SCALE_RULES = ("worst", "pooled")


def family_scales(records: pd.DataFrame, mode: str, coverage: float = DEFAULT_COVERAGE, rule: str = "worst") -> dict:
    """Conformal scales per target: each family of ``records`` predicted by a model fitted without it
    (with one family: 5 folds grouped by scene); target -> (largest per-family scale, {family: scale})."""
    families = records["dataset"].map(family_of).to_numpy()
    predicted, actual, groups = [], [], []
    if len(set(families.tolist())) > 1:
        folds = [(families != f, families == f, f) for f in dict.fromkeys(families.tolist())]
    else:  # one family: 5 folds grouped by scene instead
        from sklearn.model_selection import GroupKFold
        folds = [(np.isin(np.arange(len(records)), a), np.isin(np.arange(len(records)), b), families[0])
                 for a, b in GroupKFold(n_splits=5).split(records, groups=records["group"].to_numpy())]
    for train, inside, family in folds:
        model = fit_model(records[train], mode)
        part = records[inside]
        predicted.append(model.predict(part[list(model.cue_names)].to_numpy()))
        actual.append(part[list(ERROR_COLUMNS)].to_numpy())
        groups += [family] * len(part)
    predicted, actual = np.concatenate(predicted), np.concatenate(actual)
    out = {target: worst_group_scale(predicted[:, i], actual[:, i], groups, coverage, PREDICTION_FLOOR[target])
           for target, i in TARGET_INDEX.items()}
    if rule == "pooled":  # one quantile over every out-of-family prediction
        out = {target: (conformal_scale(predicted[:, i], actual[:, i], coverage, PREDICTION_FLOOR[target]), per)
               for (target, (_, per)), i in zip(out.items(), TARGET_INDEX.values())}
    return out


def evaluate(records: pd.DataFrame, predicted: np.ndarray, promise: ReliabilityPromise, mode: str) -> dict:
    """Ranking and promise figures of predictions (n, 3) for records with actual errors."""
    actual = records[list(ERROR_COLUMNS)].to_numpy()
    focal, tilt = actual[:, 2], actual[:, 1]
    has_tilt = np.isfinite(tilt)  # NYU-VP photos without a known vertical have a focal error only
    good = np.isfinite(predicted).all(1) & np.isfinite(focal)
    bounds = [promise.bounds(dict(zip(TARGET_INDEX, row)), mode) for row in predicted]
    reliable = np.array([b is not None and not promise.violations(b) for b in bounds]) & good
    order = np.flatnonzero(good)[np.argsort(predicted[good, 2], kind="stable")]
    quarter = order[: max(1, len(order) // 4)]
    within_f = focal <= promise.limits["focal_pct"]
    within_t = tilt <= promise.limits["tilt_deg"]
    bound_f = np.array([b["focal_pct"] for b in bounds])
    bound_t = np.array([b["tilt_deg"] for b in bounds])
    share = lambda mask: float(mask.mean()) if mask.size else math.nan  # noqa: E731
    rt = good & has_tilt
    return {"n": len(records), "focal_mae": float(focal[good].mean()),
            "rho_focal": float(spearmanr(predicted[good, 2], focal[good]).statistic),
            "rho_tilt": float(spearmanr(predicted[rt, 1], tilt[rt]).statistic),
            "top_quarter_focal_mae": float(focal[quarter].mean()),
            "top_quarter_ratio": float(focal[quarter].mean() / focal[good].mean()),
            "reliable_n": int(reliable.sum()), "reliable_pct": 100 * share(reliable),
            "reliable_focal_mae": float(focal[reliable].mean()) if reliable.any() else math.nan,
            "coverage_focal": 100 * share(within_f[reliable]),
            "coverage_tilt": 100 * share(within_t[reliable & has_tilt]),
            "coverage_both": 100 * share((within_f & within_t)[reliable & has_tilt]),
            "bound_holds_focal": 100 * share((focal <= bound_f)[good]),
            "bound_holds_tilt": 100 * share((tilt <= bound_t)[rt])}


def lodo_table(cache: Path, limits: dict, coverage: float, modes: Sequence[str] = ("fr", "fast"),
               rule: str = "worst") -> pd.DataFrame:
    """One row per (mode, reported dataset): the reliability stage fitted without the dataset's family
    and judged on its held-out predictions (module docstring)."""
    rows = []
    for mode in modes:
        records = {d: train_records(d, mode, cache) for d in TRAIN_DATASETS}
        for dataset, split in REPORTED:
            family = family_of(dataset)
            train = pd.concat([r for d, r in records.items() if family_of(d) != family], ignore_index=True)
            model = fit_model(train, mode)
            scales = family_scales(train, mode, coverage, rule)
            promise = ReliabilityPromise(limits=limits, coverage=coverage,
                                         scales={mode: {t: scales[t][0] for t in PROMISE_TARGETS}})
            test = held_out_records(dataset, split, mode, cache)
            predicted = model.predict(test[list(model.cue_names)].to_numpy())
            row = {"mode": mode, "dataset": dataset, "split": split, "k": model.k,
                   "scale_focal": scales["focal_pct"][0], "scale_tilt": scales["tilt_deg"][0],
                   **evaluate(test, predicted, promise, mode)}
            rows.append(row)
            print(f"{mode} {dataset}: rho_f {row['rho_focal']:.2f} rho_t {row['rho_tilt']:.2f} "
                  f"q {row['top_quarter_ratio']:.2f} reliable {row['reliable_pct']:.0f} % "
                  f"coverage {row['coverage_both']:.0f} %", file=sys.stderr)
    return pd.DataFrame(rows)


def markdown(table: pd.DataFrame, limits: dict, coverage: float) -> str:
    lines = [f"Promise: predicted {round(100 * coverage)} % bounds focal <= {limits['focal_pct']:g} %, "
             f"tilt <= {limits['tilt_deg']:g}°.", "",
             "| mode | held-out dataset | n | ρ focal | ρ tilt | top-quarter / all focal MAE | reliable | "
             "of reliable: focal within | tilt within | both | focal MAE reliable / all | scales (focal, tilt) |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in table.itertuples():
        lines.append(f"| {'fR' if r.mode == 'fr' else 'Fast-fR'} | {r.dataset} {r.split} | {r.n} | {r.rho_focal:.2f} | "
                     f"{r.rho_tilt:.2f} | {r.top_quarter_focal_mae:.2f} / {r.focal_mae:.2f} = {r.top_quarter_ratio:.2f} | "
                     f"{r.reliable_n} ({r.reliable_pct:.0f} %) | {r.coverage_focal:.0f} % | {r.coverage_tilt:.0f} % | "
                     f"{r.coverage_both:.0f} % | {r.reliable_focal_mae:.2f} / {r.focal_mae:.2f} | "
                     f"{r.scale_focal:.2f}, {r.scale_tilt:.2f} |")
    return "\n".join(lines)


def shipped_promise(cache: Path, limits: dict, coverage: float) -> dict:
    """The ``promise`` block for configs/reliability.json: scales per mode from every family's train
    records, each family predicted by a model fitted without it (largest per-family quantile)."""
    scales, detail = {}, {}
    for mode in ("fr", "fast"):
        records = pd.concat([train_records(d, mode, cache) for d in TRAIN_DATASETS], ignore_index=True)
        fitted = family_scales(records, mode, coverage)
        scales[mode] = {t: round(fitted[t][0], 3) for t in PROMISE_TARGETS}
        detail[mode] = {t: {k: round(v, 3) for k, v in fitted[t][1].items()} for t in PROMISE_TARGETS}
    return {"coverage": coverage, "limits": limits, "enforce": False, "scales": scales, "per_family_scales": detail,
            "doc": "error_bound = scale x predicted error, a 90 % bound; with enforce true, reliable = every bound "
                   "is within its limit (false: reported only, reliable keeps the thresholds); scales: "
                   "split-conformal quantiles of actual / predicted error, each dataset family (YUD + crops, "
                   "ZInD-fR, NYU-VP; train splits) predicted by a model fitted without it, the largest kept "
                   "(python -m fr_eval.protocols.lodo_reliability promise --write; docs/reliability.md)"}


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m fr_eval.protocols.lodo_reliability", description=__doc__.split("\n")[0])
    parser.add_argument("action", choices=("table", "promise"))
    parser.add_argument("--cache", default=str(cache_root() / "lodo"))
    parser.add_argument("--focal-limit", type=float, default=DEFAULT_LIMITS["focal_pct"], help="T_f, percent")
    parser.add_argument("--tilt-limit", type=float, default=DEFAULT_LIMITS["tilt_deg"], help="T_t, degrees")
    parser.add_argument("--coverage", type=float, default=DEFAULT_COVERAGE)
    parser.add_argument("--scale-rule", choices=SCALE_RULES, default="worst",
                        help="table: conformal scale = the largest per-family quantile (worst, shipped) or one "
                             "quantile over all out-of-family predictions (pooled)")
    parser.add_argument("--out", default=str(REPO / "results" / "cross_dataset"))
    parser.add_argument("--write", action="store_true", help="promise: write it into configs/reliability.json")
    args = parser.parse_args(argv)
    limits = {"focal_pct": args.focal_limit, "tilt_deg": args.tilt_limit}
    cache = Path(args.cache)
    if args.action == "table":
        table = lodo_table(cache, limits, args.coverage, rule=args.scale_rule)
        out = Path(args.out)
        out.mkdir(parents=True, exist_ok=True)
        stem = f"reliability_f{args.focal_limit:g}_t{args.tilt_limit:g}" + (
            "" if args.scale_rule == "worst" else f"_{args.scale_rule}")
        table.to_csv(out / f"{stem}.csv", index=False)
        text = markdown(table, limits, args.coverage)
        (out / f"{stem}.md").write_text(text + "\n")
        print(text)
        return 0
    block = shipped_promise(cache, limits, args.coverage)
    if args.write:
        path = REPO / "configs" / "reliability.json"
        config = json.loads(path.read_text())
        block["enforce"] = bool(config.get("promise", {}).get("enforce", False))  # the owner's choice stays
        config["promise"] = block
        path.write_text(json.dumps(config, indent=1) + "\n")
    print(json.dumps(block, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
