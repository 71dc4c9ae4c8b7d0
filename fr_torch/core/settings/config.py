"""The search configuration and the modes (fR, Fast-fR) that preset it.

A :class:`SearchConfig` is built once from its dataclass defaults, the overrides of
``configs/search.json`` (which holds overrides only; empty as shipped) and the caller's keyword
overrides (:meth:`SearchConfig.from_config`).  The mode-dependent fields (refinement steps,
segment cap, stage-1 segment count) may be left ``None``; :meth:`SearchConfig.resolve` fills them
from the mode's preset (:data:`MODE_PRESETS`), so the estimator always runs one concrete
configuration.

Example::

    config = SearchConfig.from_config(fov_range="paper").resolve(Mode.FAST)
    config.refine_iterations, config.max_segments     # 10, 500
"""
from __future__ import annotations

import json
import math
from dataclasses import dataclass, fields, replace
from enum import StrEnum
from pathlib import Path

from fr_torch.core.geometry.vanishing import overrides_from_text
from fr_torch.core.settings.checks import enum_member
from fr_torch.core.settings.distortion import DistortionSetting
from fr_torch.core.settings.fov import FovRange, two_numbers
from fr_torch.errors import FRInputError
from fr_torch.resources import config_path

FOCAL_GRIDS = ("linear_f", "log_f", "fov")


class Mode(StrEnum):
    """The estimator's modes: ``fr`` refines to convergence, ``fast`` (Fast-fR) for 10 steps."""

    FR = "fr"
    FAST = "fast"

    @classmethod
    def parse(cls, value) -> "Mode":
        """A mode from ``"fr"``, ``"fast"`` or a :class:`Mode`; FRInputError (one line) otherwise."""
        return enum_member(cls, value, "mode")


#: Refinement steps of Fast-fR (the paper's definition).
FAST_REFINE_ITERATIONS = 10

#: The mode-dependent settings of each mode: refinement steps, the segment cap per image
#: (``max_segments``: each image keeps its longest this many) and the segments stage 1 scores
#: (``grid_segments``, 0 = all).  ``results/DECISIONS.md`` records how they were chosen.
MODE_PRESETS: dict[Mode, dict[str, int]] = {
    Mode.FR: {"refine_iterations": 100, "max_segments": 750, "grid_segments": 0},
    Mode.FAST: {"refine_iterations": FAST_REFINE_ITERATIONS, "max_segments": 500, "grid_segments": 0},
}


#: Settings that no longer exist, each with the one-line error that says what replaced it (kept for
#: a release, so that a configuration written for an older version fails with a reason).
REMOVED_SETTINGS = {
    "compile_search": "compile_search (--compile) was removed in 0.2: the fused CPU kernels "
                      "(fr_torch.core.likelihood.native) replaced it and give the same bits as the default search; "
                      "drop the setting",
    "fit": "fit (--fit horizon|choose) was removed in 0.2: the Manhattan fit is the only search (on held-out street "
           "photos its horizon was the more accurate; docs/changelog.md); families=auto (--families auto) lets every "
           "horizontal direction vote for the horizon; drop the setting",
    "horizon": "horizon (the horizon fit's settings) was removed in 0.2 with fit (--fit): drop the setting",
}


