"""The lens setting: :class:`DistortionSetting` (pinhole, the division model's k estimated with f and
R, or ``auto``: pinhole, then the division model where the lines bend), its k range and the
"lines bend" test's thresholds, parsed once from ``--distortion``, ``--k`` or ``configs/search.json``.

The model itself (what k means, how points move) is :mod:`fr_torch.core.geometry.lens`.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, fields
from enum import StrEnum

from fr_torch.core.geometry.lens import K_LIMITS
from fr_torch.core.settings.checks import enum_member, finite_number
from fr_torch.errors import FRInputError


class DistortionMode(StrEnum):
    """``pinhole`` (no distortion: the paper's model, the default), ``division`` (estimate k of the
    division model jointly with f and R) or ``auto`` (the pinhole search, then the division search
    for the images whose lines bend: :attr:`DistortionSetting.bend_min_gain`)."""

    PINHOLE = "pinhole"
    DIVISION = "division"
    AUTO = "auto"

    @classmethod
    def parse(cls, value) -> "DistortionMode":
        """A mode from its name (or a :class:`DistortionMode`); FRInputError (one line) otherwise."""
        return enum_member(cls, value, "distortion")


@dataclass(frozen=True)
class DistortionSetting:
    """What the search assumes about the lens, parsed once (``--distortion``, ``--k``).

    ``mode``: a :class:`DistortionMode`.  ``known_k``: a given k (normalised, module docstring);
    the search then holds it fixed (``mode`` becomes ``division``); None = estimate it.
    ``k_range``: the search box of k (default [-0.6, 0.2]: from no distortion to a fisheye-like
    barrel whose border lines bow by ~10 % of the width, and a mild pincushion), within
    :data:`~fr_torch.core.geometry.lens.K_LIMITS`.  ``k_prior_weight`` (gamma >= 0): a prior on k, ``log p(k) = -(gamma / 2) W k^2``
    per image (W its total segment length, pixels; nats), which holds k near 0 where the lines say
    little about it (:meth:`fr_torch.core.search.lens.SegmentGeometry.k_log_prior`).
    ``bend_min_gain``, ``bend_min_share``, ``bend_min_pairs``,
    ``bend_min_bow_pct``: when the lines of a pinhole estimate bend
    (:func:`fr_torch.core.reliability.sanity.lines_bend_reason`; the estimate is then not reliable, and ``auto``
    searches that image with the division model instead).  ``results/decisions/46.md`` says how they
    were chosen (train splits; 2-3 % of undistorted photos flagged).
    """

    mode: DistortionMode = DistortionMode.PINHOLE
    known_k: float | None = None
    k_range: tuple[float, float] = (-0.6, 0.2)
    k_prior_weight: float = 3.0
    bend_min_gain: float = 60.0
    bend_min_share: float = 0.15
    bend_min_pairs: int = 8
    bend_min_bow_pct: float = 1.0

    def __post_init__(self) -> None:
        object.__setattr__(self, "mode", DistortionMode.parse(self.mode))
        low, high = (float(v) for v in self.k_range)
        if not (math.isfinite(low) and math.isfinite(high) and K_LIMITS[0] < low < high < K_LIMITS[1]):
            raise FRInputError(f"k range must be finite MIN,MAX with {K_LIMITS[0]:g} < MIN < MAX < {K_LIMITS[1]:g}, "
                               f"got {self.k_range}")
        object.__setattr__(self, "k_range", (low, high))
        if self.known_k is not None:
            k = finite_number(self.known_k, "k")
            if not K_LIMITS[0] < k < K_LIMITS[1]:
                raise FRInputError(f"k must lie in ({K_LIMITS[0]:g}, {K_LIMITS[1]:g}) (division model, normalised by "
                                   f"half the image diagonal), got {self.known_k!r}")
            object.__setattr__(self, "known_k", k)
            if self.mode is DistortionMode.PINHOLE:
                object.__setattr__(self, "mode", DistortionMode.DIVISION)
        for name in ("k_prior_weight", "bend_min_gain", "bend_min_share", "bend_min_pairs", "bend_min_bow_pct"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value >= 0):
                raise FRInputError(f"{name} must be a finite number >= 0, got {value!r}")

    @classmethod
    def parse(cls, value=None) -> "DistortionSetting":
        """A setting from a :class:`DistortionSetting`, a mode name (``"division"``), a dict of the
        fields (``configs/search.json``) or None (the default, pinhole); FRInputError otherwise."""
        if value is None:
            return cls()
        if isinstance(value, cls):
            return value
        if isinstance(value, (str, DistortionMode)):
            return cls(mode=value)
        if isinstance(value, dict):
            unknown = sorted(set(value) - {f.name for f in fields(cls)})
            if unknown:
                raise FRInputError(f"distortion setting: unknown field(s) {', '.join(unknown)}")
            return cls(**{key: tuple(v) if isinstance(v, list) else v for key, v in value.items()})
        raise FRInputError(f"distortion must be a mode name or a setting, got {value!r}")

    @property
    def estimates_k(self) -> bool:
        """True when the search has a k parameter (``division`` or ``auto``, known k included)."""
        return self.mode is not DistortionMode.PINHOLE

    def k_box(self) -> tuple[float, float]:
        """The search box of k: ``k_range``, or (k, k) for a known k."""
        return (self.known_k, self.known_k) if self.known_k is not None else self.k_range
