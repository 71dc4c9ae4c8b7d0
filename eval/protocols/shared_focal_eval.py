"""Shared focal length (issue 38): per-photo focal profiles, random groups, the focal prior.

Usage (``FR_DATA`` set; results under ``results/shared_focal/``, caches under ``data_local/shared_focal/``)::

    python -m fr_eval.protocols.shared_focal_eval profile --dataset nyu-vp --split train --limit 400
    python -m fr_eval.protocols.shared_focal_eval tune                  # settings from train caches only
    python -m fr_eval.protocols.shared_focal_eval groups --dataset nyu-vp --split val
    python -m fr_eval.protocols.shared_focal_eval rotation --dataset yud --split test --size 10
    python -m fr_eval.protocols.shared_focal_eval prior --dataset yud --split test
    python -m fr_eval.protocols.shared_focal_eval principal-point --dataset nyu-vp --split val --size 10

``profile`` calibrates every photo alone with fR (the library defaults) and caches, per photo, its
estimate, predicted errors, kept segments and focal profile (:func:`fr_torch.runtime.shared_focal.focal_profiles`),
so the other stages only combine cached profiles (seconds), except ``rotation`` and ``prior``, which
search each photo again with the focal length known, and ``principal-point``, which runs the whole
group method (:func:`fr_torch.runtime.shared_focal.shared_from_results`) per group, with and
without the shared principal point (:attr:`~fr_torch.runtime.shared_focal.SharedFocalSettings.principal_point`).  ``--pp calibrated`` uses the dataset's
calibrated principal point instead of the image centre (the library default).

Groups: the photos of a split are shuffled and cut into groups of ``size`` (the last, smaller
group dropped), ``repeats`` times with seeds 0..repeats-1; the shared focal error is
``100 |f - f_gt| / f_gt`` per group.
"""
from __future__ import annotations

import argparse
import json
import math
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from fr_eval.paths import REPO, cache_root

OUT_DIR = REPO / "results" / "shared_focal"


def load_samples(dataset: str, split: str):
    if dataset == "nyu-vp":
        from fr_eval.datasets.nyu_vp import load_nyu_vp

        return load_nyu_vp(split=split)
    from fr_eval.datasets.yud import load_yud

    return load_yud(split=split)


def cache_path(dataset: str, split: str, pp: str) -> Path:
    folder = cache_root() / "shared_focal"
    folder.mkdir(parents=True, exist_ok=True)
    return folder / f"{dataset}_{split}_{pp}.npz"


def gt_angles(sample) -> tuple[float, float]:
    return float(sample.roll_deg), float(sample.tilt_deg)


def calibrate_alone(estimator, samples, pp: str):
    """Per-photo fR results (segments kept), in sample order."""
    pps = [tuple(s.principal_point) for s in samples] if pp == "calibrated" else None
    if "detected_segments" in samples[0].extra:
        return estimator.calibrate_segments([s.extra["detected_segments"] for s in samples],
                                            [(s.width, s.height) for s in samples],
                                            names=[s.name for s in samples], principal_point=pps)
    return estimator.calibrate_images([str(s.image_path) for s in samples], names=[s.name for s in samples],
                                      principal_point=pps)


