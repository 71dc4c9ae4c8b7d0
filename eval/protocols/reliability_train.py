"""``fr train-reliability``: run fR over training images, record cues + errors, fit the error predictor.

Examples::

    # default models shipped in configs/ (ZInD-fR train + YUD train + 300 synthetic scenes)
    fr train-reliability --dataset zind-fr,yud --split train --method fr --extra-synthetic 300
    fr train-reliability --dataset zind-fr,yud --split train --method fast --extra-synthetic 300
    # + the held-out reliability table (results/reliability/)
    fr train-reliability --dataset zind-fr,yud --split train --method fr --extra-synthetic 300 \\
        --report-dataset zind-fr --report-split test --report-dir results/reliability

What is recorded per image (one CSV row, cached under ``--records``, default
``results/reliability/records/<dataset>_<split>_<mode>.csv``; delete it or pass ``--no-cache`` to
recompute): the cues of :meth:`fr_torch.runtime.estimator.FREstimator._cues`, the estimate, the ground
truth and the absolute errors

* ``roll_err_deg`` = ``|roll_est - roll_gt|`` and ``tilt_err_deg`` = ``|tilt_est - tilt_gt|``, both
  angles with the paper's horizon definitions (:func:`fr_torch.core.geometry.conventions.horizon_angles`; the same
  numbers as ``eval/scoring/metrics.py``);
* ``focal_err_pct`` = ``100 |f_est - f_gt| / f_gt``.

The estimator runs as ``fr calibrate`` does (unknown focal length, principal point at the image
centre).  Images whose estimate failed (``ok`` False) are kept in the CSV but not used for fitting.
``group`` (panorama for ZInD-fR, image for YUD, scene for synthetic data) keeps correlated views in
the same cross-validation fold.

Synthetic training scenes (``--extra-synthetic N``): :func:`synthetic_records` draws a random
camera (pan +-45, pitch +-30, roll +-10 deg, horizontal FOV 50-120 deg at 640 x 480) and a random
difficulty -- per-family segment counts log-uniform in [2, 80], endpoint noise 0.3-3 px, clutter
share 0-75 % -- and calibrates the segments with :meth:`FREstimator.calibrate_segments`; every
``render_every``-th scene is instead rendered with :func:`fr_torch.synthetic.render_manhattan_room`
(320 x 240, image noise 2-12 grey levels) and goes through the line detector.  Never train on a
split you report on: the report split must differ from the training split (checked).
"""
from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd

from fr_eval.paths import REPO
from fr_torch.core.geometry.conventions import focal_from_hfov, rotation_angles
from fr_torch.core.reliability.model import (
    ERROR_COLUMNS,
    FR_MODEL_CUE_NAMES,
    MODEL_CUE_NAMES,
    PAPER_CUE_NAMES,
    ReliabilityModel,
    model_cue_names,
)
from fr_torch.resources import config_dir

DEFAULT_RECORDS = REPO / "results" / "reliability" / "records"


# ---------------------------------------------------------------------------------- records

def _record(result, gt: dict) -> dict:
    """One CSV row: identity, GT, estimate, cues, absolute errors (NaN when the estimate failed)."""
    row = dict(gt)
    row.update(ok=bool(result.ok), sanity_reliable=bool(result.reliable), num_segments=int(result.num_segments),
               manhattan_fraction=result.manhattan_fraction, reason=result.reason)
    for name in FR_MODEL_CUE_NAMES:
        row[name] = result.cues.get(name, math.nan) if result.ok else math.nan
    row.update(est_focal_px=result.focal_px, est_roll_deg=result.roll_deg, est_tilt_deg=result.tilt_deg)
    if result.ok:
        row["roll_err_deg"] = abs(result.roll_deg - gt["gt_roll_deg"])
        row["tilt_err_deg"] = abs(result.tilt_deg - gt["gt_tilt_deg"])
        row["focal_err_pct"] = 100.0 * abs(result.focal_px - gt["gt_focal_px"]) / gt["gt_focal_px"]
    else:
        row.update(roll_err_deg=math.nan, tilt_err_deg=math.nan, focal_err_pct=math.nan)
    row["runtime_s"] = result.runtime_s.get("total", math.nan)
    return row


