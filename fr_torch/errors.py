"""The library's one exception type for bad input."""
from __future__ import annotations


class FRInputError(ValueError):
    """Bad user input (unreadable file, wrong shape, NaNs...): reported as one clear line."""