def run_profile(args) -> None:
    import torch

    from fr_torch import FREstimator
    from fr_torch.runtime.shared_focal import SharedFocalSettings, profile_results

    torch.set_num_threads(1)
    samples = load_samples(args.dataset, args.split)
    if args.limit:
        samples = samples[:args.limit]
    estimator = FREstimator(mode="fr")
    settings = SharedFocalSettings()
    path = cache_path(args.dataset, args.split, args.pp)
    records = dict(np.load(path, allow_pickle=True)) if path.exists() else {}
    done = set(records.get("name", np.array([], dtype=object)).tolist())
    todo = [s for s in samples if s.name not in done]
    rows = {key: list(records[key]) for key in records} if records else {}
    t0 = time.perf_counter()
    for start in range(0, len(todo), args.chunk):
        chunk = todo[start:start + args.chunk]
        alone = calibrate_alone(estimator, chunk, args.pp)
        ok = [r for r in alone if r.ok and r.segments is not None and len(r.segments)]
        log_ratios, profiles, lengths = profile_results(estimator, ok, settings)
        by_name = {r.image: (p, w) for r, p, w in zip(ok, profiles, lengths)}
        for sample, result in zip(chunk, alone):
            profile, length = by_name.get(result.image, (np.full(len(log_ratios), -np.inf), 0.0))
            roll, tilt = gt_angles(sample)
            pred = result.predicted_error or {}
            row = dict(name=sample.name, ok=bool(result.ok), reliable=bool(result.reliable),
                       focal_px=float(result.focal_px) if result.ok else math.nan,
                       roll_deg=float(result.roll_deg) if result.ok else math.nan,
                       tilt_deg=float(result.tilt_deg) if result.ok else math.nan,
                       gt_focal_px=float(sample.focal_px), gt_roll_deg=roll, gt_tilt_deg=tilt,
                       width=sample.width, height=sample.height,
                       pp=np.asarray(result.principal_point if result.ok else (np.nan, np.nan), np.float64),
                       pred_focal_pct=float(pred.get("focal_pct", math.nan)),
                       pred_roll_deg=float(pred.get("roll_deg", math.nan)),
                       pred_tilt_deg=float(pred.get("tilt_deg", math.nan)),
                       total_length=float(length), profile=np.asarray(profile, np.float64),
                       segments=np.asarray(result.segments if result.segments is not None else np.zeros((0, 4))))
            for key, value in row.items():
                rows.setdefault(key, []).append(value)
        arrays = {key: (np.array(values, dtype=object) if key in ("segments", "name") else np.array(values))
                  for key, values in rows.items()}
        arrays["log_ratios"] = log_ratios
        np.savez(path, **arrays)
        print(f"{len(rows['name'])} photos profiled ({time.perf_counter() - t0:.0f} s)", file=sys.stderr)


def load_cache(dataset: str, split: str, pp: str) -> dict:
    """The cached photos of ``profile``; ``profile`` (data term) becomes the full objective's
    (:func:`fr_torch.runtime.shared_focal.with_estimator_prior`, as :func:`fr_torch.runtime.shared_focal.calibrate_shared`
    combines them)."""
    from fr_torch import FREstimator
    from fr_torch.runtime.shared_focal import with_estimator_prior

    data = dict(np.load(cache_path(dataset, split, pp), allow_pickle=True))
    long_side = np.maximum(data["width"], data["height"]).astype(np.float64)
    data["profile"] = with_estimator_prior(FREstimator(mode="fr", reliability=None), data["log_ratios"],
                                           data["profile"], data["total_length"], long_side)
    return data


def random_groups(count: int, size: int, repeats: int) -> list[np.ndarray]:
    groups = []
    for seed in range(repeats):
        order = np.random.default_rng(seed).permutation(count)
        groups += [order[i:i + size] for i in range(0, count - size + 1, size)]
    return groups