def dataset_records(dataset: str, split: str, mode: str, data_root=None, batch_size: int = 8,
                    limit: int | None = None, progress: bool = True) -> pd.DataFrame:
    """Run FREstimator(mode) over a registered evaluation dataset (``fr_eval.datasets``)."""
    from tqdm import tqdm

    from fr_eval.datasets.registry import load_dataset
    from fr_torch.runtime.estimator import FREstimator

    samples = load_dataset(dataset, root=data_root, split=split)
    samples = [s for s in samples if s.focal_px and s.roll_deg is not None and s.tilt_deg is not None]
    if limit:
        samples = samples[:limit]
    if not samples:
        raise ValueError(f"{dataset} {split}: no samples with ground-truth focal, roll and tilt")
    estimator = FREstimator(mode=mode, reliability=None, profile_gap=mode == "fr")  # the raw sanity flag and cues
    rows = []
    bar = tqdm(total=len(samples), desc=f"{mode} on {dataset}/{split}", disable=not progress, file=sys.stderr)
    for start in range(0, len(samples), batch_size):
        chunk = samples[start:start + batch_size]
        results = estimator.calibrate_images([str(s.image_path) for s in chunk], names=[s.name for s in chunk])
        for s, r in zip(chunk, results):
            extra = s.extra if isinstance(s.extra, dict) else {}
            # group = scene: views of one panorama, or a crop and the photo it was cut from
            group = f"{extra.get('scene_source') or dataset}:{extra.get('pano', s.name)}"
            gt = dict(source=dataset, split=split, name=s.name, group=group, width=s.width,
                      height=s.height, gt_focal_px=float(s.focal_px), gt_roll_deg=float(s.roll_deg),
                      gt_tilt_deg=float(s.tilt_deg), gt_hfov_deg=s.hfov_deg)
            rows.append(_record(r, gt))
        bar.update(len(chunk))
    bar.close()
    return pd.DataFrame(rows)


def synthetic_records(count: int, mode: str, seed: int = 0, batch_size: int = 8, render_every: int = 5,
                      progress: bool = True) -> pd.DataFrame:
    """``count`` synthetic scenes of random camera and difficulty (see the module docstring)."""
    from tqdm import tqdm

    from fr_torch.runtime.estimator import FREstimator
    from fr_torch.synthetic import random_rotation, render_manhattan_room, synthetic_segments

    rng = np.random.default_rng(seed)
    estimator = FREstimator(mode=mode, reliability=None, profile_gap=mode == "fr")  # the raw sanity flag and cues
    rows = []
    bar = tqdm(total=count, desc=f"{mode} on synthetic", disable=not progress, file=sys.stderr)
    for start in range(0, count, batch_size):
        seg_items, img_items = [], []
        for i in range(start, min(count, start + batch_size)):
            rotation = random_rotation(rng)
            hfov = rng.uniform(50.0, 120.0)
            rendered = render_every > 0 and i % render_every == render_every - 1
            width, height = (320, 240) if rendered else (640, 480)
            focal = float(focal_from_hfov(hfov, width))
            angles = rotation_angles(rotation)
            gt = dict(source="synthetic-render" if rendered else "synthetic", split="train", name=f"syn{seed}_{i:05d}",
                      group=f"synthetic:{seed}_{i}", width=width, height=height, gt_focal_px=focal,
                      gt_roll_deg=float(angles["roll_deg"]), gt_tilt_deg=float(angles["tilt_deg"]), gt_hfov_deg=hfov)
            if rendered:
                image = render_manhattan_room(focal, rotation, width, height, seed=int(rng.integers(1 << 30)),
                                              noise_sigma=float(rng.uniform(2, 12)))
                img_items.append((image, gt))
            else:
                segs, labels = synthetic_segments(focal, rotation, width, height, n_per_family=80,
                                                  noise_px=float(rng.uniform(0.3, 3.0)),
                                                  clutter_fraction=0.0, seed=int(rng.integers(1 << 30)))
                keep = []
                for family in range(3):  # independent, log-uniform family sizes in [2, 80]
                    idx = np.flatnonzero(labels == family)
                    n = int(round(math.exp(rng.uniform(math.log(2), math.log(80)))))
                    keep.append(rng.permutation(idx)[:n])
                manhattan = segs[np.concatenate(keep)]
                share = rng.uniform(0.0, 0.75)
                n_clutter = int(round(share / (1 - share) * len(manhattan)))
                centre = np.stack([rng.uniform(0, width, n_clutter), rng.uniform(0, height, n_clutter)], 1)
                angle = rng.uniform(0, np.pi, n_clutter)
                half = rng.uniform(15, 120, n_clutter)[:, None] / 2
                offset = np.stack([np.cos(angle), np.sin(angle)], 1) * half
                clutter = np.concatenate([centre - offset, centre + offset], 1)
                seg_items.append((np.concatenate([manhattan, clutter]), gt))
        if seg_items:
            results = estimator.calibrate_segments([s for s, _ in seg_items], [(g["width"], g["height"]) for _, g in seg_items],
                                                   names=[g["name"] for _, g in seg_items])
            rows += [_record(r, g) for r, (_, g) in zip(results, seg_items)]
        if img_items:
            results = estimator.calibrate_images([im for im, _ in img_items], names=[g["name"] for _, g in img_items])
            rows += [_record(r, g) for r, (_, g) in zip(results, img_items)]
        bar.update(len(seg_items) + len(img_items))
    bar.close()
    return pd.DataFrame(rows)


