"""``fr eval --task vp``: vanishing points scored with CONSAC's metric, per method and intrinsics.

Example::

    fr eval --task vp --dataset nyu-vp --split val --methods fr,fast-fr,"fr[atlanta=on]",lee2009,simon2018,consac
    fr eval --task vp --dataset yud+ --split test --methods fr,consac --intrinsics unknown

Datasets: any whose samples carry labelled vanishing directions (``extra["vp_directions"]`` (M, 3)
and the calibration ``extra["vp_calibration"]`` (3, 3) that turns a method's VPs into directions):
``nyu-vp`` (``train`` 0-999, ``val`` 1000-1223), ``yud+`` (CONSAC's split of YorkUrbanDB, every
labelled VP) and ``yud`` (the same photos and split with the three Manhattan VPs only, as CONSAC
evaluates "YUD": :data:`VP_DATASET_ALIASES`; **not** the ECCV split of ``fr eval --dataset yud``).

Each method runs once per ``--intrinsics`` setting: ``unknown`` (nothing given: focal length
searched, principal point at the image centre) and ``known`` (the dataset's focal length and
calibrated principal point given, ``--known-focal --pp calibrated``).  A method that ignores the
intrinsics (attribute ``uses_intrinsics = False``, e.g. CONSAC) runs once and its answers fill both
columns.  Scoring (:mod:`fr_eval.scoring.vp_metric`, docs/vp.md): the estimate's
``ranked_vanishing_points`` (else the camera's three Manhattan VPs in column order; a failed
estimate without points scores 90 degrees per labelled VP) against the labelled directions,
errors pooled over the split, AUC at 5 / 10 / 20 degrees.  An estimate's
``extra["vp_variants"]`` ({name: (M, 3) ranked points}) adds rows ``<method> (<name>)`` scored
from the same run (CONSAC's VPs before EM).

Outputs (``--out``, default ``results/vp/<dataset>-<split>``): ``vp_errors.csv`` (one row per
labelled VP: method, intrinsics, image, index, error), ``vp_summary.{md,csv,tex}`` (rows methods,
columns AUC@5/10/20 and unmatched VPs per intrinsics setting, time per image), ``vp_recall.png``
(recall curves up to 20 degrees), ``run_info.json``.

``--reuse METHODS`` (:mod:`fr_eval.protocols.reuse`) takes those methods' rows (their variant rows
``<method> (<name>)`` too) from the ``vp_errors.csv`` already in ``--out`` and their time per image
from its ``vp_summary.csv``, instead of running them; the old run must have had the same
``--intrinsics`` settings.
"""
from __future__ import annotations

import argparse
import json
import platform
import sys
import time
from pathlib import Path
from typing import Any, Sequence

import numpy as np
import pandas as pd
from fr_eval.datasets.registry import load_dataset
from fr_eval.machine import machine_description
from fr_eval.paths import REPO
from fr_eval.protocols import reuse
from fr_eval.protocols.run_eval import (
    _call,
    _na_reason,
    build_calibrators,
    build_meta,
    load_samples,
    parse_fov_range,
    split_methods,
)
from fr_eval.scoring.plots import safe_name, vp_recall_figure
from fr_eval.scoring.tables import to_latex, to_markdown
from fr_eval.scoring.vp_metric import AUC_CUTOFFS_DEG, MISSING_VP_DEG, auc_table, directions_from_vps, match_errors
from tqdm import tqdm

from fr_torch.images.io import load_image
from fr_torch.plugins.interface import CameraEstimate