def shared_errors(data: dict, groups, settings, use_reliability: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """(focal error %, predicted error %) per group."""
    from fr_torch.runtime.shared_focal import combine_profiles

    log_ratios = data["log_ratios"]
    long_side = np.maximum(data["width"], data["height"]).astype(np.float64)
    errors, predicted = [], []
    for group in groups:
        combined = combine_profiles(log_ratios, data["profile"][group], data["total_length"][group],
                                    data["pred_focal_pct"][group] if use_reliability else None, settings)
        focal = math.exp(combined.log_ratio) * long_side[group[0]] if math.isfinite(combined.log_ratio) else math.nan
        gt = data["gt_focal_px"][group[0]]
        errors.append(100 * abs(focal - gt) / gt if math.isfinite(focal) else math.inf)
        predicted.append(combined.predicted_error_pct)
    return np.array(errors), np.array(predicted)


def summary(errors: np.ndarray) -> dict:
    return {"median": float(np.median(errors)), "p90": float(np.percentile(errors, 90)),
            "mean": float(np.mean(np.minimum(errors, 100))), "groups": int(len(errors))}


def per_photo_errors(data: dict) -> np.ndarray:
    ok = data["ok"].astype(bool)
    err = np.full(len(ok), np.inf)
    err[ok] = 100 * np.abs(data["focal_px"][ok] - data["gt_focal_px"][ok]) / data["gt_focal_px"][ok]
    return err


def run_tune(args) -> None:
    """Choose ``cap`` (at ``beta`` 30: only cap / beta moves the estimate) and the reliability weight
    on the train caches (NYU-VP train, YUD train; image-centre principal point): the lowest sum of
    the median errors of groups of 2 and 10; then ``kappa``, the 68th percentile of error /
    uncalibrated predicted error over the train groups of 10."""
    from fr_torch.runtime.shared_focal import SharedFocalSettings

    sets = {name: load_cache(dataset, "train", "centre") for name, dataset in (("NYU-VP", "nyu-vp"), ("YUD", "yud"))}
    base = replace(SharedFocalSettings(), beta=30.0, kappa=1.0)
    lines = ["| cap (nats) | weight scale % | NYU-VP train g2 median / p90 | NYU-VP train g10 median / p90 | "
             "YUD train g2 median / p90 | YUD train g10 median / p90 | sum of medians |", "|---|---|---|---|---|---|---|"]
    best = None
    for cap in args.caps:
        for scale in args.scales + [None]:
            settings = replace(base, cap=cap, error_scale_pct=scale)
            cells, total = [], 0.0
            for data in sets.values():
                for size in (2, 10):
                    groups = random_groups(len(data["name"]), size, args.repeats)
                    s = summary(shared_errors(data, groups, settings, scale is not None)[0])
                    cells.append(f"{s['median']:.2f} / {s['p90']:.2f}")
                    total += s["median"]
            lines.append(f"| {cap:g} | {'off' if scale is None else f'{scale:g}'} | " + " | ".join(cells)
                         + f" | {total:.2f} |")
            if best is None or total < best[0] - 1e-9:
                best = (total, settings, scale is not None)
    _, settings, reliability = best
    ratios = []
    for data in sets.values():
        err, pred = shared_errors(data, random_groups(len(data["name"]), 10, args.repeats), settings, reliability)
        ratios += list(err / pred)
    kappa = float(np.percentile(ratios, 68.3))
    weight = "off" if settings.error_scale_pct is None else f"{settings.error_scale_pct:g} %"
    text = "\n".join(lines) + f"\n\nlowest sum: cap={settings.cap:g}, weight scale {weight}; kappa = {kappa:.3f}\n"
    print(text)
    OUT_DIR.mkdir(parents=True, exist_ok=True)
    (OUT_DIR / "tune_train.md").write_text(text)


def run_groups(args) -> None:
    from fr_torch.runtime.shared_focal import SharedFocalSettings

    settings = SharedFocalSettings()
    data = load_cache(args.dataset, args.split, args.pp)
    photo = per_photo_errors(data)
    rows = [f"| per photo (fR alone) | {np.median(photo):.2f} | {np.percentile(photo, 90):.2f} | "
            f"{np.mean(np.minimum(photo, 100)):.2f} | {len(photo)} photos | |"]
    curve = {}
    for size in args.sizes:
        groups = random_groups(len(data["name"]), size, args.repeats)
        err, pred = shared_errors(data, groups, settings)
        s = summary(err)
        within = float(np.mean(err <= pred)) * 100
        curve[size] = s
        rows.append(f"| shared, groups of {size} | {s['median']:.2f} | {s['p90']:.2f} | {s['mean']:.2f} | "
                    f"{s['groups']} groups | {within:.0f} % |")
    header = (f"### {args.dataset} {args.split}, principal point: {args.pp} ({len(data['name'])} photos, "
              f"{args.repeats} random partitions per size)\n\n| estimate | focal error median % | p90 % | mean % | n "
              "| within predicted error |\n|---|---|---|---|---|---|")
    text = header + "\n" + "\n".join(rows) + "\n"
    print(text)
    OUT_DIR.mkdir(parents=True, exist_ok=True)
    stem = f"groups_{args.dataset}_{args.split}_{args.pp}"
    (OUT_DIR / f"{stem}.md").write_text(text)
    (OUT_DIR / f"{stem}.json").write_text(json.dumps({"per_photo": summary(photo), "groups": curve}, indent=1))


def run_plot(args) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(9, 4.5))
    for stem, label in (("groups_nyu-vp_val_centre", "NYU-VP val (image centre pp)"),
                        ("groups_nyu-vp_val_calibrated", "NYU-VP val (calibrated pp)"),
                        ("groups_yud_test_centre", "YUD test (image centre pp)")):
        path = OUT_DIR / f"{stem}.json"
        if not path.exists():
            continue
        data = json.loads(path.read_text())
        sizes = sorted(int(k) for k in data["groups"])
        med = [data["groups"][str(k)]["median"] for k in sizes]
        p90 = [data["groups"][str(k)]["p90"] for k in sizes]
        line, = ax.plot(sizes, med, "o-", label=f"{label}: median")
        ax.plot(sizes, p90, "s--", color=line.get_color(), label=f"{label}: p90")
        ax.axhline(data["per_photo"]["median"], color=line.get_color(), lw=0.8, ls=":")
    for dataset, label in (("nyu-vp_val", "NYU-VP val (group's own pp, default)"),
                           ("yud_test", "YUD test (group's own pp, default)")):
        runs = sorted((json.loads(p.read_text()) for p in OUT_DIR.glob(f"principal_point_{dataset}_*.json")),
                      key=lambda run: run["size"])
        if runs:
            sizes = [run["size"] for run in runs]
            variant = "shared principal point"
            line, = ax.plot(sizes, [run[variant]["median"] for run in runs], "D-", lw=2, label=f"{label}: median")
            ax.plot(sizes, [run[variant]["p90"] for run in runs], "D--", color=line.get_color(), lw=2,
                    label=f"{label}: p90")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xticks([1, 2, 5, 10, 50])
    ax.set_xticklabels(["1", "2", "5", "10", "50"])
    ax.set_xlabel("photos per group")
    ax.set_ylabel("shared focal error (%)")
    ax.axhline(1.5, color="grey", lw=0.5)
    ax.axhline(4.0, color="grey", lw=0.5)
    ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(OUT_DIR / "group_size_curve.png", dpi=120)


