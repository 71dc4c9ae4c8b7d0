"""Does the promise of ``reliable`` hold on another line detector's segments?  torch-lines vs LSD, same photos.

Usage (``eval/reproduce.sh lodo``, after the promise's scales are written; runs are cached, a rerun
computes what is missing)::

    python -m fr_eval.protocols.detector_reliability run      # the runs (data_local/lodo/shipped/)
    python -m fr_eval.protocols.detector_reliability table    # results/reliability/torch_lines.{md,csv,png}

Every (dataset, split) of :data:`DATASETS` is estimated by fR and Fast-fR with the shipped settings
(FOV range [30, 120] deg across the long side, image-centre principal point), once per detector of
:data:`DETECTORS`, on the same photos (:func:`fr_eval.protocols.lodo.run_predictions`, setting
``shipped``: the LSD train runs are the files of the LODO protocol's reliability stage).  For another
detector the reliability stage is the shipped one with that detector among its promise's
``validated_detectors`` (:func:`calibrator`), so ``reliable`` is what the library gives once the
detector is declared -- whether or not ``configs/reliability.json`` declares it.

Reported per (mode, dataset, detector), with the shipped promise (90 % bounds = the shipped scale x the
estimate's own spreads, :mod:`fr_torch.core.reliability.bounds`; limits focal 10 %, tilt 3 deg):
precision, recall and share of ``reliable`` (:func:`fr_eval.protocols.lodo_reliability.evaluate`;
"good" = within both limits), the focal MAE of the reliable photos and of all, the share within each
bound, each error's own 90 % quantile of actual / sigma (the scale the detector's photos would need;
the shipped one is the largest over the calibration families), the focal bound's Spearman rho and
AURC / oracle, and the KNN's ``predicted_error`` (rho with the focal error, mean predicted / mean
actual).  Train rows are also pooled per family (YUD with its crops, ZInD-fR: :data:`FAMILY_ROWS`),
the unit the scales were fitted on.

:func:`verdict` applies the decision rule of results/decisions/45.md to the train families.  The
shipped scales were fitted on the LSD records of these train splits (and NYU-VP's): the LSD train
rows are in-sample, the test rows "as installed".
"""
from __future__ import annotations

import argparse
import math
import sys
from dataclasses import replace
from pathlib import Path
from typing import Sequence

import numpy as np
import pandas as pd
from scipy.stats import spearmanr

from fr_eval.paths import REPO, cache_root
from fr_eval.protocols.lodo import SHIPPED, family_of, prediction_path, run_predictions
from fr_eval.protocols.lodo_reliability import ERROR_OF, METHOD_OF_MODE, MODE_LABEL, evaluate, records_from_predictions
from fr_eval.scoring.plots import risk_coverage_panel, save_figure
from fr_torch.core.reliability.bounds import PROMISE_TARGETS, SIGMAS, ReliabilityPromise, conformal_scale
from fr_torch.core.reliability.model import ReliabilityModel

DETECTORS = ("lsd", "torch-lines")
#: (dataset, split) of every run: the test splits first (as installed), then the train splits.
DATASETS = (("yud", "test"), ("yud-crop-400x300", "test"), ("yud-crop-480x360", "test"), ("zind-fr", "test"),
            ("yud", "train"), ("yud-crop-400x300", "train"), ("yud-crop-480x360", "train"), ("zind-fr", "train"))
#: Pooled rows: label -> the (dataset, split) runs they pool (the train families the scales were fitted on).
FAMILY_ROWS = {"YUD family train": (("yud", "train"), ("yud-crop-400x300", "train"), ("yud-crop-480x360", "train")),
               "ZInD-fR train": (("zind-fr", "train"),)}
#: The decision rule's floor on precision (%), where LSD's reaches it (results/decisions/45.md).
PRECISION_FLOOR_PCT = 90.0


