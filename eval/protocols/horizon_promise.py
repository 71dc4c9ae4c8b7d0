"""The horizon promise (``horizon_reliable``) under the leave-one-dataset-out protocol, and its shipped scales.

Usage (after ``python -m fr_eval.protocols.lodo run --stage reliability``, the runs this module reads)::

    python -m fr_eval.protocols.horizon_promise table      # results/horizon/promise/{floors,lodo}.{md,csv}
    python -m fr_eval.protocols.horizon_promise promise --write   # the horizon block -> configs/reliability.json
    python -m fr_eval.protocols.horizon_promise final --dataset ecd-tune --split all   # a set no choice saw

Records: the LODO cache's prediction rows (:mod:`fr_eval.protocols.lodo_reliability`: the train
splits of :data:`~fr_eval.protocols.lodo.RELIABILITY_TRAIN` under the shipped estimator, each
reported dataset under its held-out setting), each with its **horizon error**: the horizon of the
estimate (``K^-T R[:, 1]``, principal point at the image centre) against the photo's ground-truth
horizon (:data:`TRUTH_ORDER`: the labelled one where the dataset labels it -- YUD, NYU-VP where two
horizontal VPs are labelled, ``ecd-tune`` -- else the ground-truth camera's, ``frame``), the
larger vertical distance at the borders, % of the image height
(:meth:`fr_torch.core.geometry.horizon.Horizon.error`).

Bounds (% of the height): ``derived`` is the horizon bound before this promise
(:func:`fr_torch.core.reliability.bounds.horizon_bound_pct`, from the focal and tilt bounds); the
**own** bound is ``scale x sigma_h`` (:func:`fr_torch.core.reliability.bounds.horizon_sigma_pct`)
with the scale the largest per-family split-conformal quantile at 90 % (as the focal / tilt
promise).  ``horizon_reliable`` = the own bound within the limit **or** the focal / tilt promise
(the route: ``or_focal_tilt``; the grid shows both rules).  The floor of ``sigma_h`` is chosen from
:data:`FLOORS` by :func:`choose_floor`: leave each calibration family out in turn, fit the scales
on the others, flag its photos; the floor with the largest smallest recall over the modes and
families (ties: the smaller floor).  For a reported dataset everything (floor, scales) is chosen
on the other families' train records; for the shipped promise on all of them.

Reported per set (limit L, default 5 % of the height): "good" = horizon error <= L; precision (of
the photos flagged, the share good), recall (of the good photos, the share flagged), the share of
photos within their bound, the median bound; for the focal / tilt promise (its two bounds within
10 % and 3 deg, scales fitted as for the horizon's) and for the derived bound <= L, the same figures
(the "before" columns).  The records do not carry the sanity checks' verdict: every column scores
the bounds alone (the estimator's flags also need the checks, which can only lower the recall).
"""
from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np
import pandas as pd

from fr_eval.datasets.registry import load_dataset
from fr_eval.paths import REPO, cache_root
from fr_eval.protocols.lodo import (
    NYU_TRAIN_STRIDE,
    RELIABILITY_TRAIN,
    REPORTED,
    SHIPPED,
    family_of,
    prediction_path,
    setting_name,
)
from fr_eval.protocols.lodo_reliability import METHOD_OF_MODE, MODE_LABEL, family_scales
from fr_eval.scoring.horizon_metric import truth_horizons
from fr_torch.core.geometry.camera import Camera
from fr_torch.core.geometry.horizon import Horizon
from fr_torch.core.reliability.bounds import (
    DEFAULT_COVERAGE,
    DEFAULT_LIMITS,
    HORIZON_LIMIT_PCT,
    SIGMAS,
    horizon_bound_pct,
    horizon_sigma_pct,
    worst_group_scale,
)
from fr_torch.core.reliability.cues import SPREAD_CUE_NAMES
from fr_torch.output import write_text_atomic

#: The ground truth a photo's horizon error is measured against: the first it has.
TRUTH_ORDER = ("labelled", "frame")
#: The floors of ``sigma_h`` (% of the image height) :func:`choose_floor` picks from.
FLOORS = (0.0, 0.25, 0.5, 0.75, 1.0, 1.5)
ROTATION_COLUMNS = [f"est_r{i}{j}" for i in range(3) for j in range(3)]


