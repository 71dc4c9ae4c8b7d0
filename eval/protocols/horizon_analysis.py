"""What fR's horizon error is made of, on YorkUrbanDB (all 102 photos) and ``ecd-tune`` (25):
``results/horizon/analysis.md`` reads the tables and figures this module writes.

Usage::

    python -m fr_eval.protocols.horizon_analysis run       # fR variants -> $FR_CACHE/horizon_analysis/<dataset>.json
    python -m fr_eval.protocols.horizon_analysis report    # -> results/horizon/analysis/ (tables.md, CSVs, figures)

``run`` calibrates every photo once per :data:`VARIANTS` entry, as ``fr calibrate`` does (file paths,
default settings unless the variant says otherwise) and keeps each result's JSON with its segments.
``report`` scores them with the horizon benchmark's metric (:mod:`fr_eval.scoring.horizon_metric`)
and splits the error:

* **Oracle substitutions** (YUD): fR with the calibrated principal point, with the known focal
  length, on the hand-labelled segments, and their combinations.
* **Attribution** (YUD, :func:`attribution`): the horizon of a pinhole camera follows from its
  tilt, roll, f and principal point alone; each of them is replaced by its ground-truth value in
  every combination, and each factor's Shapley share of the
  error against the ``labelled`` horizon is reported; with all four replaced what is left is the
  gap between the orthogonalised frame's horizon and the labelled VPs' line (``definition``).
* **Free vanishing points** (:func:`free_horizons`): from fR's own segments and labels, each
  family's VP fitted alone (length-weighted least squares on the Gaussian sphere of fR's K), and the
  horizon taken as (a) the line through the two free horizontal VPs, (b) the polar of the free
  vertical, (c) the plane that fits the vertical and every horizontal family (with ``--atlanta``'s
  extra families: (d)).  They say whether the horizon is better read from the horizontal directions
  than from fR's Manhattan fit.
* **Centre and slope** (:func:`centre_and_slope`): the error at the image centre (tilt, f and the
  principal point move it) and half the change of slope across the width (roll); the benchmark's
  error is their sum.
* **Segment filters**: fR with short segments dropped (``min_length_px`` in working pixels, long
  side 640).
"""
from __future__ import annotations

import argparse
import itertools
import json
import math
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pandas as pd
from tqdm import tqdm

from fr_eval.datasets.registry import load_dataset
from fr_eval.paths import REPO, cache_root
from fr_eval.protocols.run_eval import make_calibrator
from fr_eval.scoring.horizon_metric import lezama_auc, truth_horizons
from fr_eval.scoring.plots import plt, save_figure
from fr_eval.scoring.tables import to_markdown
from fr_torch import FREstimator
from fr_torch.core.geometry.camera import Camera
from fr_torch.core.geometry.horizon import Horizon, border_columns
from fr_torch.core.likelihood.segments import SegmentFilter
from fr_torch.core.reliability.bounds import horizon_bound_pct
from fr_torch.images.io import WORKING_LONG_SIDE, load_image
from fr_torch.plugins.interface import ImageMeta

DATASETS = {"yud": "all", "ecd-tune": "all"}
@dataclass(frozen=True)
class Variant:
    """One way of running fR: ``options`` for :class:`~fr_torch.FREstimator`; the dataset's calibrated
    principal point, known focal length, hand-labelled segments (YUD only); the working resolution's
    long side (None: the input's)."""

    options: dict = field(default_factory=dict)
    calibrated_pp: bool = False
    known_focal: bool = False
    labelled_segments: bool = False
    working_long_side: int | None = WORKING_LONG_SIDE

    @property
    def needs_truth(self) -> bool:
        return self.calibrated_pp or self.known_focal or self.labelled_segments


def _long_segments(min_length_px: float) -> dict:
    return {"segment_filter": SegmentFilter(min_length_px=min_length_px, max_segments=750)}