def resolve_at(estimator, data: dict, index: np.ndarray, focal: np.ndarray):
    """Each photo ``index`` searched again with its focal length ``focal`` (pixels)."""
    segments = [np.asarray(data["segments"][i], np.float64) for i in index]
    sizes = [(int(data["width"][i]), int(data["height"][i])) for i in index]
    pps = [tuple(data["pp"][i]) for i in index]
    return estimator.calibrate_segments(segments, sizes, names=[str(data["name"][i]) for i in index],
                                        focal_px=[float(f) for f in focal], principal_point=pps, apply_filter=False)


def angle_errors(data, index, results) -> tuple[np.ndarray, np.ndarray]:
    roll = np.array([abs(r.roll_deg - data["gt_roll_deg"][i]) if r.ok else np.inf for i, r in zip(index, results)])
    tilt = np.array([abs(r.tilt_deg - data["gt_tilt_deg"][i]) if r.ok else np.inf for i, r in zip(index, results)])
    return roll, tilt


def cached_photos(args):
    """(the ``profile`` cache of ``args``' dataset / split / principal point (:func:`load_cache`), fR's
    estimator, indices of the photos calibrated alone) for the stages that search cached photos
    again, searching on one torch thread."""
    import torch

    from fr_torch import FREstimator

    torch.set_num_threads(1)
    data = load_cache(args.dataset, args.split, args.pp)
    return data, FREstimator(mode="fr"), np.flatnonzero(data["ok"].astype(bool))