def cached(path: Path, make, use_cache: bool = True) -> pd.DataFrame:
    """Read ``path`` if it exists (and ``use_cache``), else ``make()`` and write it."""
    if use_cache and path.is_file():
        return pd.read_csv(path)
    frame = make()
    path.parent.mkdir(parents=True, exist_ok=True)
    frame.to_csv(path, index=False)
    return frame


def gather(datasets: list[str], split: str, mode: str, extra_synthetic: int, records_dir: Path, data_root=None,
           batch_size: int = 8, use_cache: bool = True, seed: int = 0, limit: int | None = None) -> pd.DataFrame:
    frames = []
    for name in datasets:
        path = records_dir / f"{name}_{split}_{mode}.csv"
        frames.append(cached(path, lambda: dataset_records(name, split, mode, data_root, batch_size, limit), use_cache))
    if extra_synthetic:
        path = records_dir / f"synthetic{extra_synthetic}_seed{seed}_{mode}.csv"
        frames.append(cached(path, lambda: synthetic_records(extra_synthetic, mode, seed, batch_size), use_cache))
    return pd.concat(frames, ignore_index=True)


def unrecorded_cues(frame: pd.DataFrame, cue_names) -> list[str]:
    """The cues of ``cue_names`` that no record of ``frame`` has: no column, or no finite value
    (focal_profile_gap in Fast-fR's records)."""
    return [name for name in cue_names
            if name not in frame.columns or not np.isfinite(frame[name].to_numpy(float)).any()]


def usable(frame: pd.DataFrame, cue_names=MODEL_CUE_NAMES) -> pd.DataFrame:
    """Rows with an estimate, finite cues (of ``cue_names``) and finite errors."""
    missing = [name for name in cue_names if name not in frame.columns]
    if missing:
        raise ValueError(f"records lack the cue columns {missing} (written by an older version): "
                         "recompute them with --no-cache")
    absent = unrecorded_cues(frame, cue_names) if len(frame) else []
    if absent:
        raise ValueError(f"no record has the cues {absent} (Fast-fR does not compute focal_profile_gap; an older "
                         "version wrote none: recompute with --no-cache)")
    cols = list(cue_names) + list(ERROR_COLUMNS)
    ok = frame["ok"].astype(bool) & np.isfinite(frame[cols].to_numpy(float)).all(1)
    return frame[ok].reset_index(drop=True)


# ---------------------------------------------------------------------------------- reliability table

FRACTIONS = (0.25, 0.5, 0.75, 1.0)


