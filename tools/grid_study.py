"""Cheaper stage-1 grids against today's: accuracy, same answer as the baseline, search CPU time.

Three steps, each a command (one thread, one photo per call: batch 1)::

    python tools/grid_study.py detect --cache CACHE
    python tools/grid_study.py run --mode fast --candidates base,k6,c2f16 --cache CACHE --out RUNS
    python tools/grid_study.py timing --mode fast --candidates base,c2f16 --cache CACHE --every 4
    python tools/grid_study.py report --runs RUNS --out results/grid/coarse_to_fine.md

``detect``: the LSD segments (working resolution, unfiltered) of YUD train (51 photos), ZInD-fR
train (210 views) and a fixed random subset of NYU-VP train (:data:`NYU_SUBSET` photos, seed
:data:`NYU_SEED`; the dataset's own LSD segments), saved in ``CACHE/segments.pkl``.

``run``: for each candidate (:data:`CANDIDATES`: ``SearchConfig`` overrides) and mode, each photo
through ``FREstimator.calibrate_segments`` (the mode's segment filter; the principal point at the
image centre, as ``fr eval``'s default); per photo the estimate, its errors against the ground truth
(:func:`fr_eval.scoring.metrics.image_errors`), the horizon error (YUD and NYU-VP: the labelled
horizon; ZInD-fR: the ground-truth camera's) and CPU seconds (``time.process_time``) of the whole
call, of the search (``search_manhattan``) and of its refinement (``refine_starts``); stage 1 (grid,
focal sweep, lattice passes) is the search less its refinement.  One warm-up call first.  Writes
``RUNS/<mode>_<candidate>.csv``.

``timing``: CPU time per photo with the candidates interleaved photo by photo (:func:`timing`):
the saving's measure (``run``'s times come from one pass each, at different moments of a shared
machine's load).

``report``: per data set and mode, each candidate's mean error ± SE, horizon AUC (a failure scores
beyond the cutoff; photos without that ground truth are left out: 33 of the NYU-VP subset), the
share of photos whose answer is the baseline's (:func:`fr_torch.core.search.passes.different_solutions`: focal
within 1 %, pan (mod 90), pitch and roll within 0.5 deg), the mean paired difference to the
baseline ± its SE, and how the reliability model's inputs and outputs move; a Markdown file (the
CPU times of ``run`` stay in its CSVs: ``timing`` measures the saving).
"""
from __future__ import annotations

import argparse
import csv
import math
import pickle
import time
from pathlib import Path

import numpy as np

#: The candidates: name -> SearchConfig overrides (``base``: the whole 8^4 grid, the baseline the
#: study measured against; ``c2f32`` is today's default).
WHOLE = {"grid_coarse_factor": 1}
CANDIDATES: dict[str, dict] = {
    "base": dict(WHOLE),
    "k7": {"grid_points_per_dim": 7, **WHOLE},
    "k6": {"grid_points_per_dim": 6, **WHOLE},
    "k6-l8": {"grid_points_per_dim": 6, "top_l": 8, **WHOLE},
    "k6-p4": {"grid_points_per_dim": 6, "grid_passes": 4, **WHOLE},
    "k5-l8": {"grid_points_per_dim": 5, "top_l": 8, **WHOLE},
    "c2f8": {"grid_coarse_factor": 2, "grid_coarse_cells": 8},
    "c2f16": {"grid_coarse_factor": 2, "grid_coarse_cells": 16},
    "c2f32": {"grid_coarse_factor": 2, "grid_coarse_cells": 32},
    "c2f64": {"grid_coarse_factor": 2, "grid_coarse_cells": 64},
    "k6-c2f16": {"grid_points_per_dim": 6, "grid_coarse_factor": 2, "grid_coarse_cells": 16},
    "c2f32-p2": {"grid_coarse_factor": 2, "grid_coarse_cells": 32, "grid_passes": 2},
    "seg150": {"grid_segments": 150, **WHOLE},
    "seg250": {"grid_segments": 250, **WHOLE},
}
DATASETS = ("yud", "zind-fr", "nyu-vp")
NYU_SUBSET, NYU_SEED = 200, 0
#: The horizon definition scored per data set.
HORIZON = {"yud": "labelled", "zind-fr": "frame", "nyu-vp": "labelled"}