@dataclass(frozen=True)
class FamiliesConfig:
    """Extra horizontal families inside the likelihood (:func:`fr_torch.core.search.manhattan.fit_families`).

    After the Manhattan fit, up to ``max_extra`` horizontal families with vanishing points on the
    horizon join the mixture (the Manhattan components and the background scaled by one minus their
    weights); f, R, their azimuths and their weights are refined together.  Each photo keeps the
    count m in 0..``max_extra`` whose families, found on one half of its segments, best explain the
    other half (:func:`fr_torch.core.search.manhattan.held_out_gains`; no penalty constant).
    ``prior``: the weight of a candidate family in the Atlanta search that proposes them, and the
    start of their weights' EM fit.
    ``min_support``: a candidate family must explain this share of the total segment length;
    ``exclusion_deg``: candidates lie at least this far (degrees) from every family in the model;
    ``window_deg``: each extra azimuth is refined within this many degrees of its candidate, and
    pan within this many degrees of the Manhattan fit's (not wrapped: an extra family's azimuth is
    measured from ``R[:, 0]``).
    """

    max_extra: int = 2
    prior: float = 0.05
    min_support: float = 0.01
    exclusion_deg: float = 5.0
    window_deg: float = 10.0

    def __post_init__(self) -> None:
        if not (isinstance(self.max_extra, int) and 0 <= self.max_extra <= 4):
            raise FRInputError(f"families max_extra must be an integer in [0, 4], got {self.max_extra!r}")
        checks = {"prior": (1e-4, 0.2), "min_support": (0.0, 1.0),
                  "exclusion_deg": (0.0, 45.0), "window_deg": (0.1, 45.0)}
        for name, (low, high) in checks.items():
            value = getattr(self, name)
            if isinstance(value, bool) or not (isinstance(value, (int, float)) and math.isfinite(value)
                                               and low <= value <= high):
                raise FRInputError(f"families {name} must be a number in [{low:g}, {high:g}], got {value!r}")

    @classmethod
    def parse(cls, value) -> "FamiliesConfig | None":
        """None / ``"off"`` / ``"0"`` -> None (the Manhattan mixture alone, the default); ``"auto"`` ->
        the defaults; ``"auto:max_extra=1:prior=0.1"`` or ``"max_extra=1"`` (``:``- or ``;``-separated
        ``key=value``) -> the defaults with those overrides; a dict of fields or a
        :class:`FamiliesConfig` as is.  FRInputError (one line) otherwise."""
        if value is None or isinstance(value, cls):
            return value
        if isinstance(value, dict):
            unknown = sorted(set(value) - {f.name for f in fields(cls)})
            if unknown:
                raise FRInputError(f"families: unknown setting(s) {', '.join(unknown)}")
            return cls(**value)
        text = str(value).strip()
        if text.lower() in ("off", "0", "none", "false", "no", ""):
            return None
        return replace(cls(), **overrides_from_text(cls, text, "families", "auto", skip=("auto", "on")))


