"""Where datasets live: ``--data-root`` option, else ``$FR_DATA``, else ``../shared/data`` beside the repo.

Generated datasets (e.g. ZInD-fR views) go under ``$FR_CACHE`` (default ``<repo>/data_local``,
which git ignores).  Dataset files are never committed to the project.
"""
from __future__ import annotations

import os
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def data_root(override: str | os.PathLike | None = None) -> Path:
    """Root folder holding ``yorkurbandb/``, ``zind_sample_tour/``, ... (raises if absent)."""
    root = Path(override or os.environ.get("FR_DATA", REPO.parent / "shared" / "data"))
    if not root.is_dir():
        raise FileNotFoundError(f"dataset root {root} not found: pass --data-root or set FR_DATA")
    return root


def cache_root(override: str | os.PathLike | None = None) -> Path:
    """Folder for generated datasets (created on demand)."""
    root = Path(override or os.environ.get("FR_CACHE", REPO / "data_local"))
    root.mkdir(parents=True, exist_ok=True)
    return root