def reliability_table(frame: pd.DataFrame, predicted: np.ndarray, rank_by: str, scales=None) -> pd.DataFrame:
    """MAE of roll / tilt / focal over the fraction of images predicted most reliable.

    ``rank_by``: ``"focal"`` (predicted focal error), ``"roll"``, ``"tilt"`` or ``"combined"``
    (sum of the three predicted errors each divided by ``scales`` -- by default the model's
    thresholds -- i.e. the largest share of its threshold).
    """
    from fr_torch.core.reliability.model import TARGETS

    if rank_by == "combined":
        scales = np.asarray(scales if scales is not None else [1.0, 1.0, 1.0], float)
        score = (predicted / scales).sum(1)
    else:
        score = predicted[:, TARGETS.index({"roll": "roll_deg", "tilt": "tilt_deg", "focal": "focal_pct"}[rank_by])]
    order = np.argsort(score, kind="stable")
    errors = frame[list(ERROR_COLUMNS)].to_numpy(float)
    rows = []
    for fraction in FRACTIONS:
        n = max(1, int(round(fraction * len(order))))
        sel = errors[order[:n]]
        rows.append({"ranking": rank_by, "fraction_kept": fraction, "n": n,
                     "roll_mae_deg": sel[:, 0].mean(), "tilt_mae_deg": sel[:, 1].mean(),
                     "focal_mae_pct": sel[:, 2].mean()})
    return pd.DataFrame(rows)


def spearman(predicted: np.ndarray, frame: pd.DataFrame) -> dict[str, float]:
    from scipy.stats import spearmanr

    from fr_torch.core.reliability.model import TARGETS

    actual = frame[list(ERROR_COLUMNS)].to_numpy(float)
    return {t: float(spearmanr(predicted[:, j], actual[:, j]).statistic) for j, t in enumerate(TARGETS)}