def run_rotation(args) -> None:
    from fr_torch.runtime.shared_focal import SharedFocalSettings, combine_profiles

    settings = SharedFocalSettings()
    data, estimator, usable = cached_photos(args)
    groups = [usable[g] for g in random_groups(len(usable), args.size, 1)]
    long_side = np.maximum(data["width"], data["height"]).astype(np.float64)
    index, focal = [], []
    for group in groups:
        c = combine_profiles(data["log_ratios"], data["profile"][group], data["total_length"][group],
                             data["pred_focal_pct"][group], settings)
        index += list(group)
        focal += list(math.exp(c.log_ratio) * long_side[group])
    index = np.array(index)
    results = resolve_at(estimator, data, index, np.array(focal))
    roll_s, tilt_s = angle_errors(data, index, results)
    roll_a = np.abs(data["roll_deg"][index] - data["gt_roll_deg"][index])
    tilt_a = np.abs(data["tilt_deg"][index] - data["gt_tilt_deg"][index])
    truth = resolve_at(estimator, data, index, data["gt_focal_px"][index])
    roll_t, tilt_t = angle_errors(data, index, truth)
    rows = [("per photo (fR alone)", roll_a, tilt_a), (f"at the shared f (groups of {args.size})", roll_s, tilt_s),
            ("at the true f (reference)", roll_t, tilt_t)]
    text = (f"### {args.dataset} {args.split}, principal point {args.pp}: roll / tilt ({len(index)} photos, "
            f"one random partition)\n\n| rotation | roll error mean / median deg | tilt error mean / median deg |\n"
            "|---|---|---|\n" + "\n".join(f"| {name} | {np.mean(r):.3f} / {np.median(r):.3f} | "
                                         f"{np.mean(t):.3f} / {np.median(t):.3f} |" for name, r, t in rows) + "\n")
    print(text)
    OUT_DIR.mkdir(parents=True, exist_ok=True)
    (OUT_DIR / f"rotation_{args.dataset}_{args.split}_{args.pp}.md").write_text(text)


def run_prior(args) -> None:
    from fr_torch.runtime.focal_prior import FocalPrior, FocalPriorOption
    from fr_torch.runtime.shared_focal import SharedFocalSettings, combine_profiles

    settings = SharedFocalSettings()
    data, estimator, usable = cached_photos(args)
    gt = data["gt_focal_px"][usable]
    long_side = np.maximum(data["width"], data["height"]).astype(np.float64)[usable]
    rows = []
    photo_err = 100 * np.abs(data["focal_px"][usable] - gt) / gt
    roll_a = np.abs(data["roll_deg"][usable] - data["gt_roll_deg"][usable])
    tilt_a = np.abs(data["tilt_deg"][usable] - data["gt_tilt_deg"][usable])
    rows.append(("none (fR alone)", photo_err, roll_a, tilt_a))
    paths = {s.name: s.image_path for s in load_samples(args.dataset, args.split)}
    exif = FocalPriorOption(exif=True)
    exif_priors = [exif.for_image(paths[str(data["name"][i])], int(data["width"][i]), int(data["height"][i]))[0]
                   for i in usable]
    settings_rows = [(f"{100 * (1 + offset):.0f} % of the truth, sigma {sigma:g} %",
                      [FocalPrior(float(gt[j]) * (1 + offset), sigma, "user") for j in range(len(usable))])
                     for offset in (0.0, 0.2) for sigma in (10.0, 25.0)]
    if all(p is not None for p in exif_priors):
        centre = np.median([p.focal_px for p in exif_priors])
        settings_rows.append((f"EXIF ({exif_priors[0].detail}: {centre:.1f} px), sigma {exif.sigma_pct:g} %",
                              exif_priors))
    for name, priors in settings_rows:
        focal = []
        for j, i in enumerate(usable):
            prior = priors[j]
            c = combine_profiles(data["log_ratios"], data["profile"][i:i + 1], data["total_length"][i:i + 1],
                                 data["pred_focal_pct"][i:i + 1], settings,
                                 prior.log_ratio_prior(int(data["width"][i]), int(data["height"][i])))
            focal.append(math.exp(c.log_ratio) * long_side[j])
        focal = np.array(focal)
        results = resolve_at(estimator, data, usable, focal)
        roll, tilt = angle_errors(data, usable, results)
        rows.append((name, 100 * np.abs(focal - gt) / gt, roll, tilt))
    text = (f"### {args.dataset} {args.split} ({len(usable)} photos), principal point {args.pp}: a focal prior "
            "`--focal-prior PX,SIGMA%`\n\n| prior centre, width | focal error mean / median % | roll error mean / "
            "median deg | tilt error mean / median deg |\n|---|---|---|---|\n" +
            "\n".join(f"| {name} | {np.mean(f):.2f} / {np.median(f):.2f} | {np.mean(r):.3f} / {np.median(r):.3f} | "
                      f"{np.mean(t):.3f} / {np.median(t):.3f} |" for name, f, r, t in rows) + "\n")
    print(text)
    OUT_DIR.mkdir(parents=True, exist_ok=True)
    (OUT_DIR / f"prior_{args.dataset}_{args.split}_{args.pp}.md").write_text(text)


