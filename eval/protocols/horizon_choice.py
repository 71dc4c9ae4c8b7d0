"""Learn the per-photo choice between fR's Manhattan fit and the horizon fit (``--fit choose``).

Usage::

    python -m fr_eval.protocols.horizon_choice train          # NYU-VP train -> configs/horizon_choice.json
    python -m fr_eval.protocols.horizon_choice train --dataset nyu-vp --split train --out results/horizon/choice

What it does: fR (mode ``fr``, the photos' own segments, principal point at the image centre, FOV
range of ``configs/search.json``) runs twice over the train split's photos that have a labelled
horizon: with ``--fit manhattan`` and with ``--fit horizon``.  The horizon run's cues hold the
choice's evidence (``choice_*``, :data:`fr_torch.core.search.choice.CHOICE_FEATURES`); the label of
a photo is whether the horizon run's horizon is nearer the labelled one than the Manhattan run's
(errors clipped at 25 % of the height, the benchmark's cutoff), weighted by how much nearer: the
rule minimises the clipped error it causes, not the number of wrong choices.  A logistic regression
on the standardised evidence, its regularisation ``C`` chosen by 5-fold cross-validation on the
same split (folds by photo), is the rule; its weights go to ``--config``
(:class:`fr_torch.core.search.choice.HorizonChooser` reads them) and the cross-validation table and
per-photo records to ``--out``.  No photo of a set a table reports is used: the shipped rule is
trained on NYU-VP train, and the horizon tables report ecd-tune, YUD and NYU-VP val.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import torch

from fr_eval.datasets.registry import load_dataset
from fr_eval.scoring.horizon_metric import lezama_auc, truth_horizons
from fr_torch.core.search.choice import CHOICE_FEATURES, CHOOSER_CONFIG, clean_evidence
from fr_torch.core.settings.config import SearchConfig
from fr_torch.resources import config_path

CUTOFF = 0.25
C_GRID = (0.01, 0.1, 1.0, 10.0, 100.0)


def records(dataset: str, split: str, mode: str = "fr") -> pd.DataFrame:
    """One row per photo with a labelled horizon: the two fits' errors (share of the height), the
    horizon run's model and its evidence (:data:`CHOICE_FEATURES`)."""
    from tqdm import tqdm

    from fr_torch import FREstimator

    samples = [s for s in load_dataset(dataset, split=split) if "labelled" in truth_horizons(s)]
    rows = {s.name: {"image": s.name} for s in samples}
    for fit in ("manhattan", "horizon"):
        estimator = FREstimator(mode=mode, search_config=SearchConfig.from_config(fit=fit))
        for start in tqdm(range(0, len(samples), 64), desc=f"{dataset} {split} --fit {fit}", unit="batch"):
            chunk = samples[start:start + 64]
            results = estimator.calibrate_segments([_segments(s) for s in chunk], [(s.width, s.height) for s in chunk],
                                                   names=[s.name for s in chunk])
            for sample, result in zip(chunk, results):
                horizon = result.horizon
                error = horizon.error(truth_horizons(sample)["labelled"]) if horizon is not None else np.inf
                rows[sample.name][f"error_{fit}"] = error
                if fit == "horizon":
                    rows[sample.name]["model"] = result.model
                    rows[sample.name].update({name: result.cues.get(f"choice_{name}", np.nan)
                                              for name in CHOICE_FEATURES})
    return pd.DataFrame(list(rows.values()))


def _segments(sample):
    segments = (sample.extra or {}).get("detected_segments")
    if segments is None:
        from fr_torch.detectors.registry import detect_segments
        from fr_torch.images.io import load_image

        segments = detect_segments(load_image(str(sample.image_path)))
    return segments


def design(table: pd.DataFrame) -> np.ndarray:
    """The evidence as :meth:`HorizonChooser.score` sees it (:func:`clean_evidence`)."""
    return clean_evidence(torch.from_numpy(table[list(CHOICE_FEATURES)].to_numpy(np.float64))).numpy()


def fit_rule(x: np.ndarray, gain: np.ndarray, c: float):
    """(mean, scale, coef, intercept) of a logistic regression of ``gain > 0`` on ``x`` weighted by
    ``|gain|``."""
    from sklearn.linear_model import LogisticRegression

    mean, scale = x.mean(0), x.std(0)
    scale = np.where(scale > 0, scale, 1.0)
    model = LogisticRegression(C=c, max_iter=1000).fit((x - mean) / scale, (gain > 0).astype(int),
                                                       sample_weight=np.abs(gain) + 1e-4)
    return mean, scale, model.coef_[0], float(model.intercept_[0])