VARIANTS = {
    "fr": Variant(),
    "fr, calibrated pp": Variant(calibrated_pp=True),
    "fr, known f": Variant(known_focal=True),
    "fr, calibrated pp + known f": Variant(calibrated_pp=True, known_focal=True),
    "fr on labelled segments": Variant(labelled_segments=True),
    "fr on labelled segments, calibrated pp + known f": Variant(calibrated_pp=True, known_focal=True,
                                                                labelled_segments=True),
    "fr --atlanta": Variant({"atlanta": "on"}),
    "fr, segments > 15 px": Variant(_long_segments(15.0)),
    "fr, segments > 30 px": Variant(_long_segments(30.0)),
    "fr --distortion auto": Variant({"distortion": "auto"}),
    "fr at the input resolution": Variant(working_long_side=None),
}
#: Per photo the smaller of fR's and Lee 2009's errors: what a perfect choice between the two would score.
BEST_OF = "the better of fr and lee2009 per photo (oracle choice)"
FACTORS = ("tilt", "roll", "f", "pp")
#: The ground truths the attribution splits fR's error against (YUD): the labelled VPs' line and
#: the ground-truth camera's own horizon (there the ``definition`` gap is 0).
ATTRIBUTION_TARGETS = ("labelled", "frame")
FREE = ("horizontal VPs' line", "free vertical's polar", "vertical + horizontal fit",
        "vertical + horizontal fit, --atlanta families")
OUT = REPO / "results" / "horizon" / "analysis"


def cache_file(dataset: str) -> Path:
    return cache_root() / "horizon_analysis" / f"{dataset}.json"


def run(datasets=DATASETS) -> None:
    """Calibrate every photo with every variant (module docstring); one JSON per dataset (variants
    already in it are kept, not run again)."""
    for dataset, split in datasets.items():
        samples = load_dataset(dataset, split=split)
        has_truth = all(s.camera is not None and s.segments is not None for s in samples)
        path = cache_file(dataset)
        records: dict[str, dict[str, Any]] = json.loads(path.read_text(encoding="utf-8")) if path.is_file() else {}
        for variant, setting in VARIANTS.items():
            if (setting.needs_truth and not has_truth) or variant in records:
                continue
            estimator = FREstimator(mode="fr", **setting.options)
            estimator.working_long_side = setting.working_long_side
            records[variant] = {}
            for sample in tqdm(samples, desc=f"{dataset}: {variant}", unit="img", file=sys.stderr):
                kwargs = {"focal_px": sample.focal_px if setting.known_focal else None,
                          "principal_point": sample.principal_point if setting.calibrated_pp else None}
                if setting.labelled_segments:
                    [result] = estimator.calibrate_segments([sample.segments], [(sample.width, sample.height)],
                                                            names=[sample.name], **kwargs)
                else:
                    [result] = estimator.calibrate_images([str(sample.image_path)], names=[sample.name], **kwargs)
                records[variant][sample.name] = result_record(result)
        for variant, keep in ORACLE_SEGMENT_VARIANTS.items():
            if variant in records:
                continue
            estimator = FREstimator(mode="fr")
            records[variant] = {}
            for sample in tqdm(samples, desc=f"{dataset}: {variant}", unit="img", file=sys.stderr):
                base = records["fr"][sample.name]
                kept = keep(np.asarray(base.get("segments") or np.zeros((0, 4)), np.float64).reshape(-1, 4),
                            truth_horizons(sample)["labelled"])
                [result] = estimator.calibrate_segments([kept], [(sample.width, sample.height)], names=[sample.name])
                records[variant][sample.name] = result_record(result)
        for variant, (method, on_fr_segments) in METHOD_VARIANTS.items():
            if variant in records:
                continue
            calibrator = make_calibrator(method, "cpu")
            records[variant] = {}
            for sample in tqdm(samples, desc=f"{dataset}: {variant}", unit="img", file=sys.stderr):
                segments = records["fr"][sample.name].get("segments") if on_fr_segments else None
                meta = ImageMeta(name=sample.name, width=sample.width, height=sample.height,
                                 segments=None if segments is None else np.asarray(segments, np.float64).reshape(-1, 4))
                estimate = calibrator.estimate(None if segments is not None else load_image(sample.image_path), meta)
                records[variant][sample.name] = estimate_record(estimate, sample)
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(records), encoding="utf-8")
        print(f"wrote {path}")