def write_report(model: ReliabilityModel, test: pd.DataFrame, out_dir: Path, title: str, command: str,
                 train_info: dict) -> dict:
    """Markdown + CSV + PNG reliability table on the held-out frame ``test``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out_dir.mkdir(parents=True, exist_ok=True)
    predicted = model.predict(test[list(model.cue_names)].to_numpy(float))
    scales = [model.thresholds[t] for t in model.thresholds] if model.thresholds else None
    tables = {rank: reliability_table(test, predicted, rank, scales) for rank in ("focal", "combined")}
    rho = spearman(predicted, test)
    mode = model.meta.get("mode", "?")
    table = pd.concat(tables.values(), ignore_index=True)
    table.insert(0, "method", mode)
    csv_path = out_dir / f"reliability_{mode}.csv"
    table.to_csv(csv_path, index=False, float_format="%.4f")
    pd.DataFrame([{"method": mode, **{f"spearman_{k}": v for k, v in rho.items()}}]).to_csv(
        out_dir / f"spearman_{mode}.csv", index=False, float_format="%.4f")

    fig, axes = plt.subplots(1, 3, figsize=(12, 3.6))
    for ax, col, label in zip(axes, ("roll_mae_deg", "tilt_mae_deg", "focal_mae_pct"),
                              ("roll MAE (deg)", "tilt MAE (deg)", "focal MAE (%)")):
        for rank, t in tables.items():
            ax.plot(100 * t["fraction_kept"], t[col], "o-", label=f"ranked by {rank}")
        # fine-grained curve for the primary ranking
        order = np.argsort(predicted[:, 2], kind="stable")
        err = test[col.replace("_mae", "_err")].to_numpy(float)[order]
        ks = np.arange(1, len(err) + 1)
        ax.plot(100 * ks / len(err), np.cumsum(err) / ks, "-", color="grey", lw=0.8, alpha=0.7)
        ax.set_xlabel("% of images kept (most reliable first)")
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=8)
    fig.suptitle(f"{title} ({mode}): MAE vs fraction kept")
    fig.tight_layout()
    png = out_dir / f"mae_vs_fraction_{mode}.png"
    fig.savefig(png, dpi=110)
    plt.close(fig)

    lines = [f"# Reliability table: {title}, method {mode}", "",
             f"Command: `{command}`", "",
             f"Held-out images with an estimate: {len(test)} (images where fR returned no estimate, e.g. no line "
             "segments detected, are left out of the table).  "
             f"Model: K = {model.k} nearest neighbours chosen by 5-fold CV, trained on {train_info}.", "",
             "MAE over the images predicted most reliable.  Primary ranking: **predicted focal error** "
             "(`ranked by focal`); `combined` ranks by the sum of the three predicted errors, each divided "
             f"by its threshold ({model.thresholds}).", ""]
    for rank, t in tables.items():
        full = t.iloc[-1]
        lines += [f"## Ranked by {rank}", "", "| kept | n | roll MAE (deg) | tilt MAE (deg) | focal MAE (%) |",
                  "|---:|---:|---:|---:|---:|"]
        for _, r in t.iterrows():
            lines.append(f"| {100 * r.fraction_kept:.0f} % | {int(r.n)} | {r.roll_mae_deg:.2f} | {r.tilt_mae_deg:.2f} "
                         f"| {r.focal_mae_pct:.2f} |")
        top = t.iloc[0]
        lines += ["", f"Top 25 % / 100 %: roll {top.roll_mae_deg / full.roll_mae_deg:.2f}, tilt "
                  f"{top.tilt_mae_deg / full.tilt_mae_deg:.2f}, focal {top.focal_mae_pct / full.focal_mae_pct:.2f} "
                  "(goal for focal: <= 0.50).", ""]
    lines += ["## Spearman correlation, predicted vs actual absolute error", "",
              "| roll | tilt | focal |", "|---:|---:|---:|",
              f"| {rho['roll_deg']:.3f} | {rho['tilt_deg']:.3f} | {rho['focal_pct']:.3f} |", "",
              f"Plot: `{png.name}` (dots: 25/50/75/100 %; grey: running MAE for the focal ranking).", "",
              "Paper (Table 4, PanoContext-fR test, top 25 % vs all): roll 0.56 vs 0.74 deg, tilt 0.68 vs 1.42 deg, "
              "focal 2.8 vs 8.3 %.", ""]
    md = out_dir / f"reliability_{mode}.md"
    md.write_text("\n".join(lines))
    return {"table": table, "spearman": rho, "markdown": md, "png": png, "csv": csv_path}


def _focal_score(frame: pd.DataFrame, predicted: np.ndarray) -> tuple[float, float]:
    """(focal MAE of the 25 % predicted most reliable / focal MAE of all, Spearman rho of predicted vs
    actual focal error)."""
    from scipy.stats import spearmanr

    err = frame[list(ERROR_COLUMNS)].to_numpy(float)
    order = np.argsort(predicted[:, 2], kind="stable")[:max(1, len(frame) // 4)]
    return err[order, 2].mean() / err[:, 2].mean(), spearmanr(predicted[:, 2], err[:, 2]).statistic


def fit_model(frame: pd.DataFrame, cue_names=MODEL_CUE_NAMES, **kwargs) -> ReliabilityModel:
    """:meth:`ReliabilityModel.fit` on training records (cues of ``cue_names``, errors, groups);
    ``kwargs`` (``k_grid``, ``seed``, ``meta``) go to it."""
    return ReliabilityModel.fit(frame[list(cue_names)].to_numpy(float), frame[list(ERROR_COLUMNS)].to_numpy(float),
                                groups=frame["group"].to_numpy(str), cue_names=cue_names, **kwargs)


def out_of_fold(target: pd.DataFrame, rest: pd.DataFrame | None = None, cue_names=MODEL_CUE_NAMES,
                folds: int = 5) -> np.ndarray:
    """Predicted errors (n, 3) for every row of ``target``, each from a model that did not see its
    group: ``folds`` folds grouped by ``group``; ``rest`` (other training data) is always in training."""
    from sklearn.model_selection import GroupKFold

    pred = np.zeros((len(target), 3))
    for tr, te in GroupKFold(folds).split(target, groups=target["group"]):
        fit_on = target.iloc[tr] if rest is None else pd.concat([target.iloc[tr], rest])
        pred[te] = fit_model(fit_on, cue_names).predict(target.iloc[te][list(cue_names)].to_numpy(float))
    return pred


def compare_training_sets(variants: dict[str, pd.DataFrame], target: pd.DataFrame, test: pd.DataFrame,
                          out: Path, mode: str, cue_names=MODEL_CUE_NAMES, folds: int = 5) -> pd.DataFrame:
    """Which training data helps: for each named training set, (a) out-of-fold on ``target`` (the
    target-domain training split; folds grouped, the rest of the variant always in training) and
    (b) on the held-out ``test``: focal MAE of the top 25 % (ranked by predicted focal error) over
    all, and Spearman rho of predicted vs actual focal error.  Select on (a); (b) is for information.
    Every model uses the cues ``cue_names``."""
    rows = []
    for name, data in variants.items():
        rest = data[~data["name"].isin(target["name"]) | (data["source"] != target["source"].iloc[0])]
        oof_ratio, oof_rho = _focal_score(target, out_of_fold(target, rest, cue_names, folds=folds))
        model = fit_model(data, cue_names)
        test_ratio, test_rho = _focal_score(test, model.predict(test[list(model.cue_names)].to_numpy(float)))
        rows.append({"training_set": name, "n": len(data), "k": model.k, "oof_top25_focal_ratio": oof_ratio,
                     "oof_spearman_focal": oof_rho, "test_top25_focal_ratio": test_ratio,
                     "test_spearman_focal": test_rho})
    table = pd.DataFrame(rows)
    table.to_csv(out / f"training_sets_{mode}.csv", index=False, float_format="%.3f")
    lines = [f"# Which training data ({mode})", "",
             "Focal MAE of the 25 % predicted most reliable divided by the MAE of all (lower is better) and "
             "Spearman rho of predicted vs actual focal error.  `oof`: out-of-fold on the ZInD-fR *train* split "
             "(5 folds grouped by panorama; the selection criterion); `test`: model fitted on the whole set, "
             "scored on the held-out test split (information only).", "",
             "| training set | n | K | oof top25/all | oof rho | test top25/all | test rho |",
             "|---|---:|---:|---:|---:|---:|---:|"]
    for r in rows:
        lines.append(f"| {r['training_set']} | {r['n']} | {r['k']} | {r['oof_top25_focal_ratio']:.2f} | "
                     f"{r['oof_spearman_focal']:.2f} | {r['test_top25_focal_ratio']:.2f} | {r['test_spearman_focal']:.2f} |")
    (out / f"training_sets_{mode}.md").write_text("\n".join(lines) + "\n")
    return table


#: Candidate model inputs compared by :func:`compare_cue_sets` (a set with a cue the records lack,
#: focal_profile_gap for Fast-fR, is left out); the shipped models use ``model_cue_names(mode)``.
CUE_SETS = {"paper": PAPER_CUE_NAMES, "paper+focal_conditioning": PAPER_CUE_NAMES + ("focal_conditioning",),
            "paper+focal_prior_share": MODEL_CUE_NAMES,
            "paper+focal_conditioning+focal_prior_share": PAPER_CUE_NAMES + ("focal_conditioning", "focal_prior_share"),
            "paper+focal_prior_share+focal_profile_gap": MODEL_CUE_NAMES + ("focal_profile_gap",), "all": FR_MODEL_CUE_NAMES}
#: ``--cues`` choices; None: the shipped model's cues of the mode (:func:`model_cue_names`).
CUE_CHOICES = {"default": None, "paper": PAPER_CUE_NAMES, "all": FR_MODEL_CUE_NAMES}


def compare_cue_sets(train: pd.DataFrame, test: pd.DataFrame, out: Path, mode: str, folds: int = 5) -> pd.DataFrame:
    """Which cues help: for each cue set of :data:`CUE_SETS`, (a) out of fold on the training data
    (folds grouped by panorama / image), scored per training source, and (b) a model fitted on all
    training data scored on the held-out ``test``: Spearman rho of predicted vs actual focal error
    and the focal MAE of the top 25 % over all.  Select on (a); (b) is for information."""
    rows = []
    for name, names in CUE_SETS.items():
        if unrecorded_cues(train, names):
            continue  # a cue this mode does not compute
        oof = out_of_fold(train, cue_names=names, folds=folds)
        model = fit_model(train, names)
        row = {"cues": name, "k": model.k}
        for source in sorted(train["source"].unique()):
            mask = (train["source"] == source).to_numpy()
            row[f"oof_{source}_top25_focal_ratio"], row[f"oof_{source}_spearman_focal"] = _focal_score(
                train[mask], oof[mask])
        predicted = model.predict(test[list(names)].to_numpy(float))
        row["test_top25_focal_ratio"], row["test_spearman_focal"] = _focal_score(test, predicted)
        rho = spearman(predicted, test)
        row["test_spearman_roll"], row["test_spearman_tilt"] = rho["roll_deg"], rho["tilt_deg"]
        rows.append(row)
    table = pd.DataFrame(rows)
    table.to_csv(out / f"cues_{mode}.csv", index=False, float_format="%.3f")
    sources = sorted(train["source"].unique())
    lines = [f"# Which cues ({mode})", "",
             "Spearman rho of predicted vs actual focal error (higher is better) and the focal MAE of the 25 % "
             "predicted most reliable divided by the MAE of all (lower is better).  `oof`: out of fold on the "
             f"*train* splits ({folds} folds grouped by panorama / image; the selection criterion), scored per "
             "dataset; `test`: model fitted on all training data, scored on the held-out test split "
             "(information only; roll and tilt rho show the added cue does not cost the angles).", "",
             "| cues | K | " + " | ".join(f"oof {s} rho | oof {s} top25/all" for s in sources)
             + " | test rho | test top25/all | test rho roll / tilt |",
             "|---|---:|" + "---:|---:|" * len(sources) + "---:|---:|---:|"]
    for r in rows:
        cells = " | ".join(f"{r[f'oof_{s}_spearman_focal']:.2f} | {r[f'oof_{s}_top25_focal_ratio']:.2f}" for s in sources)
        lines.append(f"| {r['cues']} | {r['k']} | {cells} | {r['test_spearman_focal']:.2f} | "
                     f"{r['test_top25_focal_ratio']:.2f} | {r['test_spearman_roll']:.2f} / {r['test_spearman_tilt']:.2f} |")
    lines += ["", f"Figure `cues_{mode}.png`: each training image's focal error against its `focal_conditioning` "
              "and its `focal_prior_share`."]
    (out / f"cues_{mode}.md").write_text("\n".join(lines) + "\n")
    _plot_focal_cues(train, out / f"cues_{mode}.png", mode)
    return table


#: (cue, axis label, x scale, x limits) of the panels of :func:`_plot_focal_cues`.
_FOCAL_CUE_PANELS = (
    ("focal_conditioning", "focal_conditioning (0 = VPs on the principal point or at infinity)", "linear", (0.0, 0.9)),
    ("focal_prior_share", "focal_prior_share (1 = the focal prior alone sets f)", "log", (1e-3, 1.2)),
)


def _plot_focal_cues(train: pd.DataFrame, png: Path, mode: str) -> None:
    """|focal error| (%, log scale) against ``focal_conditioning`` and ``focal_prior_share``, one
    panel each, points coloured by training source."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(_FOCAL_CUE_PANELS), figsize=(11, 4), sharey=True)
    for ax, (cue, label, scale, limits) in zip(axes, _FOCAL_CUE_PANELS):
        for source, part in train.groupby("source"):
            ax.scatter(part[cue].clip(lower=limits[0]), part["focal_err_pct"].clip(lower=0.01), s=10,
                       alpha=0.6, label=f"{source} train (n = {len(part)})")
        ax.set_xscale(scale)
        ax.set_yscale("log")
        ax.set_xlim(*limits)
        ax.set_xlabel(label)
        ax.grid(alpha=0.3, which="both")
    axes[0].set_ylabel("|focal error| (%, floored at 0.01)")
    axes[0].legend(fontsize=8)
    fig.suptitle(f"{mode}: focal error vs the focal cues")
    fig.tight_layout()
    fig.savefig(png, dpi=110)
    plt.close(fig)