def run_principal_point(args) -> None:
    """Groups of ``--size`` photos (image-centre principal point given to nobody): the shared focal
    length without and with the group's estimated principal point, the principal point's error
    against the dataset's calibrated one, and each photo's roll / tilt at the shared camera."""
    import torch
    from tqdm import tqdm

    from fr_torch import FREstimator
    from fr_torch.core.geometry.conventions import image_centre
    from fr_torch.runtime.shared_focal import SharedFocalSettings, shared_from_results

    torch.set_num_threads(1)
    samples = load_samples(args.dataset, args.split)
    estimator = FREstimator(mode="fr")
    alone = calibrate_alone(estimator, samples, "centre")
    gt_focal = np.array([s.focal_px for s in samples])
    gt_pp = np.array([s.principal_point for s in samples], np.float64)
    gt_roll, gt_tilt = np.array([(math.nan, math.nan) if s.roll_deg is None else gt_angles(s) for s in samples]).T
    variants = {"image centre": SharedFocalSettings(principal_point=False),
                "shared principal point": SharedFocalSettings(principal_point=True)}
    groups = random_groups(len(samples), args.size, args.repeats)
    focal_err = {name: [] for name in variants}
    roll_err = {name: [] for name in variants}
    tilt_err = {name: [] for name in variants}
    pp_err = []
    for group in tqdm(groups, desc=f"groups of {args.size}", file=sys.stderr):
        for name, settings in variants.items():
            shared = shared_from_results(estimator, [alone[i] for i in group], settings=settings)
            if not shared.ok:
                continue
            focal_err[name].append(100 * abs(shared.focal_ratio * max(samples[group[0]].width, samples[group[0]].height)
                                             / gt_focal[group[0]] - 1))
            for i, result in zip(group, shared.results):
                if result.ok:
                    roll_err[name].append(abs(result.roll_deg - gt_roll[i]))
                    tilt_err[name].append(abs(result.tilt_deg - gt_tilt[i]))
            if shared.principal_point is not None:
                pp_err.append(np.asarray(shared.principal_point) - gt_pp[group[0]])
    photo = np.array([100 * abs(r.focal_px / f - 1) for r, f in zip(alone, gt_focal) if r.ok])
    alone_roll = np.nanmean([abs(r.roll_deg - g) for r, g in zip(alone, gt_roll) if r.ok])
    alone_tilt = np.nanmean([abs(r.tilt_deg - g) for r, g in zip(alone, gt_tilt) if r.ok])
    rows = [f"| per photo (fR alone) | {np.median(photo):.2f} | {np.percentile(photo, 90):.2f} | "
            f"{alone_roll:.2f} | {alone_tilt:.2f} |"]
    for name in variants:
        err = np.array(focal_err[name])
        rows.append(f"| shared focal, {name} | {np.median(err):.2f} | {np.percentile(err, 90):.2f} | "
                    f"{np.nanmean(roll_err[name]):.2f} | {np.nanmean(tilt_err[name]):.2f} |")
    offsets = np.array(pp_err).reshape(-1, 2)
    centre = image_centre(samples[0].width, samples[0].height)
    text = (f"### {args.dataset} {args.split}: groups of {args.size} ({len(groups)} groups, {args.repeats} random "
            f"partitions), the principal point not given\n\n"
            "| estimate | focal error median % | p90 % | roll MAE (deg) | tilt MAE (deg) |\n|---|---|---|---|---|\n"
            + "\n".join(rows) + "\n\n"
            f"Shared principal point minus the calibrated one ({len(offsets)} groups): mean "
            f"({offsets[:, 0].mean():+.1f}, {offsets[:, 1].mean():+.1f}) px, SD ({offsets[:, 0].std():.1f}, "
            f"{offsets[:, 1].std():.1f}) px; the image centre is "
            f"({centre[0] - gt_pp[0, 0]:+.1f}, {centre[1] - gt_pp[0, 1]:+.1f}) px from it.\n")
    print(text)
    OUT_DIR.mkdir(parents=True, exist_ok=True)
    stem = f"principal_point_{args.dataset}_{args.split}_{args.size}"
    (OUT_DIR / f"{stem}.md").write_text(text)
    (OUT_DIR / f"{stem}.json").write_text(json.dumps(
        {"size": args.size, "groups": len(groups), "per_photo": summary(photo),
         **{name: summary(np.array(focal_err[name])) for name in variants}}, indent=1))


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m fr_eval.protocols.shared_focal_eval", description=__doc__.split("\n")[0])
    sub = parser.add_subparsers(dest="stage", required=True)
    for name in ("profile", "groups", "rotation", "prior"):
        p = sub.add_parser(name)
        p.add_argument("--dataset", choices=("nyu-vp", "yud"), default="nyu-vp")
        p.add_argument("--split", default="val")
        p.add_argument("--pp", choices=("centre", "calibrated"), default="centre")
        if name == "profile":
            p.add_argument("--limit", type=int, default=0)
            p.add_argument("--chunk", type=int, default=16)
        if name == "groups":
            p.add_argument("--sizes", type=lambda s: [int(v) for v in s.split(",")], default=[1, 2, 5, 10, 50])
            p.add_argument("--repeats", type=int, default=20)
        if name == "rotation":
            p.add_argument("--size", type=int, default=10)
    pp = sub.add_parser("principal-point")
    pp.add_argument("--dataset", choices=("nyu-vp", "yud"), default="nyu-vp")
    pp.add_argument("--split", default="val")
    pp.add_argument("--size", type=int, default=10)
    pp.add_argument("--repeats", type=int, default=2)
    tune = sub.add_parser("tune")
    tune.add_argument("--caps", type=lambda s: [float(v) for v in s.split(",")], default=[1.5, 3, 6])
    tune.add_argument("--scales", type=lambda s: [float(v) for v in s.split(",")], default=[3, 5, 10, 20])
    tune.add_argument("--repeats", type=int, default=10)
    sub.add_parser("plot")
    args = parser.parse_args(argv)
    {"profile": run_profile, "tune": run_tune, "groups": run_groups, "rotation": run_rotation,
     "prior": run_prior, "plot": run_plot, "principal-point": run_principal_point}[args.stage](args)
    return 0


if __name__ == "__main__":
    sys.exit(main())