def samples(name: str):
    from fr_eval.datasets.registry import load_dataset
    items = list(load_dataset(name, split="train"))
    if name == "nyu-vp":
        pick = np.sort(np.random.default_rng(NYU_SEED).choice(len(items), NYU_SUBSET, replace=False))
        items = [items[i] for i in pick]
    return items


def detect(cache: Path) -> None:
    from fr_torch.detectors.lsd import LSDDetector
    from fr_torch.images.io import read_working
    detector = LSDDetector()
    out = {}
    for name in DATASETS:
        rows = []
        for sample in samples(name):
            if sample.image_path is None:  # NYU-VP: the dataset's segments
                segments = np.asarray(sample.extra["detected_segments"], np.float32)
                size = (sample.width, sample.height)
            else:
                gray, scale, size = read_working(str(sample.image_path), sample.name)
                assert scale == 1.0, f"{sample.name}: working scale {scale}"
                segments = np.asarray(detector(gray), np.float32)
            rows.append((sample.name, segments, tuple(size)))
        out[name] = rows
        print(name, len(rows), "photos")
    cache.mkdir(parents=True, exist_ok=True)
    (cache / "segments.pkl").write_bytes(pickle.dumps(out))


def run(mode: str, candidates: list[str], cache: Path, out: Path) -> None:
    import torch
    torch.set_num_threads(1)
    import fr_torch.core.estimator as estimator_module
    from fr_eval.scoring.horizon_metric import truth_horizons
    from fr_eval.scoring.metrics import image_errors
    from fr_torch import FREstimator, SearchConfig
    from fr_torch.core.geometry.horizon import Horizon
    from fr_torch.core.geometry.params import angles_from_search_rotation
    from fr_torch.core.search import manhattan
    from fr_torch.plugins.methods import estimate_from_result

    spent = {"search": 0.0, "refine": 0.0}

    def timed(module, name, key):
        function = getattr(module, name)

        def wrapper(*a, **k):
            start = time.process_time()
            try:
                return function(*a, **k)
            finally:
                spent[key] += time.process_time() - start
        setattr(module, name, wrapper)

    timed(estimator_module, "search_manhattan", "search")
    timed(manhattan, "refine_starts", "refine")
    data = pickle.loads((cache / "segments.pkl").read_bytes())
    truth = {name: {s.name: s for s in samples(name)} for name in DATASETS}
    out.mkdir(parents=True, exist_ok=True)
    for candidate in candidates:
        estimator = FREstimator(mode=mode, search_config=SearchConfig.from_config(**CANDIDATES[candidate]))
        first = data["yud"][0]
        estimator.calibrate_segments([first[1]], [first[2]])  # warm-up (kernels compiled and checked)
        rows = []
        for dataset in DATASETS:
            for name, segments, size in data[dataset]:
                spent.update(search=0.0, refine=0.0)
                start = time.process_time()
                [result] = estimator.calibrate_segments([segments], [size], names=[name])
                total = time.process_time() - start
                sample = truth[dataset][name]
                errors = image_errors(sample, estimate_from_result(candidate, result, 0.0))
                row = {"dataset": dataset, "name": name, "mode": mode, "candidate": candidate, "ok": result.ok,
                       **errors, "cpu_total_s": total, "cpu_search_s": spent["search"],
                       "cpu_refine_s": spent["refine"]}
                if result.ok:
                    rotation = torch.as_tensor(np.asarray(result.camera.rotation, np.float64))
                    pan, pitch, roll = angles_from_search_rotation(rotation).tolist()
                    row.update(pan=pan, pitch=pitch, roll=roll, focal=float(result.camera.focal_px),
                               log_likelihood=result.log_likelihood, reliable=result.reliable,
                               grid_entropy=result.cues.get("grid_entropy"),
                               predicted_focal_err=(result.predicted_error or {}).get("focal_pct"))
                    truth_line = truth_horizons(sample).get(HORIZON[dataset])
                    estimate = Horizon.from_camera(result.camera)
                    row["horizon_err"] = (math.inf if estimate is None else estimate.error(truth_line)) \
                        if truth_line is not None else math.nan
                rows.append(row)
        keys = sorted({k for r in rows for k in r}, key=lambda k: (k not in rows[0], k))
        with open(out / f"{mode}_{candidate}.csv", "w", newline="") as handle:
            writer = csv.DictWriter(handle, keys)
            writer.writeheader()
            writer.writerows(rows)
        frame = np.array([r["cpu_search_s"] for r in rows])
        print(f"{mode} {candidate}: search {1000 * frame.mean():.1f} ms per photo, {len(rows)} photos", flush=True)