# ---------------------------------------------------------------------------------- CLI

def trained_for(mode: str) -> dict[str, str]:
    """The setting the records of :func:`gather` come from (the estimator's defaults: the default
    likelihood config and its deviation measure, LSD), stored as the model's ``meta["trained_for"]``
    (:attr:`fr_torch.core.reliability.model.ReliabilityModel.trained_for`)."""
    from fr_torch.core.likelihood.mixture import LikelihoodParams

    return {"measure": LikelihoodParams.from_config(mode=mode).measure, "detector": "lsd", "likelihood": "default"}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--dataset", default="zind-fr",
                        help="comma-separated registered datasets to train on (zind-fr, yud, ...); '' for none")
    parser.add_argument("--split", default="train", help="training split (default train)")
    parser.add_argument("--method", choices=("fr", "fast"), default="fr", help="estimator mode (default fr)")
    parser.add_argument("--out", type=Path, default=None,
                        help="model file (default configs/reliability_<method>.npz; a .json sidecar is written too)")
    parser.add_argument("--extra-synthetic", type=int, default=0, metavar="N",
                        help="add N synthetic scenes of random camera and difficulty to the training data")
    parser.add_argument("--data-root", default=None, help="dataset root (default $FR_DATA or ../shared/data)")
    parser.add_argument("--records", type=Path, default=DEFAULT_RECORDS, help="cache folder of per-image records")
    parser.add_argument("--no-cache", action="store_true", help="recompute records even when cached")
    parser.add_argument("--batch-size", type=int, default=8)
    parser.add_argument("--limit", type=int, default=None, help="at most this many images per dataset (debug)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--k-grid", default=None, help="comma-separated candidate K (default: built-in grid)")
    parser.add_argument("--report-dataset", default=None,
                        help="comma-separated held-out datasets for the reliability table (e.g. zind-fr)")
    parser.add_argument("--report-split", default="test")
    parser.add_argument("--report-dir", type=Path, default=REPO / "results" / "reliability")
    parser.add_argument("--cues", choices=tuple(CUE_CHOICES), default="default",
                        help="cues the model uses: default (the paper's three and focal_prior_share; for fr "
                             "focal_profile_gap too), paper (min_family_segments, grid_entropy, "
                             "mean_log_likelihood) or all (every cue; fr only)")
    parser.add_argument("--compare-synthetic", type=int, default=0, metavar="N",
                        help="with a report: also compare training sets with/without N synthetic scenes "
                             "(training_sets_<method>.md)")


