"""The shipped configuration files: likelihood and search settings, reliability models.

The single source is the repository's top-level ``configs/`` folder.  A wheel ships it as the
package ``fr_torch.configs`` (``package-dir`` in ``pyproject.toml``), so an installed ``fr`` finds
it from any working directory; an editable install (``pip install -e .``) maps it to the
folder itself.  Every reader goes through :func:`config_dir`.
"""
from __future__ import annotations

from functools import lru_cache
from importlib import resources
from pathlib import Path


@lru_cache(maxsize=1)
def config_dir() -> Path:
    """Folder holding ``likelihood*.json``, ``search.json``, ``reliability*.{json,npz}``.

    Wheels install unpacked (never zipped), so this is a real folder on disk.
    """
    return Path(str(resources.files("fr_torch.configs")))


def config_path(name: str) -> Path:
    """Path of one shipped configuration file, e.g. ``config_path("search.json")``."""
    return config_dir() / name
