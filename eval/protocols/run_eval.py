"""``fr eval``: run calibration methods on a dataset and write predictions, tables and histograms.

Example::

    fr eval --dataset yud --split test --methods fr,fast-fr --out results/yud
    fr eval --dataset yud --methods fr --measures a,b,c,d,e      # the deviation-measure table
    fr eval --dataset yud --methods "fr,fr@labelled,my_pkg.mod:MyCalibrator" --pp calibrated
    fr eval --dataset zind-fr --methods all                        # every registered method, per-FOV table
    fr eval --dataset yud --methods "fr,fr[range=paper],lee2009,lee2009[range=paper]" --fov-range 30,120

Methods are anything :func:`fr_torch.plugins.interface.get_calibrator` accepts (registered names,
``module:attr`` import paths, configuration variants such as ``fr[measure=a]`` passed through
verbatim); ``all`` expands to every registered method (:func:`fr_torch.plugins.interface.available_methods`),
oracle methods included only on datasets with hand-labelled segments.  A ``@labelled`` suffix feeds that method the dataset's hand-labelled segments
(``meta.segments``; oracle run); methods named ``oracle*`` (``oracle-fr``) always get them.  Every method also finds them in
``meta.extra["labelled_segments"]`` / ``meta.extra["labelled_segment_labels"]`` when the dataset has
them; ground-truth *camera* values are never passed (except the focal length with
``--known-focal``).

Outputs (``--out``, default ``results/<dataset>``):

* ``predictions.csv``: one row per (method, image): GT, estimate, errors, run time, failure reason,
  the method's predicted errors (``pred_err_*``), reliability flag and, for fR, its reliability
  cues (``cue_<name>`` from ``extra["cues"]``) -- the input of the reliability analysis;
* ``summary.{md,csv,tex}``: rows = methods, columns n, valid % (share of images with a valid
  result), failures, run time, roll / tilt MAE, FOV / focal MAE %, frame error, each mean ± SE over
  the successful images ("n/a" when the method does not estimate the quantity); failures are
  counted, never dropped silently.  A method whose weights / predictions are absent (every estimate
  failed with a reason starting "n/a (", e.g. ``ctrlc`` without ONNX weights, ``external`` without a
  CSV) shows "n/a (not supplied)" in every cell; after its first such image it is only asked
  without the image (no decoding), so it costs nothing;
* ``summary_common.{md,csv,tex}``: the same table on the images every method estimated (written
  when some method failed on some image), so methods with a low valid share compare fairly.
* ``by_fov.{md,csv,tex}`` (``--group-by hfov``; automatic when the GT horizontal FOV takes 2..10
  distinct rounded values, as in ZInD-fR): rows method x FOV bin, columns n, valid %, roll, tilt,
  FOV %, focal % mean ± SE (``--group-by <attribute>`` writes ``by_<attribute>.*``);
* ``distributions.png``: GT vs estimated roll, tilt and FOV of all methods (overlaid histograms and
  estimate-vs-GT scatter with the identity line; the paper's Fig. 4);
* ``deviation_measures.{md,csv,tex}``: the same table restricted to ``[measure=x]`` variants, one
  row per deviation measure (written when such variants ran);
* ``hist_<method>.png``: estimated vs GT roll, tilt and FOV histograms;
* ``run_info.json``: the command line, settings and machine (CPU, cores, torch, threads), the
  weights caption of each learned row (``weights``) and, with ``--reuse``, where reused rows came from.

``--reuse METHODS`` (:mod:`fr_eval.protocols.reuse`) takes those methods' rows from the
``predictions.csv`` already in ``--out`` (and their weights caption from its ``run_info.json``)
instead of building and running them; every output above is written as if they had run.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import platform
import sys
import time
from pathlib import Path
from typing import Any, Sequence

import numpy as np
import pandas as pd
from tqdm import tqdm

from fr_eval.datasets.registry import available_datasets, load_dataset
from fr_eval.machine import machine_description
from fr_eval.paths import REPO
from fr_eval.protocols import reuse
from fr_eval.scoring.metrics import (
    estimate_quantities,
    failure_reason,
    image_errors,
    is_failure,
    summarize,
    summarize_groups,
)
from fr_eval.scoring.plots import distributions_figure, histogram_figure, safe_name
from fr_eval.scoring.tables import (
    deviation_measure_summaries,
    parse_method_spec,
    write_tables,
)
from fr_torch.cli.options import add_device_arguments, add_fov_range_argument
from fr_torch.core.settings.fov import FovRange
from fr_torch.images.io import load_image
from fr_torch.plugins.interface import (
    CALIBRATORS,
    CameraEstimate,
    ImageMeta,
    available_methods,
    get_calibrator,
)
from fr_torch.registry import NA_PREFIX, split_method_list, with_option

LABELLED_SUFFIX = "@labelled"
ALL_METHODS = "all"
TABLE_ORDER = ("fr", "fast-fr", "oracle-fr", "lee2009", "simon2018", "hold-geoffroy2018", "ctrlc", "ctrlc-retrained",
               "prior", "external")
GROUP_METRICS = ("roll_err_deg", "tilt_err_deg", "fov_err_pct", "focal_err_pct")
#: Methods that search the focal length: ``--fov-range`` is given to each of them (as ``range``),
#: unless the spec sets its own (``[range=...]``).
FOCAL_SEARCH_METHODS = ("fr", "fast-fr", "oracle-fr", "lee2009", "simon2018")
RANGE_OPTIONS = ("range",)
AUTO_GROUP_MAX_VALUES = 10


split_methods = split_method_list  # kept name: a comma-separated method list (commas in [...] kept)


def expand_methods(methods: Sequence[str], measures: Sequence[str] | None) -> list[str]:
    """``--measures a,b`` turns each method ``m`` into ``m[measure=a]``, ``m[measure=b]``."""
    if not measures:
        return list(methods)
    out = []
    for method in methods:
        spec, labelled = _strip_labelled(method)
        for measure in measures:
            out.append(with_option(spec, "measure", measure) + (LABELLED_SUFFIX if labelled else ""))
    return out


def resolve_methods(methods: Sequence[str], has_segments: bool) -> tuple[list[str], list[str]]:
    """Expand ``all`` into every registered method; returns (methods, skipped).

    ``all`` lists the paper's methods first (``TABLE_ORDER``), then any other registered ones.
    Oracle methods (``oracle*`` names) that ``all`` brings in are skipped on a dataset without
    hand-labelled segments (``has_segments`` False), and the generic ``external`` adapter unless
    ``$FR_EXTERNAL_CSV`` is set.  Duplicates are removed, order kept.
    """
    out, skipped = [], []
    for method in methods:
        if method.strip().lower() != ALL_METHODS:
            out.append(method)
            continue
        registered = available_methods()
        ordered = [m for m in TABLE_ORDER if m in registered] + [m for m in registered if m not in TABLE_ORDER]
        for name in ordered:
            if name == "external" and not os.environ.get("FR_EXTERNAL_CSV"):
                skipped.append(name)  # the generic CSV adapter: a row only when a CSV is given
            elif _strip_labelled(name)[1] and not has_segments:
                skipped.append(name)
            else:
                out.append(name)
    return list(dict.fromkeys(out)), skipped


def _strip_labelled(method: str) -> tuple[str, bool]:
    """(method spec without ``@labelled``, whether it gets the hand-labelled segments).

    Methods whose name starts with ``oracle`` (e.g. ``oracle-fr``) always get them.
    """
    if method.endswith(LABELLED_SUFFIX):
        return method[: -len(LABELLED_SUFFIX)], True
    return method, method.strip().lower().startswith("oracle")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--dataset", default="yud",
                        help="dataset name (%s) or import path module:function" % ", ".join(_dataset_names()))
    parser.add_argument("--split", default="test", help="split (train / test / all; default test)")
    parser.add_argument("--methods", default="fr,fast-fr",
                        help="comma-separated methods: registered names, module:attr import paths, "
                             "variants like 'fr[measure=a]'; suffix @labelled = use hand-labelled segments")
    parser.add_argument("--measures", default=None,
                        help="comma-separated deviation measures (e.g. a,b,c,d,e): run every method as "
                             "<method>[measure=x] and write the deviation-measure table")
    parser.add_argument("--out", default=None, help="output folder (default results/<dataset>)")
    reuse.add_argument(parser)
    parser.add_argument("--no-progress", action="store_true",
                        help="no progress bar (there is one only when stderr is a terminal)")
    parser.add_argument("--data-root", default=None, help="dataset root (default $FR_DATA or ../shared/data)")
    parser.add_argument("--pp", choices=("centre", "calibrated"), default="centre",
                        help="principal point given to the methods: image centre (paper, default) or "
                             "the dataset's calibrated one")
    parser.add_argument("--known-focal", action="store_true",
                        help="give the methods the ground-truth focal length (known-focal evaluation)")
    parser.add_argument("--limit", type=int, default=None, help="evaluate only the first N images")
    parser.add_argument("--ctrlc-onnx", default=None, metavar="ONNX",
                        help="CTRL-C weights exported by 'fr export-ctrlc' for the ctrlc row (or $FR_CTRLC_ONNX)")
    parser.add_argument("--ctrlc-retrained-onnx", default=None, metavar="ONNX",
                        help="the second CTRL-C training, for the ctrlc-retrained row (or $FR_CTRLC_RETRAINED_ONNX)")
    parser.add_argument("--consac-weights", default=None, metavar="PATH",
                        help="CONSAC's weights for the consac rows: a folder holding consac_vp.net / consac-s_vp.net "
                             "or one .net file (or $FR_CONSAC_WEIGHTS; default ../shared/models/consac)")
    add_device_arguments(parser, device_help="torch device passed to the methods (default cpu)")
    add_fov_range_argument(parser, "FOV search range (degrees, image long side) given to every method that "
                                   f"searches the focal length ({', '.join(FOCAL_SEARCH_METHODS)}) unless its spec "
                                   "sets [range=...]; default 30,120; 'paper' = 50,130. Stated in every table caption")
    parser.add_argument("--no-plots", action="store_true",
                        help="skip the figures (hist_<method>.png, distributions.png)")
    parser.add_argument("--group-by", default="auto",
                        help="per-group breakdown table: 'hfov' (per-FOV table by_fov.*), another sample "
                             "attribute / extra key, 'none', or 'auto' (default: hfov when the GT "
                             f"horizontal FOV takes 2..{AUTO_GROUP_MAX_VALUES} distinct rounded values)")


def range_caption(methods: Sequence[str], fov_range: FovRange) -> str:
    """The caption sentence stating the FOV search range of every method in the table."""
    searched = [m for m in methods if method_fov_range(m, fov_range) is not None]
    own = [m for m in methods if m not in searched and parse_method_spec(_strip_labelled(m)[0])[0]
           in FOCAL_SEARCH_METHODS]
    text = (f"FOV search range {fov_range} (FOV across the image's long side) for "
            f"{', '.join(searched) if searched else 'no method'}")
    if own:
        text += "; rows with [range=...] use their own (paper = [50°, 130°])"
    if any(parse_method_spec(m)[0] == "prior" for m in methods):
        text += "; prior: fixed 60° HFOV, no search"
    return text


def _dataset_names() -> list[str]:
    try:
        return available_datasets()
    except Exception:  # never let a broken plugin break --help
        return ["yud"]


def method_fov_range(spec: str, fov_range: FovRange | None) -> FovRange | None:
    """The FOV range ``fr eval`` gives method ``spec``: ``fov_range`` for a focal-searching method
    (:data:`FOCAL_SEARCH_METHODS`) whose spec sets no range option, else None (its own)."""
    base, options = parse_method_spec(_strip_labelled(spec)[0])
    if fov_range is None or base not in FOCAL_SEARCH_METHODS or any(k in options for k in RANGE_OPTIONS):
        return None
    return fov_range


def make_calibrator(spec: str, device: str, fov_range: FovRange | None = None, **kwargs):
    """Build a method; offers ``device`` (and, to the focal-searching methods, the table's FOV
    search range as ``range``, :func:`method_fov_range`) to a factory that takes them
    (``docs/plugins-options.md``); ``kwargs`` go to the factory as they are (e.g. fR's
    ``reliability``)."""
    offered: dict[str, Any] = {"device": device}
    method_range = method_fov_range(spec, fov_range)
    if method_range is not None:
        offered["range"] = method_range
    if device not in ("cpu", None) and not CALIBRATORS.takes(spec, "device"):
        print(f"warning: method {spec!r} takes no device argument; it runs on its own default", file=sys.stderr)
    return get_calibrator(spec, offered=offered, **kwargs)


def build_meta(sample: Any, pp_mode: str, labelled: bool, known_focal: bool, dataset: str, device: str) -> ImageMeta:
    extra: dict[str, Any] = {"dataset": dataset, "split": getattr(sample, "split", ""), "device": device}
    segments = getattr(sample, "segments", None)
    if segments is not None:
        extra["labelled_segments"] = np.asarray(segments, dtype=np.float64)
        extra["labelled_segment_labels"] = getattr(sample, "segment_labels", None)
    if labelled and segments is None:
        raise ValueError(f"{sample.name}: @labelled needs hand-labelled segments, the dataset has none")
    pp = None
    if pp_mode == "calibrated":
        pp = getattr(sample, "principal_point", None)
        if pp is None:
            raise ValueError(f"{sample.name}: --pp calibrated but the dataset gives no principal point")
        pp = (float(pp[0]), float(pp[1]))
    return ImageMeta(
        name=sample.name,
        width=int(sample.width),
        height=int(sample.height),
        focal_px=float(sample.focal_px) if known_focal and sample.focal_px is not None else None,
        principal_point=pp,
        segments=np.asarray(segments, dtype=np.float64) if labelled else given_segments(sample),
        extra=extra,
    )


def given_segments(sample: Any) -> np.ndarray | None:
    """The segments a dataset without pixels gives every method (``extra["detected_segments"]``,
    (N, 4) pixels, e.g. NYU-VP's own LSD segments), else None (the methods detect on the image)."""
    given = (getattr(sample, "extra", None) or {}).get("detected_segments")
    return None if given is None else np.asarray(given, dtype=np.float64).reshape(-1, 4)


def _num(x) -> float:
    return float(x) if x is not None else math.nan


def _call(method, spec: str, image, meta: ImageMeta) -> tuple[CameraEstimate, float]:
    start = time.perf_counter()
    try:
        est = method.estimate(image, meta)
        if est is not None and not isinstance(est, CameraEstimate):
            raise TypeError(f"estimate() returned {type(est).__name__}, not CameraEstimate")
    except Exception as exc:  # noqa: BLE001 - a crash on one image is a counted failure
        est = CameraEstimate.failure(spec, f"{type(exc).__name__}: {exc}")
    return est, time.perf_counter() - start


def _na_reason(est: CameraEstimate | None) -> str | None:
    """The reason of an "n/a (...)" failure (weights / predictions not supplied), else None."""
    if est is not None and is_failure(est) and (est.reason or "").startswith(NA_PREFIX):
        return est.reason
    return None


def evaluate_method(spec: str, samples: Sequence[Any], *, pp_mode: str = "centre", known_focal: bool = False,
                    dataset: str = "", device: str = "cpu", calibrator=None, progress: bool = True,
                    row_of=None) -> list[dict]:
    """Per-image prediction rows of one method on ``samples`` (exceptions count as failures);
    ``row_of(spec, sample, estimate, wall_s) -> dict`` builds a row (default :func:`prediction_row`).

    A method whose answers so far are all the same "n/a (...)" failure (weights / predictions not
    supplied) is first asked without the image; the same answer is taken as is (no image decoding),
    any other makes it run on the decoded image as usual (and ends this shortcut).  The first image
    is estimated twice and the second, warm run is recorded (run times exclude one-time start-up).
    """
    base_spec, labelled = _strip_labelled(spec)
    method = calibrator if calibrator is not None else make_calibrator(base_spec, device)
    rows = []
    na_streak: str | None = None  # the n/a reason every answer so far had
    for i, sample in enumerate(tqdm(samples, desc=spec, unit="img", disable=not progress or not sys.stderr.isatty(),
                                    file=sys.stderr)):
        meta = build_meta(sample, pp_mode, labelled, known_focal, dataset, device)
        has_image = getattr(sample, "image_path", None) is not None
        est = None
        if na_streak is not None and has_image:
            probe, wall = _call(method, spec, None, meta)
            if _na_reason(probe) == na_streak:
                est = probe
            else:
                na_streak = None
        if est is None:
            image = load_image(sample.image_path) if has_image else None
            est, wall = _call(method, spec, image, meta)
            if i == 0 and _na_reason(est) is None:
                # The first call pays one-time costs (lazy imports, allocator, thread pools): time a
                # second run of the first image so that 'run time' is the steady per-image cost.
                est, wall = _call(method, spec, image, meta)
            reason = _na_reason(est)
            na_streak = reason if i == 0 or (na_streak is not None and reason == na_streak) else None
        rows.append((row_of or prediction_row)(spec, sample, est, wall))
    return rows


def common_subset_summaries(rows: Sequence[dict], summaries: Sequence[Any]):
    """(summaries on the images every method estimated, their number), or None when that table adds
    nothing (fewer than two methods, or no method failed anywhere, or no common image)."""
    methods = [s.method for s in summaries]
    if len(methods) < 2:
        return None
    by_method = {m: [r for r in rows if r["method"] == m] for m in methods}
    if not any(r.get("failed") for m in methods for r in by_method[m]):
        return None
    common = set.intersection(*({r["image"] for r in by_method[m] if not r.get("failed")} for m in methods))
    if not common:
        return None
    return [summarize(m, [r for r in by_method[m] if r["image"] in common]) for m in methods], len(common)


def prediction_row(spec: str, sample: Any, est: CameraEstimate | None, wall_s: float) -> dict:
    failed = is_failure(est)
    q = estimate_quantities(est, int(sample.width)) if not failed else {}
    errors = image_errors(sample, est)
    row: dict[str, Any] = {
        "method": spec,
        "image": sample.name,
        "split": getattr(sample, "split", ""),
        "failed": bool(failed),
        "reason": failure_reason(est) if failed else "",
        "runtime_s": wall_s,
        "method_runtime_s": _num(getattr(est, "runtime_s", None)),
    }
    for key in ("roll_deg", "tilt_deg", "pitch_deg", "hfov_deg", "focal_px"):
        row[f"gt_{key}"] = _num(getattr(sample, key, None))
        row[f"est_{key}"] = _num(q.get(key))
    for key, value in errors.items():
        row[key] = _num(value)
    rotation = q.get("rotation")
    for i in range(3):
        for j in range(3):
            row[f"est_r{i}{j}"] = float(rotation[i, j]) if rotation is not None else math.nan
    row["reliable"] = getattr(est, "reliable", None) if est is not None else None
    predicted = (getattr(est, "predicted_error", None) or {}) if est is not None else {}
    for key in ("roll_deg", "tilt_deg", "focal_pct"):
        row[f"pred_err_{key}"] = _num(predicted.get(key))
    extra = (getattr(est, "extra", None) or {}) if est is not None else {}
    cues = extra.get("cues") if isinstance(extra, dict) else None
    for key, value in (cues or {}).items():  # fR's reliability cues, for the reliability analysis
        try:
            row[f"cue_{key}"] = float(value)
        except (TypeError, ValueError):
            continue
    if isinstance(extra, dict) and "num_segments" in extra:
        row["num_segments"] = _num(extra["num_segments"])
    return row


def group_value(sample: Any, key: str) -> str | None:
    """The group label of a sample for ``--group-by key``: attribute ``key`` (or ``extra[key]``),
    numbers rounded to integers ("60"), None when missing."""
    value = getattr(sample, key, None)
    if value is None:
        value = (getattr(sample, "extra", None) or {}).get(key)
    if value is None:
        return None
    try:
        number = float(value)
    except (TypeError, ValueError):
        return str(value)
    return str(int(round(number))) if math.isfinite(number) else None


def resolve_group_by(option: str | None, samples: Sequence[Any]) -> str | None:
    """The grouping key for ``--group-by`` (None = no breakdown); ``auto`` picks ``hfov_deg`` when the
    GT horizontal FOV takes 2..AUTO_GROUP_MAX_VALUES distinct rounded values."""
    option = (option or "auto").strip()
    if option.lower() in ("none", "off", ""):
        return None
    if option.lower() in ("hfov", "fov", "hfov_deg"):
        return "hfov_deg"
    if option.lower() == "auto":
        values = {group_value(s, "hfov_deg") for s in samples} - {None}
        return "hfov_deg" if 2 <= len(values) <= AUTO_GROUP_MAX_VALUES else None
    return option


def _group_names(key: str) -> tuple[str, str]:
    """(file stem, column label) of the breakdown table for grouping key ``key``."""
    if key == "hfov_deg":
        return "by_fov", "GT FOV (°)"
    return f"by_{safe_name(key)}", key


def load_samples(args: argparse.Namespace, loader=load_dataset) -> list | None:
    """The samples of ``--dataset`` / ``--split`` (``loader(dataset, root=, split=)``), the first
    ``--limit``; None after printing a one-line error when the dataset cannot be loaded or is empty."""
    try:
        samples = loader(args.dataset, root=args.data_root, split=args.split)
    except (FileNotFoundError, ValueError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return None
    if args.limit is not None:
        samples = samples[: max(0, args.limit)]
    if not samples:
        print(f"error: dataset {args.dataset!r} split {args.split!r} has no samples", file=sys.stderr)
        return None
    return samples


def run(args: argparse.Namespace) -> int:
    requested = split_methods(args.methods)
    if not requested:
        print("error: no methods given", file=sys.stderr)
        return 2
    samples = load_samples(args)
    if samples is None:
        return 2
    has_segments = all(getattr(s, "segments", None) is not None for s in samples)
    resolved, skipped = resolve_methods(requested, has_segments)
    if skipped:
        print(f"note: 'all' leaves out {', '.join(skipped)} (oracle methods need hand-labelled segments; "
              "'external' needs $FR_EXTERNAL_CSV)", file=sys.stderr)
    methods = expand_methods(resolved, [m.strip() for m in args.measures.split(",") if m.strip()]
                             if args.measures else None)
    if not methods:
        print("error: no methods to run", file=sys.stderr)
        return 2
    oracle = [m for m in methods if _strip_labelled(m)[1]]
    if oracle and not has_segments:
        print(f"error: {', '.join(oracle)} need hand-labelled segments; dataset {args.dataset!r} has none "
              "(for every image)", file=sys.stderr)
        return 2
    group_key = resolve_group_by(getattr(args, "group_by", "auto"), samples)
    fov_range = parse_fov_range(args)
    if fov_range is None:
        return 2
    out_dir = Path(args.out) if args.out else REPO / "results" / safe_name(args.dataset)
    prepared = reuse_and_build(args, out_dir, "predictions.csv", "camera", methods, samples, fov_range)
    if prepared is None:
        return 2
    previous, calibrators = prepared
    out_dir.mkdir(parents=True, exist_ok=True)

    groups = {s.name: group_value(s, group_key) for s in samples} if group_key else {}
    all_rows: list[dict] = []
    summaries, group_summaries = [], []
    for spec in methods:
        if spec in calibrators:
            rows = evaluate_method(spec, samples, pp_mode=args.pp, known_focal=args.known_focal,
                                   dataset=args.dataset, device=args.device, calibrator=calibrators[spec],
                                   progress=not args.no_progress)
        else:  # --reuse: the old run's rows, without their group (set below as for a fresh row)
            rows = previous.rows_of(spec, samples, blank=lambda s, spec=spec: prediction_row(spec, s, None, math.nan))
            for row in rows:
                row.pop("group", None)
        if group_key:
            for row in rows:
                row["group"] = groups.get(row["image"])
        all_rows.extend(rows)
        pd.DataFrame(all_rows).to_csv(out_dir / "predictions.csv", index=False)  # after each method
        summary = summarize(spec, rows)
        summaries.append(summary)
        if group_key:
            group_summaries += summarize_groups(spec, rows, key="group")
        if not args.no_plots and not summary.not_supplied:
            histogram_figure(pd.DataFrame(rows), spec, out_dir / f"hist_{safe_name(spec)}.png",
                             title=f"{spec} on {args.dataset} ({args.split}): estimated vs ground truth")
    weights = weights_texts(calibrators)
    if previous is not None:
        weights.update(reused_weights(previous))
    weights = {spec: weights[spec] for spec in methods if weights.get(spec)}
    settings = (f"dataset {args.dataset}, split {args.split} ({len(samples)} images), principal point "
                f"{args.pp}, focal {'known' if args.known_focal else 'estimated'}; "
                + range_caption(methods, fov_range))
    note = ("Mean ± standard error (std(ddof=1)/√n) over the images a method succeeded on; 'valid (%)' is "
            "the share of images with a valid result; failures are counted in 'failures' (share of all "
            "images) and excluded from the error means only; run time (wall time of estimate(), all images, "
            "after one warm-up call) includes them. n/a = not estimated; n/a (not supplied) = the method's "
            f"weights / predictions were not supplied (no numbers). Settings: {settings}."
            + weights_caption(weights))
    written = write_tables(summaries, out_dir, "summary", title=f"Calibration results: {args.dataset} {args.split}",
                           note=note)
    common = common_subset_summaries(all_rows, [s for s in summaries if not s.not_supplied])
    if common is not None:
        summaries_common, n_common = common
        written += write_tables(summaries_common, out_dir, "summary_common",
                                title=f"Common subset: {args.dataset} {args.split}, the {n_common} images every "
                                      "method estimated",
                                note="Same metrics, restricted to the images on which every method above (n/a rows "
                                     "excluded) returned an estimate, so methods that fail often are compared on "
                                     "equal terms. " + note)
    if group_key and group_summaries:
        stem, column = _group_names(group_key)
        written += write_tables(group_summaries, out_dir, stem, group_label=column, metrics=GROUP_METRICS,
                                title=f"Results by {column}: {args.dataset} {args.split}", note=note)
    if not args.no_plots and all_rows:
        written.append(distributions_figure(
            pd.DataFrame(all_rows), out_dir / "distributions.png",
            methods=[s.method for s in summaries if not s.not_supplied],
            title=f"{args.dataset} ({args.split}): ground truth vs estimates"))
    deviation = deviation_measure_summaries(summaries)
    if deviation:
        written += write_tables(deviation, out_dir, "deviation_measures", label="deviation measure",
                                title=f"Deviation measures: {args.dataset} {args.split}", note=note)
    info = {"argv": sys.argv, "methods": methods, "dataset": args.dataset, "split": args.split,
            "requested_methods": requested, "skipped_methods": skipped, "group_by": group_key,
            "n_images": len(samples), "pp": args.pp, "known_focal": args.known_focal, "device": args.device,
            "limit": args.limit, "fov_range_deg": list(fov_range), "python": platform.python_version(),
            # fR's figures move by ~0.1 point between CPUs (last-bit differences of vector maths carried through
            # 100 refinement steps; results/yud/README.md), so a table records the machine it came from.
            "machine": machine_description(args.device), "date": time.strftime("%Y-%m-%d %H:%M:%S"),
            "weights": weights}
    if previous is not None:
        info["reused"] = previous.provenance()
    (out_dir / "run_info.json").write_text(json.dumps(info, indent=2), encoding="utf-8")
    print((out_dir / "summary.md").read_text(encoding="utf-8"))
    print(f"wrote {out_dir}/predictions.csv, " + ", ".join(p.name for p in written))
    return 0


#: ``fr eval`` options naming a learned method's weights -> the environment variable the method reads.
WEIGHT_OPTIONS = (("ctrlc_onnx", "FR_CTRLC_ONNX"), ("ctrlc_retrained_onnx", "FR_CTRLC_RETRAINED_ONNX"),
                  ("consac_weights", "FR_CONSAC_WEIGHTS"))


def parse_fov_range(args: argparse.Namespace) -> FovRange | None:
    """``--fov-range`` as a :class:`FovRange`; None after a one-line error."""
    try:
        return FovRange.parse(getattr(args, "fov_range", None))
    except ValueError as exc:
        print(f"error: --fov-range: {exc}", file=sys.stderr)
        return None


def reuse_and_build(args: argparse.Namespace, out_dir: Path, per_image: str, task: str, methods: Sequence[str],
                    samples: Sequence[Any], fov_range: FovRange) -> tuple[reuse.PreviousRun | None, dict[str, Any]] | None:
    """A camera or horizon run's ``--reuse`` old run (None without the option; checked against this
    run's settings, :func:`fr_eval.protocols.reuse.image_task_settings`) and the calibrators of the
    methods it leaves to run; None after a one-line error (exit status 2)."""
    try:
        previous = reuse.previous_run(args, out_dir, per_image, methods=methods, samples=samples,
                                      settings=reuse.image_task_settings(args, task, fov_range))
    except reuse.ReuseError as exc:
        reuse.refuse(exc)
        return None
    calibrators = build_calibrators(args, reuse.left_to_run(methods, previous), fov_range)
    return None if calibrators is None else (previous, calibrators)


def build_calibrators(args: argparse.Namespace, methods: Sequence[str], fov_range: FovRange) -> dict[str, Any] | None:
    """Every method of the table built before any work (a typo fails before hours of work), with the
    weight options applied (:func:`apply_weight_options`): spec -> calibrator; None after a one-line
    error."""
    apply_weight_options(args)
    calibrators = {}
    for spec in methods:
        try:
            calibrators[spec] = make_calibrator(_strip_labelled(spec)[0], args.device, fov_range)
        except ValueError as exc:
            print(f"error: {exc}", file=sys.stderr)
            return None
    return calibrators


def apply_weight_options(args: argparse.Namespace) -> None:
    """Export the weight options given (:data:`WEIGHT_OPTIONS`) to the environment variables the
    methods read; an option wins over a variable already set."""
    for option, env in WEIGHT_OPTIONS:
        if getattr(args, option, None):
            os.environ[env] = str(Path(getattr(args, option)).expanduser().resolve())


def weights_note(calibrators: dict[str, Any]) -> str:
    """Caption text naming the weights of each learned row (methods with a ``weights`` property:
    file name + sha256), e.g. " Weights: ctrlc = gsv.onnx (sha256 ...)."; "" when there are none."""
    return weights_caption(weights_texts(calibrators))


def weights_texts(calibrators: dict[str, Any]) -> dict[str, str]:
    """``{spec: weights text}`` of the learned rows (methods with a ``weights`` property)."""
    texts = {}
    for spec, calibrator in calibrators.items():
        try:
            weights = getattr(calibrator, "weights", None)
        except Exception as exc:  # noqa: BLE001 - an unreadable file still gets a caption
            weights = f"unreadable ({type(exc).__name__}: {exc})"
        if weights:
            texts[spec] = str(weights)
    return texts


def weights_caption(texts: dict[str, str]) -> str:
    """" Weights: a = ...; b = ..." from :func:`weights_texts`; "" when empty."""
    return f" Weights: {'; '.join(f'{spec} = {text}' for spec, text in texts.items())}." if texts else ""


def reused_weights(previous: reuse.PreviousRun) -> dict[str, str]:
    """The weights texts of the reused rows: the old run_info.json's ``weights``, or, from a run that
    did not record them there, the "Weights:" sentence of its summary.md."""
    if isinstance(previous.info.get("weights"), dict):
        texts = previous.info["weights"]
    else:
        path = previous.folder / "summary.md"
        lines = path.read_text(encoding="utf-8").splitlines() if path.is_file() else []
        sentence = next((line.rpartition(" Weights: ")[2] for line in lines if " Weights: " in line), "")
        texts = dict(part.partition(" = ")[::2] for part in sentence.removesuffix(".").split("; ") if " = " in part)
    return {spec: texts[spec] for spec in previous.methods if texts.get(spec)}
