"""``fr eval --task horizon``: the horizon benchmark (Barinova 2010, Lezama 2014, Zhai 2016) for any
method behind the common interface.

Example::

    fr eval --task horizon --dataset yud --split test --methods fr,fast-fr,lee2009,simon2018,consac
    fr eval --task horizon --dataset ecd-tune --split all --methods fr
    fr eval --task horizon --dataset yud --split test --methods fr,oracle-fr --pp calibrated --known-focal

Datasets: any whose samples carry a ground-truth horizon (:func:`fr_eval.scoring.horizon_metric.truth_horizons`):
``yud`` (definitions ``labelled``, ``lezama-code`` and ``frame``: :mod:`fr_eval.datasets.yud`),
``ecd-tune`` (``labelled``), ``nyu-vp`` (``labelled`` where two horizontal VPs are labelled, ``frame``),
and any dataset with a ground-truth camera (``frame``).  Each method's horizon is
:meth:`fr_torch.core.geometry.horizon.Horizon.from_camera` of its estimate (focal length and vertical, through
its lens when it estimated one); the options ``--pp`` and ``--known-focal`` give every method the
calibrated principal point / the focal length, as for the camera task.

Scoring (:mod:`fr_eval.scoring.horizon_metric`): per photo the larger vertical distance between the
estimated and the labelled horizon at the borders ``x = 0`` and ``x = w - 1``, in % of the image height;
over the split the AUC of its cumulative curve on [0, 25 %] exactly as Lezama et al.'s ``calc_auc.m``
(a failure counts as beyond 25 %).  Every column names its ground-truth definition.  A method that
reports a 90 % bound of its horizon error (fR: ``horizon.bound_pct``) gets its coverage, the share
of photos whose error is within the bound.  Published numbers (:data:`PUBLISHED`) are added as
external rows on the data they were published for.

Outputs (``--out``, default ``results/horizon/<dataset>-<split>``): ``horizon_errors.csv`` (one row
per method and photo: both border crossings of the estimate and of every ground truth, the error
per definition, the bound, run time, failure reason), ``horizon_summary.{md,csv,tex}``,
``horizon_curves.png`` (the cumulative error curves, one panel per definition), ``run_info.json``.

``--reuse METHODS`` (:mod:`fr_eval.protocols.reuse`) takes those methods' rows (run time included)
from the ``horizon_errors.csv`` already in ``--out`` instead of running them.
"""
from __future__ import annotations

import argparse
import json
import math
import platform
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

import numpy as np
import pandas as pd

from fr_eval.machine import machine_description
from fr_eval.paths import REPO
from fr_eval.protocols.run_eval import (
    evaluate_method,
    load_samples,
    parse_fov_range,
    range_caption,
    reuse_and_build,
    split_methods,
)
from fr_eval.scoring.horizon_metric import CUTOFF, definition_notes, estimate_horizon, lezama_auc, truth_horizons
from fr_eval.scoring.metrics import failure_reason, is_failure
from fr_eval.scoring.plots import recall_figure, safe_name
from fr_eval.scoring.tables import to_latex, to_markdown

#: Definitions in the order the tables show them (others follow in the order met).
DEFINITION_ORDER = ("labelled", "lezama-code", "frame")


@dataclass(frozen=True)
class PublishedRow:
    """A published horizon AUC (%) on ``dataset`` / ``split`` against ground-truth ``definition``."""

    method: str
    dataset: str
    split: str
    definition: str
    auc: float
    source: str


PUBLISHED = (
    PublishedRow("Zhai 2016 (published)", "yud", "all", "lezama-code", 94.78,
                 "Zhai, Workman & Jacobs, Detecting vanishing points using global image context in a non-Manhattan "
                 "world, CVPR 2016, Table 1"),
    PublishedRow("Lezama 2014 (published)", "yud", "all", "lezama-code", 94.51,
                 "Lezama, Grompone von Gioi, Randall & Morel, Finding vanishing points via point alignments in image "
                 "primal and dual domains, CVPR 2014, as reported by Zhai 2016, Table 1"),
)


def horizon_row(spec: str, sample: Any, estimate, wall_s: float) -> dict[str, Any]:
    """One photo's row of ``horizon_errors.csv`` (module docstring); errors in % of the height (inf:
    no horizon)."""
    failed = is_failure(estimate)
    horizon = None if failed else estimate_horizon(estimate)
    row: dict[str, Any] = {"method": spec, "image": sample.name, "width": int(sample.width),
                           "height": int(sample.height), "failed": bool(failed),
                           "reason": failure_reason(estimate) if failed else "", "runtime_s": wall_s,
                           "est_left_y": _number(horizon, "left_y"), "est_right_y": _number(horizon, "right_y"),
                           "bound_pct": _number(horizon, "bound_pct")}
    for name, truth in truth_horizons(sample).items():
        row[f"gt_{name}_left_y"], row[f"gt_{name}_right_y"] = truth.left_y, truth.right_y
        row[f"error_pct_{name}"] = 100.0 * horizon.error(truth) if horizon is not None else math.inf
    return row