@dataclass(frozen=True)
class SearchConfig:
    """Search settings; angles in degrees.

    ``fov_range``: the :class:`~fr_torch.core.settings.fov.FovRange` searched (FOV across the image's long
    side; default [30, 120]); a name, ``"MIN,MAX"`` or a pair is parsed on construction.
    ``pan_range_deg`` / ``pitch_range_deg`` / ``roll_range_deg``: the angle boxes of the grid and the
    refinement (default [-45, 45], [-35, 35], [-15, 15]; pitch and roll within [-89, 89];
    :meth:`with_angle_range`).  A pan box of exactly 90 deg wraps (:attr:`periodic_pan`); a pitch
    or roll estimate at its box's edge is flagged unreliable (:func:`fr_torch.core.reliability.sanity.check_result`).
    ``grid_points_per_dim``: k of the stage-1 k^4 grid.  ``top_l``: grid points refined.
    ``focal_grid``: spacing of the stage-1 focal values: ``linear_f`` (the paper / MATLAB release),
    ``log_f`` (uniform in log f) or ``fov`` (uniform in FOV).
    ``focal_sweep_points``: focal values of :func:`fr_torch.core.search.passes.sweep_focal` (each ``top_l``
    start tried at this many focal lengths over the whole range with its vertical VP fixed, the
    best added as a second start; 0 = off).
    ``grid_passes``: coarse-to-fine passes around each start before refinement
    (:func:`fr_torch.core.search.passes.subdivide_starts`); each scores 3^4 = 81 points per start.
    0 = the paper's two stages.
    ``grid_coarse_factor``: s; 1 = the whole k^4 grid; None (the default) = 2 where 2 divides k, else
    1 (resolved on construction).  With s > 1 stage 1 is coarse to fine (:func:`fr_torch.core.search.grid.coarse_to_fine_scores`; k must be a multiple of s): it
    scores the (k/s)^4 grid of cells s times as large, keeps each image's ``grid_coarse_cells``
    (default 32) best of them and scores only the k^4 grid's points inside those (s^4 per cell), so
    ``(k/s)^4 + grid_coarse_cells * s^4`` hypotheses instead of k^4 (768 instead of 4,096); the
    starts are the best of those points.  Only the Manhattan search's stage 1 with the focal length
    unknown (a known focal length's k^3 grid, the lens fit, the shared-focal search and the cues'
    known-focal grids score their whole grids).
    ``results/grid/coarse_to_fine.md`` measures it.
    ``refine_iterations``: refinement steps; ``max_segments``: each image keeps at most this many
    of its longest segments (bounds the time per image whatever the photo); ``grid_segments``:
    stage 1 scores only each image's longest this many (0 = all; the later stages use all).  None =
    the mode's preset (:data:`MODE_PRESETS`, filled by :meth:`resolve`).
    ``refine_tolerance``: refinement stops once no hypothesis' normalised objective (per unit
    segment length) changed by more than this over ``refine_patience`` steps; 0 = always the full
    count.
    ``max_chunk_elements``: on a GPU, at most this many per-segment deviations are scored and
    refined at once (about 7 bytes each in the eager grid; 2^27 is under 1 GB).  On a CPU the
    chunks are cache-sized (:mod:`fr_torch.core.search.passes`) and this only caps them.  Results do not
    depend on it.
    ``distortion``: the lens model (:class:`~fr_torch.core.settings.distortion.DistortionSetting`; a mode
    name or a dict is parsed on construction): pinhole (the default) or the division model's k
    estimated jointly with f and R (:mod:`fr_torch.core.search.lens`).
    ``distortion_grid_k``: the values of k stage 1 scores besides (``distortion_plumb_line``) the
    k that straightens pieces of lines (:func:`fr_torch.core.search.lens.plumb_line`); a known
    k replaces them all; ``distortion_grid_size``: the k of the k^4 angle-and-focal grid at each
    (0 = ``grid_points_per_dim``); ``distortion_lattice``: the lattice passes step k on its own axis
    (``axis``: the 3^4 lattice at the start's k, and k one step either side) or with the other
    parameters (``joint``, the 3^5 lattice); ``distortion_k_spacing``: the k spacing the passes
    start from (their first k step is a third of it).
    ``results/decisions/46.md`` says how they were chosen.
    ``families``: extra horizontal families inside the likelihood after the Manhattan fit
    (:class:`FamiliesConfig`; ``"auto"``, a dict or key=value text is parsed on construction;
    None = off, the default): f and R are then refitted with them (pinhole search only).

    Invalid values raise :class:`~fr_torch.errors.FRInputError` (one line).
    """

    grid_points_per_dim: int = 8
    pan_range_deg: tuple[float, float] = (-45.0, 45.0)
    pitch_range_deg: tuple[float, float] = (-35.0, 35.0)
    roll_range_deg: tuple[float, float] = (-15.0, 15.0)
    fov_range: FovRange = FovRange(*FovRange.NAMED["default"])
    focal_grid: str = "log_f"
    top_l: int = 4
    focal_sweep_points: int = 16
    grid_passes: int = 3
    grid_coarse_factor: int | None = None
    grid_coarse_cells: int = 32
    refine_iterations: int | None = None
    max_segments: int | None = None
    grid_segments: int | None = None
    refine_tolerance: float = 0.0
    refine_patience: int = 10
    max_chunk_elements: int = 1 << 27
    distortion: DistortionSetting = DistortionSetting()
    distortion_grid_k: tuple[float, ...] = (-0.4, 0.0)
    distortion_grid_size: int = 6
    distortion_plumb_line: bool = True
    distortion_lattice: str = "axis"
    distortion_k_spacing: float = 0.4
    families: FamiliesConfig | None = None

    def __post_init__(self):
        object.__setattr__(self, "fov_range", FovRange.parse(self.fov_range))
        object.__setattr__(self, "families", FamiliesConfig.parse(self.families))
        object.__setattr__(self, "distortion", DistortionSetting.parse(self.distortion))
        object.__setattr__(self, "distortion_grid_k", tuple(float(k) for k in self.distortion_grid_k))
        if not (self.distortion_grid_k or self.distortion_plumb_line) or self.distortion_grid_size < 0 \
                or not all(-1.0 < k < 1.0 for k in self.distortion_grid_k) \
                or not (math.isfinite(self.distortion_k_spacing) and self.distortion_k_spacing >= 0):
            raise FRInputError("distortion_grid_k must hold values in (-1, 1) (or distortion_plumb_line be on), "
                               "distortion_grid_size and distortion_k_spacing must be >= 0")
        if self.distortion_lattice not in ("joint", "axis"):
            raise FRInputError(f"distortion_lattice must be joint or axis, got {self.distortion_lattice!r}")
        for key in ("pan_range_deg", "pitch_range_deg", "roll_range_deg"):
            low, high = getattr(self, key)
            if not (math.isfinite(low) and math.isfinite(high) and low <= high):
                raise FRInputError(f"{key} must be finite (min, max) with min <= max, got {low}, {high}")
            object.__setattr__(self, key, (float(low), float(high)))
        for key in ("pitch_range_deg", "roll_range_deg"):  # +-90 deg: the vertical VP swaps families
            low, high = getattr(self, key)
            if not (-89.0 <= low and high <= 89.0):
                raise FRInputError(f"{key} must lie within [-89, 89] degrees, got {low:g}, {high:g}")
        if self.grid_points_per_dim < 1 or self.top_l < 1:
            raise FRInputError("grid_points_per_dim and top_l must be at least 1")
        if self.grid_passes < 0:
            raise FRInputError(f"grid_passes must be >= 0, got {self.grid_passes}")
        if self.grid_coarse_factor is None:
            object.__setattr__(self, "grid_coarse_factor", 2 if self.grid_points_per_dim % 2 == 0 else 1)
        if self.grid_coarse_factor < 1 or self.grid_coarse_cells < 1:
            raise FRInputError("grid_coarse_factor and grid_coarse_cells must be >= 1, got "
                               f"{self.grid_coarse_factor}, {self.grid_coarse_cells}")
        if self.grid_points_per_dim % self.grid_coarse_factor:
            raise FRInputError(f"grid_coarse_factor {self.grid_coarse_factor} must divide grid_points_per_dim "
                               f"{self.grid_points_per_dim}")
        if self.focal_sweep_points < 0:
            raise FRInputError(f"focal_sweep_points must be >= 0 (0 = off), got {self.focal_sweep_points}")
        minimum = {"refine_iterations": 0, "max_segments": 1, "grid_segments": 0}
        for key, low in minimum.items():
            value = getattr(self, key)
            if value is not None and value < low:
                raise FRInputError(f"{key} must be >= {low}, got {value}")
        if self.focal_grid not in FOCAL_GRIDS:
            raise FRInputError(f"focal_grid must be one of {', '.join(FOCAL_GRIDS)}, got {self.focal_grid!r}")

    @property
    def periodic_pan(self) -> bool:
        """True when the pan range spans exactly one period of a Manhattan frame (90 deg, the
        default [-45, 45]): pan is then an angle on a circle, and the sweep, the lattice passes and
        the refinement wrap it around (-45 and +45 are the same camera with its two horizontal
        families swapped, which score the same) instead of pinning it at the box's edge."""
        low, high = self.pan_range_deg
        return abs((high - low) - 90.0) < 1e-9

    @classmethod
    def from_config(cls, path: str | Path | None = None, **overrides) -> "SearchConfig":
        """Defaults, then the JSON overrides of ``path`` (default ``configs/search.json``), then
        ``overrides``.  Unknown keys are an FRInputError naming them."""
        path = Path(path) if path is not None else config_path("search.json")
        try:
            values = json.loads(path.read_text()) if path.exists() else {}
        except (OSError, UnicodeDecodeError, ValueError) as exc:
            raise FRInputError(f"search config {path}: not a readable JSON file ({exc})") from None
        if not isinstance(values, dict):
            raise FRInputError(f"search config {path}: expected a JSON object of overrides")
        values = {k: tuple(v) if isinstance(v, list) else v for k, v in values.items()}
        values.update(overrides)
        for name in values:
            if name in REMOVED_SETTINGS:
                raise FRInputError(REMOVED_SETTINGS[name])
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(values) - known)
        if unknown:
            raise FRInputError(f"search config: unknown setting(s) {', '.join(unknown)}")
        return cls(**values)

    def resolve(self, mode: Mode | str) -> "SearchConfig":
        """This configuration with every mode-dependent field left None filled from ``mode``'s
        preset (:data:`MODE_PRESETS`)."""
        preset = MODE_PRESETS[Mode.parse(mode)]
        return replace(self, **{k: v for k, v in preset.items() if getattr(self, k) is None})

    def with_angle_range(self, name: str, value) -> "SearchConfig":
        """A copy with the ``name`` (``pitch`` or ``roll``) search range from ``"MIN,MAX"`` or a
        (min, max) pair (degrees, within [-89, 89]); FRInputError (one line) when malformed."""
        if name not in ("pitch", "roll"):
            raise FRInputError(f"angle range name must be 'pitch' or 'roll', got {name!r}")
        parts = value.split(",") if isinstance(value, str) else list(value)
        low, high = two_numbers(parts, f"{name} range must be MIN,MAX in degrees, got {value!r}")
        if not (math.isfinite(low) and math.isfinite(high) and low < high):
            raise FRInputError(f"{name} range must be finite MIN,MAX with MIN < MAX, got {value!r}")
        return replace(self, **{f"{name}_range_deg": (low, high)})

    def with_distortion(self, mode=None, known_k: float | None = None) -> "SearchConfig":
        """A copy with the lens model ``mode`` (``pinhole``, ``division``, ``auto``; None keeps the
        current one) and, when given, a known k (normalised: :mod:`fr_torch.core.geometry.lens`)."""
        current = self.distortion
        setting = replace(current, mode=current.mode if mode is None else mode,
                          known_k=current.known_k if known_k is None else known_k)
        return replace(self, distortion=setting)

    def with_families(self, value) -> "SearchConfig":
        """A copy with the extra-families setting ``value`` (anything :meth:`FamiliesConfig.parse` takes)."""
        return replace(self, families=FamiliesConfig.parse(value))

    def with_fov_range(self, value) -> "SearchConfig":
        """A copy searching the FOV range ``value`` (anything :meth:`FovRange.parse` accepts)."""
        return replace(self, fov_range=FovRange.parse(value))