def truth_table(dataset: str, split: str, stride: int = 1, root: str | None = None) -> pd.DataFrame:
    """image, width, height, truth (the definition used), gt_left_y, gt_right_y of every photo of
    ``dataset``/``split`` (every ``stride``-th, as the LODO runs) that has a ground-truth horizon."""
    rows = []
    for sample in load_dataset(dataset, root=root, split=split)[::stride]:
        truths = truth_horizons(sample)
        name = next((n for n in TRUTH_ORDER if n in truths), None)
        if name is not None:
            rows.append({"image": sample.name, "width": int(sample.width), "height": int(sample.height),
                         "truth": name, "gt_left_y": truths[name].left_y, "gt_right_y": truths[name].right_y})
    return pd.DataFrame(rows)


def horizon_errors(predictions: pd.DataFrame, truths: pd.DataFrame) -> pd.DataFrame:
    """The estimates of ``predictions`` (``fr eval`` rows, failures left out) with their horizon
    error (``horizon_err_pct``, % of the height; inf without a horizon), the image size and the
    truth used, joined by image; photos without a ground-truth horizon are left out."""
    ok = predictions[~predictions["failed"].astype(bool)]
    table = ok.merge(truths, on="image", how="inner")
    errors = []
    for row in table.itertuples(index=False):
        rotation = np.array([getattr(row, c) for c in ROTATION_COLUMNS], np.float64).reshape(3, 3)
        camera = Camera(int(row.width), int(row.height), float(row.est_focal_px), None, rotation)
        horizon = Horizon.from_camera(camera)
        truth = Horizon(line=(0.0, 1.0, 0.0), left_y=row.gt_left_y, right_y=row.gt_right_y,
                        width=int(row.width), height=int(row.height))
        errors.append(math.inf if horizon is None else 100.0 * horizon.error(truth))
    table = table.assign(horizon_err_pct=errors)
    return table.reset_index(drop=True)


def records(cache: Path, setting: str, dataset: str, split: str, mode: str, stride: int = 1,
            root: str | None = None) -> pd.DataFrame:
    """Records of one cached LODO run: the spread cues, the focal and tilt errors (NaN where the set has
    no ground-truth camera), ``horizon_err_pct``, ``est_focal_px``, ``est_tilt_deg``, ``width``,
    ``height``, ``truth``, ``image``, ``dataset``."""
    path = prediction_path(cache, setting, dataset, split, METHOD_OF_MODE[mode])
    if not path.is_file():
        raise FileNotFoundError(f"{path} is missing: run `python -m fr_eval.protocols.lodo run --stage reliability`")
    predictions = pd.read_csv(path, dtype={"image": str})  # names like "000" stay names
    table = horizon_errors(predictions, truth_table(dataset, split, stride, root))
    base = pd.DataFrame({name: pd.to_numeric(table.get(f"cue_{name}"), errors="coerce") for name in SPREAD_CUE_NAMES})
    for column in ("focal_err_pct", "tilt_err_deg", "horizon_err_pct", "est_focal_px", "est_tilt_deg", "width", "height"):
        base[column] = pd.to_numeric(table.get(column), errors="coerce").to_numpy(np.float64)
    base["truth"], base["image"], base["dataset"] = table["truth"].to_numpy(), table["image"].to_numpy(), dataset
    return base


def train_records(mode: str, cache: Path, root: str | None = None) -> dict[str, pd.DataFrame]:
    """dataset -> its train records under the shipped estimator (NYU-VP: every 2nd photo)."""
    return {d: records(cache, SHIPPED, d, "train", mode, NYU_TRAIN_STRIDE if d == "nyu-vp" else 1, root)
            for d in RELIABILITY_TRAIN}


def sigma_h(table: pd.DataFrame, floor: float) -> np.ndarray:
    """``sigma_h`` (% of the height) of each record at ``floor``."""
    return np.asarray(horizon_sigma_pct(table, table["est_focal_px"].to_numpy(np.float64),
                                        table["est_tilt_deg"].to_numpy(np.float64),
                                        table["height"].to_numpy(np.float64), floor), np.float64)


def horizon_scale(calibration: pd.DataFrame, floor: float, coverage: float = DEFAULT_COVERAGE) -> tuple[float, dict]:
    """(the largest per-family conformal scale of horizon error / ``sigma_h``, each family's)."""
    families = calibration["dataset"].map(family_of).to_numpy()
    return worst_group_scale(sigma_h(calibration, floor), calibration["horizon_err_pct"].to_numpy(np.float64),
                             families, coverage)