def timing(mode: str, candidates: list[str], cache: Path, rounds: int, datasets: list[str], every: int) -> None:
    """CPU ms per photo of the search and of the whole call, the candidates interleaved photo by
    photo (each photo through every candidate in turn, the order rotated from photo to photo), so
    that a shared machine's load falls on all alike; ``rounds`` passes over every ``every``-th photo
    of ``datasets``.  Prints, per data set and over all, each candidate's mean over photos (the
    median over rounds) and its ratio to the first candidate."""
    import statistics

    import torch
    torch.set_num_threads(1)
    import fr_torch.core.estimator as estimator_module
    from fr_torch import FREstimator, SearchConfig

    spent = {"search": 0.0}
    function = estimator_module.search_manhattan

    def wrapper(*a, **k):
        start = time.process_time()
        try:
            return function(*a, **k)
        finally:
            spent["search"] += time.process_time() - start
    estimator_module.search_manhattan = wrapper
    data = pickle.loads((cache / "segments.pkl").read_bytes())
    photos = [(name, segments, size) for name in datasets for _, segments, size in data[name][::every]
              if len(segments)]
    estimators = [FREstimator(mode=mode, search_config=SearchConfig.from_config(**CANDIDATES[c])) for c in candidates]
    for estimator in estimators:
        estimator.calibrate_segments([photos[0][1]], [photos[0][2]])  # warm-up
    groups = [*datasets, "all"] if len(datasets) > 1 else list(datasets)
    counts = {g: sum(1 for p in photos if g in (p[0], "all")) for g in groups}
    per_round = {(g, c, key): [] for g in groups for c in candidates for key in ("search", "total")}
    for _ in range(rounds):
        sums = dict.fromkeys(per_round, 0.0)
        for i, (name, segments, size) in enumerate(photos):
            for j in range(len(candidates)):
                c = (i + j) % len(candidates)
                spent["search"] = 0.0
                start = time.process_time()
                estimators[c].calibrate_segments([segments], [size])
                total = time.process_time() - start
                for g in {name, "all"} & set(groups):
                    sums[(g, candidates[c], "total")] += total
                    sums[(g, candidates[c], "search")] += spent["search"]
        for key, value in sums.items():
            per_round[key].append(1000 * value / counts[key[0]])
    first = candidates[0]
    print(f"{mode}: every {every}th photo, {rounds} rounds, candidates interleaved photo by photo; "
          "CPU ms per photo (median over rounds), ratio to " + first)
    print("| data set | photos | candidate | search CPU ms | vs " + first + " | whole call CPU ms | vs " + first + " |")
    print("|---|---|---|---|---|---|---|")
    for g in groups:
        base = {key: statistics.median(per_round[(g, first, key)]) for key in ("search", "total")}
        for c in candidates:
            search = statistics.median(per_round[(g, c, "search")])
            total = statistics.median(per_round[(g, c, "total")])
            print(f"| {g} | {counts[g]} | {c} | {search:.1f} | {search / base['search']:.2f} | {total:.1f} "
                  f"| {total / base['total']:.2f} |")


def _mean_se(values) -> tuple[float, float]:
    values = np.asarray([v for v in values if v is not None and np.isfinite(v)], np.float64)
    if len(values) == 0:
        return math.nan, math.nan
    return float(values.mean()), float(values.std(ddof=1) / math.sqrt(len(values))) if len(values) > 1 else math.nan


def reliability_lines(tables: dict, mode: str, names: list[str]) -> list[str]:
    """Markdown: per data set and candidate (the runs that recorded them), how the reliability model's
    inputs and outputs move against the baseline: the ``grid_entropy`` cue (mean and largest
    absolute difference, nats), the ``reliable`` flag (photos where it differs) and the predicted
    focal error (mean absolute difference, %)."""
    base_all = tables[(mode, "base")]
    if "grid_entropy" not in base_all:
        return []
    lines = ["Reliability model's inputs and outputs against the baseline (photos estimated by both):", "",
             ("| data set | candidate | grid_entropy mean abs diff (largest) | reliable flag differs "
              "| predicted focal error mean abs diff (%) |"), "|---|---|---|---|---|"]
    for dataset in DATASETS:
        base = base_all[(base_all.dataset == dataset) & base_all.ok].set_index("name")
        for candidate in names:
            frame = tables[(mode, candidate)]
            if candidate == "base" or "grid_entropy" not in frame:
                continue
            frame = frame[frame.dataset == dataset].set_index("name").loc[base.index]
            entropy = (frame.grid_entropy - base.grid_entropy).abs()
            flags = int((frame.reliable.astype(bool) != base.reliable.astype(bool)).sum())
            predicted = (frame.predicted_focal_err - base.predicted_focal_err).abs().mean()
            lines.append(f"| {dataset} | {candidate} | {entropy.mean():.4f} ({entropy.max():.4f}) "
                         f"| {flags}/{len(base)} | {predicted:.3f} |")
    return lines + [""]


