"""Histograms of estimated vs ground-truth roll, tilt and FOV (matplotlib, Agg backend)."""
from __future__ import annotations

import re
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402

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
    fig.suptitle(title or f"{method}: estimated vs ground truth" + (f" ({failures} failed)" if failures else ""))
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
