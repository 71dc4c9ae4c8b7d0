"""Radial distortion (issue 46): fR with and without the division model on distorted and undistorted sets.

    python -m fr_eval.protocols.distortion_eval run --datasets zind-fr-d,yud-crop-480x360-d --split test \\
        --methods "fr,fr[distortion=division],fast-fr[distortion=division],fr[distortion=auto]"
    python -m fr_eval.protocols.distortion_eval table --out results/distortion

``run`` calibrates every image of each dataset with each method (batches of ``--batch-size``) and
caches one CSV per (dataset, split, method) under ``$FR_CACHE/distortion`` (a method already
cached is skipped: the command resumes).  Per image: focal / roll / tilt errors
(:func:`fr_eval.scoring.metrics.image_errors`), the true and estimated k and their border bows
(:func:`fr_torch.core.distortion.border_bow_percent`, % of the width), ``reliable`` and its reason,
and the "lines bend" cue.  ``table`` writes ``results/distortion/README.md``'s tables from the cache
and the figure of estimated against true k.

Method specs: ``fr`` / ``fast-fr`` with options ``distortion=pinhole|division|auto``, ``k=K`` (known)
and any :class:`fr_torch.core.config.SearchConfig` field of the distortion search
(``distortion_grid_points``, ``distortion_grid_segments``, ``grid_passes``, ...) for screening on
the train splits.
"""
from __future__ import annotations

import argparse
import math
import os
from dataclasses import fields
from pathlib import Path

import numpy as np
import pandas as pd
from fr_eval.datasets.registry import load_dataset
from fr_eval.paths import cache_root
from fr_eval.protocols.run_eval import given_segments
from fr_eval.scoring.metrics import image_errors, mean_se
from fr_eval.scoring.tables import parse_method_spec
from tqdm import tqdm

from fr_torch.core.config import SearchConfig
from fr_torch.core.cues import LINE_BEND_CUES
from fr_torch.core.distortion import border_bow_percent
from fr_torch.runtime.estimator import FREstimator

MODES = {"fr": "fr", "fast-fr": "fast"}
#: Datasets of the issue's table: the distorted sets and the undistorted ones division must not hurt.
DISTORTED = ("zind-fr-d", "yud-crop-480x360-d")
UNDISTORTED = ("zind-fr", "yud-crop-480x360", "yud", "nyu-vp")


def make_estimator(spec: str) -> FREstimator:
    """An estimator for a method spec (module docstring)."""
    name, options = parse_method_spec(spec)
    if name not in MODES:
        raise ValueError(f"{spec}: method must be one of {', '.join(MODES)}")
    options = dict(options)
    distortion, k = options.pop("distortion", None), options.pop("k", None)
    known = {f.name: f.type for f in fields(SearchConfig)}
    overrides = {}
    for key, value in options.items():
        if key not in known:
            raise ValueError(f"{spec}: unknown option {key!r}")
        overrides[key] = _number_or_text(value)
    config = SearchConfig.from_config(**overrides)
    return FREstimator(mode=MODES[name], search_config=config, distortion=distortion,
                       k=None if k is None else float(k))


def _number_or_text(value: str):
    for kind in (int, float):
        try:
            return kind(value)
        except ValueError:
            pass
    return value


def cache_file(dataset: str, split: str, spec: str) -> Path:
    safe = spec.replace("[", "(").replace("]", ")").replace("/", "_").replace(",", ";")
    return cache_root() / "distortion" / f"{dataset}_{split}" / f"{safe}.csv"


def image_row(sample, result) -> dict:
    """One image's record: errors, k (true and estimated), bows, reliability."""
    true_k = float(sample.extra.get("distortion_k", 0.0)) if sample.extra else 0.0
    errors = image_errors(sample, result)
    est_k = result.distortion_k if result.ok else math.nan
    bow = border_bow_percent(true_k, sample.width, sample.height)
    est_bow = border_bow_percent(est_k, sample.width, sample.height) if result.ok else math.nan
    return {"image": sample.name, "ok": result.ok, "reliable": bool(result.reliable), "reason": result.reason,
            **errors, "k_true": true_k, "k_est": est_k, "k_err": abs(est_k - true_k), "bow_true_pct": bow,
            "bow_est_pct": est_bow, "bow_err_pct": abs(est_bow - bow),
            "model": result.distortion_model if result.ok else "",
            **{name: result.cues.get(name, math.nan) for name in LINE_BEND_CUES},
            "focal_px": result.focal_px if result.ok else math.nan,
            "log_likelihood": result.log_likelihood if result.ok else math.nan,
            "runtime_s": result.runtime_s.get("total", math.nan)}