def method_name(mode: str, detector: str) -> str:
    """``fr`` / ``fast-fr`` with ``[detector=...]`` for a detector other than LSD."""
    return METHOD_OF_MODE[mode] + ("" if detector == "lsd" else f"[detector={detector}]")


def calibrator(mode: str, detector: str, device: str = "cpu"):
    """The method of ``mode`` on ``detector``'s segments on ``device``, its reliability stage the
    shipped one with ``detector`` declared validated (None for LSD on the CPU: the shipped method as
    :func:`~fr_eval.protocols.lodo.run_predictions` builds it)."""
    if detector == "lsd" and device == "cpu":
        return None
    from fr_eval.protocols.run_eval import make_calibrator
    from fr_torch.core.settings.fov import FovRange

    model = ReliabilityModel.load_default(mode)
    if model is None or model.promise is None:
        raise RuntimeError("the shipped reliability model or its promise is missing (configs/reliability*.json)")
    if detector not in model.detectors:
        model = replace(model, promise=replace(model.promise,
                                               validated_detectors=(*model.promise.validated_detectors, detector)))
    return make_calibrator(method_name(mode, detector), device, FovRange.parse(None), reliability=model)


def run_all(cache: Path, root: str | None = None, only: Sequence[str] | None = None, device: str = "cpu") -> None:
    """Every run of :data:`DATASETS` x modes x :data:`DETECTORS` not cached yet (``only``: those
    datasets) on ``device`` (runs on another device than the CPU belong in a cache of their own)."""
    for dataset, split in DATASETS:
        if only and dataset not in only:
            continue
        for mode in ("fr", "fast"):
            for detector in DETECTORS:
                method = method_name(mode, detector)
                path = prediction_path(cache, SHIPPED, dataset, split, method)
                if path.is_file():
                    continue
                print(f"== {dataset} {split} {method}", file=sys.stderr)
                run_predictions(dataset, split, method, SHIPPED, None, cache, root=root,
                                calibrator=calibrator(mode, detector, device))


def _predictions(cache: Path, dataset: str, split: str, mode: str, detector: str) -> pd.DataFrame:
    path = prediction_path(cache, SHIPPED, dataset, split, method_name(mode, detector))
    if not path.is_file():
        raise FileNotFoundError(f"{path} is missing: run `python -m fr_eval.protocols.detector_reliability run`")
    return pd.read_csv(path)


def shipped_bounds(records: pd.DataFrame, mode: str, promise: ReliabilityPromise) -> dict[str, np.ndarray]:
    """target -> (n,) the shipped promise's bound of each record (scale x sigma)."""
    return {t: promise.scales[mode][t] * np.asarray(SIGMAS[t](records), np.float64) for t in PROMISE_TARGETS}


def row_figures(records: pd.DataFrame, mode: str, promise: ReliabilityPromise) -> dict:
    """The table's figures of one set of records (module docstring)."""
    bounds = shipped_bounds(records, mode, promise)
    limits = dict(promise.limits)
    shipped = evaluate(records, bounds, limits, flagged=records["reliable"].to_numpy(bool))
    by_bounds = evaluate(records, bounds, limits)
    focal = records["focal_err_pct"].to_numpy(np.float64)
    predicted = records["pred_err_focal_pct"].to_numpy(np.float64)
    own = {t: conformal_scale(SIGMAS[t](records), records[ERROR_OF[t]].to_numpy(np.float64), promise.coverage)
           for t in PROMISE_TARGETS}
    return {**shipped, "bounds_precision_pct": by_bounds["precision_pct"], "bounds_recall_pct": by_bounds["recall_pct"],
            "bounds_coverage_pct": by_bounds["coverage_pct"],
            "q_focal": own["focal_pct"], "q_tilt": own["tilt_deg"],
            "scale_focal": promise.scales[mode]["focal_pct"], "scale_tilt": promise.scales[mode]["tilt_deg"],
            "knn_rho_focal": float(spearmanr(predicted, focal, nan_policy="omit").statistic),
            "knn_level": float(np.nanmean(predicted) / np.nanmean(focal))}