INTRINSICS = ("unknown", "known")
#: ``fr eval --task vp --dataset yud`` = YUD+'s photos and split (CONSAC's) with the 3 Manhattan VPs.
VP_DATASET_ALIASES = {"yud": ("yud+", {"manhattan_only": True})}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The options only the VP task has (the others are ``fr eval``'s)."""
    parser.add_argument("--intrinsics", default=",".join(INTRINSICS),
                        help="VP task: comma-separated settings to run: 'unknown' (focal searched, principal point at "
                             "the image centre) and/or 'known' (the dataset's focal length and calibrated principal "
                             "point given); default both")


def ranked_points(estimate: CameraEstimate | None) -> np.ndarray | None:
    """(M, 3) the VPs an estimate offers for scoring, most confident first, or None (module docstring)."""
    if estimate is None:
        return None
    points = estimate.ranked_vanishing_points
    if points is None and estimate.ok:
        points = estimate.vanishing_points  # the camera's three, column order
    return _usable(points)


def _usable(points) -> np.ndarray | None:
    """Rows that are finite and not zero, (M, 3); None when there are none."""
    if points is None:
        return None
    points = np.asarray(points, np.float64).reshape(-1, 3)
    keep = np.isfinite(points).all(1) & (np.linalg.norm(points, axis=1) > 0)
    return points[keep] if keep.any() else None


def image_errors(sample: Any, points: np.ndarray | None) -> np.ndarray:
    """Errors (degrees) of the labelled VPs of ``sample`` against ranked points (M, 3) or None."""
    truth = np.asarray(sample.extra["vp_directions"], np.float64).reshape(-1, 3)
    estimated = None if points is None else directions_from_vps(points, sample.extra["vp_calibration"])
    return match_errors(truth, estimated)


def run_setting(spec: str, calibrator, samples: Sequence[Any], intrinsics: str, dataset: str, device: str,
                progress: bool = True) -> tuple[dict[str, list[np.ndarray | None]], list[float], list[str]]:
    """One method under one intrinsics setting: ({row name: ranked points per image}, run times (s),
    failure reasons per image ("" = ok)).  The first image is estimated twice and the second, warm
    run timed (as ``fr eval``)."""
    known = intrinsics == "known"
    per_image: list[dict[str, np.ndarray | None]] = []
    times, reasons = [], []
    for i, sample in enumerate(tqdm(samples, desc=f"{spec} ({intrinsics})", unit="img",
                                    disable=not progress or not sys.stderr.isatty(), file=sys.stderr)):
        meta = build_meta(sample, "calibrated" if known else "centre", False, known, dataset, device)
        image = load_image(sample.image_path) if getattr(sample, "image_path", None) is not None else None
        estimate, wall = _call(calibrator, spec, image, meta)
        if i == 0 and _na_reason(estimate) is None:
            estimate, wall = _call(calibrator, spec, image, meta)
        found = {spec: ranked_points(estimate)}
        for name, variant in ((estimate.extra or {}).get("vp_variants") or {}).items():
            found[f"{spec} ({name})"] = _usable(variant)
        per_image.append(found)
        times.append(wall)
        reasons.append("" if estimate.ok else (estimate.reason or "failed"))
    names = list(dict.fromkeys(name for found in per_image for name in found))
    return {name: [found.get(name) for found in per_image] for name in names}, times, reasons


def summary_rows(errors: pd.DataFrame, times: dict[tuple[str, str], float], settings: Sequence[str]) -> pd.DataFrame:
    """One row per method: AUC@cutoffs (%) and unmatched VPs per setting, time per image (s)."""
    rows = []
    for method in dict.fromkeys(errors["method"]):
        row: dict[str, Any] = {"method": method}
        for setting in settings:
            chosen = errors[(errors["method"] == method) & (errors["intrinsics"] == setting)]
            if not len(chosen):
                continue
            values = chosen["error_deg"].to_numpy()
            for key, value in auc_table(values).items():
                row[f"{key}_{setting}"] = value
            row[f"unmatched_{setting}"] = int((values >= MISSING_VP_DEG).sum())
            row[f"n_vps_{setting}"] = len(values)
            row[f"time_s_{setting}"] = times.get((method.split(" (")[0], setting), np.nan)
        rows.append(row)
    return pd.DataFrame(rows)


def display_table(summary: pd.DataFrame, settings: Sequence[str]) -> pd.DataFrame:
    """The summary as strings: AUC columns per setting, unmatched, time per image."""
    out = pd.DataFrame({"method": summary["method"]})
    for setting in settings:
        label = "f unknown" if setting == "unknown" else "K known"
        for cutoff in AUC_CUTOFFS_DEG:
            key = f"auc{cutoff:g}_{setting}"
            if key in summary:
                out[f"AUC@{cutoff:g}° ({label})"] = [f"{v:.1f}" if np.isfinite(v) else "n/a" for v in summary[key]]
        if f"unmatched_{setting}" in summary:
            out[f"unmatched ({label})"] = [f"{int(u)}/{int(n)}" if np.isfinite(n) else "n/a" for u, n in
                                           zip(summary[f"unmatched_{setting}"].fillna(0),
                                               summary[f"n_vps_{setting}"].fillna(np.nan))]
    time_cols = [f"time_s_{s}" for s in settings if f"time_s_{s}" in summary]
    if time_cols:
        out["time per image (s)"] = [f"{v:.3f}" if np.isfinite(v) else "n/a"
                                     for v in summary[time_cols].mean(axis=1, skipna=True)]
    return out


def load_vp_samples(dataset: str, root=None, split: str = "test") -> list[Any]:
    """Samples of ``dataset`` (with :data:`VP_DATASET_ALIASES`) that carry VP labels; ValueError otherwise."""
    name, kwargs = VP_DATASET_ALIASES.get(dataset, (dataset, {}))
    samples = load_dataset(name, root=root, split=split, **kwargs)
    missing = [s.name for s in samples if "vp_directions" not in (getattr(s, "extra", None) or {})]
    if missing:
        raise ValueError(f"dataset {dataset!r} has no vanishing-point labels (extra['vp_directions']); "
                         "the VP task runs on nyu-vp, yud, yud+")
    return samples


def run(args: argparse.Namespace) -> int:
    methods = split_methods(args.methods)
    settings = [s.strip() for s in str(getattr(args, "intrinsics", ",".join(INTRINSICS))).split(",") if s.strip()]
    bad = [s for s in settings if s not in INTRINSICS]
    if not methods or not settings or bad:
        print(f"error: need methods and --intrinsics from {', '.join(INTRINSICS)}", file=sys.stderr)
        return 2
    fov_range = parse_fov_range(args)
    samples = None if fov_range is None else load_samples(args, load_vp_samples)
    if samples is None:
        return 2
    out_dir = Path(args.out) if args.out else REPO / "results" / "vp" / safe_name(f"{args.dataset}-{args.split}")
    try:
        previous = reuse.previous_run(args, out_dir, "vp_errors.csv", methods=methods, samples=samples,
                                      per={"intrinsics": settings}, settings={
                                          "task": "vp", "dataset": args.dataset, "split": args.split,
                                          "limit": args.limit, "fov_range_deg": list(fov_range),
                                          "intrinsics": settings})
        times = {(spec, setting): previous.value("vp_summary.csv", spec, f"time_s_{setting}")
                 for spec in reuse.reused_of(previous) for setting in settings}
    except reuse.ReuseError as exc:
        return reuse.refuse(exc)
    calibrators = build_calibrators(args, reuse.left_to_run(methods, previous), fov_range)
    if calibrators is None:
        return 2
    out_dir.mkdir(parents=True, exist_ok=True)
    error_rows = []
    for spec in methods:
        if spec not in calibrators:  # --reuse: the old run's rows (its time per image read above)
            error_rows += previous.rows_of(spec, samples, variants=True)
        calibrator, answers = calibrators.get(spec), None
        for setting in settings if calibrator is not None else ():
            if answers is None or getattr(calibrator, "uses_intrinsics", True):
                answers = run_setting(spec, calibrator, samples, setting, args.dataset, args.device,
                                      progress=not getattr(args, "no_progress", False))
            points, wall, reasons = answers
            times[(spec, setting)] = float(np.mean(wall))
            for name, per_image in points.items():
                for sample, pts, reason in zip(samples, per_image, reasons):
                    for index, error in enumerate(image_errors(sample, pts)):
                        error_rows.append({"method": name, "intrinsics": setting, "image": sample.name,
                                           "vp_index": index, "error_deg": float(error),
                                           "n_labelled": len(sample.extra["vp_directions"]),
                                           "n_estimated": 0 if pts is None else len(pts), "reason": reason})
        pd.DataFrame(error_rows).to_csv(out_dir / "vp_errors.csv", index=False)  # after each method
    errors = pd.DataFrame(error_rows)
    summary = summary_rows(errors, times, settings)
    summary.to_csv(out_dir / "vp_summary.csv", index=False)
    display = display_table(summary, settings)
    n_vps = int(sum(len(s.extra["vp_directions"]) for s in samples))
    title = f"Vanishing points: {args.dataset} {args.split} ({len(samples)} images, {n_vps} labelled VPs)"
    note = ("AUC (%) of the recall curve of the pooled VP errors up to 5 / 10 / 20°, CONSAC's metric (docs/vp.md): "
            "a method's VPs ranked by its confidence, the first as many as were labelled, Hungarian matching on "
            "the angle between lines of sight with the dataset's calibrated K, 90° per unmatched labelled VP. "
            "f unknown: focal length searched over the FOV range "
            f"{fov_range} (long side), principal point at the image centre; K known: the dataset's focal length and "
            "calibrated principal point given. A method that ignores intrinsics (CONSAC) runs once for both "
            "columns. Time per image: wall time of one estimate (s), one warm-up call excluded.")
    (out_dir / "vp_summary.md").write_text(f"# {title}\n\n" + to_markdown(display) + f"\n{note}\n", encoding="utf-8")
    (out_dir / "vp_summary.tex").write_text(to_latex(display, caption=title), encoding="utf-8")
    vp_recall_figure({setting: {method: errors[(errors["method"] == method) & (errors["intrinsics"] == setting)]
                                ["error_deg"].to_numpy() for method in dict.fromkeys(errors["method"])}
                      for setting in settings}, out_dir / "vp_recall.png", title)
    info = {"argv": sys.argv, "task": "vp", "methods": methods, "dataset": args.dataset, "split": args.split,
            "n_images": len(samples), "n_labelled_vps": n_vps, "intrinsics": settings,
            "fov_range_deg": list(fov_range), "device": args.device, "limit": args.limit,
            "python": platform.python_version(), "machine": machine_description(args.device),
            "date": time.strftime("%Y-%m-%d %H:%M:%S")}
    if previous is not None:
        info["reused"] = previous.provenance()
    (out_dir / "run_info.json").write_text(json.dumps(info, indent=2), encoding="utf-8")
    print((out_dir / "vp_summary.md").read_text(encoding="utf-8"))
    print(f"wrote {out_dir}/vp_errors.csv, vp_summary.md/.csv/.tex, vp_recall.png, run_info.json")
    return 0
