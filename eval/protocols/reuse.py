"""``fr eval --reuse METHODS``: take the named methods' per-image rows from the output folder's last run.

Regenerating a table after one method changed (fR's search, say) need not run the slow baselines
again (CONSAC: 3-30 s per photo)::

    fr eval --task vp --dataset nyu-vp --split val --methods "fr,...,consac,consac-s" \\
        --out results/vp/nyu-vp-val --reuse consac,consac-s

Each method spec listed (exactly as written in ``--methods``, after ``all`` / ``--measures``
expanded them) is not built (no weights loaded) and not run: its rows come from the per-image file
already in ``--out`` (``predictions.csv``, ``vp_errors.csv`` or ``horizon_errors.csv``), in this
run's image order, and every other method runs as usual.  The per-image file, the summaries, tables,
figures and ``run_info.json`` are then written as if every method had run: the same rows in the
``--methods`` order, the same columns; what a summary takes from outside the per-image file (the
VP task's time per image, the camera task's weights caption) comes from the old run's other files.

:func:`previous_run` refuses (:class:`ReuseError`, one line; the tasks print it and exit 2) when
``--out`` holds no ``run_info.json`` or no per-image file, when the old run's settings (task,
dataset, split, FOV range, principal point, known focal length, ``--limit``, the VP task's
intrinsics) differ from this run's, when a reused method is not among this run's methods or has no
rows in the old file, or when the old file lacks a row of a reused method for an image of this run.

``run_info.json`` records ``"reused": {method: date}``: the date of the run that computed the rows
(the old run's ``date``, or the date the old run itself recorded for a method it reused).
"""
from __future__ import annotations

import argparse
import json
import math
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterable, Mapping, Sequence

import pandas as pd

from fr_torch.registry import split_method_list

#: Text columns of the per-image files: read as text ("" where empty), never as numbers or NaN.
TEXT_COLUMNS = ("method", "image", "split", "reason", "intrinsics")
#: Settings a run_info.json may lack, with the value that meant (camera runs record no "task").
SETTING_DEFAULTS = {"task": "camera"}
#: pandas before 3 parses floats exactly only when asked (3 does by default and deprecates asking).
_EXACT_FLOATS = {"float_precision": "round_trip"} if int(pd.__version__.split(".")[0]) < 3 else {}


class ReuseError(ValueError):
    """Why ``--reuse`` cannot be honoured: one line for the user."""


def add_argument(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--reuse", default=None, metavar="METHODS",
                        help="comma-separated method specs of --methods whose per-image rows are taken from the "
                             "run already in --out instead of running them (its settings must match); the "
                             "outputs are written as if every method had run, run_info.json records the reuse")


def reused_methods(args: argparse.Namespace) -> list[str]:
    """The method specs of ``--reuse`` (duplicates removed), [] without the option."""
    return list(dict.fromkeys(split_method_list(getattr(args, "reuse", None) or "")))


def read_table(path: Path) -> pd.DataFrame:
    """A CSV the harness wrote, read back exactly: floats bit for bit, text columns as text ("" for
    empty; "n/a" and "None" stay text)."""
    frame = pd.read_csv(path, keep_default_na=False, na_values=[""], dtype={c: str for c in TEXT_COLUMNS},
                        **_EXACT_FLOATS)
    for column in TEXT_COLUMNS:
        if column in frame:
            frame[column] = frame[column].fillna("")
    return frame


def _json(value: Any) -> Any:
    return json.loads(json.dumps(value))


@dataclass
class PreviousRun:
    """The run in the output folder whose rows ``--reuse`` takes (:func:`previous_run`)."""

    folder: Path
    info: dict[str, Any]
    rows: pd.DataFrame
    methods: tuple[str, ...]
    tables: dict[str, pd.DataFrame] = field(default_factory=dict)

    def rows_of(self, spec: str, samples: Sequence[Any], *, variants: bool = False,
                blank: Callable[[Any], Mapping[str, Any]] | None = None) -> list[dict[str, Any]]:
        """Method ``spec``'s old rows for ``samples``, as a fresh run orders them: grouped as the old file
        grouped them (by method, then by any other text column such as the intrinsics setting), images
        in ``samples`` order.  ``variants`` also takes rows ``"<spec> (<name>)"`` (the VP task's
        variant rows).  ``blank(sample)`` -- the row a fresh run writes for a failed estimate -- names
        the columns every row has; a row keeps those and the columns it holds a value in (the old
        file's other columns are other methods'), in the old file's column order.  Without
        ``blank`` a row keeps every column."""
        method = self.rows["method"]
        chosen = self.rows[(method == spec) | (method.str.startswith(f"{spec} (") if variants else False)]
        position = {str(s.name): i for i, s in enumerate(samples)}
        chosen = chosen[chosen["image"].isin(position)]
        groups = [c for c in TEXT_COLUMNS if c in chosen and c not in ("image", "split", "reason")]
        block = pd.factorize(chosen[groups].astype(str).agg("\x1f".join, axis=1))[0] if len(chosen) else []
        chosen = chosen.assign(_block=block, _image=chosen["image"].map(position))
        chosen = chosen.sort_values(["_block", "_image"], kind="stable").drop(columns=["_block", "_image"])
        by_name = {str(s.name): s for s in samples}
        out = []
        for record in chosen.to_dict("records"):
            always = set(blank(by_name[record["image"]])) if blank is not None else set(record)
            out.append({k: v for k, v in record.items() if k in always or not _empty(v)})
        return out

    def value(self, name: str, method: str, column: str) -> float:
        """One number of the old run's summary CSV ``name`` (e.g. the VP task's time per image in
        ``vp_summary.csv``): column ``column`` of the row of ``method``; ReuseError when absent."""
        path = self.folder / name
        if name not in self.tables:
            if not path.is_file():
                raise ReuseError(f"{path} is missing (the reused rows' {column} is read from it)")
            self.tables[name] = read_table(path)
        table = self.tables[name]
        chosen = table.loc[table["method"] == method, column] if {"method", column} <= set(table.columns) else []
        if not len(chosen):
            raise ReuseError(f"{path} has no {column} of {method}")
        return float(chosen.iloc[0])

    def provenance(self) -> dict[str, str]:
        """``{method: date}`` for run_info.json: the date of the run that computed each reused method's
        rows (a method the old run itself reused keeps the date it recorded)."""
        earlier = self.info.get("reused")
        earlier = earlier if isinstance(earlier, dict) else {}
        return {m: earlier.get(m, self.info.get("date", "unknown")) for m in self.methods}


