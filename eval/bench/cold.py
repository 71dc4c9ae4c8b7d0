"""``fr bench --sections cold``: what a fresh process pays before its first answer.

Each run is a new ``fr calibrate [--fast] --workers 0 --batch-size 1 PHOTO PHOTO`` process (the kernels already
built, as on any machine after its first run): its wall time, and the search time of its first
and second photo (``runtime_s``: grid + refinement + cues, the same photo twice), whose ratio is
the cold start's cost to the search (the kernels' load and check, first-call work, the garbage
collector's first full pass).  ``python -c "import torch"`` in a new process is timed beside it:
the part of the wall time no change of fR can remove.
"""
from __future__ import annotations

import json
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

#: The search's stages in ``runtime_s``.
SEARCH_STAGES = ("grid", "refine", "cues")


def _search_ms(record: dict) -> float:
    return 1000.0 * sum(record["runtime_s"][stage] for stage in SEARCH_STAGES)


def _wall_s(command: list[str]) -> tuple[float, subprocess.CompletedProcess]:
    start = time.perf_counter()
    done = subprocess.run(command, capture_output=True, text=True, timeout=300)
    return time.perf_counter() - start, done


def cold_rows(image: tuple[str, str], modes, runs: int, progress) -> list[dict]:
    """One row per mode: medians over ``runs`` fresh processes of the wall time (s), the first and
    second search (ms) and their ratio, and of ``import torch`` alone (s)."""
    label, path = image
    torch_import = statistics.median(_wall_s([sys.executable, "-c", "import torch"])[0] for _ in range(runs))
    rows = []
    for mode in modes:
        walls, firsts, seconds = [], [], []
        with tempfile.TemporaryDirectory() as folder:
            out = Path(folder) / "out.json"
            command = [sys.executable, "-m", "fr_torch.cli", "calibrate", *(["--fast"] if mode == "fast" else []),
                       "--workers", "0", "--batch-size", "1", "--no-progress", "--json", str(out), path, path]
            _wall_s(command)  # the kernels built and checked on this machine, as after a first run
            for _ in range(runs):
                wall, done = _wall_s(command)
                if done.returncode != 0:
                    raise RuntimeError(f"fr calibrate failed: {done.stderr.strip()[-300:]}")
                first, second = json.loads(out.read_text())[:2]
                walls.append(wall)
                firsts.append(_search_ms(first))
                seconds.append(_search_ms(second))
        row = {"image": label, "mode": mode, "runs": runs, "wall_s": statistics.median(walls),
               "import_torch_s": torch_import, "first_search_ms": statistics.median(firsts),
               "second_search_ms": statistics.median(seconds),
               "ratio": statistics.median(f / s for f, s in zip(firsts, seconds))}
        progress.update(1, "cold", row)
        rows.append(row)
    return rows


def markdown_lines(rows: list[dict]) -> list[str]:
    """The report's table of :func:`cold_rows`."""
    if not rows:
        return []
    lines = ["## A cold start (`fr calibrate --workers 0 --batch-size 1 PHOTO PHOTO` in a new process, CPU)", "",
             "| image | mode | runs | wall (s) | of it `import torch` (s) | first search (ms) | second search (ms) "
             "| first ÷ second |", "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['image']} | {r['mode']} | {r['runs']} | {r['wall_s']:.2f} | {r['import_torch_s']:.2f} | "
                     f"{r['first_search_ms']:.1f} | {r['second_search_ms']:.1f} | {r['ratio']:.2f} |")
    lines += ["", "Medians over the runs (ratio: the median of each run's own ratio); search = grid + refinement "
              "+ cues of `runtime_s`, the same photo twice; the kernels were built before the first run.", ""]
    return lines
