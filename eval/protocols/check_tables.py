"""Check regenerated tables against the committed ones, within a stated tolerance.

``python -m fr_eval.protocols.check_tables [PATH ...] [--rev HEAD] [--rtol 1e-6]`` compares every
CSV under PATH (default ``results/``) that git tracks with its version at ``--rev``: the same rows
and columns, text columns equal, numeric columns equal within ``rtol`` (relative) / ``atol``
(absolute), timing columns (``runtime``, ``seconds``, ``_s``, ``per_s``, ``ms``) ignored.  It prints
one line per file that differs and exits 1 when any differs beyond the tolerance.
``eval/reproduce.sh --check STEP...`` runs the steps and then this.

``--moves`` asks the other question, for a change of the method: how far each mean moved in units
of its committed standard error.  Every CSV with a ``method`` column and ``<metric>_mean`` /
``<metric>_se`` columns gives one line per (method, metric) that moved: the committed mean ± SE,
the new mean and the move in SEs; a move beyond ``--limit`` SEs (default 1) is flagged and makes
the exit status 1.  Timing metrics are left out.

The default tolerance, 1e-6 relative: on one machine a step reproduces bit for bit (``docs/
reproducibility.md``); another CPU family's ``exp`` / ``log`` moves a photo's estimate by about
1e-7 relative, and a table's mean by less.
"""
from __future__ import annotations

import argparse
import io
import math
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd

from fr_eval.paths import REPO

#: Columns whose values are timings (never compared).
TIMING = re.compile(r"(runtime|seconds|(^|_)s$|per_s|_ms$|(^|_)ms(_|$)|images_per_s|wall)", re.IGNORECASE)


def tracked_csvs(paths: list[str], rev: str) -> list[str]:
    """CSV files under ``paths`` that git tracks at ``rev`` (repository-relative)."""
    listing = subprocess.run(["git", "ls-tree", "-r", "--name-only", rev, "--", *paths], cwd=REPO,
                             capture_output=True, text=True, check=True).stdout.split()
    return [p for p in listing if p.endswith(".csv")]


def compare(committed: pd.DataFrame, current: pd.DataFrame, rtol: float, atol: float) -> tuple[bool, str]:
    """(within tolerance, what differs) for two tables of one file."""
    if list(committed.columns) != list(current.columns):
        return False, f"columns differ: {sorted(set(committed.columns) ^ set(current.columns))}"
    if len(committed) != len(current):
        return False, f"{len(committed)} rows committed, {len(current)} now"
    worst, where = 0.0, ""
    for column in committed.columns:
        if TIMING.search(str(column)):
            continue
        a, b = committed[column], current[column]
        a_num, b_num = pd.to_numeric(a, errors="coerce"), pd.to_numeric(b, errors="coerce")
        numeric = a_num.notna() | b_num.notna()
        text_a, text_b = a[~numeric].astype(str).tolist(), b[~numeric].astype(str).tolist()
        if text_a != text_b:
            return False, f"column {column!r}: text differs"
        x, y = a_num[numeric].to_numpy(np.float64), b_num[numeric].to_numpy(np.float64)
        if not np.array_equal(np.isnan(x), np.isnan(y)):
            return False, f"column {column!r}: missing values differ"
        ok = ~np.isnan(x)
        excess = np.abs(x[ok] - y[ok]) - (atol + rtol * np.abs(x[ok]))
        if excess.size and excess.max() > 0:
            rel = np.abs(x[ok] - y[ok]) / np.maximum(np.abs(x[ok]), 1e-300)
            return False, f"column {column!r}: up to {rel.max():.2e} relative"
        if excess.size:
            rel = (np.abs(x[ok] - y[ok]) / np.maximum(np.abs(x[ok]), 1e-300)).max()
            if rel > worst:
                worst, where = rel, column
    return True, f"within tolerance (largest {worst:.1e} in {where!r})" if worst else "identical"