def estimate_record(estimate, sample) -> dict:
    """The fields of a result's JSON that the report reads, from another method's estimate."""
    camera = estimate.camera if estimate.ok else None
    if camera is None or camera.focal_px is None or camera.rotation is None:
        return {"ok": False, "width": sample.width, "height": sample.height}
    return {"ok": True, "width": sample.width, "height": sample.height, "focal_px": camera.focal_px,
            "principal_point": list(camera.principal_point), "rotation": camera.rotation.tolist(), "distortion_k": 0.0}


def result_record(result) -> dict:
    """A result's JSON with its segments, lens k and vanishing-point families (what the report reads)."""
    record = result.to_json(include_segments=True)
    record["distortion_k"] = result.distortion_k
    return record


def above(segments: np.ndarray, horizon: Horizon) -> np.ndarray:
    """The segments whose both endpoints lie above ``horizon`` (``a x + b y + c < 0``)."""
    a, b, c = horizon.line
    side = np.stack([a * segments[:, 0] + b * segments[:, 1] + c, a * segments[:, 2] + b * segments[:, 3] + c], 1)
    return segments[(side < 0).all(1)]


#: Other methods through the common interface: (registered name, run on the segments of fR's default
#: run instead of its own detection on the decoded image).
METHOD_VARIANTS = {"lee2009": ("lee2009", False), "lee2009 on fR's segments": ("lee2009", True)}
#: Re-runs of fR on the segments of its default run ("fr"): all of them (the control: the same
#: segments through calibrate_segments), and those above the labelled horizon (an oracle filter: what
#: ground-plane segments, roads and markings, cost).
ORACLE_SEGMENT_VARIANTS = {
    "fr on its own segments": lambda segments, horizon: segments,
    "fr on its segments above the labelled horizon (oracle)": above,
}


# ----------------------------------------------------------------------------------- geometry

def column(horizon: str, definition: str) -> str:
    """The per-photo table's column of a horizon's error against a ground-truth definition."""
    return f"{horizon} [{definition}]"


def record_camera(record: dict) -> Camera | None:
    if not record.get("ok"):
        return None
    return Camera(record["width"], record["height"], record["focal_px"], record["principal_point"],
                  np.asarray(record["rotation"], np.float64))


def record_horizon(record: dict) -> Horizon | None:
    camera = record_camera(record)
    return None if camera is None else Horizon.from_camera(camera, record.get("distortion_k", 0.0))


def attribution(estimate: Camera, truth: Camera, target: Horizon) -> dict[str, float]:
    """Shapley shares (% of the height) of tilt, roll, f and the principal point in the error of
    ``estimate``'s horizon against ``target``, and ``definition``: the error left with all four from
    ``truth`` (module docstring).  The shares and ``definition`` add up to the error."""
    values = {"tilt": (estimate.angles["tilt_deg"], truth.angles["tilt_deg"]),
              "roll": (estimate.angles["roll_deg"], truth.angles["roll_deg"]),
              "f": (estimate.focal_px, truth.focal_px), "pp": (estimate.principal_point, truth.principal_point)}

    def error(replaced) -> float:
        chosen = {k: values[k][1 if k in replaced else 0] for k in FACTORS}
        camera = Camera.from_angles(estimate.width, estimate.height, chosen["f"], roll_deg=chosen["roll"],
                                    tilt_deg=chosen["tilt"], principal_point=chosen["pp"])
        return 100.0 * Horizon.from_camera(camera).error(target)

    n = len(FACTORS)
    out = {}
    for factor in FACTORS:
        others = [k for k in FACTORS if k != factor]
        share = 0.0
        for size in range(n):
            weight = math.factorial(size) * math.factorial(n - size - 1) / math.factorial(n)
            for subset in itertools.combinations(others, size):
                share += weight * (error(subset) - error(subset + (factor,)))
        out[factor] = share
    out["definition"] = error(FACTORS)
    out["total"] = error(())
    return out