def _number(horizon, key: str) -> float:
    value = None if horizon is None else getattr(horizon, key)
    return math.nan if value is None else float(value)


def ordered_definitions(names) -> list[str]:
    """Definition names in :data:`DEFINITION_ORDER`, then the others."""
    names = list(dict.fromkeys(names))
    return [n for n in DEFINITION_ORDER if n in names] + [n for n in names if n not in DEFINITION_ORDER]


def summary_rows(errors: pd.DataFrame, definitions: Sequence[str]) -> pd.DataFrame:
    """One row per method: AUC (%) per definition; for the first definition the photos scored, the
    median error (% of the height), the shares within 1 % / 2 % and beyond 10 % / 25 %; the bound's
    coverage per definition and its median; failures, time per photo (s)."""
    rows = []
    primary = definitions[0]
    for method in dict.fromkeys(errors["method"]):
        chosen = errors[errors["method"] == method]
        row: dict[str, Any] = {"method": method, "n": len(chosen), "failures": int(chosen["failed"].sum())}
        for name in definitions:
            values = chosen[f"error_pct_{name}"].dropna().to_numpy() if f"error_pct_{name}" in chosen else []
            row[f"auc_{name}"] = 100.0 * lezama_auc(np.asarray(values) / 100.0)[0] if len(values) else math.nan
        values = chosen[f"error_pct_{primary}"].dropna().to_numpy()
        row["n_scored"] = len(values)
        if len(values):
            row.update(median_pct=float(np.median(values)), within_1_pct=100.0 * np.mean(values <= 1.0),
                       within_2_pct=100.0 * np.mean(values <= 2.0), beyond_10_pct=100.0 * np.mean(values > 10.0),
                       beyond_25_pct=100.0 * np.mean(values > 100.0 * CUTOFF))
        bound = chosen["bound_pct"].to_numpy(np.float64)
        for name in definitions:
            scored = chosen[f"error_pct_{name}"].to_numpy(np.float64) if f"error_pct_{name}" in chosen else None
            has = np.isfinite(bound) & (~np.isnan(scored) if scored is not None else False)
            if np.any(has):
                row[f"bound_coverage_pct_{name}"] = 100.0 * float(np.mean(scored[has] <= bound[has]))
        if np.isfinite(bound).any():
            row["bound_median_pct"] = float(np.median(bound[np.isfinite(bound)]))
        row["time_s"] = float(chosen["runtime_s"].mean())
        rows.append(row)
    return pd.DataFrame(rows)


def published_rows(dataset: str, split: str) -> list[PublishedRow]:
    """The :data:`PUBLISHED` rows of this dataset and split."""
    return [p for p in PUBLISHED if p.dataset == dataset and p.split == split]


def display_table(summary: pd.DataFrame, definitions: Sequence[str], published: Sequence[PublishedRow]) -> pd.DataFrame:
    """The summary as strings (the markdown / LaTeX table); published rows fill their definition's column."""
    def fmt(value, pattern="{:.1f}"):
        return pattern.format(value) if value is not None and np.isfinite(value) else "n/a"

    primary = definitions[0]
    table = []
    for _, row in summary.iterrows():
        out = {"method": row["method"]}
        for name in definitions:
            out[f"AUC ({name})"] = fmt(row.get(f"auc_{name}"), "{:.2f}")
        out[f"median error ({primary}, % of h)"] = fmt(row.get("median_pct"), "{:.2f}")
        for key, label in (("within_1_pct", "≤ 1 %"), ("within_2_pct", "≤ 2 %"), ("beyond_10_pct", "> 10 %"),
                           ("beyond_25_pct", "> 25 %")):
            out[f"{label} (% of photos)"] = fmt(row.get(key), "{:.0f}")
        coverage = [f"{row[f'bound_coverage_pct_{name}']:.0f} %" for name in definitions
                    if np.isfinite(row.get(f"bound_coverage_pct_{name}", math.nan))]
        out[f"90 % bound holds ({', '.join(definitions)}; median bound)"] = (
            f"{' / '.join(coverage)} ({row['bound_median_pct']:.1f} % of h)" if coverage else "—")
        out[f"scored ({primary})"] = f"{int(row['n_scored'])}/{int(row['n'])}"
        out["failures"] = f"{int(row['failures'])}/{int(row['n'])}"
        out["time per photo (s)"] = fmt(row.get("time_s"), "{:.2f}")
        table.append(out)
    for row in published:
        out = {key: "—" for key in (table[0] if table else {"method": ""})}
        out["method"] = row.method
        out[f"AUC ({row.definition})"] = f"{row.auc:.2f}"
        table.append(out)
    return pd.DataFrame(table)


