"""Summary tables (Markdown, CSV, LaTeX) from :class:`fr_eval.scoring.metrics.Summary` objects.

Rows are methods (optionally method x group, e.g. the per-FOV breakdown); columns n, valid
(share of images with a valid result, %), failures, run time, roll MAE, tilt MAE, FOV MAE %, focal
MAE %, frame error, each "mean ± SE" ("n/a" where the method does not estimate the quantity).  A
method whose weights / predictions were not supplied shows "n/a (not supplied)" in every cell of its
row.  The CSV keeps the raw numbers (``n_valid``, ``valid_pct``, ``<metric>_mean``, ``<metric>_se``,
``<metric>_n``; NaN for a method not supplied, whose ``status`` column says so).
"""
from __future__ import annotations

import math
from pathlib import Path
from typing import Sequence

import pandas as pd
from fr_eval.scoring.metrics import METRICS, NOT_SUPPLIED, Summary

from fr_torch.registry import parse_method_spec as _parse_method_spec

HEADERS = {
    "runtime_s": "run time (s)",
    "roll_err_deg": "roll MAE (°)",
    "tilt_err_deg": "tilt MAE (°)",
    "fov_err_pct": "FOV MAE (%)",
    "focal_err_pct": "focal MAE (%)",
    "frame_err_deg": "frame error (°)",
}
DECIMALS = {"runtime_s": 3}
VALID_HEADER = "valid (%)"

def parse_method_spec(spec: str) -> tuple[str, dict[str, str]]:
    """:func:`fr_torch.registry.parse_method_spec` for labels read back (never raises)."""
    return _parse_method_spec(spec, strict=False)


def format_mean_se(mean: float, se: float, n: int, decimals: int = 2) -> str:
    if n == 0 or not math.isfinite(mean):
        return "n/a"
    if not math.isfinite(se):
        return f"{mean:.{decimals}f}"
    return f"{mean:.{decimals}f} ± {se:.{decimals}f}"


def display_frame(summaries: Sequence[Summary], label: str = "method", metrics: Sequence[str] = METRICS,
                  group_label: str | None = None) -> pd.DataFrame:
    """Human-readable table (strings) with one row per summary.

    ``group_label``: add a column with each summary's ``group`` after the label column.  A summary
    marked not supplied shows :data:`fr_eval.scoring.metrics.NOT_SUPPLIED` in every cell but label and group.
    """
    rows = []
    for s in summaries:
        row = {label: s.method}
        if group_label is not None:
            row[group_label] = "" if s.group is None else str(s.group)
        cells = {"n": str(s.n_images),
                 VALID_HEADER: f"{s.valid_pct:.1f}" if s.n_images else "n/a",
                 "failures": f"{s.failures} ({s.failure_pct:.1f}%)" if s.n_images else "0"}
        for m in metrics:
            cells[HEADERS[m]] = format_mean_se(s.mean[m], s.se[m], s.n[m], DECIMALS.get(m, 2))
        if s.not_supplied:
            cells = dict.fromkeys(cells, s.na_reason or NOT_SUPPLIED)
        row.update(cells)
        rows.append(row)
    return pd.DataFrame(rows, dtype=object)


def numeric_frame(summaries: Sequence[Summary], metrics: Sequence[str] = METRICS,
                  group_label: str | None = None) -> pd.DataFrame:
    frame = pd.DataFrame([s.as_row(group_label) for s in summaries])
    drop = [f"{m}_{k}" for m in METRICS if m not in metrics for k in ("mean", "se", "n")]
    return frame.drop(columns=[c for c in drop if c in frame.columns])


def to_markdown(frame: pd.DataFrame) -> str:
    cols = [str(c) for c in frame.columns]
    lines = ["| " + " | ".join(cols) + " |", "|" + "|".join(["---"] * len(cols)) + "|"]
    for _, row in frame.iterrows():
        lines.append("| " + " | ".join(str(v).replace("|", "\\|") for v in row.tolist()) + " |")
    return "\n".join(lines) + "\n"


def _latex_escape(text: str) -> str:
    text = str(text)
    for a, b in (("\\", r"\textbackslash{}"), ("&", r"\&"), ("%", r"\%"), ("_", r"\_"), ("#", r"\#"),
                 ("{", r"\{"), ("}", r"\}"), ("$", r"\$")):
        if a == "\\":
            text = text.replace(a, "\0")
        else:
            text = text.replace(a, b)
    text = text.replace("\0", r"\textbackslash{}")
    return text.replace("±", r"$\pm$").replace("°", r"$^\circ$")


def to_latex(frame: pd.DataFrame, caption: str = "") -> str:
    cols = list(frame.columns)
    out = [r"\begin{table}[t]", r"\centering", r"\small"]
    if caption:
        out.append(r"\caption{" + _latex_escape(caption) + "}")
    out += [r"\begin{tabular}{l" + "r" * (len(cols) - 1) + "}", r"\toprule",
            " & ".join(_latex_escape(c) for c in cols) + r" \\", r"\midrule"]
    for _, row in frame.iterrows():
        out.append(" & ".join(_latex_escape(v) for v in row.tolist()) + r" \\")
    out += [r"\bottomrule", r"\end{tabular}", r"\end{table}"]
    return "\n".join(out) + "\n"


def write_tables(summaries: Sequence[Summary], out_dir: Path, stem: str = "summary", title: str = "",
                 label: str = "method", note: str = "", metrics: Sequence[str] = METRICS,
                 group_label: str | None = None) -> list[Path]:
    """Write ``<stem>.md``, ``<stem>.csv`` (raw numbers) and ``<stem>.tex``; returns the paths."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    display = display_frame(summaries, label=label, metrics=metrics, group_label=group_label)
    md = (f"# {title}\n\n" if title else "") + to_markdown(display) + (f"\n{note}\n" if note else "")
    paths = [out_dir / f"{stem}.md", out_dir / f"{stem}.csv", out_dir / f"{stem}.tex"]
    paths[0].write_text(md, encoding="utf-8")
    numeric = numeric_frame(summaries, metrics=metrics, group_label=group_label)
    if label != "method":
        numeric.insert(0, label, display[label].tolist())
    numeric.to_csv(paths[1], index=False)
    paths[2].write_text(to_latex(display, caption=title), encoding="utf-8")
    return paths


def deviation_measure_summaries(summaries: Sequence[Summary]) -> list[Summary]:
    """The summaries of methods run with a ``[measure=...]`` option, ordered by base method and measure.

    Their ``method`` field is relabelled ``"<measure> (<base>)"`` for the deviation-measure table.
    """
    picked = []
    for s in summaries:
        base, opts = parse_method_spec(s.method)
        if "measure" in opts:
            picked.append((base, opts["measure"], s))
    picked.sort(key=lambda t: (t[0], t[1]))
    out = []
    for base, measure, s in picked:
        others = {k: v for k, v in parse_method_spec(s.method)[1].items() if k != "measure"}
        suffix = "".join(f", {k}={v}" for k, v in others.items())
        out.append(Summary(method=f"{measure} ({base}{suffix})", n_images=s.n_images, failures=s.failures,
                           mean=s.mean, se=s.se, n=s.n, group=s.group, na_reason=s.na_reason))
    return out