def report(runs: Path, out: Path) -> None:
    import pandas as pd
    import torch
    from fr_eval.scoring.horizon_metric import lezama_auc
    from fr_torch.core.search.passes import different_solutions

    tables = {}
    for path in sorted(runs.glob("*.csv")):
        frame = pd.read_csv(path)
        tables[(frame["mode"].iloc[0], frame["candidate"].iloc[0])] = frame
    order = {name: i for i, name in enumerate(CANDIDATES)}
    lines = []
    for mode in ("fast", "fr"):
        names = sorted((c for m, c in tables if m == mode), key=lambda c: order.get(c, 99))
        if "base" not in names:
            continue
        base_all = tables[(mode, "base")]
        lines += [f"### {'Fast-fR' if mode == 'fast' else 'fR'}", ""]
        for dataset in DATASETS:
            base = base_all[base_all.dataset == dataset].set_index("name")
            lines += [f"**{dataset}** train ({len(base)} photos)", "",
                      ("| candidate | failed | focal % | Δ focal (paired) | tilt ° | roll ° | horizon AUC % "
                       "| same answer |"),
                      "|---|---|---|---|---|---|---|---|"]
            for candidate in names:
                frame = tables[(mode, candidate)]
                frame = frame[frame.dataset == dataset].set_index("name").loc[base.index]
                focal = _mean_se(frame.focal_err_pct)
                paired = _mean_se(frame.focal_err_pct - base.focal_err_pct)
                tilt, roll = _mean_se(frame.tilt_err_deg), _mean_se(frame.roll_err_deg)
                horizon = np.where(frame.ok, frame.horizon_err, math.inf)  # a failure: beyond the cutoff
                horizon = horizon[~np.isnan(horizon)]  # photos without that ground truth: not scored
                auc = 100 * lezama_auc(horizon)[0] if len(horizon) else math.nan
                both = frame.ok & base.ok
                a = torch.tensor(frame.loc[both, ["pan", "pitch", "roll", "focal"]].to_numpy())
                b = torch.tensor(base.loc[both, ["pan", "pitch", "roll", "focal"]].to_numpy())
                same = int((~different_solutions(a, b)).sum()) + int((~frame.ok & ~base.ok).sum())
                lines.append(f"| {candidate} | {int((~frame.ok).sum())} | {focal[0]:.2f} ± {focal[1]:.2f} "
                             f"| {paired[0]:+.2f} ± {paired[1]:.2f} | {tilt[0]:.2f} ± {tilt[1]:.2f} "
                             f"| {roll[0]:.2f} ± {roll[1]:.2f} | {auc:.2f} "
                             f"| {same}/{len(frame)} |")
            lines.append("")
        lines += reliability_lines(tables, mode, names)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("step", choices=("detect", "run", "timing", "report"))
    parser.add_argument("--cache", type=Path, default=Path("data_local/grid_study"))
    parser.add_argument("--mode", default="fast")
    parser.add_argument("--candidates", default="base")
    parser.add_argument("--runs", "--out-runs", dest="runs", type=Path, default=Path("results/grid/runs"))
    parser.add_argument("--out", type=Path, default=None)
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--datasets", default=",".join(DATASETS))
    parser.add_argument("--every", type=int, default=1)
    args = parser.parse_args()
    if args.step == "detect":
        detect(args.cache)
    elif args.step == "timing":
        timing(args.mode, args.candidates.split(","), args.cache, args.rounds, args.datasets.split(","), args.every)
    elif args.step == "run":
        run(args.mode, args.candidates.split(","), args.cache, args.out or args.runs)
    else:
        report(args.runs, args.out or Path("results/grid/coarse_to_fine.md"))


if __name__ == "__main__":
    main()
