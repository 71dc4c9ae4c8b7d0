"""Figures of estimated vs ground-truth roll, tilt and FOV (matplotlib, Agg backend).

* :func:`histogram_figure` (``hist_<method>.png``): one method, GT and estimated histograms overlaid;
* :func:`distributions_figure` (``distributions.png``): the paper's Fig. 4 style comparison of all
  methods -- top row: GT histogram (grey) with every method's estimated distribution overlaid (step
  histograms); bottom row: estimate vs GT scatter per method with the identity line;
* :func:`risk_coverage_panel`: a panel of the reliability stage's risk-coverage figures
  (``results/reliability/``); :func:`save_figure`: every figure's title and file.
"""
from __future__ import annotations

import re
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402
from fr_eval.scoring.metrics import aurc, risk_coverage  # noqa: E402
from fr_eval.scoring.vp_metric import auc_table, recall_curve  # noqa: E402

QUANTITIES = (("roll_deg", "roll (°)"), ("tilt_deg", "tilt (°)"), ("hfov_deg", "horizontal FOV (°)"))


def safe_name(text: str) -> str:
    """File-name-safe version of a method spec (``fr[measure=a]`` -> ``fr_measure-a``)."""
    text = re.sub(r"[=]", "-", text)
    text = re.sub(r"[^A-Za-z0-9._-]+", "_", text)
    return text.strip("_") or "method"


def histogram_figure(predictions: pd.DataFrame, method: str, path: Path, title: str = "") -> Path:
    """One PNG with three panels (roll, tilt, FOV): GT and estimated distributions overlaid.

    ``predictions`` holds ``gt_<q>`` and ``est_<q>`` columns for one method; failed estimates have
    NaN estimates and are not drawn (their count is in the legend).
    """
    fig, axes = plt.subplots(1, 3, figsize=(13, 3.6))
    failures = int(predictions["failed"].astype(bool).sum()) if "failed" in predictions else 0
    for ax, (q, label) in zip(axes, QUANTITIES):
        gt, est = (pd.to_numeric(predictions[c], errors="coerce").to_numpy(dtype=float)
                   if c in predictions else np.zeros(0) for c in (f"gt_{q}", f"est_{q}"))
        gt, est = gt[np.isfinite(gt)], est[np.isfinite(est)]
        values = np.concatenate([gt, est])
        if values.size == 0:
            ax.text(0.5, 0.5, "n/a", ha="center", va="center", transform=ax.transAxes)
        else:
            lo, hi = float(values.min()), float(values.max())
            if hi - lo < 1e-6:
                lo, hi = lo - 1.0, hi + 1.0
            bins = np.linspace(lo, hi, 31)
            ax.hist(gt, bins=bins, alpha=0.5, label=f"ground truth (n={gt.size})", color="tab:gray")
            if est.size:
                ax.hist(est, bins=bins, alpha=0.5, label=f"{method} (n={est.size})", color="tab:blue")
            else:
                ax.text(0.5, 0.9, "not estimated", ha="center", transform=ax.transAxes)
        ax.set_xlabel(label)
        ax.set_ylabel("images")
        if values.size:
            ax.legend(fontsize=7)
    return save_figure(fig, path, title or f"{method}: estimated vs ground truth"
                       + (f" ({failures} failed)" if failures else ""), fontsize=None)


def _values(frame: pd.DataFrame, column: str) -> np.ndarray:
    if column not in frame:
        return np.full(len(frame), np.nan)
    return pd.to_numeric(frame[column], errors="coerce").to_numpy(dtype=float)


def distributions_figure(predictions: pd.DataFrame, path: Path, title: str = "",
                         methods: list[str] | None = None) -> Path:
    """GT vs estimated roll, tilt and FOV of all methods in one PNG (2 x 3 panels).

    ``predictions`` is the per-image table of several methods (``method``, ``failed``, ``gt_<q>``,
    ``est_<q>``).  Failed estimates are not drawn; each method's legend entry gives how many images
    it has a valid estimate for.  Methods without any valid estimate are listed in the title.
    """
    methods = list(methods) if methods is not None else list(dict.fromkeys(predictions["method"].tolist()))
    fig, axes = plt.subplots(2, 3, figsize=(14, 8.4), squeeze=False)
    colours = plt.rcParams["axes.prop_cycle"].by_key().get("color", ["tab:blue"])
    gt_frame = predictions.drop_duplicates("image") if "image" in predictions else predictions
    empty = []
    for col, (q, label) in enumerate(QUANTITIES):
        hist_ax, scatter_ax = axes[0, col], axes[1, col]
        gt_all = _values(gt_frame, f"gt_{q}")
        gt_all = gt_all[np.isfinite(gt_all)]
        per_method = []
        for method in methods:
            sub = predictions[predictions["method"] == method]
            gt, est = _values(sub, f"gt_{q}"), _values(sub, f"est_{q}")
            per_method.append((method, gt, est))
        values = np.concatenate([gt_all] + [est[np.isfinite(est)] for _, _, est in per_method])
        if values.size == 0:
            for ax in (hist_ax, scatter_ax):
                ax.text(0.5, 0.5, "n/a", ha="center", va="center", transform=ax.transAxes)
            hist_ax.set_xlabel(label)
            continue
        lo, hi = float(np.percentile(values, 0.5)), float(np.percentile(values, 99.5))
        if hi - lo < 1e-6:
            lo, hi = lo - 1.0, hi + 1.0
        bins = np.linspace(lo, hi, 31)
        # outliers beyond the 0.5-99.5 percentiles are piled into the end bins
        hist_ax.hist(np.clip(gt_all, lo, hi), bins=bins, color="0.75", label=f"ground truth (n={gt_all.size})")
        for k, (method, gt, est) in enumerate(per_method):
            colour = colours[k % len(colours)]
            ok = np.isfinite(est)
            if not ok.any():
                if col == 0:
                    empty.append(method)
                continue
            hist_ax.hist(np.clip(est[ok], lo, hi), bins=bins, histtype="step", linewidth=1.6, color=colour,
                         label=f"{method} (n={int(ok.sum())})")
            both = ok & np.isfinite(gt)
            scatter_ax.scatter(gt[both], est[both], s=9, alpha=0.6, color=colour, label=method)
        s_lo, s_hi = float(values.min()), float(values.max())  # the scatter shows outliers too
        if s_hi - s_lo < 1e-6:
            s_lo, s_hi = s_lo - 1.0, s_hi + 1.0
        pad = 0.03 * (s_hi - s_lo)
        s_lo, s_hi = s_lo - pad, s_hi + pad
        scatter_ax.plot([s_lo, s_hi], [s_lo, s_hi], color="k", linewidth=1, linestyle="--", label="identity")
        scatter_ax.set_xlim(s_lo, s_hi)
        scatter_ax.set_ylim(s_lo, s_hi)
        scatter_ax.set_xlabel(f"ground-truth {label}")
        scatter_ax.set_ylabel(f"estimated {label}")
        hist_ax.set_xlabel(label)
        hist_ax.set_ylabel("images")
        hist_ax.legend(fontsize=7)
        if col == 0:
            scatter_ax.legend(fontsize=7, markerscale=1.5)
    head = title or "Estimated vs ground truth"
    if empty:
        head += "\n(no valid estimate: " + ", ".join(empty) + ")"
    return save_figure(fig, path, head, fontsize=None, dpi=100)