def _empty(value: Any) -> bool:
    return value is None or (isinstance(value, float) and math.isnan(value))


def image_task_settings(args: argparse.Namespace, task: str, fov_range) -> dict[str, Any]:
    """The settings a camera or horizon run must share with the run it reuses (``fov_range``: the
    parsed FOV range): task, dataset, split, principal point, known focal, limit, FOV range."""
    return {"task": task, "dataset": args.dataset, "split": args.split, "pp": args.pp,
            "known_focal": args.known_focal, "limit": args.limit, "fov_range_deg": list(fov_range)}


def previous_run(args: argparse.Namespace, out_dir: Path, per_image: str, settings: Mapping[str, Any],
                 methods: Sequence[str], samples: Sequence[Any],
                 per: Mapping[str, Iterable[str]] | None = None) -> PreviousRun | None:
    """The old run in ``out_dir`` that ``--reuse`` takes rows from, checked; None without ``--reuse``.

    ``per_image``: the task's per-image file; ``settings``: this run's values of the run_info.json keys
    that must match (the old run's missing keys read as :data:`SETTING_DEFAULTS`); ``methods``: this
    run's method specs; ``samples``: this run's images, each of which needs a row of every reused
    method -- under every value of ``per``'s columns (the VP task: ``{"intrinsics": settings}``).
    ReuseError (one line) when any of that fails (module docstring)."""
    reused = reused_methods(args)
    if not reused:
        return None
    missing = [m for m in reused if m not in methods]
    if missing:
        raise ReuseError(f"{', '.join(missing)} not among this run's methods ({', '.join(methods)}); give each "
                         "method exactly as --methods names it")
    info_path, rows_path = out_dir / "run_info.json", out_dir / per_image
    for path in (info_path, rows_path):
        if not path.is_file():
            raise ReuseError(f"{path} not found: --reuse takes rows from an earlier run in the same --out folder")
    try:
        info = json.loads(info_path.read_text(encoding="utf-8"))
    except (OSError, ValueError) as exc:
        raise ReuseError(f"{info_path}: cannot read ({type(exc).__name__}: {exc})") from None
    if not isinstance(info, dict):
        raise ReuseError(f"{info_path} is not a run's record (a JSON object)")
    differ = [f"{key} {_json(info.get(key, SETTING_DEFAULTS.get(key)))!r} (this run {_json(value)!r})"
              for key, value in settings.items() if _json(info.get(key, SETTING_DEFAULTS.get(key))) != _json(value)]
    if differ:
        raise ReuseError(f"the run in {out_dir} had other settings: {'; '.join(differ)}")
    try:
        rows = read_table(rows_path)
    except (OSError, ValueError) as exc:
        raise ReuseError(f"{rows_path}: cannot read ({type(exc).__name__}: {exc})") from None
    if not {"method", "image"} <= set(rows.columns):
        raise ReuseError(f"{rows_path} has no method / image columns")
    images = [str(s.name) for s in samples]
    for spec in reused:
        own = rows[rows["method"] == spec]
        if own.empty:
            raise ReuseError(f"{rows_path} holds no rows of {spec}")
        subsets = [("", own)] + [(f" ({column} {value})", own[own[column] == value] if column in own else own[:0])
                                 for column, values in (per or {}).items() for value in values]
        for where, subset in subsets:
            held = set(subset["image"])
            absent = [name for name in images if name not in held]
            if absent:
                raise ReuseError(f"{rows_path} lacks {spec}{where} on {len(absent)} of this run's "
                                 f"{len(images)} images (e.g. {absent[0]})")
    return PreviousRun(folder=out_dir, info=info, rows=rows, methods=tuple(m for m in methods if m in reused))


def reused_of(previous: PreviousRun | None) -> tuple[str, ...]:
    """The methods whose rows are reused (none without ``--reuse``)."""
    return () if previous is None else previous.methods


def left_to_run(methods: Sequence[str], previous: PreviousRun | None) -> list[str]:
    """``methods`` less the reused ones: those to build and run."""
    return [m for m in methods if m not in reused_of(previous)]


def refuse(error: ReuseError, stream=None) -> int:
    """Print ``error`` as one line on stderr; the exit status 2."""
    print(f"error: --reuse: {' '.join(str(error).split())}", file=stream or sys.stderr)
    return 2