def centre_and_slope(horizon: Horizon, truth: Horizon) -> tuple[float, float]:
    """(error at the image's middle column, half the border-to-border change of the difference), % of
    the height; the benchmark's error is their sum."""
    d_left, d_right = horizon.left_y - truth.left_y, horizon.right_y - truth.right_y
    return 100.0 * abs(d_left + d_right) / 2 / truth.height, 100.0 * abs(d_right - d_left) / 2 / truth.height


def family_directions(record: dict, K: np.ndarray) -> dict[int, tuple[np.ndarray, float]]:
    """family -> (unit direction (3,) of its VP fitted alone, support = its segments' length in pixels):
    the length-weighted least-squares direction orthogonal to the interpretation planes of the family's
    segments (fR's labels), with fR's K."""
    segments = np.asarray(record.get("segments") or np.zeros((0, 4)), np.float64).reshape(-1, 4)
    labels = np.asarray(record.get("labels") or np.zeros(0), np.int64)
    if not len(segments):
        return {}
    inverse = np.linalg.inv(K)
    p = np.c_[segments[:, :2], np.ones(len(segments))] @ inverse.T
    q = np.c_[segments[:, 2:], np.ones(len(segments))] @ inverse.T
    normals = np.cross(p, q)
    normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)
    lengths = np.hypot(segments[:, 2] - segments[:, 0], segments[:, 3] - segments[:, 1])
    out = {}
    for family in (0, 1, 2):
        chosen = labels == family
        if chosen.sum() < 2:
            continue
        scatter = (normals[chosen] * lengths[chosen, None]).T @ normals[chosen]
        out[family] = (np.linalg.eigh(scatter)[1][:, 0], float(lengths[chosen].sum()))
    return out


def plane_horizon(K: np.ndarray, normal: np.ndarray, width: int, height: int) -> Horizon | None:
    """The horizon whose vertical (the horizontal planes' normal) is ``normal``, seen with K."""
    return Horizon.from_line(np.linalg.solve(K.T, normal), width, height)


def free_horizons(record: dict, atlanta: dict | None) -> dict[str, Horizon | None]:
    """The horizons of :data:`FREE` from fR's result ``record`` (and its ``--atlanta`` run's); None
    where a family is missing."""
    camera = record_camera(record)
    out = dict.fromkeys(FREE)
    if camera is None:
        return out
    K, width, height = camera.K, camera.width, camera.height
    families = family_directions(record, K)
    if 0 in families and 2 in families:
        out[FREE[0]] = plane_horizon(K, np.cross(families[0][0], families[2][0]), width, height)
    if 1 in families:
        out[FREE[1]] = plane_horizon(K, families[1][0], width, height)
        horizontal = [families[k] for k in (0, 2) if k in families]
        out[FREE[2]] = fitted_plane(K, families[1], horizontal, width, height)
        if atlanta is not None and atlanta.get("ok"):
            out[FREE[3]] = fitted_plane(K, families[1], horizontal + atlanta_directions(atlanta, K), width, height)
    return out


def atlanta_directions(record: dict, K: np.ndarray) -> list[tuple[np.ndarray, float]]:
    """The extra (Atlanta) horizontal families of an ``--atlanta`` result: (unit direction, support)."""
    out = []
    for item in record.get("ranked_vanishing_points") or []:
        if item["family"] >= 3:
            d = np.linalg.solve(K, np.asarray(item["point"], np.float64))
            out.append((d / np.linalg.norm(d), float(item["support_px"])))
    return out


def fitted_plane(K, vertical, horizontal, width, height) -> Horizon | None:
    """The normal n minimising ``sum_h w_h (n . d_h)^2 + w_v (1 - (n . d_v)^2)``: the horizontal
    directions in the plane, the vertical along its normal, each weighted by its support."""
    d_v, w_v = vertical
    matrix = sum(w * np.outer(d, d) for d, w in horizontal) - w_v * np.outer(d_v, d_v)
    return plane_horizon(K, np.linalg.eigh(matrix)[1][:, 0], width, height)