def run(args: argparse.Namespace) -> int:
    datasets = [d for d in args.dataset.split(",") if d]
    report = [d for d in (args.report_dataset or "").split(",") if d]
    if report and args.report_split == args.split and set(report) & set(datasets):
        raise ValueError(f"refusing to report on {args.split!r}: it is the training split")
    start = time.time()
    frame = gather(datasets, args.split, args.method, args.extra_synthetic, args.records, args.data_root,
                   args.batch_size, not args.no_cache, args.seed, args.limit)
    cue_names = CUE_CHOICES[args.cues] or model_cue_names(args.method)
    train = usable(frame, cue_names)
    if len(train) < 10:
        raise ValueError(f"only {len(train)} usable training images")
    k_grid = [int(k) for k in args.k_grid.split(",")] if args.k_grid else None
    sizes = train.groupby("source").size().to_dict()
    command = " ".join(["fr train-reliability"] + sys.argv[2:])
    model = fit_model(train, cue_names, k_grid=k_grid, seed=args.seed,
                      meta={"mode": args.method, "training_data": sizes, "split": args.split,
                            "trained_for": trained_for(args.method),
                            "failed_or_dropped": int(len(frame) - len(train)), "command": command})
    out = args.out or config_dir() / f"reliability_{args.method}.npz"
    model.save(out)
    print(f"trained on {len(train)} images {sizes}; K = {model.k} (CV loss {model.meta['cv_loss'][str(model.k)]:.4f}); "
          f"saved {out} ({time.time() - start:.0f} s)")
    if report:
        test = usable(gather(report, args.report_split, args.method, 0, args.records, args.data_root,
                             args.batch_size, not args.no_cache, args.seed, args.limit), cue_names)
        title = "+".join(report) + f" {args.report_split}"
        info = write_report(model, test, args.report_dir, title, command, f"{len(train)} images {sizes}")
        print(info["table"].to_string(index=False))
        print("spearman", json.dumps({k: round(v, 3) for k, v in info["spearman"].items()}))
        if args.cues == "default":
            print(compare_cue_sets(train, test, args.report_dir, args.method).to_string(index=False))
        if args.compare_synthetic and datasets:
            syn = usable(gather([], args.split, args.method, args.compare_synthetic, args.records, args.data_root,
                                args.batch_size, not args.no_cache, args.seed), cue_names)
            parts = {d: train[train["source"] == d] for d in datasets}
            variants = {datasets[0]: parts[datasets[0]], "+".join(datasets): train}
            variants["+".join(datasets) + f"+synthetic{args.compare_synthetic}"] = pd.concat([train, syn])
            variants[f"{datasets[0]}+synthetic{args.compare_synthetic}"] = pd.concat([parts[datasets[0]], syn])
            print(compare_training_sets(variants, parts[datasets[0]], test, args.report_dir, args.method,
                                        cue_names).to_string(index=False))
    return 0
