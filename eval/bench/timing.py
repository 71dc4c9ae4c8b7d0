"""What every ``fr bench`` section shares: medians of repeated timings, the synthetic segments
and estimators it times, device synchronisation, and the progress bar + row log + time budget."""
from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import numpy as np

STAGES = ("detect", "grid", "refine", "cues", "total")


def median_times(fn, repeats: int, warmup: int = 1, sync=None) -> list[float]:
    """Wall times (s) of ``repeats`` calls of ``fn`` after ``warmup`` untimed ones; ``sync`` (say
    ``torch.cuda.synchronize``) runs before and after each timed call."""
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(repeats):
        if sync:
            sync()
        start = time.perf_counter()
        fn()
        if sync:
            sync()
        times.append(time.perf_counter() - start)
    return times


def scene_segments(n: int, seed: int = 0) -> np.ndarray:
    """About n synthetic segments of a 640x480 Manhattan scene (70 % Manhattan, 30 % clutter)."""
    from fr_torch.core.geometry.conventions import focal_from_hfov, rotation_from_angles
    from fr_torch.synthetic import synthetic_segments

    rng = np.random.default_rng(seed)
    R = rotation_from_angles(*[np.float64(rng.uniform(-20, 20)) for _ in range(3)]).numpy()
    per_family = max(2, int(round(n * 0.7 / 3)))
    seg, _ = synthetic_segments(focal_from_hfov(70.0, 640), R, 640, 480, n_per_family=per_family,
                                clutter_fraction=0.3, seed=seed, min_length_px=10.0, max_length_px=80.0)
    if len(seg) < n:  # pad with jittered copies to reach exactly n
        extra = seg[rng.integers(0, len(seg), n - len(seg))] + rng.normal(0, 0.5, (n - len(seg), 4))
        seg = np.concatenate([seg, extra])
    return seg[:n]


def bench_estimator(mode: str, device="cpu", k: int | None = None, reliability: bool = True, distortion: str | None = None):
    """The estimator of a bench row; ``reliability=False``: no reliability stage (and so, in fR, no
    ``focal_profile_gap`` cue: ``fr batch --no-reliability``); ``distortion``: the lens setting
    (None: pinhole)."""
    from fr_torch import FREstimator
    from fr_torch.core.settings.config import SearchConfig

    config = SearchConfig.from_config(**({"grid_points_per_dim": k} if k else {}))
    return FREstimator(mode=mode, device=device, search_config=config, distortion=distortion,
                       **({} if reliability else {"reliability": None}))


def device_sync(device: str):
    """``torch.cuda.synchronize`` for a CUDA device, else None (nothing to wait for)."""
    if device.startswith("cuda"):
        import torch

        return torch.cuda.synchronize
    return None


class Progress:
    """tqdm bar + one JSON line per measurement, flushed at once (``<out>/bench.jsonl``), and a
    time budget: once ``budget_s`` has passed, the remaining settings are skipped (and listed)."""

    def __init__(self, total: int, disable: bool, log_path: Path | None = None, budget_s: float = 0.0):
        from tqdm import tqdm

        self.bar = tqdm(total=total, desc="fr bench", unit="step", disable=disable, file=sys.stderr)
        self.log = open(log_path, "w") if log_path else None
        self.start, self.budget_s, self.skipped = time.perf_counter(), budget_s, []

    def update(self, n: int = 1, section: str | None = None, row: dict | None = None) -> None:
        self.bar.update(n)
        if row is not None and self.log:
            self.log.write(json.dumps({"section": section, **row}) + "\n")
            self.log.flush()
        if row is not None:
            brief = ", ".join(f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}" for k, v in row.items()
                              if not isinstance(v, (dict, list)))
            self.bar.write(f"fr bench [{section}] {brief}", file=sys.stderr)

    def out_of_time(self, what: str) -> bool:
        if self.budget_s and time.perf_counter() - self.start > self.budget_s:
            self.skipped.append(what)
            return True
        return False

    def close(self) -> None:
        self.bar.close()
        if self.log:
            self.log.close()
