"""Radial distortion (issue 46): fR with and without the division model on distorted and undistorted sets.

    python -m fr_eval.protocols.distortion_eval run --datasets zind-fr-d,yud-crop-480x360-d --split test \\
        --methods "fr,fr[distortion=division],fast-fr[distortion=division],fr[distortion=auto]"
    python -m fr_eval.protocols.distortion_eval report --out results/distortion

``run`` calibrates every image of each dataset with each method (batches of ``--batch-size``) and
caches one CSV per (dataset, split, method) under ``$FR_CACHE/distortion`` (a method already
cached is skipped: the command resumes).  Per image: focal / roll / tilt errors
(:func:`fr_eval.scoring.metrics.image_errors`), the true and estimated k and their border bows
(:func:`fr_torch.core.geometry.lens.border_bow_percent`, % of the width), ``reliable`` and its reason,
and the "lines bend" cues.  ``table`` prints a summary of cached runs; ``report`` writes
``results/distortion/tables.md`` (the tables of ``results/distortion/README.md``, the issue's
targets) and the figure of estimated against true k from the cache.

Method specs: ``fr`` / ``fast-fr`` with options ``distortion=pinhole|division|auto``, ``k=K`` (known)
and any :class:`fr_torch.core.settings.config.SearchConfig` field of the distortion search
(``distortion_grid_size``, ``distortion_lattice``, ``grid_passes``, ...; ``distortion_grid_k`` as
K1:K2:...) for screening on
the train splits.
"""
from __future__ import annotations

import argparse
import math
import os
from pathlib import Path

import numpy as np
import pandas as pd
from tqdm import tqdm

from fr_eval.datasets.registry import load_dataset
from fr_eval.paths import cache_root
from fr_eval.protocols.run_eval import given_segments
from fr_eval.scoring.metrics import image_errors, mean_se
from fr_eval.scoring.tables import format_mean_se, parse_method_spec
from fr_torch.core.geometry.lens import border_bow_percent
from fr_torch.core.reliability.sanity import LINE_BEND_CUES
from fr_torch.core.settings.config import SearchConfig
from fr_torch.registry import split_method_list
from fr_torch.runtime.estimator import FREstimator

MODES = {"fr": "fr", "fast-fr": "fast"}


def make_estimator(spec: str) -> FREstimator:
    """An estimator for a method spec (module docstring)."""
    name, options = parse_method_spec(spec)
    if name not in MODES:
        raise ValueError(f"{spec}: method must be one of {', '.join(MODES)}")
    options = dict(options)
    distortion, k = options.pop("distortion", None), options.pop("k", None)
    config = SearchConfig.from_config(**{key: _number_or_text(value) for key, value in options.items()})
    return FREstimator(mode=MODES[name], search_config=config, distortion=distortion,
                       k=None if k is None else float(k))


def _number_or_text(value: str):
    if ":" in value:  # a tuple of numbers, K1:K2
        return tuple(float(v) for v in value.split(":") if v)
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


#: The report's methods (rows) and columns: (dataset, split, label).
REPORT_METHODS = (("fr", "fR, pinhole"), ("fr[distortion=division]", "fR + division"),
                  ("fast-fr[distortion=division]", "Fast-fR + division"), ("fr[distortion=auto]", "fR, auto"))
REPORT_COLUMNS = (("zind-fr-d", "test", "ZInD-fR-D test"), ("yud-crop-480x360-d", "test", "YUD-D 480x360 test"),
                  ("zind-fr", "test", "ZInD-fR test"), ("yud-crop-480x360", "test", "YUD crop 480x360 test"),
                  ("yud", "test", "YUD test"), ("nyu-vp", "val", "NYU-VP val"))
#: Each distorted set and the same views undistorted (the focal target's yardstick).
SAME_VIEWS = {"zind-fr-d": "zind-fr", "yud-crop-480x360-d": "yud-crop-480x360"}
#: A photo is visibly distorted from this border bow (% of the width; ``k`` = -0.058 in 4:3).
VISIBLE_BOW_PCT = 1.0
BEND_REASON = "the lines bend"