def non_orthogonality_deg(record: dict) -> float:
    """|90 deg - the angle between the two free horizontal directions| with fR's K (nan without them)."""
    camera = record_camera(record)
    families = family_directions(record, camera.K) if camera is not None else {}
    if 0 not in families or 2 not in families:
        return math.nan
    return abs(90.0 - math.degrees(math.acos(min(1.0, abs(float(families[0][0] @ families[2][0]))))))


# ----------------------------------------------------------------------------------- report

def per_photo(dataset: str, records: dict, samples) -> pd.DataFrame:
    """One row per photo: the error (% of the height) of every variant and free horizon against every
    definition, fR's centre / slope split, attribution (YUD) and the photo's traits."""
    rows = []
    atlanta = records.get("fr --atlanta", {})
    for sample in samples:
        truths = truth_horizons(sample)
        base = records["fr"][sample.name]
        row: dict[str, Any] = {"image": sample.name, "split": sample.split}
        for variant, by_image in records.items():
            horizon = record_horizon(by_image[sample.name])
            for name, truth in truths.items():
                row[column(variant, name)] = 100.0 * horizon.error(truth) if horizon is not None else math.inf
        for free, horizon in free_horizons(base, atlanta.get(sample.name)).items():
            for name, truth in truths.items():
                row[column(free, name)] = 100.0 * horizon.error(truth) if horizon is not None else math.nan
        if "lee2009" in records:
            for name in truths:
                row[column(BEST_OF, name)] = min(row[column("fr", name)], row[column("lee2009", name)])
        horizon, labelled = record_horizon(base), truths.get("labelled")
        if horizon is not None and labelled is not None:
            row["centre_pct"], row["slope_pct"] = centre_and_slope(horizon, labelled)
        if horizon is not None and sample.camera is not None:
            for target in ATTRIBUTION_TARGETS:
                for key, value in attribution(record_camera(base), sample.camera, truths[target]).items():
                    row[f"share_{target}_{key}"] = value
        lee = record_camera(records["lee2009"][sample.name]) if "lee2009" in records else None
        if horizon is not None and lee is not None and labelled is not None:
            for key, value in attribution(record_camera(base), lee, labelled).items():
                row[f"share_to_lee2009_{key}"] = value
        row["manhattan_fraction"] = base.get("manhattan_fraction")
        row["num_segments"] = base.get("num_segments")
        camera = record_camera(base)
        row["bound_pct"] = None if camera is None else horizon_bound_pct(base.get("error_bound"), camera.focal_px,
                                                                         camera.angles["tilt_deg"], camera.height)
        row["non_orthogonality_deg"] = non_orthogonality_deg(base)
        extra = [v for v in (atlanta.get(sample.name, {}).get("ranked_vanishing_points") or []) if v["family"] >= 3]
        row["atlanta_families"] = len(extra)
        row["atlanta_support_share"] = (sum(v["support_px"] for v in extra)
                                        / max(sum(v["support_px"] for v in atlanta[sample.name]["ranked_vanishing_points"]),
                                              1e-9)) if extra else 0.0
        rows.append(row)
    return pd.DataFrame(rows)


def auc_table(frame: pd.DataFrame, names, definitions, split: str | None = None) -> pd.DataFrame:
    """Rows ``names`` (variants / free horizons), columns AUC and median per definition."""
    chosen = frame if split is None else frame[frame["split"] == split]
    rows = []
    for name in names:
        row = {"horizon": name}
        for definition in definitions:
            key = column(name, definition)
            if key not in chosen:
                continue
            values = chosen[key].to_numpy(np.float64)
            values = np.where(np.isnan(values), np.inf, values)
            row[f"AUC ({definition})"] = f"{100.0 * lezama_auc(values / 100.0)[0]:.2f}"
            row[f"median ({definition}, % of h)"] = f"{np.median(values):.2f}"
            row[f"> 10 % ({definition})"] = int((values > 10.0).sum())
        if len(row) > 1:
            rows.append(row)
    return pd.DataFrame(rows)


