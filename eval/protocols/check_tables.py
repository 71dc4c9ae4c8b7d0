"""Check regenerated tables against the committed ones, within a stated tolerance.

``python -m fr_eval.protocols.check_tables [PATH ...] [--rev HEAD] [--rtol 1e-6]`` compares every
CSV under PATH (default ``results/``) that git tracks with its version at ``--rev``: the same rows
and columns, text columns equal, numeric columns equal within ``rtol`` (relative) / ``atol``
(absolute), timing columns (``runtime``, ``seconds``, ``_s``, ``per_s``, ``ms``) ignored.  It prints
one line per file that differs and exits 1 when any differs beyond the tolerance.
``eval/reproduce.sh --check STEP...`` runs the steps and then this.

The default tolerance, 1e-6 relative: on one machine a step reproduces bit for bit (``docs/
reproducibility.md``); another CPU family's ``exp`` / ``log`` moves a photo's estimate by about
1e-7 relative, and a table's mean by less.
"""
from __future__ import annotations

import argparse
import io
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


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m fr_eval.protocols.check_tables", description=__doc__.splitlines()[0])
    parser.add_argument("paths", nargs="*", default=["results"])
    parser.add_argument("--rev", default="HEAD", help="the committed version (default HEAD)")
    parser.add_argument("--rtol", type=float, default=1e-6)
    parser.add_argument("--atol", type=float, default=1e-9)
    args = parser.parse_args(argv)
    failed = 0
    for path in tracked_csvs(args.paths, args.rev):
        committed_text = subprocess.run(["git", "show", f"{args.rev}:{path}"], cwd=REPO, capture_output=True,
                                        text=True, check=True).stdout
        current_path = REPO / path
        if not current_path.is_file():
            print(f"{path}: missing now")
            failed += 1
            continue
        current_text = current_path.read_text()
        if current_text == committed_text:
            continue
        ok, message = compare(pd.read_csv(io.StringIO(committed_text)), pd.read_csv(current_path), args.rtol, args.atol)
        print(f"{path}: {message}")
        failed += not ok
    print(f"{failed} file(s) beyond rtol {args.rtol:g} / atol {args.atol:g}" if failed else
          f"every table within rtol {args.rtol:g} / atol {args.atol:g}")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