def _frame(dataset: str, split: str, spec: str) -> pd.DataFrame | None:
    path = cache_file(dataset, split, spec)
    return pd.read_csv(path) if path.is_file() else None


def native_k(split: str = "train") -> float:
    """The YUD camera's own k at the 480x360 crops: the median division estimate on the undistorted
    crops of ``split`` (YUD is calibrated without distortion; its lens has a little barrel)."""
    frame = _frame("yud-crop-480x360", split, "fr[distortion=division]")
    return float(np.nanmedian(frame["k_est"])) if frame is not None else math.nan


def report(out: Path) -> str:
    """``results/distortion/README.md``'s tables (returned and written to ``out``) and the figure
    ``k_true_vs_estimated.png`` from the cache of :func:`run_method`."""
    frames = {(d, spec): _frame(d, split, spec) for d, split, _ in REPORT_COLUMNS for spec, _ in REPORT_METHODS}
    summaries = {key: summary(frame) for key, frame in frames.items() if frame is not None}
    header = "| method | " + " | ".join(label for _, _, label in REPORT_COLUMNS) + " |"
    rule = "|---|" + "---|" * len(REPORT_COLUMNS)
    lines = []
    for metric, title in (("focal_err_pct", "Focal length: mean absolute error, % of the true focal length"),
                          ("roll_err_deg", "Roll: mean absolute error, degrees"),
                          ("tilt_err_deg", "Tilt: mean absolute error, degrees")):
        lines += [f"### {title}", "", header, rule]
        for spec, label in REPORT_METHODS:
            cells = [format_mean_se(*summaries[(d, spec)][metric]) if (d, spec) in summaries else "not run"
                     for d, _, _ in REPORT_COLUMNS]
            lines.append(f"| {label} | " + " | ".join(cells) + " |")
        lines.append("")
    offset = native_k()
    lines += ["### Radial distortion k (division model, normalised by half the diagonal)", "",
              "Median absolute error of k, and of the border bow it implies (% of the width); YUD-D also "
              f"against the warp's k plus the YUD lens's own k ({offset:+.4f}, the median division estimate on "
              "the undistorted YUD crops of the *train* split).", "",
              "| method | ZInD-fR-D: k | ZInD-fR-D: bow (%) | YUD-D: k vs warp | YUD-D: k vs warp + lens | "
              "YUD-D: bow (%) |", "|---|---|---|---|---|---|"]
    for spec, label in REPORT_METHODS[1:]:
        zind, yud = frames.get(("zind-fr-d", spec)), frames.get(("yud-crop-480x360-d", spec))
        if zind is None or yud is None:
            lines.append(f"| {label} | not run | | | | |")
            continue
        lens_err = (yud["k_est"] - yud["k_true"] - offset).abs()
        lines.append(f"| {label} | {np.nanmedian(zind['k_err']):.4f} | {np.nanmedian(zind['bow_err_pct']):.3f} | "
                     f"{np.nanmedian(yud['k_err']):.4f} | {np.nanmedian(lens_err):.4f} | "
                     f"{np.nanmedian(yud['bow_err_pct']):.3f} |")
    lines += ["", "### Can the pinhole estimates be trusted?", "",
              f"fR, pinhole: estimates flagged `reliable` among the visibly distorted photos (border bow >= "
              f"{VISIBLE_BOW_PCT:g} % of the width), and the share of photos whose estimate the lines-bend check "
              "marks unreliable (on the undistorted sets: its false positives). fR, auto: share of photos searched "
              "with the division model.", "",
              "| | " + " | ".join(label for _, _, label in REPORT_COLUMNS) + " |", rule]
    pinhole = [frames.get((d, "fr")) for d, _, _ in REPORT_COLUMNS]
    auto = [frames.get((d, "fr[distortion=auto]")) for d, _, _ in REPORT_COLUMNS]
    visible = ["n/a" if f is None or d not in SAME_VIEWS else
               f"{int((f['reliable'] & (f['bow_true_pct'] >= VISIBLE_BOW_PCT)).sum())} of "
               f"{int((f['bow_true_pct'] >= VISIBLE_BOW_PCT).sum())}" for f, (d, _, _) in zip(pinhole, REPORT_COLUMNS)]
    bent = ["n/a" if f is None else f"{100 * f['reason'].astype(object).fillna('').str.contains(BEND_REASON).mean():.1f} %"
            for f in pinhole]
    chosen = ["n/a" if f is None else f"{100 * (f['model'] == 'division').mean():.1f} %" for f in auto]
    lines += ["| pinhole `reliable` among visibly distorted | " + " | ".join(visible) + " |",
              "| pinhole flagged \"the lines bend\" | " + " | ".join(bent) + " |",
              "| auto: division chosen | " + " | ".join(chosen) + " |", ""]
    lines += _targets(summaries, frames) + [""]
    _k_figure(frames, out / "k_true_vs_estimated.png")
    text = "\n".join(lines)
    out.mkdir(parents=True, exist_ok=True)
    (out / "tables.md").write_text(text + "\n")
    return text