def detector_table(cache: Path, promise: ReliabilityPromise | None = None) -> pd.DataFrame:
    """One row per (mode, dataset split or pooled train family, detector)."""
    promise = promise or ReliabilityPromise.from_config()
    rows = []
    for mode in ("fr", "fast"):
        for detector in DETECTORS:
            records, images = {}, {}
            for dataset, split in DATASETS:
                table = _predictions(cache, dataset, split, mode, detector)
                records[dataset, split] = records_from_predictions(table, dataset, mode)
                images[dataset, split] = len(table)
                rows.append({"mode": mode, "rows": f"{dataset} {split}", "family": family_of(dataset), "split": split,
                             "detector": detector, "images": len(table),
                             **row_figures(records[dataset, split], mode, promise)})
            for label, parts in FAMILY_ROWS.items():
                pooled = pd.concat([records[p] for p in parts], ignore_index=True)
                rows.append({"mode": mode, "rows": label, "family": family_of(parts[0][0]), "split": "train pooled",
                             "detector": detector,
                             "images": sum(images[p] for p in parts),
                             **row_figures(pooled, mode, promise)})
    return pd.DataFrame(rows)


def verdict(table: pd.DataFrame, detector: str = "torch-lines") -> tuple[bool, list[str]]:
    """The decision rule (results/decisions/45.md) on the pooled train families, per mode: the
    promise holds for ``detector`` when on every family its precision is at least
    :data:`PRECISION_FLOOR_PCT` wherever LSD's is, and at least the lowest of LSD's family
    precisions (within LSD's per-family spread).  (holds, one line per mode and family)."""
    lines, holds = [], True
    pooled = table[table["split"] == "train pooled"]
    for mode in ("fr", "fast"):
        lsd = pooled[(pooled["mode"] == mode) & (pooled["detector"] == "lsd")].set_index("rows")
        other = pooled[(pooled["mode"] == mode) & (pooled["detector"] == detector)].set_index("rows")
        lowest = float(lsd["precision_pct"].min())
        for family in lsd.index:
            mine, theirs = float(other.loc[family, "precision_pct"]), float(lsd.loc[family, "precision_pct"])
            floor = PRECISION_FLOOR_PCT if theirs >= PRECISION_FLOOR_PCT else -math.inf
            ok = mine >= floor and mine >= lowest
            holds &= ok
            lines.append(f"{MODE_LABEL[mode]}, {family}: {detector} precision {mine:.1f} % vs LSD {theirs:.1f} % "
                         f"(LSD's lowest family {lowest:.1f} %): {'holds' if ok else 'FAILS'}")
    return holds, lines


def _pct(value: float) -> str:
    return "—" if math.isnan(value) else f"{value:.0f} %"