def committed_text(path: str, rev: str) -> str:
    """The text of the repository-relative ``path`` at ``rev``."""
    return subprocess.run(["git", "show", f"{rev}:{path}"], cwd=REPO, capture_output=True, text=True,
                          check=True).stdout


def standard_error_moves(committed: pd.DataFrame, current: pd.DataFrame) -> list[dict]:
    """Per (method, metric) of a summary table: the committed mean and SE, the current mean and the
    move in committed SEs (``inf`` where the SE is 0 and the mean moved; rows or metrics present in
    only one table are left out)."""
    if "method" not in committed.columns or "method" not in current.columns:
        return []
    metrics = [c[:-5] for c in committed.columns
               if c.endswith("_mean") and f"{c[:-5]}_se" in committed.columns and not TIMING.search(c[:-5])
               and f"{c[:-5]}_mean" in current.columns]
    now = current.drop_duplicates("method").set_index("method")
    moves = []
    for _, row in committed.drop_duplicates("method").iterrows():
        if row["method"] not in now.index:
            continue
        for metric in metrics:
            old, se = float(row[f"{metric}_mean"]), float(row[f"{metric}_se"])
            new = float(now.loc[row["method"], f"{metric}_mean"])
            if not (np.isfinite(old) and np.isfinite(new)) or old == new:
                continue
            moves.append({"method": row["method"], "metric": metric, "old": old, "se": se, "new": new,
                          "se_moved": (new - old) / se if se > 0 else math.copysign(math.inf, new - old)})
    return moves


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m fr_eval.protocols.check_tables", description=__doc__.splitlines()[0])
    parser.add_argument("paths", nargs="*", default=["results"])
    parser.add_argument("--rev", default="HEAD", help="the committed version (default HEAD)")
    parser.add_argument("--rtol", type=float, default=1e-6)
    parser.add_argument("--atol", type=float, default=1e-9)
    parser.add_argument("--moves", action="store_true",
                        help="print how far each mean moved in committed standard errors instead")
    parser.add_argument("--limit", type=float, default=1.0, help="--moves: flag moves beyond this many SEs")
    args = parser.parse_args(argv)
    if args.moves:
        return print_moves(args.paths, args.rev, args.limit)
    failed = 0
    for path in tracked_csvs(args.paths, args.rev):
        committed = committed_text(path, args.rev)
        current_path = REPO / path
        if not current_path.is_file():
            print(f"{path}: missing now")
            failed += 1
            continue
        if current_path.read_text() == committed:
            continue
        ok, message = compare(pd.read_csv(io.StringIO(committed)), pd.read_csv(current_path), args.rtol, args.atol)
        print(f"{path}: {message}")
        failed += not ok
    print(f"{failed} file(s) beyond rtol {args.rtol:g} / atol {args.atol:g}" if failed else
          f"every table within rtol {args.rtol:g} / atol {args.atol:g}")
    return 1 if failed else 0


def print_moves(paths: list[str], rev: str, limit: float) -> int:
    """``--moves``: one line per moved mean of every summary table under ``paths``; 1 when any
    moved beyond ``limit`` committed SEs."""
    beyond = 0
    for path in tracked_csvs(paths, rev):
        current_path = REPO / path
        if not current_path.is_file():
            continue
        committed = pd.read_csv(io.StringIO(committed_text(path, rev)))
        for move in standard_error_moves(committed, pd.read_csv(current_path)):
            flag = abs(move["se_moved"]) > limit
            beyond += flag
            print(f"{'!! ' if flag else '   '}{path} | {move['method']} | {move['metric']} | "
                  f"{move['old']:.4g} ± {move['se']:.3g} -> {move['new']:.4g} | {move['se_moved']:+.2f} SE")
    print(f"{beyond} mean(s) moved beyond {limit:g} SE" if beyond else f"every mean within {limit:g} SE")
    return 1 if beyond else 0


if __name__ == "__main__":
    sys.exit(main())