def derived_bounds(table: pd.DataFrame, scales: dict[str, float]) -> np.ndarray:
    """The horizon bound before this promise (:func:`horizon_bound_pct`) of each record, from its
    focal and tilt bounds at ``scales`` (target -> conformal scale)."""
    focal = scales["focal_pct"] * np.asarray(SIGMAS["focal_pct"](table), np.float64)
    tilt = scales["tilt_deg"] * np.asarray(SIGMAS["tilt_deg"](table), np.float64)
    out = [horizon_bound_pct({"focal_pct": f, "tilt_deg": t}, fp, td, h) for f, t, fp, td, h in
           zip(focal, tilt, table["est_focal_px"], table["est_tilt_deg"], table["height"])]
    return np.array([math.inf if v is None else v for v in out], np.float64)


def focal_tilt_flags(table: pd.DataFrame, scales: dict[str, float]) -> np.ndarray:
    """The focal / tilt promise of each record at ``scales`` (target -> conformal scale): both bounds
    within the shipped limits (as :func:`fr_eval.protocols.lodo_reliability.evaluate`; the sanity
    checks are not in the records)."""
    flags = np.ones(len(table), bool)
    for target, limit in DEFAULT_LIMITS.items():
        flags &= scales[target] * np.asarray(SIGMAS[target](table), np.float64) <= limit
    return flags


def promise_figures(errors: np.ndarray, flagged: np.ndarray, bounds: np.ndarray | None, limit: float) -> dict:
    """n, good %, flagged n, precision, recall (%), within bound %, median bound of one set."""
    errors = np.asarray(errors, np.float64)
    flagged = np.asarray(flagged, bool)
    good = errors <= limit
    share = lambda mask: 100 * float(mask.mean()) if mask.size else math.nan  # noqa: E731
    out = {"n": int(errors.size), "good_n": int(good.sum()), "flagged_n": int(flagged.sum()),
           "precision_pct": share(good[flagged]), "recall_pct": share(flagged[good])}
    if bounds is not None:
        out.update(within_bound_pct=share(errors <= bounds), median_bound_pct=float(np.median(bounds)))
    return out


def floor_grid(calibration: pd.DataFrame, limit: float, coverage: float = DEFAULT_COVERAGE,
               floors: Sequence[float] = FLOORS) -> pd.DataFrame:
    """One row per floor, route (own bound alone, or with the focal / tilt route) and family of
    ``calibration``: that family's figures with the scales fitted on the other families."""
    families = calibration["dataset"].map(family_of).to_numpy()
    rows = []
    for family in dict.fromkeys(families.tolist()):
        inside, rest = calibration[families == family], calibration[families != family]
        fitted = family_scales(rest, "fr", coverage)  # the spreads' scales: the records decide the mode
        focal_tilt = focal_tilt_flags(inside, {t: fitted[t][0] for t in DEFAULT_LIMITS})
        for floor in floors:
            scale, _ = horizon_scale(rest, floor, coverage)
            bounds = scale * sigma_h(inside, floor)
            for route in (False, True):
                flags = (bounds <= limit) | (focal_tilt & route)
                rows.append({"floor_pct": floor, "or_focal_tilt": route, "family": family, "scale": scale,
                             **promise_figures(inside["horizon_err_pct"], flags, bounds, limit)})
    return pd.DataFrame(rows)


def choose_floor(calibrations: Mapping[str, pd.DataFrame], limit: float, coverage: float = DEFAULT_COVERAGE,
                 floors: Sequence[float] = FLOORS) -> tuple[float, pd.DataFrame]:
    """(the chosen floor, the grid of every mode) over ``calibrations`` (mode -> records): with the
    focal / tilt route on, the floor with the largest smallest recall over the modes and the
    left-out families (ties: the smaller floor; module docstring)."""
    grid = pd.concat([floor_grid(c, limit, coverage, floors).assign(mode=m) for m, c in calibrations.items()],
                     ignore_index=True)
    on = grid[grid["or_focal_tilt"]].groupby("floor_pct")["recall_pct"].min()
    return float(on.index[on == on.max()].min()), grid


def held_out_rows(dataset: str, split: str, cache: Path, train: Mapping[str, Mapping[str, pd.DataFrame]],
                  limit: float, coverage: float) -> list[dict]:
    """One reported set's figures per mode (``train``: mode -> dataset -> train records), every
    choice (floor, scales) made without its family."""
    family = family_of(dataset)
    calibrations = {m: pd.concat([r for d, r in t.items() if family_of(d) != family], ignore_index=True)
                    for m, t in train.items()}
    floor, _ = choose_floor(calibrations, limit, coverage)
    rows = []
    for mode, calibration in calibrations.items():
        scale, _ = horizon_scale(calibration, floor, coverage)
        test = records(cache, setting_name(family), dataset, split, mode)
        fitted = family_scales(calibration, mode, coverage)
        rows.append(set_row(test, mode, dataset, split, floor, scale,
                            {t: fitted[t][0] for t in DEFAULT_LIMITS}, limit))
    return rows