def markdown(table: pd.DataFrame, promise: ReliabilityPromise) -> str:
    lines = [f"Shipped promise: {round(100 * promise.coverage)} % bounds (scale x the estimate's own spreads), "
             f"focal <= {promise.limits['focal_pct']:g} %, tilt <= {promise.limits['tilt_deg']:g}°; fR and Fast-fR "
             "with the shipped settings, FOV range [30°, 120°] across the long side, image-centre principal point; "
             "each detector on the same photos (n: photos with an estimate / photos). *reliable*: the flag the "
             "estimator gives (sanity checks and the promise) with the detector declared validated; *precision*: "
             "of the reliable photos, the share within both limits; *recall*: of the photos within both limits, "
             "the share reliable. *q90 / scale*: each error's own 90 % quantile of actual / sigma against the "
             "shipped scale (below 1: the bound is wider than this set needs). *KNN*: `predicted_error`'s Spearman "
             "ρ with the focal error and its mean over the mean focal error.", "",
             "| mode | photos | detector | n | within both | reliable | precision | recall | "
             "focal MAE reliable / all (%) | within bound (focal, tilt) | q90 / scale (focal, tilt) | "
             "ρ focal bound | AURC / oracle | KNN ρ, level |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in table.itertuples():
        label = f"**{r.rows}**" if r.split == "train pooled" else r.rows
        reliable_mae = "—" if math.isnan(r.reliable_focal_mae) else f"{r.reliable_focal_mae:.2f}"
        lines.append(f"| {MODE_LABEL[r.mode]} | {label} | {r.detector} | {r.n} / {r.images} | {r.good_pct:.0f} % | "
                     f"{r.reliable_n} ({r.coverage_pct:.0f} %) | {_pct(r.precision_pct)} | {_pct(r.recall_pct)} | "
                     f"{reliable_mae} / {r.focal_mae:.2f} | {r.bound_holds_focal:.0f} %, {r.bound_holds_tilt:.0f} % | "
                     f"{r.q_focal / r.scale_focal:.2f}, {r.q_tilt / r.scale_tilt:.2f} | {r.rho_focal:.2f} | "
                     f"{r.aurc_ratio:.2f} | {r.knn_rho_focal:.2f}, {r.knn_level:.2f} |")
    return "\n".join(lines)


def risk_coverage_figure(cache: Path, path: Path, promise: ReliabilityPromise) -> Path:
    """Focal MAE of the photos kept vs the share kept, in the order of the shipped focal bound, per
    detector (solid) with its oracle (dotted): rows = modes, columns = the test sets and the pooled
    train families."""
    import matplotlib.pyplot as plt

    panels = [(f"{d} {s}", ((d, s),)) for d, s in DATASETS if s == "test"] + list(FAMILY_ROWS.items())
    fig, axes = plt.subplots(2, len(panels), figsize=(3.2 * len(panels), 6.0), squeeze=False)
    for i, mode in enumerate(("fr", "fast")):
        for j, (label, parts) in enumerate(panels):
            curves = []
            for detector, color in zip(DETECTORS, ("C0", "C3")):
                records = pd.concat([records_from_predictions(_predictions(cache, *p, mode, detector), p[0], mode)
                                     for p in parts], ignore_index=True)
                focal = records["focal_err_pct"].to_numpy(np.float64)
                curves += [(detector, shipped_bounds(records, mode, promise)["focal_pct"], focal, f"{color}-"),
                           (None, focal, focal, f"{color}:")]
            risk_coverage_panel(axes[i, j], curves, f"{MODE_LABEL[mode]}, {label}", j == 0)
    return save_figure(fig, path, "Photos kept in the order of the shipped focal bound, per detector (dotted: "
                                  "oracle; AURC / oracle in brackets)")


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m fr_eval.protocols.detector_reliability",
                                     description=__doc__.split("\n")[0])
    parser.add_argument("action", choices=("run", "table"))
    parser.add_argument("--cache", default=str(cache_root() / "lodo"))
    parser.add_argument("--data-root", default=None)
    parser.add_argument("--only", default="", help="run: comma-separated datasets (default: all)")
    parser.add_argument("--device", default="cpu",
                        help="run: where the estimator runs (e.g. cuda; with a --cache of its own)")
    parser.add_argument("--out", default=str(REPO / "results" / "reliability" / "torch_lines"),
                        help="table: output stem (.md, .csv, .png)")
    args = parser.parse_args(argv)
    cache = Path(args.cache)
    if args.action == "run":
        run_all(cache, args.data_root, [d for d in args.only.split(",") if d], args.device)
        return 0
    promise = ReliabilityPromise.from_config()
    table = detector_table(cache, promise)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    table.to_csv(out.with_suffix(".csv"), index=False)
    holds, lines = verdict(table)
    text = markdown(table, promise) + "\n\nDecision rule (results/decisions/45.md), pooled train families:\n\n" + \
        "\n".join(f"* {line}" for line in lines) + f"\n\nThe promise {'holds' if holds else 'does not hold'} for torch-lines."
    out.with_suffix(".md").write_text(text + "\n")
    risk_coverage_figure(cache, out.with_suffix(".png"), promise)
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