def caption(dataset: str, split: str, n: int, notes: dict[str, str], settings: str,
            published: Sequence[PublishedRow]) -> str:
    """The note under the table: the metric, every ground-truth definition, the settings, the sources."""
    text = (f"Horizon error on {dataset} {split} ({n} photos): per photo the larger vertical distance between the "
            "estimated and the labelled horizon at the left and right borders (x = 0 and x = w - 1), in % of the image "
            "height; AUC (%) of its cumulative curve on [0, 25 %] as Lezama 2014's calc_auc.m computes it (a failure "
            "counts beyond 25 %). Ground truth: " + "; ".join(f"**{name}** = {note}" for name, note in notes.items())
            + f". The detail columns use {next(iter(notes))}. 90 % bound holds: the share of photos whose error is "
            "within the method's own 90 % bound (fR's horizon.bound_pct) against each definition, the bound's median "
            "in brackets. Scored: the photos that have the first definition. " + settings)
    if published:
        text += " Published rows: " + "; ".join(f"{p.method}: {p.source}" for p in published) + "."
    return text


def curves_figure(errors: pd.DataFrame, definitions: Sequence[str], path: Path, title: str) -> Path:
    """The cumulative error curves up to 25 % of the height, one panel per definition."""
    curves = {name: {method: errors.loc[errors["method"] == method, f"error_pct_{name}"].dropna().to_numpy()
                     for method in dict.fromkeys(errors["method"])} for name in definitions}
    return recall_figure(curves, path, title, 100.0 * CUTOFF,
                         label=lambda method, values: f"{method} (AUC {100.0 * lezama_auc(values / 100.0)[0]:.1f})",
                         panel_title=lambda name: f"ground truth: {name}", xlabel="horizon error (% of image height)",
                         ylabel="share of photos")


def run(args: argparse.Namespace) -> int:
    methods = split_methods(args.methods)
    if not methods:
        print("error: no methods given", file=sys.stderr)
        return 2
    fov_range = parse_fov_range(args)
    samples = None if fov_range is None else load_samples(args)
    if samples is None:
        return 2
    definitions = ordered_definitions(name for s in samples for name in truth_horizons(s))
    if not definitions:
        print(f"error: dataset {args.dataset!r} has no ground-truth horizon (a labelled horizon or a camera with "
              "K and a vertical); the horizon task runs on yud, ecd-tune, nyu-vp, ...", file=sys.stderr)
        return 2
    out_dir = Path(args.out) if args.out else REPO / "results" / "horizon" / safe_name(f"{args.dataset}-{args.split}")
    prepared = reuse_and_build(args, out_dir, "horizon_errors.csv", "horizon", methods, samples, fov_range)
    if prepared is None:
        return 2
    previous, calibrators = prepared
    out_dir.mkdir(parents=True, exist_ok=True)
    rows: list[dict] = []
    for spec in methods:
        if spec not in calibrators:  # --reuse: the old run's rows
            rows += previous.rows_of(spec, samples, blank=lambda s, spec=spec: horizon_row(spec, s, None, math.nan))
        else:
            try:
                rows += evaluate_method(spec, samples, pp_mode=args.pp, known_focal=args.known_focal,
                                        dataset=args.dataset, device=args.device, calibrator=calibrators[spec],
                                        row_of=horizon_row, progress=not args.no_progress)
            except ValueError as exc:  # e.g. --pp calibrated on a dataset without a principal point
                print(f"error: {exc}", file=sys.stderr)
                return 2
        pd.DataFrame(rows).to_csv(out_dir / "horizon_errors.csv", index=False)  # after each method
    errors = pd.DataFrame(rows)
    summary = summary_rows(errors, definitions)
    summary.to_csv(out_dir / "horizon_summary.csv", index=False)
    published = published_rows(args.dataset, args.split)
    display = display_table(summary, definitions, published)
    every_note = definition_notes(samples)
    notes = {name: every_note[name] for name in definitions}
    settings = (f"Settings: principal point {args.pp}, focal {'known' if args.known_focal else 'estimated'}; "
                + range_caption(methods, fov_range) + ".")
    title = f"Horizon: {args.dataset} {args.split} ({len(samples)} photos)"
    note = caption(args.dataset, args.split, len(samples), notes, settings, published)
    (out_dir / "horizon_summary.md").write_text(f"# {title}\n\n" + to_markdown(display) + f"\n{note}\n",
                                                encoding="utf-8")
    (out_dir / "horizon_summary.tex").write_text(to_latex(display, caption=title), encoding="utf-8")
    if not args.no_plots:
        curves_figure(errors, definitions, out_dir / "horizon_curves.png", title)
    info = {"argv": sys.argv, "task": "horizon", "methods": methods, "dataset": args.dataset, "split": args.split,
            "n_images": len(samples), "definitions": notes, "pp": args.pp, "known_focal": args.known_focal,
            "fov_range_deg": list(fov_range), "device": args.device, "limit": args.limit,
            "python": platform.python_version(), "machine": machine_description(args.device),
            "date": time.strftime("%Y-%m-%d %H:%M:%S")}
    if previous is not None:
        info["reused"] = previous.provenance()
    (out_dir / "run_info.json").write_text(json.dumps(info, indent=2), encoding="utf-8")
    print((out_dir / "horizon_summary.md").read_text(encoding="utf-8"))
    print(f"wrote {out_dir}/horizon_errors.csv, horizon_summary.md/.csv/.tex, "
          f"{'' if args.no_plots else 'horizon_curves.png, '}run_info.json")
    return 0