def risk_coverage_panel(ax, curves, title: str, ylabel: bool = True, legend_size: int = 7) -> None:
    """One risk-coverage panel: for each ``(label, score, error, style)`` of ``curves``, the mean
    ``error`` of the photos kept in the order of ``score`` (lowest first,
    :func:`fr_eval.scoring.metrics.risk_coverage`) against the % kept.  A curve whose score is not
    its error (the oracle) gets its AURC over the oracle's in the label; a None label stays out of
    the legend."""
    for label, score, error, style in curves:
        kept, risk = risk_coverage(score, error)
        if label is not None and score is not error:
            label = f"{label} ({aurc(score, error) / aurc(error, error):.2f}x)"
        ax.plot(100 * kept, risk, style, label=label)
    ax.set_title(title, fontsize=9)
    ax.set_xlabel("% of photos kept")
    if ylabel:
        ax.set_ylabel("focal MAE of kept (%)")
    ax.legend(fontsize=legend_size, loc="upper left")


def save_figure(fig, path: Path, title: str, fontsize: float | None = 10, dpi: int = 110) -> Path:
    """Title ``fig`` (``fontsize`` points, None: matplotlib's), write it to ``path`` (PNG at ``dpi``,
    folders made) and close it."""
    fig.suptitle(title, **({} if fontsize is None else {"fontsize": fontsize}))
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=dpi)
    plt.close(fig)
    return path


def vp_recall_figure(errors: dict[str, dict[str, np.ndarray]], path: Path, title: str = "",
                     max_deg: float = 20.0) -> Path:
    """Recall curves of pooled VP errors (degrees) up to ``max_deg``: ``errors[setting][method]``, one
    panel per setting (``unknown``: f unknown, ``known``: K known), AUC@10 in each label."""
    return recall_figure(
        errors, path, title, max_deg, label=lambda method, values: f"{method} (AUC@10 {auc_table(values, (10.0,))['auc10']:.1f})",
        panel_title=lambda setting: "f unknown, image-centre principal point" if setting == "unknown" else "K known",
        xlabel="error threshold (°)", ylabel="recall (share of labelled VPs)", marker=10.0)


def recall_figure(errors: dict[str, dict[str, np.ndarray]], path: Path, title: str, max_error: float, label,
                  panel_title, xlabel: str, ylabel: str, marker: float | None = None) -> Path:
    """Recall curves (share of errors <= a threshold, thresholds 0..``max_error``): ``errors[panel][method]``
    arrays, one panel per key; ``label(method, values)`` and ``panel_title(panel)`` the texts, a dotted
    line at ``marker``."""
    panels = list(errors)
    methods = list(dict.fromkeys(m for by_method in errors.values() for m in by_method))
    colours = plt.get_cmap("tab20")
    fig, axes = plt.subplots(1, len(panels), figsize=(6.2 * len(panels), 4.4), squeeze=False)
    for ax, panel in zip(axes[0], panels):
        for method, values in errors[panel].items():
            if not len(values):
                continue
            x, y = recall_curve(values, max_error)
            ax.plot(x, y, lw=1.6, color=colours(methods.index(method) % 20), label=label(method, values))
        if marker is not None:
            ax.axvline(marker, color="0.6", lw=0.8, ls=":")
        ax.set_xlim(0, max_error)
        ax.set_ylim(0, 1)
        ax.set_xlabel(xlabel)
        ax.set_ylabel(ylabel)
        ax.set_title(panel_title(panel), fontsize=9)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7, loc="lower right")
    return save_figure(fig, path, title, dpi=120)