def trait_correlations(frame: pd.DataFrame) -> pd.DataFrame:
    """Spearman correlation of fR's error (and of fR's minus Lee 2009's) with the photos' traits."""
    traits = ("manhattan_fraction", "num_segments", "non_orthogonality_deg", "atlanta_support_share", "bound_pct",
              "centre_pct", "slope_pct")
    error = frame[column("fr", "labelled")]
    gain = error - frame[column("lee2009", "labelled")] if column("lee2009", "labelled") in frame else None
    rows = []
    for trait in traits:
        values = pd.to_numeric(frame[trait], errors="coerce")
        rows.append({"trait": trait, "with fR's error": f"{error.corr(values, method='spearman'):+.2f}",
                     "with fR's minus Lee 2009's error": "n/a" if gain is None
                     else f"{gain.corr(values, method='spearman'):+.2f}"})
    return pd.DataFrame(rows)


def attribution_table(frame: pd.DataFrame, split: str | None, target: str) -> pd.DataFrame:
    """Mean, share of the mean error and median of each factor's Shapley share against ``target``."""
    chosen = frame if split is None else frame[frame["split"] == split]
    keys = list(FACTORS) + ["definition", "total"]
    out = {"statistic": ["mean (% of h)", "share of the mean error (%)", "median (% of h)"]}
    total = chosen[f"share_{target}_total"].mean()
    for key in keys:
        values = chosen[f"share_{target}_{key}"].to_numpy(np.float64)
        out[key] = [f"{values.mean():.2f}", f"{100 * values.mean() / total:.0f}", f"{np.median(values):.2f}"]
    return pd.DataFrame(out)


def attribution_figure(frame: pd.DataFrame, path: Path, title: str) -> Path:
    """Per photo (sorted by fR's error) the stacked Shapley shares and the definition gap, one panel
    per target of :data:`ATTRIBUTION_TARGETS`."""
    colours = {"tilt": "tab:blue", "roll": "tab:orange", "f": "tab:green", "pp": "tab:red", "definition": "0.6"}
    fig, axes = plt.subplots(len(ATTRIBUTION_TARGETS), 1, figsize=(12, 3.8 * len(ATTRIBUTION_TARGETS)))
    for ax, target in zip(np.atleast_1d(axes), ATTRIBUTION_TARGETS):
        chosen = frame.sort_values(f"share_{target}_total").reset_index(drop=True)
        x = np.arange(len(chosen))
        above_zero, below_zero = np.zeros(len(chosen)), np.zeros(len(chosen))
        for key, colour in colours.items():
            values = chosen[f"share_{target}_{key}"].to_numpy(np.float64)
            ax.bar(x, values, bottom=np.where(values >= 0, above_zero, below_zero), color=colour, label=key, width=0.8)
            above_zero += np.clip(values, 0, None)
            below_zero += np.clip(values, None, 0)
        ax.plot(x, chosen[f"share_{target}_total"], "k.", ms=4, label="error")
        ax.axhline(0, color="k", lw=0.6)
        ax.set_title(f"against `{target}`", fontsize=9)
        ax.set_xlabel("photo (sorted by fR's error)")
        ax.set_ylabel("% of image height")
        ax.legend(fontsize=8, ncol=6, loc="upper left")
        ax.grid(alpha=0.3, axis="y")
    return save_figure(fig, path, title)