def run_method(dataset: str, split: str, spec: str, batch_size: int, limit: int | None, progress: bool) -> Path:
    """Calibrate ``dataset``/``split`` with ``spec``; write (and return) its cache CSV."""
    target = cache_file(dataset, split, spec)
    if target.is_file():
        return target
    samples = load_dataset(dataset, split=split)
    if limit:
        samples = samples[:limit]
    estimator = make_estimator(spec)
    rows = []
    for start in tqdm(range(0, len(samples), batch_size), desc=f"{dataset} {spec}", disable=not progress):
        chunk = samples[start:start + batch_size]
        given = [given_segments(s) for s in chunk]
        if all(g is not None for g in given):  # a dataset without pixels (NYU-VP): its own segments
            results = estimator.calibrate_segments(given, [(s.width, s.height) for s in chunk],
                                                   names=[s.name for s in chunk])
        else:
            results = estimator.calibrate_images([str(s.image_path) for s in chunk], names=[s.name for s in chunk])
        rows += [image_row(s, r) for s, r in zip(chunk, results)]
    target.parent.mkdir(parents=True, exist_ok=True)
    pd.DataFrame(rows).to_csv(target.with_suffix(".tmp"), index=False)
    os.replace(target.with_suffix(".tmp"), target)
    return target


def summary(frame: pd.DataFrame) -> dict:
    """Mean +- SE of the errors, median k error, share of reliable estimates."""
    out = {}
    for column in ("focal_err_pct", "roll_err_deg", "tilt_err_deg", "k_err", "bow_err_pct"):
        out[column] = mean_se(frame[column].tolist())
    out["k_err_median"] = float(np.nanmedian(frame["k_err"])) if len(frame) else math.nan
    out["bow_err_median"] = float(np.nanmedian(frame["bow_err_pct"])) if len(frame) else math.nan
    out["reliable_pct"] = 100.0 * float(frame["reliable"].mean()) if len(frame) else math.nan
    out["n"] = len(frame)
    return out


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)
    run = sub.add_parser("run", help="calibrate datasets with methods into the cache")
    run.add_argument("--datasets", required=True)
    run.add_argument("--split", default="test")
    run.add_argument("--methods", required=True, help="method specs separated by ';' (or ',' outside brackets)")
    run.add_argument("--batch-size", type=int, default=8)
    run.add_argument("--limit", type=int, default=None, help="first N images only (screening)")
    run.add_argument("--no-progress", action="store_true")
    table = sub.add_parser("table", help="print a summary of cached runs")
    table.add_argument("--datasets", required=True)
    table.add_argument("--split", default="test")
    table.add_argument("--methods", required=True)
    args = parser.parse_args(argv)
    methods = split_specs(args.methods)
    for dataset in args.datasets.split(","):
        for spec in methods:
            if args.command == "run":
                run_method(dataset, args.split, spec, args.batch_size, args.limit, not args.no_progress)
            else:
                path = cache_file(dataset, args.split, spec)
                if not path.is_file():
                    print(f"{dataset} {spec}: not run")
                    continue
                s = summary(pd.read_csv(path))
                print(f"{dataset:22s} {spec:45s} n={s['n']:4d} focal {s['focal_err_pct'][0]:6.2f}±{s['focal_err_pct'][1]:.2f} "
                      f"roll {s['roll_err_deg'][0]:5.2f}±{s['roll_err_deg'][1]:.2f} tilt {s['tilt_err_deg'][0]:5.2f}±"
                      f"{s['tilt_err_deg'][1]:.2f} k med {s['k_err_median']:.4f} mean {s['k_err'][0]:.4f} "
                      f"bow med {s['bow_err_median']:.3f} rel {s['reliable_pct']:.0f}%")
    return 0


def split_specs(text: str) -> list[str]:
    """Method specs separated by ',' outside brackets (or by ';')."""
    specs, depth, current = [], 0, ""
    for char in text:
        if char in "[(":
            depth += 1
        elif char in "])":
            depth -= 1
        if (char == "," and depth == 0) or char == ";":
            specs.append(current.strip())
            current = ""
        else:
            current += char
    if current.strip():
        specs.append(current.strip())
    return specs


if __name__ == "__main__":
    raise SystemExit(main())