def set_row(test: pd.DataFrame, mode: str, dataset: str, split: str, floor: float, scale: float,
            focal_tilt_scales: Mapping[str, float], limit: float) -> dict:
    """The figures of one set's records: the focal / tilt promise, the derived bound, the own bound
    and ``horizon_reliable`` (own bound within the limit or the focal / tilt promise)."""
    derived = derived_bounds(test, focal_tilt_scales)
    bounds = scale * sigma_h(test, floor)
    focal_tilt = focal_tilt_flags(test, focal_tilt_scales)
    errors = test["horizon_err_pct"].to_numpy(np.float64)
    row = {"mode": mode, "dataset": dataset, "split": split, "truth": "/".join(sorted(set(test["truth"]))),
           "floor_pct": floor, "scale": scale}
    for key, flags, b in (("reliable", focal_tilt, None), ("derived", derived <= limit, derived),
                          ("own", bounds <= limit, bounds), ("horizon", (bounds <= limit) | focal_tilt, bounds)):
        row.update({f"{key}_{k}": v for k, v in promise_figures(errors, flags, b, limit).items()})
    return row


def lodo_table(cache: Path, limit: float, coverage: float, modes: Sequence[str] = ("fr", "fast")) -> tuple[pd.DataFrame, pd.DataFrame]:
    """(the held-out table, the floor grid over all families' train records)."""
    train = {mode: train_records(mode, cache) for mode in modes}
    _, grid = choose_floor({m: pd.concat(t.values(), ignore_index=True) for m, t in train.items()}, limit, coverage)
    rows = []
    for dataset, split in REPORTED:
        for row in held_out_rows(dataset, split, cache, train, limit, coverage):
            rows.append(row)
            print(f"{row['mode']} {dataset}: precision {row['horizon_precision_pct']:.0f} % recall "
                  f"{row['horizon_recall_pct']:.0f} % (focal/tilt {row['reliable_precision_pct']:.0f} / "
                  f"{row['reliable_recall_pct']:.0f} %)", file=sys.stderr)
    table = pd.DataFrame(rows)
    return table.sort_values("mode", key=lambda m: m.map({"fr": 0, "fast": 1}), kind="stable"), grid


def _pct(value: float) -> str:
    return "—" if value is None or (isinstance(value, float) and math.isnan(value)) else f"{value:.0f} %"


def _figures(r, key: str) -> str:
    get = lambda name: getattr(r, f"{key}_{name}")  # noqa: E731
    return f"{get('flagged_n')}, {_pct(get('precision_pct'))}, {_pct(get('recall_pct'))}"