def ecd_figure(frame: pd.DataFrame, path: Path, title: str) -> Path:
    """Per photo (sorted by fR's error): fR's error split into centre and slope, and the errors of
    the free horizons and variants beside it."""
    chosen = frame.sort_values(column("fr", "labelled")).reset_index(drop=True)
    x = np.arange(len(chosen))
    fig, axes = plt.subplots(2, 1, figsize=(12, 7), sharex=True)
    axes[0].bar(x, chosen["centre_pct"], color="tab:blue", label="at the centre (tilt, f, pp)")
    axes[0].bar(x, chosen["slope_pct"], bottom=chosen["centre_pct"], color="tab:orange", label="slope (roll)")
    top = 10.0
    for i, total in enumerate(chosen["centre_pct"] + chosen["slope_pct"]):
        if total > top:  # clipped: say how high
            axes[0].text(i, top * 0.97, f"{total:.0f}", ha="center", va="top", fontsize=7, color="w")
    axes[0].set_ylim(0, top)
    axes[0].set_ylabel("fR's error, % of h (axis cut at 10)")
    axes[0].legend(fontsize=8)
    for name, marker in (("fr", "ko"), ("lee2009", "s"), ("lee2009 on fR's segments", "D"),
                         ("fr at the input resolution", "^"), ("fr on its segments above the labelled horizon (oracle)", "v"),
                         (FREE[2], "x")):
        key = column(name, "labelled")
        if key in chosen:
            axes[1].plot(x, np.minimum(chosen[key], 30.0), marker, ms=5, label=name, alpha=0.8,
                         **({} if marker == "ko" else {"ls": "none"}))
    axes[1].set_yscale("symlog", linthresh=1.0)
    axes[1].set_ylabel("error, % of h (capped at 30)")
    axes[1].set_xlabel("photo (sorted by fR's error)")
    axes[1].set_xticks(x, chosen["image"], fontsize=7)
    axes[1].legend(fontsize=7, ncol=3)
    for ax in axes:
        ax.grid(alpha=0.3, axis="y")
    return save_figure(fig, path, title)


def overlay_panel(sample, record: dict, free: dict[str, Horizon | None]) -> np.ndarray:
    """The photo (darkened) with fR's segments by family, fR's horizon (yellow), the labelled one
    (white) and the vertical + horizontal fit's (magenta), RGB."""
    image = (load_image(sample.image_path).astype(np.float32) * 0.55).astype(np.uint8)
    colours = {0: (40, 40, 230), 1: (40, 200, 40), 2: (230, 120, 30), 3: (150, 150, 150)}
    segments = np.asarray(record.get("segments") or np.zeros((0, 4)))
    labels = np.asarray(record.get("labels") or np.zeros(0, int))
    thickness = max(1, round(max(image.shape) / 500))
    for seg, label in sorted(zip(segments, labels), key=lambda item: item[1] != 3):
        a, b = tuple(int(round(v)) for v in seg[:2]), tuple(int(round(v)) for v in seg[2:])
        cv2.line(image, a, b, colours[int(label)], thickness, cv2.LINE_AA)
    x0, x1 = border_columns(sample.width)
    lines = [(truth_horizons(sample)["labelled"], (255, 255, 255)), (record_horizon(record), (0, 220, 255)),
             (free.get(FREE[2]), (255, 0, 255))]
    for horizon, colour in lines:
        if horizon is not None and horizon.left_y is not None and horizon.right_y is not None:
            cv2.line(image, (int(x0), int(round(horizon.left_y))), (int(x1), int(round(horizon.right_y))), colour,
                     thickness + 1, cv2.LINE_AA)
    return image[..., ::-1]


def worst_figure(frame: pd.DataFrame, samples, records: dict, path: Path, count: int = 6) -> Path:
    """Overlays of the ``count`` photos with fR's largest errors (:func:`overlay_panel`)."""
    by_name = {s.name: s for s in samples}
    worst = frame.sort_values(column("fr", "labelled"), ascending=False).head(count)
    columns = 3
    rows = math.ceil(len(worst) / columns)
    fig, axes = plt.subplots(rows, columns, figsize=(4.2 * columns, 3.8 * rows), squeeze=False)
    atlanta = records.get("fr --atlanta", {})
    for ax, (_, row) in zip(axes.ravel(), worst.iterrows()):
        sample = by_name[row["image"]]
        record = records["fr"][sample.name]
        ax.imshow(overlay_panel(sample, record, free_horizons(record, atlanta.get(sample.name))))
        ax.set_title(f"{sample.name}: fR {row[column('fr', 'labelled')]:.1f} %, fit {row[column(FREE[2], 'labelled')]:.1f} %, "
                     f"Manhattan {row['manhattan_fraction']:.2f}", fontsize=8)
        ax.axis("off")
    for ax in axes.ravel()[len(worst):]:
        ax.axis("off")
    return save_figure(fig, path, "Largest horizon errors of fR on ecd-tune: segments by family (red, green = "
                                  "vertical, blue, grey = background); horizon labelled (white), fR (yellow), "
                                  "vertical + horizontal fit (magenta)", fontsize=8, dpi=80)