def _targets(summaries: dict, frames: dict) -> list[str]:
    """The issue's targets, each with the figures it compares."""
    lines = ["### The issue's targets", "", "| target | figures | met |", "|---|---|---|"]
    division = "fr[distortion=division]"
    for bent, straight in SAME_VIEWS.items():
        if (bent, division) not in summaries or (straight, "fr") not in summaries:
            continue
        d, p = summaries[(bent, division)], summaries[(straight, "fr")]
        ratio = d["focal_err_pct"][0] / p["focal_err_pct"][0]
        lines.append(f"| {bent}: focal MAE <= 1.25 x the same views undistorted (pinhole fR) | "
                     f"{d['focal_err_pct'][0]:.2f} vs {p['focal_err_pct'][0]:.2f} ({ratio:.2f} x) | "
                     f"{'yes' if ratio <= 1.25 else 'no'} |")
        for metric in ("roll_err_deg", "tilt_err_deg"):
            gap, se = d[metric][0] - p[metric][0], p[metric][1]
            lines.append(f"| {bent}: {metric.split('_')[0]} within one SE of the undistorted figure | "
                         f"{d[metric][0]:.2f} vs {p[metric][0]:.2f} ± {se:.2f} | {'yes' if gap <= se else 'no'} |")
        lines.append(f"| {bent}: median k error <= 0.01 | {d['k_err_median']:.4f} | "
                     f"{'yes' if d['k_err_median'] <= 0.01 else 'no'} |")
    for straight in ("yud", "nyu-vp"):
        if (straight, "fr") not in summaries:
            continue
        base = summaries[(straight, "fr")]["focal_err_pct"][0]
        for spec in (division, "fr[distortion=auto]"):
            if (straight, spec) in summaries:
                value = summaries[(straight, spec)]["focal_err_pct"][0]
                lines.append(f"| {straight}: {spec} focal MAE <= pinhole + 0.3 points | {value:.2f} vs {base:.2f} | "
                             f"{'yes' if value <= base + 0.3 else 'no'} |")
    return lines


def _k_figure(frames: dict, path: Path) -> None:
    """Estimated against true k (fR + division) on the distorted sets."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(9, 4.2))
    for ax, (dataset, label) in zip(axes, (("zind-fr-d", "ZInD-fR-D test"), ("yud-crop-480x360-d", "YUD-D test"))):
        for spec, name, colour in (("fr[distortion=division]", "fR + division", "C0"),
                                   ("fast-fr[distortion=division]", "Fast-fR + division", "C1")):
            frame = frames.get((dataset, spec))
            if frame is not None:
                ax.plot(frame["k_true"], frame["k_est"], ".", color=colour, alpha=0.6, label=name)
        ax.plot([-0.45, 0.05], [-0.45, 0.05], "k-", lw=0.8)
        ax.set(title=label, xlabel="true k (warp)", ylabel="estimated k", xlim=(-0.45, 0.05), ylim=(-0.65, 0.2))
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)


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
    write = sub.add_parser("report", help="write the tables (tables.md) and the k figure from the cache")
    write.add_argument("--out", type=Path, required=True)
    args = parser.parse_args(argv)
    if args.command == "report":
        print(report(args.out))
        return 0
    methods = split_method_list(args.methods.replace(";", ","))
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


if __name__ == "__main__":
    raise SystemExit(main())
