"""Fingerprints of the files a baseline's row comes from (supplied weights, predictions), for table
captions and the metadata ``fr export-ctrlc`` writes."""
from __future__ import annotations

import hashlib
import os


def sha256(path: str | os.PathLike, chunk: int = 1 << 20) -> str:
    """Hex sha256 of a file, read in blocks of ``chunk`` bytes."""
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        while block := f.read(chunk):
            digest.update(block)
    return digest.hexdigest()