def report(out: Path = OUT) -> None:
    out.mkdir(parents=True, exist_ok=True)
    sections = []
    for dataset, split in DATASETS.items():
        records = json.loads(cache_file(dataset).read_text(encoding="utf-8"))
        samples = load_dataset(dataset, split=split)
        frame = per_photo(dataset, records, samples)
        frame.to_csv(out / f"{dataset}_per_photo.csv", index=False)
        definitions = [d for d in ("labelled", "lezama-code", "frame") if column("fr", d) in frame]
        splits = ("test", None) if dataset == "yud" else (None,)
        for chosen in splits:
            label = f"{dataset} {chosen or split} ({int((frame['split'] == chosen).sum()) if chosen else len(frame)} photos)"
            sections.append(f"## {label}: variants and free horizons\n\n"
                            + to_markdown(auc_table(frame, list(records) + [BEST_OF] + list(FREE), definitions, chosen)))
            if "share_to_lee2009_total" in frame:
                sections.append(f"## {label}: fR's error against `labelled` split by the parameters in which Lee 2009's "
                                "estimate differs (Shapley: each of fR's tilt, roll, f replaced by Lee's; "
                                "`definition` = Lee 2009's own error; % of h)\n\n"
                                + to_markdown(attribution_table(frame, chosen, "to_lee2009")))
            for target in ATTRIBUTION_TARGETS:
                if f"share_{target}_total" in frame:
                    sections.append(f"## {label}: attribution of fR's error against `{target}` (Shapley, % of h)\n\n"
                                    + to_markdown(attribution_table(frame, chosen, target)))
        if f"share_{ATTRIBUTION_TARGETS[0]}_total" in frame:
            attribution_figure(frame[frame["split"] == "test"], out / f"{dataset}_attribution.png",
                               "YUD test: fR's horizon error split into tilt, roll, f, principal point (Shapley) and "
                               "the gap between the ground truth's two definitions")
        else:
            ecd_figure(frame, out / f"{dataset}_errors.png",
                       "ecd-tune: fR's horizon error per photo (top: centre vs slope) and the alternatives (bottom)")
            # the photos themselves stay out of the repository (their terms): this figure goes to the cache
            worst_figure(frame, samples, records, cache_root() / "horizon_analysis" / f"{dataset}_worst.png")
            traits = frame[["image", column("fr", "labelled"), "centre_pct", "slope_pct", column("lee2009", "labelled"),
                            column("lee2009 on fR's segments", "labelled"), column("fr at the input resolution", "labelled"),
                            column("fr on its segments above the labelled horizon (oracle)", "labelled"),
                            column(FREE[2], "labelled"), "manhattan_fraction", "non_orthogonality_deg", "atlanta_families",
                            "atlanta_support_share", "bound_pct"]]
            traits = traits.sort_values(column("fr", "labelled"), ascending=False).round(2)
            sections.append("## ecd-tune per photo (sorted by fR's error; % of h, degrees)\n\n" + to_markdown(traits))
            sections.append("## ecd-tune: what goes with fR's error (Spearman rank correlation over the 25 photos)\n\n"
                            + to_markdown(trait_correlations(frame)))
    (out / "tables.md").write_text("# Horizon analysis: generated tables\n\nWritten by "
                                   "`python -m fr_eval.protocols.horizon_analysis report`; read by "
                                   "`results/horizon/analysis.md`. AUC: Lezama 2014's calc_auc.m on [0, 25 %].\n\n"
                                   + "\n\n".join(sections) + "\n", encoding="utf-8")
    print(f"wrote {out}")


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m fr_eval.protocols.horizon_analysis", description=__doc__.split("\n")[0])
    parser.add_argument("step", choices=("run", "report"))
    args = parser.parse_args(argv)
    run() if args.step == "run" else report()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