def apply_rule(x: np.ndarray, rule) -> np.ndarray:
    mean, scale, coef, intercept = rule
    return ((x - mean) / scale) @ coef + intercept > 0


def train(args: argparse.Namespace) -> int:
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    cache = out / f"records_{args.dataset}_{args.split}.csv"
    table = pd.read_csv(cache, dtype={"image": str}) if cache.exists() and not args.no_cache else \
        records(args.dataset, args.split)
    table.to_csv(cache, index=False)
    usable = (table.model == "horizon").to_numpy()
    manhattan = np.minimum(table.error_manhattan.to_numpy(np.float64), CUTOFF)
    horizon = np.where(usable, np.minimum(table.error_horizon.to_numpy(np.float64), CUTOFF), manhattan)
    gain = manhattan - horizon
    x = design(table)
    folds = np.arange(len(table)) % 5
    rng = np.random.default_rng(0)
    folds = folds[rng.permutation(len(table))]
    lines = ["| C | AUC (cross-validated) | horizon chosen | mean clipped error (% of h) |", "|---|---|---|---|"]
    best = None
    for c in C_GRID:
        chosen = np.zeros(len(table), bool)
        for k in range(5):
            train_rows = (folds != k) & usable
            chosen[folds == k] = apply_rule(x[folds == k], fit_rule(x[train_rows], gain[train_rows], c))
        chosen &= usable
        error = np.where(chosen, horizon, manhattan)
        auc = 100 * lezama_auc(error)[0]
        lines.append(f"| {c:g} | {auc:.2f} | {100 * chosen.mean():.0f} % | {100 * error.mean():.3f} |")
        if best is None or error.mean() < best[1]:
            best = (c, error.mean())
    c = best[0]
    mean, scale, coef, intercept = fit_rule(x[usable], gain[usable], c)
    config = {"features": list(CHOICE_FEATURES), "mean": mean.tolist(), "scale": scale.tolist(),
              "coef": coef.tolist(), "intercept": intercept, "C": c,
              "trained_on": f"{args.dataset} {args.split} ({int(usable.sum())} of {len(table)} photos with a horizon "
                            "fit; python -m fr_eval.protocols.horizon_choice train)"}
    Path(args.config).write_text(json.dumps(config, indent=1) + "\n")
    summary = [f"# The horizon choice, learned on {args.dataset} {args.split}", "",
               f"{len(table)} photos with a labelled horizon; {int(usable.sum())} where the horizon fit found a "
               "camera in the box. AUC of the per-photo choice, 5-fold cross-validated on this split, by the "
               "regularisation C; for reference the Manhattan fit alone "
               f"{100 * lezama_auc(manhattan)[0]:.2f}, the horizon fit wherever it runs "
               f"{100 * lezama_auc(horizon)[0]:.2f}, the better of the two per photo (an oracle) "
               f"{100 * lezama_auc(np.minimum(manhattan, horizon))[0]:.2f}.", "", *lines, "",
               f"Chosen: C = {c:g}; weights in `{os.path.relpath(args.config)}` (standardised evidence):", "",
               "| evidence | weight |", "|---|---|",
               *[f"| {name} | {w:+.3f} |" for name, w in zip(CHOICE_FEATURES, coef)], f"| (intercept) | {intercept:+.3f} |",
               ""]
    (out / "train.md").write_text("\n".join(summary))
    print("\n".join(summary))
    return 0


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m fr_eval.protocols.horizon_choice", description=__doc__.split("\n")[0])
    sub = parser.add_subparsers(dest="command", required=True)
    command = sub.add_parser("train", help="learn the rule on a train split")
    command.add_argument("--dataset", default="nyu-vp")
    command.add_argument("--split", default="train")
    command.add_argument("--out", default="results/horizon/choice")
    command.add_argument("--config", default=str(config_path(CHOOSER_CONFIG)))
    command.add_argument("--no-cache", action="store_true", help="recompute the records even when --out holds them")
    args = parser.parse_args(argv)
    return train(args)


if __name__ == "__main__":
    sys.exit(main())