def markdown(table: pd.DataFrame, limit: float) -> str:
    lines = ["| mode | held-out set (truth) | n | good (≤ L) | focal/tilt promise | derived bound ≤ L | "
             "derived bound: holds, median | own bound ≤ L | own bound: holds, median | "
             "**`horizon_reliable`** | floor, scale |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in table.itertuples():
        lines.append(
            f"| {MODE_LABEL[r.mode]} | {r.dataset} {r.split} ({r.truth}) | {r.horizon_n} | {r.horizon_good_n} | "
            f"{_figures(r, 'reliable')} | {_figures(r, 'derived')} | "
            f"{_pct(r.derived_within_bound_pct)}, {r.derived_median_bound_pct:.1f} % | {_figures(r, 'own')} | "
            f"{_pct(r.own_within_bound_pct)}, {r.own_median_bound_pct:.1f} % | **{_figures(r, 'horizon')}** | "
            f"{r.floor_pct:g}, {r.scale:.2f} |")
    return ("\n".join(lines) + f"\n\nEach cell of flags: photos flagged, precision, recall (good = horizon error "
            f"≤ L = {limit:g} % of the image height); 90 % bounds.")


def grid_markdown(grid: pd.DataFrame) -> str:
    lines = ["| mode | floor (% of h) | route | left-out family | scale (other families) | n | flagged | precision | "
             "recall | own bound holds |", "|---|---|---|---|---|---|---|---|---|---|"]
    for r in grid.itertuples():
        lines.append(f"| {MODE_LABEL[r.mode]} | {r.floor_pct:g} | {'or focal/tilt' if r.or_focal_tilt else 'own bound'} | "
                     f"{r.family} | {r.scale:.2f} | {r.n} | {r.flagged_n} | {_pct(r.precision_pct)} | "
                     f"{_pct(r.recall_pct)} | {_pct(r.within_bound_pct)} |")
    return "\n".join(lines)


def shipped_block(cache: Path, limit: float, coverage: float) -> dict:
    """The ``horizon`` block of configs/reliability.json's promise: the floor and the scales from every
    family's train records."""
    calibrations = {m: pd.concat(train_records(m, cache).values(), ignore_index=True) for m in ("fr", "fast")}
    floor, _ = choose_floor(calibrations, limit, coverage)
    scales, per_family = {}, {}
    for mode, calibration in calibrations.items():
        scale, per = horizon_scale(calibration, floor, coverage)
        scales[mode], per_family[mode] = round(scale, 3), {k: round(v, 3) for k, v in per.items()}
    return {"limit_pct": limit, "floor_pct": floor, "or_focal_tilt": True, "scales": scales,
            "per_family_scales": per_family,
            "doc": "horizon_reliable = the 90 % bound of the horizon error (% of the image height; the larger "
                   "vertical distance at the borders) <= limit_pct, or (or_focal_tilt) the focal / tilt promise "
                   "holds; bound = scale x sigma_h, sigma_h = 100 / h sqrt((f sec^2 t s_p)^2 + (f |tan t| s_f)^2) "
                   "(+) floor_pct (fr_torch.core.reliability.bounds.horizon_sigma_pct); scales: the largest per-family "
                   "split-conformal quantile over the train splits of YUD + crops, ZInD-fR, NYU-VP; the floor: the "
                   "largest smallest recall when each family is left out in turn (python -m "
                   "fr_eval.protocols.horizon_promise promise --write; results/horizon/promise/)"}


def final_table(cache: Path, dataset: str, split: str, limit: float, modes: Sequence[str], root: str | None) -> pd.DataFrame:
    """The shipped promise (configs/reliability.json) on a set no choice saw: runs the shipped estimator
    on it (cached under ``cache/shipped``) and scores it as :func:`set_row`."""
    from fr_eval.protocols.lodo import run_predictions
    from fr_torch.core.reliability.bounds import ReliabilityPromise

    promise = ReliabilityPromise.from_config()
    rows = []
    for mode in modes:
        run_predictions(dataset, split, METHOD_OF_MODE[mode], SHIPPED, None, cache, root=root)
        test = records(cache, SHIPPED, dataset, split, mode, root=root)
        hp = promise.horizon
        rows.append(set_row(test, mode, dataset, split, hp.floor_pct, hp.scales[mode], promise.scales[mode], limit))
    return pd.DataFrame(rows)


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m fr_eval.protocols.horizon_promise", description=__doc__.split("\n")[0])
    parser.add_argument("action", choices=("table", "promise", "final"))
    parser.add_argument("--cache", default=str(cache_root() / "lodo"))
    parser.add_argument("--limit", type=float, default=HORIZON_LIMIT_PCT, help="L, % of the image height")
    parser.add_argument("--coverage", type=float, default=DEFAULT_COVERAGE)
    parser.add_argument("--modes", default="fr,fast")
    parser.add_argument("--dataset", default="ecd-tune", help="final: the set")
    parser.add_argument("--split", default="all", help="final: its split")
    parser.add_argument("--data-root", default=None)
    parser.add_argument("--out", default=str(REPO / "results" / "horizon" / "promise"))
    parser.add_argument("--write", action="store_true", help="promise: write it into configs/reliability.json")
    args = parser.parse_args(argv)
    cache, out, modes = Path(args.cache), Path(args.out), tuple(args.modes.split(","))
    out.mkdir(parents=True, exist_ok=True)
    if args.action == "table":
        table, grid = lodo_table(cache, args.limit, args.coverage, modes)
        table.to_csv(out / "lodo.csv", index=False)
        grid.to_csv(out / "floors.csv", index=False)
        (out / "lodo.md").write_text(markdown(table, args.limit) + "\n")
        (out / "floors.md").write_text(grid_markdown(grid) + "\n")
        print(markdown(table, args.limit))
        return 0
    if args.action == "final":
        table = final_table(cache, args.dataset, args.split, args.limit, modes, args.data_root)
        stem = f"final_{args.dataset}_{args.split}"
        table.to_csv(out / f"{stem}.csv", index=False)
        (out / f"{stem}.md").write_text(markdown(table, args.limit) + "\n")
        print(markdown(table, args.limit))
        return 0
    path = REPO / "configs" / "reliability.json"
    config = json.loads(path.read_text())
    block = shipped_block(cache, args.limit, args.coverage)
    if args.write:
        config["promise"]["horizon"] = block
        write_text_atomic(path, json.dumps(config, indent=1) + "\n")  # searches running now read it whole
    print(json.dumps(block, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
