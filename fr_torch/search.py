"""Two-stage search for (f, R): a k^4 grid, then batched refinement of the best l grid points.

Stage 1 scores every grid hypothesis (pan x pitch x roll x focal, k values each, cell centres
of the ranges; focal spaced uniformly in log f between f(hfov_max) and f(hfov_min) by default) as
one batched tensor computation, chunked so that at most ``max_chunk_elements`` per-segment
deviations exist at once.  Each of the best ``top_l`` grid points gains a second start, its best
point along its focal ridge (:func:`sweep_focal`: the vertical VP, the best-determined, held
fixed while f runs over the whole range); all 2l starts are then sharpened by ``grid_passes``
coarse-to-fine passes (:func:`subdivide_starts`: a 3^4 lattice at a third of the previous spacing
around each, keep the best), so refinement starts within 1/27 of a grid cell of the best lattice
point instead of half a cell.  Stage 2 refines these starts of every image together
with ``torch.optim`` (Adam on box-normalised parameters, projected back into the box after every
step), focal length included (the MATLAB release pins f to its grid value; we refine it
continuously, as the paper does).  ``fr`` mode runs ``refine_iterations_fr`` steps with a decaying step size, ``fast`` mode
``refine_iterations_fast`` (10).  Each hypothesis' update depends only on its own gradient, so a
batch gives the same answer as images one by one.

Speed and memory (same math; see also :mod:`fr_torch.likelihood`):

* Grid: on CPU the hypotheses are scored in cache-sized chunks (``CPU_CHUNK_ELEMENTS`` deviations
  per intra-op thread, a few MB of buffers per thread) that reuse the same buffers, instead of ``max_chunk_elements`` (which
  still bounds the chunk on GPU and caps it on CPU); rotations / vanishing points are built once
  per image slice, not per chunk.  Large batches are cut into image slices, so memory stays
  bounded for any batch size.
* Refinement: images are refined in independent slices of at most ``max_chunk_elements``
  (``CPU_REFINE_ELEMENTS`` on CPU) deviations per step (identical results: every image's loss and
  Adam update are its own), and the rotation is built in closed form
  (``R.T = Ry(pan) Rx(pitch) Rz(roll)``, equal to :func:`fr_torch.camera.rotation_from_angles`
  to rounding) with fewer, smaller autograd nodes.
  The iteration counts and step-size schedule are unchanged.
"""
from __future__ import annotations

import json
import math
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import torch
from torch.optim.adam import adam as adam_update  # torch.optim's functional Adam (see _FusedAdam)

from .camera import VERTICAL_AXIS, focal_from_hfov, hfov_from_focal, pan_from_rotation, rotation_from_angles
from .likelihood import (CONFIG_DIR, MixtureLikelihood, SegmentFeatures, compiled_call, measure_b_backward,
                         measure_b_forward, vp_major)
from .segments import FRInputError

PARAMS = ("pan_deg", "pitch_deg", "roll_deg", "focal_px")
# Grid deviations per chunk and intra-op thread on CPU: float32 buffers of a few MB.  Fewer, larger
# chunks mean less per-op overhead: on an AMD EPYC 2^17 was 12 % slower than 2^18; on an Intel Xeon
# (2 MB L2 per core) 2^19 took Fast-fR's search at batch 1 from 37.7 to 34.0 ms (fR 112 -> 108 ms),
# 2^20 gained no more.  Scores are the same for any chunk size.
CPU_CHUNK_ELEMENTS = 1 << 19
CPU_REFINE_ELEMENTS = 1 << 20  # deviations per refinement slice on CPU (~25 live tensors of 4 MB)


#: Named FOV search ranges (degrees, FOV across the image's long side).  ``default`` covers the
#: cameras users have (phones, action cameras, webcams, DSLR kit zooms); ``paper`` is Qian & Elder's
#: [50, 130] (the like-for-like row with the paper; YUD's 50.7 deg sits at its lower edge).
NAMED_FOV_RANGES: dict[str, tuple[float, float]] = {"default": (30.0, 120.0), "paper": (50.0, 130.0)}
FOV_LIMITS_DEG = (1.0, 179.0)
EDGE_REASON = "focal at the edge of the search range"
NON_FINITE_REASON = "non-finite estimate (NaN/inf in the parameters, objective or outputs)"
FOCAL_GRIDS = ("linear_f", "log_f", "fov")


def angle_edge_reason(name: str, low: float, high: float) -> str:
    """The reason given for a ``name`` angle (pan, pitch or roll) found at the edge of its search
    box [``low``, ``high``] (degrees): the camera may lie outside it."""
    return f"{name} at the edge of the search range [{low:g}, {high:g}] deg (the camera may lie outside it)"


def parse_fov_range(text) -> tuple[float, float]:
    """A FOV search range from a name (``default``, ``paper``), ``"MIN,MAX"`` or a pair (degrees).

    Raises :class:`~fr_torch.segments.FRInputError` (one line) for anything else; the range itself is
    validated by :class:`SearchConfig`.
    """
    if isinstance(text, str):
        key = text.strip().lower()
        if key in NAMED_FOV_RANGES:
            return NAMED_FOV_RANGES[key]
        parts = key.replace(":", ",").split(",")
    else:
        parts = list(text)
    return _two_numbers(parts, f"FOV range must be MIN,MAX in degrees or one of {', '.join(NAMED_FOV_RANGES)}, "
                               f"got {text!r}")


def _two_numbers(parts, message: str) -> tuple[float, float]:
    """``parts`` (two items) as floats; FRInputError(``message``) when they are not two numbers."""
    try:
        low, high = (float(v) for v in parts)
    except (TypeError, ValueError):
        raise FRInputError(message) from None
    return low, high


def check_fov_range(low, high, name: str = "FOV search range") -> tuple[float, float]:
    """(low, high) as floats if finite and ``1 <= low < high <= 179`` degrees, else FRInputError."""
    try:
        low, high = float(low), float(high)
    except (TypeError, ValueError):
        raise FRInputError(f"{name} must be two numbers in degrees, got {low!r}, {high!r}") from None
    lo_lim, hi_lim = FOV_LIMITS_DEG
    if not (math.isfinite(low) and math.isfinite(high) and lo_lim <= low < high <= hi_lim):
        raise FRInputError(f"{name} must be finite with {lo_lim:g} <= min < max <= {hi_lim:g} deg, "
                           f"got {low:g}, {high:g}")
    return low, high


def search_fov_range(value=None) -> tuple[float, float]:
    """A validated FOV range (degrees, long side): None -> the library default (``configs/search.json``),
    else a name, ``"MIN,MAX"`` / ``"MIN:MAX"`` or a pair (:func:`parse_fov_range`).  Used by every
    method that searches the focal length, so one range means the same thing for all of them."""
    if value is None:
        return SearchConfig.from_config().hfov_range_deg
    return check_fov_range(*parse_fov_range(value))


@dataclass(frozen=True)
class SearchConfig:
    """Search settings (angles in degrees); ``configs/search.json`` holds the defaults.

    ``hfov_range_deg``: search range of the field of view **across the image's long side** (for a
    landscape image that is the horizontal FOV; a portrait image gets the same focal range in
    pixels as the same camera held in landscape).  Results still report ``hfov_deg``, the
    horizontal FOV.  Validated here (the one place): finite, 1 <= min < max <= 179.
    ``pan_range_deg`` / ``pitch_range_deg`` / ``roll_range_deg``: the angle boxes of the grid and the
    refinement (default [-45, 45], [-35, 35], [-15, 15]; pitch and roll within [-89, 89];
    :meth:`with_angle_range`).  A pan box of exactly 90 deg wraps (:attr:`periodic_pan`); a pitch
    or roll estimate at its box's edge is flagged unreliable (:func:`check_result`).
    ``focal_grid``: spacing of the stage-1 focal values: ``linear_f`` (the paper / MATLAB release),
    ``log_f`` (uniform in log f) or ``fov`` (uniform in FOV).
    ``grid_segments`` (``fr`` mode) / ``grid_segments_fast`` (``fast`` mode): stage 1 scores only
    the longest this many segments of each image (0 = all, the default for both); the focal
    sweep, the passes, refinement and the final labels use all of them.  A speed option that
    costs search quality: with 250 of the at most 500 kept segments, Fast-fR's final objective
    was lower than with all of them on 9 of the 51 YUD train images (and measure d's focal error
    doubled), so it is off by default (results/yud/README.md).
    ``focal_sweep_points``: focal values of :func:`sweep_focal` (each ``top_l`` start tried at this
    many focal lengths over the whole range with its vertical VP fixed, the best added as a
    second start, so 2 ``top_l`` starts are sharpened and refined; 0 = off).
    ``grid_passes``: coarse-to-fine passes around each start before refinement
    (:func:`subdivide_starts`); each scores 3^4 = 81 points per start (about 16 % of the 8^4 grid
    for the 2 x 4 starts of l = 4 with the sweep).  0 = the paper's two stages.
    ``max_segments_fr`` / ``max_segments_fast``: each image keeps at most this many of its longest
    segments (the estimator's :class:`~fr_torch.segments.SegmentFilter`), which bounds the time per
    image whatever the photo.  fR keeps 750: on YUD train (51 busy photos, 460 to 1800 LSD segments
    at 640 x 480) fR's focal MAE / median fall from 4.87 / 2.74 % with 500 to 4.32 / 2.21 % (1000:
    4.30 / 2.21, 1500: 4.28 / 2.09, all: 4.29 / 2.09), ZInD-fR train and the YUD train crops are
    unchanged (6.85 / 6.85 %, 12.09 / 12.03 % at 1000); of the counts that tie, 750 costs least (a
    batch pads every image to the cap: with 1000, 306 photos took fR 21.6 s instead of 11.9 s).
    Fast-fR keeps 500: with 1000 its MAE is the same (5.23 / 5.29 %) and its time would pass 50 ms.
    ``compile_search``: score the no-gradient hypotheses (grid, focal sweep, passes, cue lattice)
    with one kernel fused by ``torch.compile`` and compile the refinement step too
    (:mod:`fr_torch.likelihood`, "Compiled search"; ``--compile``).  The same estimates to float
    rounding; a compilation per process (10-25 s on a 2-core CPU), then faster: for long batch jobs and
    video, not for one photo.  Off by default.
    ``max_chunk_elements``: on a GPU, at most this many per-segment deviations are scored at once
    (grid, sweep, passes, cue lattice) and refined at once; about 7 bytes each in the eager grid
    (2^27: under 1 GB).  Larger chunks mean fewer kernel launches: with 2^24 a batch of 1024
    images took the H100 about 27,000 launches for Fast-fR and kept it about 20 % busy (issue 14).
    On a CPU the chunks are cache-sized (``CPU_CHUNK_ELEMENTS``, ``CPU_REFINE_ELEMENTS``) and this
    only caps them.  Results do not depend on it.
    ``refine_tolerance``: fR refinement stops once no hypothesis' normalised objective (per unit
    segment length) changed by more than this over ``refine_patience`` steps, or after
    ``refine_iterations_fr`` steps; 0 = always the full count.
    """

    grid_points_per_dim: int = 8
    pan_range_deg: tuple[float, float] = (-45.0, 45.0)
    pitch_range_deg: tuple[float, float] = (-35.0, 35.0)
    roll_range_deg: tuple[float, float] = (-15.0, 15.0)
    hfov_range_deg: tuple[float, float] = NAMED_FOV_RANGES["default"]
    focal_grid: str = "log_f"
    top_l: int = 4
    grid_segments: int = 0
    grid_segments_fast: int = 0
    max_segments_fr: int = 750
    max_segments_fast: int = 500
    focal_sweep_points: int = 16
    grid_passes: int = 3
    refine_iterations_fr: int = 100
    refine_iterations_fast: int = 10
    refine_tolerance: float = 0.0
    refine_patience: int = 10
    max_chunk_elements: int = 1 << 27
    compile_search: bool = False

    def __post_init__(self):
        object.__setattr__(self, "hfov_range_deg", check_fov_range(*self.hfov_range_deg))
        for key in ("pan_range_deg", "pitch_range_deg", "roll_range_deg"):
            low, high = getattr(self, key)
            if not (math.isfinite(low) and math.isfinite(high) and low <= high):
                raise FRInputError(f"{key} must be finite (min, max) with min <= max, got {low}, {high}")
        for key in ("pitch_range_deg", "roll_range_deg"):  # +-90 deg: the vertical VP swaps families
            low, high = getattr(self, key)
            if not (-89.0 <= low and high <= 89.0):
                raise FRInputError(f"{key} must lie within [-89, 89] degrees, got {low:g}, {high:g}")
        if self.grid_points_per_dim < 1 or self.top_l < 1:
            raise FRInputError("grid_points_per_dim and top_l must be at least 1")
        if self.grid_passes < 0:
            raise FRInputError(f"grid_passes must be >= 0, got {self.grid_passes}")
        if self.focal_sweep_points < 0:
            raise FRInputError(f"focal_sweep_points must be >= 0 (0 = off), got {self.focal_sweep_points}")
        for key in ("grid_segments", "grid_segments_fast"):
            if getattr(self, key) < 0:
                raise FRInputError(f"{key} must be >= 0 (0 = all), got {getattr(self, key)}")
        for key in ("max_segments_fr", "max_segments_fast"):
            if getattr(self, key) < 1:
                raise FRInputError(f"{key} must be >= 1, got {getattr(self, key)}")
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
        path = Path(path) if path is not None else CONFIG_DIR / "search.json"
        values = json.loads(path.read_text()) if path.exists() else {}
        values = {k: tuple(v) if isinstance(v, list) else v for k, v in values.items()}
        return replace(cls(**values), **overrides)

    def with_angle_range(self, name: str, value) -> "SearchConfig":
        """A copy with the ``name`` (``pitch`` or ``roll``) search range from ``"MIN,MAX"`` or a
        (min, max) pair (degrees, within [-89, 89]); FRInputError (one line) when malformed."""
        if name not in ("pitch", "roll"):
            raise FRInputError(f"angle range name must be 'pitch' or 'roll', got {name!r}")
        parts = value.split(",") if isinstance(value, str) else list(value)
        low, high = _two_numbers(parts, f"{name} range must be MIN,MAX in degrees, got {value!r}")
        if not (math.isfinite(low) and math.isfinite(high) and low < high):
            raise FRInputError(f"{name} range must be finite MIN,MAX with MIN < MAX, got {value!r}")
        return replace(self, **{f"{name}_range_deg": (low, high)})

    def with_fov_range(self, value) -> "SearchConfig":
        """A copy with the FOV range from a name, ``"MIN,MAX"`` or a pair (see :func:`parse_fov_range`)."""
        return replace(self, hfov_range_deg=parse_fov_range(value))

    @staticmethod
    def _for_mode(mode: str, fr_value: int, fast_value: int) -> int:
        """``fr_value`` for mode ``fr``, ``fast_value`` for ``fast``; ValueError for any other mode."""
        if mode not in ("fr", "fast"):
            raise ValueError(f"mode must be 'fr' or 'fast', got {mode!r}")
        return fr_value if mode == "fr" else fast_value

    def iterations(self, mode: str) -> int:
        """Refinement steps of ``mode``."""
        return self._for_mode(mode, self.refine_iterations_fr, self.refine_iterations_fast)

    def max_segments(self, mode: str) -> int:
        """How many of each image's longest segments ``mode`` keeps (its segment filter's cap)."""
        return self._for_mode(mode, self.max_segments_fr, self.max_segments_fast)

    def grid_segment_count(self, mode: str) -> int:
        """How many of each image's longest segments stage 1 scores in ``mode`` (0 = all)."""
        return self._for_mode(mode, self.grid_segments, self.grid_segments_fast)


def _cell_centres(low: float, high: float, k: int) -> torch.Tensor:
    return low + (torch.arange(k, dtype=torch.float64) + 0.5) * (high - low) / k


def focal_bounds(config: SearchConfig, long_side: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(f_min, f_max) in pixels per image from its long side (B,) in pixels: f(fov_max), f(fov_min)."""
    long_side = long_side.to(torch.float64)
    return focal_from_hfov(torch.tensor(config.hfov_range_deg[1], dtype=torch.float64), long_side), \
        focal_from_hfov(torch.tensor(config.hfov_range_deg[0], dtype=torch.float64), long_side)


def parameter_box(config: SearchConfig, long_side: torch.Tensor, known_focal: torch.Tensor | None):
    """Lower and upper bounds, (B, 4) float64, of [pan, pitch, roll, focal] per image.

    ``long_side``: (B,) the longer image side in pixels (``max(width, height)``).
    """
    f_lo, f_hi = focal_bounds(config, long_side)
    if known_focal is not None:
        f_lo = f_hi = known_focal.to(torch.float64)
    lo = torch.stack([torch.full_like(f_lo, config.pan_range_deg[0]), torch.full_like(f_lo, config.pitch_range_deg[0]),
                      torch.full_like(f_lo, config.roll_range_deg[0]), f_lo], -1)
    hi = torch.stack([torch.full_like(f_hi, config.pan_range_deg[1]), torch.full_like(f_hi, config.pitch_range_deg[1]),
                      torch.full_like(f_hi, config.roll_range_deg[1]), f_hi], -1)
    return lo, hi


def into_box(points: torch.Tensor, lower: torch.Tensor, upper: torch.Tensor, periodic_pan: bool) -> torch.Tensor:
    """``points`` (..., 4) [pan, pitch, roll, f or log f] moved into the box [``lower``, ``upper``]
    (broadcastable to ``points``): clamped, but for pan when ``periodic_pan``
    (:attr:`SearchConfig.periodic_pan`), which is wrapped into [lower, upper) instead."""
    boxed = torch.minimum(torch.maximum(points, lower), upper)
    if not periodic_pan:
        return boxed
    pan_low, pan_span = lower[..., :1], (upper - lower)[..., :1]
    return torch.cat([pan_low + torch.remainder(points[..., :1] - pan_low, pan_span), boxed[..., 1:]], -1)


def _log_spaced_focals(f_lo: torch.Tensor, f_hi: torch.Tensor, count: int) -> torch.Tensor:
    """``count`` focal lengths per image, (B, count) float64 pixels, at the centres of ``count``
    equal cells in log f between ``f_lo`` and ``f_hi`` ((B,) float64 pixels)."""
    fraction = (torch.arange(count, dtype=torch.float64, device=f_lo.device) + 0.5) / count
    return torch.exp(f_lo.log()[:, None] + fraction * (f_hi / f_lo).log()[:, None])


def focal_grid(config: SearchConfig, long_side: torch.Tensor) -> torch.Tensor:
    """The k stage-1 focal values per image, (B, k) float64 pixels, at cell centres of the range,
    spaced per ``config.focal_grid`` (linear in f, in log f, or in FOV)."""
    k = config.grid_points_per_dim
    frac = (torch.arange(k, dtype=torch.float64, device=long_side.device) + 0.5) / k
    long_side = long_side.to(torch.float64)
    if config.focal_grid == "fov":
        lo, hi = config.hfov_range_deg
        fov = torch.tensor(hi, dtype=torch.float64) - frac * (hi - lo)  # wide -> narrow: f ascending
        return focal_from_hfov(fov[None, :], long_side[:, None])
    f_lo, f_hi = focal_bounds(config, long_side)
    if config.focal_grid == "log_f":
        return _log_spaced_focals(f_lo, f_hi, k)
    return f_lo[:, None] + frac * (f_hi - f_lo)[:, None]


def grid_hypotheses(config: SearchConfig, long_side: torch.Tensor, known_focal: torch.Tensor | None = None):
    """Grid of [pan, pitch, roll, focal] per image: (B, G, 4) float64, G = k^4 (k^3 with known f),
    on the device of ``known_focal`` if given, else of ``long_side``.

    ``long_side``: (B,) the longer image side in pixels.  Order: focal slowest, then pitch, roll,
    pan fastest -- runs of k hypotheses differing only in pan share the vertical VP (pan turns the
    camera about the vertical), which :func:`score_grid` scores once per run (``vertical_block``).
    """
    k = config.grid_points_per_dim
    if known_focal is not None:
        focal = known_focal.to(torch.float64)[:, None]
    else:
        focal = focal_grid(config, long_side)
    pan = _cell_centres(*config.pan_range_deg, k)
    pitch = _cell_centres(*config.pitch_range_deg, k)
    roll = _cell_centres(*config.roll_range_deg, k)
    # (k^3, 3) as [pan, pitch, roll], on the device of the inputs (a GPU batch's grid is built there:
    # 128 KB per image, 0.5 GB for 4096 images, is not worth a host->device copy)
    angles = torch.cartesian_prod(pitch, roll, pan)[:, [2, 0, 1]].to(focal.device)
    batch, n_focal = focal.shape
    hyp = torch.cat([angles.expand(batch, n_focal, -1, -1),
                     focal[:, :, None, None].expand(-1, -1, angles.shape[0], 1)], -1)
    return hyp.reshape(batch, -1, 4)


def select_starts(config: SearchConfig, grid_scores: torch.Tensor, hypotheses: torch.Tensor):
    """Stage-2 starting points: the ``top_l`` best grid points, best first.

    ``grid_scores`` (B, G) and ``hypotheses`` (B, G, 4) as from :func:`grid_hypotheses`.
    Returns (starts (B, L, 4), their scores (B, L)), L = min(top_l, G).
    """
    scores, index = grid_scores.topk(min(config.top_l, grid_scores.shape[1]), dim=1)
    return torch.gather(hypotheses, 1, index[..., None].expand(-1, -1, 4)), scores


def grid_cell(config: SearchConfig, lower: torch.Tensor, upper: torch.Tensor) -> torch.Tensor:
    """Size of one stage-1 grid cell per image, (B, 4) float64: [pan, pitch, roll] in degrees and
    the focal step in log f (``log(f_max / f_min) / k``, the log-f grid's spacing; 0 for a known
    focal).  ``lower``, ``upper``: (B, 4) from :func:`parameter_box`."""
    k = config.grid_points_per_dim
    angles = (upper[:, :3] - lower[:, :3]) / k
    log_focal = (upper[:, 3:].log() - lower[:, 3:].log()) / k
    return torch.cat([angles, log_focal], -1)


def angles_from_search_rotation(rotation: torch.Tensor) -> torch.Tensor:
    """[pan, pitch, roll] in degrees, (..., 3), from world->camera R (..., 3, 3): the inverse of
    :func:`fast_rotations` (``R.T = Ry(pan) Rx(pitch) Rz(roll)``) for |pitch| < 90 deg, pan folded
    into [-45, 45) (:func:`fr_torch.camera.pan_from_rotation`; the Manhattan frame is symmetric
    under quarter turns about the vertical)."""
    pitch = torch.rad2deg(torch.asin((-rotation[..., 2, 1]).clamp(-1.0, 1.0)))
    roll = torch.rad2deg(torch.atan2(rotation[..., 0, 1], rotation[..., 1, 1]))
    return torch.stack([pan_from_rotation(rotation), pitch, roll], -1)


def _focal_ridge_rotations(rotation: torch.Tensor, ratio: torch.Tensor) -> torch.Tensor:
    """Rotations that keep the vertical VP's image position when f is multiplied by ``ratio``.

    ``rotation`` (..., 3, 3) world->camera (column i = world axis i in camera coordinates),
    ``ratio`` (..., m) = f_new / f.  A VP at pp + f (d_x, d_y) / d_z stays put when d_z scales
    with the ratio (a VP at infinity, d_z = 0, stays put by itself).  The vertical column is
    rescaled that way; the horizontal column whose VP lies nearer the image centre (larger |d_z|)
    is rescaled too and made orthogonal to the vertical (it moves as little as the orthogonality
    of the VPs allows); the third column completes a right-handed frame.  Returns (..., m, 3, 3).
    """
    def rescaled(direction):  # (..., 3) -> (..., m, 3), unit length
        d = direction[..., None, :].expand(ratio.shape + (3,))
        d = torch.cat([d[..., :2], d[..., 2:] * ratio[..., None]], -1)
        return d / d.norm(dim=-1, keepdim=True)

    first_nearer = rotation[..., 2, 0].abs() >= rotation[..., 2, 2].abs()  # (...)
    horizontal = torch.where(first_nearer[..., None], rotation[..., :, 0], rotation[..., :, 2])
    vertical = rescaled(rotation[..., :, VERTICAL_AXIS])
    horizontal = rescaled(horizontal)
    horizontal = horizontal - (horizontal * vertical).sum(-1, keepdim=True) * vertical
    horizontal = horizontal / horizontal.norm(dim=-1, keepdim=True)
    first_nearer = first_nearer[..., None, None]
    column0 = torch.where(first_nearer, horizontal, torch.cross(vertical, horizontal, dim=-1))
    column2 = torch.where(first_nearer, torch.cross(horizontal, vertical, dim=-1), horizontal)
    return torch.stack([column0, vertical, column2], -1)


def sweep_focal(likelihood: MixtureLikelihood, features: SegmentFeatures, starts: torch.Tensor,
                scores: torch.Tensor, config: SearchConfig, lower: torch.Tensor, upper: torch.Tensor):
    """Add to each start its best point along its focal ridge: the best of
    ``config.focal_sweep_points`` focal values with the vertical VP held fixed.

    Focal length and pitch trade off along a ridge of the objective: the vertical VP (the family
    with the most segments and the smallest deviations) is pinned down well, its distance from
    the principal point, f / tan(pitch), much less its f and pitch apart.  A k^4 grid samples that
    ridge coarsely, so all ``top_l`` starts can sit on the wrong part of it (a 120 deg view found
    at 90 deg with 12 deg more pitch).  For every start this scores m focal values spaced
    uniformly in log f over the whole range, each with the start's vertical VP held fixed and
    its nearer horizontal VP moved as little as orthogonality allows
    (:func:`_focal_ridge_rotations`), at pan offsets 0 and +-1/3 of a grid cell.

    The swept points are added, not swapped in: a point that scores higher than its start can
    still lie in a lower basin, and replacing the start lost the better answer on 42 of 204
    ZInD-fR train views (fR); with both refined, 3 (results/yud/README.md).

    ``starts`` (B, L, 4) [pan, pitch, roll, f], ``scores`` (B, L), ``lower`` / ``upper`` (B, 4)
    the parameter box (points are moved into it by :func:`into_box`).  Returns (starts, scores) of shape (B, 2L, 4)
    and (B, 2L): the L inputs, then for each the best swept point if it beats the start's score,
    else a copy of the start.  Each start is swept on its own (a batch gives the same answer as
    images one by one).  A known focal (``lower`` f == ``upper`` f) or m = 0 returns the inputs.
    """
    count = config.focal_sweep_points
    if count == 0 or bool((upper[:, 3] <= lower[:, 3]).all()):
        return starts, scores
    device = features.weight.device
    batch, n_start = starts.shape[:2]
    start64 = starts.to(device=device, dtype=torch.float64)
    lower64 = lower.to(device=device, dtype=torch.float64)
    upper64 = upper.to(device=device, dtype=torch.float64)
    focal = _log_spaced_focals(lower64[:, 3], upper64[:, 3], count)[:, None, :].expand(batch, n_start, count)
    rotation = _focal_ridge_rotations(fast_rotations(start64), focal / start64[..., 3:])  # (B, L, m, 3, 3)
    angles = angles_from_search_rotation(rotation)  # (B, L, m, 3)
    pan_step = (upper64[:, 0] - lower64[:, 0]) / (3 * config.grid_points_per_dim)  # 1/3 of a grid cell
    pan_offsets = torch.stack([torch.zeros_like(pan_step), -pan_step, pan_step], -1)  # (B, 3)
    points = torch.cat([angles, focal[..., None]], -1)[:, :, :, None, :].repeat(1, 1, 1, 3, 1)
    points[..., 0] += pan_offsets[:, None, None, :]  # pan fastest: runs of 3 share the vertical VP
    points = into_box(points, lower64[:, None, None, None], upper64[:, None, None, None], config.periodic_pan)
    points = points.view(batch, n_start, -1, 4)
    point_scores = score_grid(likelihood, features, points.view(batch, -1, 4), config.max_chunk_elements,
                              vertical_block=3)
    swept, swept_scores = _keep_best(starts, scores, points, point_scores)
    return torch.cat([starts, swept], 1), torch.cat([scores, swept_scores], 1)


def _keep_best(starts: torch.Tensor, scores: torch.Tensor, points: torch.Tensor, point_scores: torch.Tensor):
    """Each start's best candidate where it scores higher than the start, else the start.

    ``starts`` (B, L, 4) with ``scores`` (B, L); ``points`` (B, L, P, 4) candidates per start with
    their ``point_scores`` (B, L * P) from :func:`score_grid`.  Returns (starts, scores), same shapes
    and dtypes as the inputs.
    """
    best_scores, best = point_scores.view(scores.shape + (-1,)).max(-1)
    better = best_scores > scores
    chosen = torch.gather(points, 2, best[..., None, None].expand(-1, -1, 1, points.shape[-1]))[:, :, 0]
    return torch.where(better[..., None], chosen.to(starts), starts), torch.where(better, best_scores, scores)


#: The 3^4 lattice offsets of a subdivision pass, [pan, pitch, roll, log f], pan varying fastest
#: (runs of 3 share the vertical VP: ``score_grid(..., vertical_block=3)``); the centre is included.
LATTICE = torch.cartesian_prod(*[torch.tensor([-1.0, 0.0, 1.0], dtype=torch.float64)] * 4)[:, [3, 1, 2, 0]]


def subdivide_starts(likelihood: MixtureLikelihood, features: SegmentFeatures, starts: torch.Tensor,
                     scores: torch.Tensor, config: SearchConfig, lower: torch.Tensor, upper: torch.Tensor):
    """Coarse-to-fine passes around the stage-1 starts: ``config.grid_passes`` times, score the
    3^4 lattice around each start (offsets -h, 0, +h per parameter; focal in log f) and move the
    start to the best point if it beats the start's score; h is a third of a grid cell in the
    first pass and a third of the previous h after that (the lattice subdivides the cell around
    the start).

    ``starts`` (B, L, 4) [pan, pitch, roll, f] and their ``scores`` (B, L); ``lower`` / ``upper``
    (B, 4) the parameter box (points are moved into it by :func:`into_box`; a known focal stays fixed).  Returns
    (starts, scores) of the same shapes; every score is >= its input score.  Each start moves on
    its own, so a batch gives the same answer as images one by one.
    """
    if config.grid_passes == 0:
        return starts, scores
    device = features.weight.device
    lower64, upper64 = lower.to(torch.float64), upper.to(torch.float64)
    log_lower = _log_focal(lower64)[:, None, None, :].to(device)
    log_upper = _log_focal(upper64)[:, None, None, :].to(device)
    step = grid_cell(config, lower64, upper64)[:, None, None, :].to(device)  # (B, 1, 1, 4)
    lattice = LATTICE.to(device)
    batch, n_start = starts.shape[:2]
    current = _log_focal(starts.to(device=device, dtype=torch.float64))
    fraction = 1.0
    for _ in range(config.grid_passes):
        fraction /= 3.0
        points = current[:, :, None, :] + lattice * (step * fraction)  # (B, L, 81, 4)
        points = into_box(points, log_lower, log_upper, config.periodic_pan)
        hypotheses = _exp_focal(points).view(batch, n_start * len(lattice), 4)
        point_scores = score_grid(likelihood, features, hypotheses, config.max_chunk_elements, vertical_block=3)
        current, scores = _keep_best(current, scores, points, point_scores)
    return _exp_focal(current).to(starts), scores


#: Lattice spacing of :func:`focal_prior_share`: [pan, pitch, roll] in degrees, then log f (5 % of f).
#: Chosen on the train splits (YUD, ZInD-fR, YUD crops) from (0.25 / 0.5 / 1 deg) x (0.01 - 0.05):
#: the Spearman rho of the cue with the focal error stays within 0.4 - 0.57 across them.
PRIOR_SHARE_STEP = (0.5, 0.5, 0.5, 0.05)


def _quadratic_fit_matrix() -> torch.Tensor:
    """(15, 81) least-squares map from objective values on :data:`LATTICE` to the coefficients of
    ``c + g.x + x.H.x / 2`` in lattice units: [c, g (4), H_00, H_01, H_02, H_03, H_11, H_12, ..., H_33]."""
    x = LATTICE
    columns = [torch.ones(len(x), dtype=torch.float64)] + [x[:, j] for j in range(4)]
    columns += [x[:, i] * x[:, j] * (0.5 if i == j else 1.0) for i in range(4) for j in range(i, 4)]
    return torch.linalg.pinv(torch.stack(columns, 1))


_QUADRATIC_FIT = _quadratic_fit_matrix()
#: Column of the fit's coefficients holding H[i, j], for the 16 entries of the symmetric 4 x 4 H.
_HESSIAN_COLUMNS = torch.tensor([5 + [(a, b) for a in range(4) for b in range(a, 4)].index((min(i, j), max(i, j)))
                                 for i in range(4) for j in range(4)])


def focal_prior_share(likelihood: MixtureLikelihood, features: SegmentFeatures, params: torch.Tensor,
                      max_chunk_elements: int = 1 << 24) -> torch.Tensor:
    """How much of the focal length's determination comes from the focal prior (a reliability cue).

    The objective (likelihood + prior) is scored on the 3^4 lattice of :data:`PRIOR_SHARE_STEP`
    around each estimate and fitted by a quadratic (a local Laplace approximation; the lattice
    spacing smooths the kinks of the exponential likelihood).  The prior's curvature in log f,
    ``c_p``, fitted the same way from its values on the lattice (:meth:`MixtureLikelihood.focal_prior`:
    the log-normal's constant ``gamma (W + W0)``, 0 inside a flat top), is taken out of the fitted
    Hessian, leaving the likelihood's; its curvature along log f with the angles re-optimised (Schur
    complement ``-(H_ff - H_fa H_aa^-1 H_af)``) is ``c_l``.  The cue is ``c_p / (c_p + max(c_l, 0))``:
    near 0 when the segments pin f down, 1 when the likelihood is flat (or curves up) along f and the
    prior alone sets it -- e.g. a narrow view whose vanishing points lie far outside the image,
    which the prior pulls towards its centre.

    Args:
        likelihood: the estimator's model (its focal prior included).
        features: the segments of B images.
        params: (B, 4) estimates [pan, pitch, roll (degrees), f (pixels)].
        max_chunk_elements: as for :func:`score_grid`.

    Returns:
        (B,) float64 in [0, 1]; 0 for every image when the model has no focal prior; 1 where the fit
        is not finite.
    """
    batch = params.shape[0]
    device = features.weight.device
    if not likelihood.params.focal_prior_weight:
        return torch.zeros(batch, dtype=torch.float64, device=device)
    step = torch.tensor(PRIOR_SHARE_STEP, dtype=torch.float64, device=device)
    centre = _log_focal(params.to(device=device, dtype=torch.float64))
    points = _exp_focal(centre[:, None, :] + LATTICE.to(device) * step)  # (B, 81, 4)
    scores = score_grid(likelihood, features, points, max_chunk_elements, vertical_block=3)
    fit = _QUADRATIC_FIT.to(device).T  # (81, 15)
    coef = scores.to(torch.float64) @ fit  # (B, 15)
    hessian = coef[:, _HESSIAN_COLUMNS.to(device)].view(batch, 4, 4)
    # The prior's curvature over the same lattice, fitted the same way (exact for the log-normal;
    # a flat-topped prior has none inside its band and part of it at the band's edge).
    prior_values = likelihood.focal_prior(features, points[..., 3].to(features.weight.dtype))[0]
    prior_hessian = prior_values.to(torch.float64) @ fit[:, _HESSIAN_COLUMNS[15].item()]  # H_33, lattice units
    hessian[:, 3, 3] -= prior_hessian  # the likelihood's Hessian alone (lattice units)
    prior = (-prior_hessian / step[3] ** 2).clamp_min(0.0)  # per (log f)^2
    angles, focal_row = hessian[:, :3, :3], hessian[:, :3, 3:]
    solved, info = torch.linalg.solve_ex(angles, focal_row)
    profile = -(hessian[:, 3, 3] - (focal_row * solved).sum((-1, -2))) / step[3] ** 2  # per (log f)^2
    share = prior / (prior + profile.clamp_min(0.0))
    ok = torch.isfinite(share) & (info == 0)
    return torch.where(ok, share.clamp(0.0, 1.0) + 0.0, torch.ones_like(share))  # + 0.0: no -0.0 in the output


#: Focal lengths of :func:`focal_profile_gap`'s profile, as multiples of the estimate: about 15 % to
#: 67 % away on either side, evenly spaced in log f (narrower than the search range's 6.5x, wider
#: than the basin of a well-determined estimate, ~5 %).
PROFILE_FOCAL_RATIOS = (0.6, 0.7, 0.8, 0.87, 1.15, 1.25, 1.43, 1.67)
#: Images profiled together by :func:`focal_profile_gap` (their segments are copied once per ratio:
#: 256 x 8 copies of 750 segments are about 90 MB); the gaps do not depend on it.
PROFILE_CHUNK_IMAGES = 256


def focal_profile_gap(likelihood: MixtureLikelihood, features: SegmentFeatures, params: torch.Tensor,
                      scores: torch.Tensor, config: SearchConfig, iterations: int) -> torch.Tensor:
    """How much better the estimate scores than the best hypothesis at a clearly different focal
    length (a reliability cue): ``scores`` minus the best objective of a known-focal search at each
    f x :data:`PROFILE_FOCAL_RATIOS` inside the search range.

    Each known-focal search is Fast-fR's with the focal length fixed: the k^3 angle grid, its
    ``top_l`` best points refined for ``iterations`` Adam steps.  A large gap (hundreds of nats)
    means the segments single out the estimate's focal length; a small one, that another focal
    length explains them almost as well (two basins: the estimate may be the wrong one); a negative
    one, that the search missed a better basin.  Values are in objective units (nats, weighted by
    segment length in pixels), like ``scores``.

    Args:
        likelihood: the estimator's model.
        features: the segments of B images.
        params: (B, 4) estimates [pan, pitch, roll (degrees), f (pixels)].
        scores: (B,) the estimates' objectives.
        config: the search settings (FOV range, grid, top_l).
        iterations: Adam steps per start.

    Returns:
        (B,) float64, finite: 0 (no evidence that the estimate's focal length is singled out) where
        the gap is not finite (a non-finite estimate, or no ratio's focal length inside the range).
    """
    batch, count = params.shape[0], len(PROFILE_FOCAL_RATIOS)
    device = features.weight.device
    if batch > PROFILE_CHUNK_IMAGES:  # each image's segments are copied once per ratio searched: bound the copies
        return torch.cat([focal_profile_gap(likelihood, features.images(b, b + PROFILE_CHUNK_IMAGES),
                                            params[b:b + PROFILE_CHUNK_IMAGES], scores[b:b + PROFILE_CHUNK_IMAGES],
                                            config, iterations)
                          for b in range(0, batch, PROFILE_CHUNK_IMAGES)])
    if batch == 0:
        return torch.zeros(0, dtype=torch.float64, device=device)
    ratios = torch.tensor(PROFILE_FOCAL_RATIOS, dtype=torch.float64)
    long_side = features.long_side.to("cpu", torch.float64)
    f_lo, f_hi = focal_bounds(config, long_side)
    focal = params[:, 3].to("cpu", torch.float64)[:, None] * ratios  # (B, R)
    inside = (focal >= f_lo[:, None]) & (focal <= f_hi[:, None])
    pairs = inside.nonzero()  # (M, 2) [image, ratio]: only focal lengths inside the range are searched
    best = torch.full((batch, count), -math.inf, dtype=torch.float64, device=device)
    if len(pairs):
        image, ratio = pairs.unbind(1)
        searched = features.take_images(image.to(device))
        long_rep, focal_rep = long_side[image], focal[image, ratio]
        hypotheses = grid_hypotheses(config, long_rep.to(device), focal_rep.to(device))  # built on the device
        grid_scores = score_grid(likelihood, searched, hypotheses, config.max_chunk_elements,
                                 vertical_block=config.grid_points_per_dim)
        starts, _ = select_starts(config, grid_scores, hypotheses)
        lower, upper = parameter_box(config, long_rep, focal_rep)
        _, refined = refine(likelihood, searched, starts, lower.to(device), upper.to(device), iterations, fast=True,
                            periodic_pan=config.periodic_pan)
        best[image.to(device), ratio.to(device)] = refined.to(torch.float64).amax(1)
    gap = scores.to(torch.float64) - best.amax(1)
    return torch.where(torch.isfinite(gap), gap, torch.zeros_like(gap))


def hypothesis_rotations(params: torch.Tensor) -> torch.Tensor:
    """World->camera R (..., 3, 3) from [pan, pitch, roll, focal] parameters (..., 4)."""
    return rotation_from_angles(params[..., 0], params[..., 1], params[..., 2])


def score_grid(likelihood: MixtureLikelihood, features: SegmentFeatures, hypotheses: torch.Tensor,
               max_chunk_elements: int, vertical_block: int = 1) -> torch.Tensor:
    """Length-weighted log-likelihood of every hypothesis, (B, G), in chunks of hypotheses and images.

    At most ``max_chunk_elements`` (``CPU_CHUNK_ELEMENTS`` on CPU, if smaller) per-segment
    deviations exist at once; scores do not depend on the chunking.  ``vertical_block`` = k:
    runs of k consecutive hypotheses differ only in pan (the grid of :func:`grid_hypotheses`), so
    their vertical VP is scored once (chunks hold whole runs; same scores to rounding).
    """
    batch, count = hypotheses.shape[:2]
    n_seg = max(1, features.weight.shape[1])
    dtype, device = features.weight.dtype, features.weight.device
    if vertical_block < 1 or count % vertical_block:
        vertical_block = 1
    # CPU: a cache-sized chunk per intra-op thread.  A fixed 2^17 chunk capped every op at 4 threads
    # (torch's GRAIN_SIZE 2^15 elements per thread), so more cores did not help.
    cpu_budget = CPU_CHUNK_ELEMENTS * max(1, torch.get_num_threads())
    budget = max(1, max_chunk_elements if device.type != "cpu" else min(max_chunk_elements, cpu_budget))
    per_hypothesis = n_seg * 3
    hyp_chunk = max(1, min(count, budget // per_hypothesis))
    hyp_chunk = max(vertical_block, hyp_chunk - hyp_chunk % vertical_block)  # whole runs
    img_chunk = max(1, min(batch, budget // (per_hypothesis * hyp_chunk)))
    scores = torch.empty(batch, count, dtype=dtype, device=device)
    workspace: dict = {}
    with torch.no_grad():
        for b0 in range(0, batch, img_chunk):
            b1 = min(batch, b0 + img_chunk)
            sub = features.images(b0, b1)
            # Rotations of this image slice: (b, G, 3, 3) -- small (9 numbers per hypothesis).
            part = hypotheses[b0:b1].to(device)
            rotation = fast_rotations(part.to(dtype))
            focal = part[..., 3].to(dtype)
            for h0 in range(0, count, hyp_chunk):
                h1 = min(count, h0 + hyp_chunk)
                scores[b0:b1, h0:h1] = likelihood.objective(sub, rotation[:, h0:h1], focal[:, h0:h1],
                                                            workspace=workspace, vertical_block=vertical_block)
    return scores.nan_to_num_(nan=-math.inf)  # a NaN score is never the best (topk ranks NaN first)


def fast_rotations(params: torch.Tensor) -> torch.Tensor:
    """World->camera R (..., 3, 3) from [pan, pitch, roll, ...] (degrees), closed form.

    ``R.T = Ry(pan) Rx(pitch) Rz(roll)`` (each a right-handed rotation about the camera axis) --
    the same rotation as :func:`hypothesis_rotations` (kornia quaternion route) up to rounding, in
    fewer operations; differentiable.
    """
    rad = torch.deg2rad(params[..., :3])
    return _rotations_from_cos_sin(torch.cos(rad), torch.sin(rad))


def _rotations_from_cos_sin(cos: torch.Tensor, sin: torch.Tensor) -> torch.Tensor:
    """:func:`fast_rotations` from the cosines and sines of [pan, pitch, roll] (..., 3)."""
    cp, ct, cr = cos.unbind(-1)
    sp, st, sr = sin.unbind(-1)
    spst, cpst = sp * st, cp * st
    # Columns of R.T are the rows of R; build R row by row (row i of R = column i of R.T).
    rows = torch.stack([cp * cr + spst * sr, ct * sr, cpst * sr - sp * cr,
                        spst * cr - cp * sr, ct * cr, sp * sr + cpst * cr,
                        sp * ct, -st, cp * ct], -1)
    return rows.view(cos.shape[:-1] + (3, 3))


def refine(likelihood: MixtureLikelihood, features: SegmentFeatures, starts: torch.Tensor,
           lower: torch.Tensor, upper: torch.Tensor, iterations: int, fast: bool,
           max_chunk_elements: int = 1 << 24, tolerance: float = 0.0,
           patience: int = 10, periodic_pan: bool = False) -> tuple[torch.Tensor, torch.Tensor]:
    """Refine starts (B, L, 4) inside the box [lower, upper] (B, 4).  Returns (params, objective).

    Parameters are optimised as u = (p - lower) / (upper - lower) in [0, 1] (a degenerate box,
    e.g. a known focal length, keeps that parameter fixed); with ``periodic_pan``
    (:attr:`SearchConfig.periodic_pan`) pan wraps around its 90-degree box instead of stopping at
    its edge.  The loss of every hypothesis is its
    negative log-likelihood divided by the image's total segment length, so step sizes do not
    depend on how many segments an image has.  Images are refined in independent slices of at
    most ``max_chunk_elements`` deviations (bounded memory; same result as one big batch).

    Stopping rule (``tolerance > 0``, not in fast mode): stop when no hypothesis of the slice changed
    its normalised objective by more than ``tolerance`` over the last ``patience`` steps.  Guards: the
    gradient is made finite (NaN, inf -> 0) and bounded by ``_GRAD_BOUND``, so no step makes a
    parameter non-finite, and a non-finite final objective is returned as -inf (never chosen over a
    finite one).
    """
    batch, n_start = starts.shape[:2]
    n_seg = max(1, features.weight.shape[1])
    if features.weight.device.type == "cpu":
        max_chunk_elements = min(max_chunk_elements, CPU_REFINE_ELEMENTS)
    step = max(1, max_chunk_elements // (n_seg * n_start * 3))
    tol = tolerance if not fast else 0.0
    if batch > step:
        parts = [_refine_slice(likelihood, features.images(b, b + step), starts[b:b + step],
                               lower[b:b + step], upper[b:b + step], iterations, fast, tol, patience, periodic_pan)
                 for b in range(0, batch, step)]
        return torch.cat([p for p, _ in parts]), torch.cat([o for _, o in parts])
    return _refine_slice(likelihood, features, starts, lower, upper, iterations, fast, tol, patience, periodic_pan)


#: Bound on each gradient component of the normalised loss in box units (real ones stay below ~1e4).
_GRAD_BOUND = 1e6


class _FusedAdam:
    """torch.optim's Adam (``fused=True``) on one tensor, stepped with an exponentially decaying
    step size: what ``torch.optim.Adam(fused=True)`` with ``ExponentialLR(gamma)`` does, bit for bit,
    through torch.optim's functional form ``torch.optim.adam.adam`` (the function ``Adam.step``
    calls) with the same state (zero moments, a float32 step count) and step sizes
    ``lr0, lr0 * gamma, ...``.

    Why not the ``torch.optim.Adam`` object: building the first optimiser object in a process
    imports ``torch._dynamo`` (its constructor is wrapped to disable the compiler), 1.2-2.2 s on a
    2-core machine -- a third of a one-photo ``fr calibrate``, paid by every process that refines.
    """

    def __init__(self, param: torch.Tensor, lr: float, gamma: float, betas: tuple[float, float], eps: float = 1e-8):
        self.param, self.lr, self.gamma, self.betas, self.eps = param, lr, gamma, betas, eps
        self.exp_avg = torch.zeros_like(param, memory_format=torch.preserve_format)
        self.exp_avg_sq = torch.zeros_like(param, memory_format=torch.preserve_format)
        self.step_count = torch.zeros((), dtype=torch.float32, device=param.device)  # as Adam(fused=True) keeps it

    def step(self, grad: torch.Tensor) -> None:
        """One Adam update of the parameter (in place) with gradient ``grad`` (same shape), then
        the step size decays by ``gamma``."""
        with torch.no_grad():
            adam_update([self.param], [grad], [self.exp_avg], [self.exp_avg_sq], [], [self.step_count], fused=True,
                        amsgrad=False, beta1=self.betas[0], beta2=self.betas[1], lr=self.lr, weight_decay=0.0,
                        eps=self.eps, maximize=False)
        self.lr = self.lr * self.gamma


def _refine_slice(likelihood, features, starts, lower, upper, iterations, fast, tolerance=0.0, patience=10,
                  periodic_pan=False):
    dtype, device = features.weight.dtype, features.weight.device
    # The focal length is refined as log f: a step is the same relative change of f (and about the
    # same change of FOV) at every zoom, matching the log-spaced stage-1 grid.
    lower = _log_focal(lower.to(device=device, dtype=dtype)[:, None, :])
    upper = _log_focal(upper.to(device=device, dtype=dtype)[:, None, :])
    starts = _log_focal(starts.to(device=device, dtype=dtype))
    span = (upper - lower)
    free = span > 0
    span_safe = torch.where(free, span, torch.ones_like(span))
    u = ((starts - lower) / span_safe).clamp(0, 1).detach().requires_grad_(True)
    total_length = features.weight.sum(-1).clamp_min(1e-9)[:, None]
    # Step sizes in box units: about a quarter of a grid cell at first, decaying geometrically.
    cell = 1.0 / 8
    lr0 = 0.25 * cell
    lr_final = (0.02 if fast else 0.002) * cell
    gamma = (lr_final / lr0) ** (1.0 / max(1, iterations - 1))
    optimiser = _FusedAdam(u, lr0, gamma, betas=(0.5, 0.9))
    all_free = bool(free.all())
    history: list[torch.Tensor] = []

    def evaluate(u_value):
        params = _exp_focal(lower + u_value * span)
        rotation = fast_rotations(params)
        return params, likelihood.objective(features, rotation, params[..., 3])

    analytic = likelihood._fast_path(features)
    grad_out = -1.0 / total_length
    for _ in range(iterations):
        u.grad = None
        if analytic:  # same gradient in closed form, no autograd graph (see objective_and_grad)
            result = (compiled_call(objective_and_grad, likelihood, likelihood, features, lower, span, u.detach(),
                                    grad_out) if likelihood.compiled else None)
            objective, grad = result or objective_and_grad(likelihood, features, lower, span, u.detach(), grad_out)
        else:
            _, objective = evaluate(u)
            finite = torch.where(torch.isfinite(objective), objective, torch.zeros_like(objective))
            loss = -(finite / total_length).sum()
            loss.backward()
            grad = u.grad
        if not all_free:
            grad = torch.where(free, grad, torch.zeros_like(grad))
        # A finite, bounded gradient keeps Adam's moments and so every parameter finite.
        optimiser.step(torch.nan_to_num(grad, nan=0.0, posinf=0.0, neginf=0.0).clamp_(-_GRAD_BOUND, _GRAD_BOUND))
        with torch.no_grad():
            if periodic_pan:  # u's pan is (pan - lower) / 90 deg: wrap it into [0, 1)
                u[..., 0] = torch.remainder(u[..., 0], 1.0)
            u.clamp_(0.0, 1.0)
        if tolerance > 0:
            history.append(objective.detach() / total_length)
            if len(history) > patience:
                old = history.pop(0)
                change = (history[-1] - old).abs()
                if bool(((change <= tolerance) | ~torch.isfinite(change)).all()):
                    break
    with torch.no_grad():
        params, objective = evaluate(u)
        objective = torch.where(torch.isfinite(objective), objective, torch.full_like(objective, -math.inf))
    return params.detach(), objective.detach()


def _log_focal(params: torch.Tensor) -> torch.Tensor:
    """[pan, pitch, roll, f] -> [pan, pitch, roll, log f] (..., 4)."""
    return torch.cat([params[..., :3], torch.log(params[..., 3:])], -1)


def _exp_focal(params: torch.Tensor) -> torch.Tensor:
    """[pan, pitch, roll, log f] -> [pan, pitch, roll, f] (..., 4)."""
    return torch.cat([params[..., :3], torch.exp(params[..., 3:])], -1)


def objective_and_grad(likelihood: MixtureLikelihood, features: SegmentFeatures, lower: torch.Tensor,
                       span: torch.Tensor, u: torch.Tensor, grad_out: torch.Tensor):
    """Measure-b objective (B, L) at ``params = lower + u * span`` and the gradient of
    ``sum(grad_out * objective)`` with respect to u (B, L, 4), without autograd.

    ``params`` = [pan, pitch, roll (degrees), log f (f in pixels)], the refinement's coordinates.

    ``lower``, ``span``: (B, 1, 4); ``grad_out``: broadcastable to (B, L).  The chain is written
    out: G = d obj / d V for the VPs V = K R from :func:`fr_torch.likelihood.measure_b_backward`;
    ``dV/df = [R_0; R_1; 0]``; and for the angles, with ``R.T = Ry(pan) Rx(pitch) Rz(roll)``
    (:func:`fast_rotations`), ``dR/d angle = -R [w]_x`` for the axis ``w`` = e_y (pan),
    ``Ry(pan) e_x`` (pitch) and ``R.T e_z`` (roll), so ``d obj / d angle = -w . axial(V.T G)``
    (``<G, K dR> = <K.T G, -R [w]_x> = -<R.T K.T G, [w]_x>``; axial(M) = (M21 - M12, M02 - M20,
    M10 - M01)).  Equal to the autograd gradient of the same objective to rounding (tests); used
    by the refinement, where autograd's per-step overhead dominated at small batches.
    """
    params = lower + u * span
    batch, n_hyp = params.shape[:2]
    rad = torch.deg2rad(params[..., :3])
    cos, sin = torch.cos(rad), torch.sin(rad)
    rotation = _rotations_from_cos_sin(cos, sin)  # (B, L, 3, 3)
    focal = torch.exp(params[..., 3])
    pp = features.principal_point[:, None, :]  # (B, 1, 2)
    # V = K R: rows 0, 1 = f R_j + c_j R_2, row 2 = R_2.
    top = focal[..., None, None] * rotation[..., :2, :] + pp[..., None] * rotation[..., 2:, :]
    vps = torch.cat([top, rotation[..., 2:, :]], -2)  # (B, L, 3, 3)
    objective, saved = measure_b_forward(features.line_along, features.weight, vp_major(vps),
                                         *likelihood._b_constants(features.weight))
    grad_flat = measure_b_backward(saved, grad_out.expand(batch, n_hyp).contiguous())
    grad_v = grad_flat.view(batch, 3, 3, n_hyp).permute(0, 3, 1, 2)  # (B, L, coord, VP)
    grad_f = (grad_v[..., :2, :] * rotation[..., :2, :]).sum((-1, -2))
    if likelihood.params.focal_prior_weight:  # the focal prior of MixtureLikelihood.objective
        prior, d_prior = likelihood.focal_prior(features, focal)
        objective = objective + prior
        grad_f = grad_f + grad_out * d_prior
    m = vps.transpose(-1, -2) @ grad_v  # R.T K.T G (B, L, 3, 3)
    anti = m - m.transpose(-1, -2)
    axial = torch.stack([anti[..., 2, 1], anti[..., 0, 2], anti[..., 1, 0]], -1)  # (B, L, 3)
    grad_pitch = cos[..., 0] * axial[..., 0] - sin[..., 0] * axial[..., 2]  # w = Ry e_x = (cos pan, 0, -sin pan)
    grad_roll = (rotation[..., 2, :] * axial).sum(-1)  # w = R.T e_z = row 2 of R
    grad_angles = torch.stack([axial[..., 1], grad_pitch, grad_roll], -1) * (-math.pi / 180)  # per degree
    grad_p = torch.cat([grad_angles, (grad_f * focal)[..., None]], -1)  # d/d log f = f d/df
    return objective, grad_p * span


def check_result(result, config: SearchConfig, known_focal: bool = False,
                 edge_tolerance_deg: float = 0.25, finite: bool | None = None,
                 search_params: Sequence[float] | None = None) -> None:
    """Final checks on an estimator result (in place; ``result`` has the fields of
    :class:`fr_torch.estimator.CalibrationResult`).

    * Anything non-finite in the focal length, angles, rotation, vanishing points or objective ->
      ``ok = False``, ``reliable = False``, camera fields cleared, ``reason`` says so (a NaN is a
      failure, never a valid number).
    * An estimated focal length whose long-side FOV lies within ``edge_tolerance_deg`` of the
      search range's edge -> ``reliable = False`` with reason :data:`EDGE_REASON` (the truth may lie
      outside the range).
    * Likewise a search angle within ``edge_tolerance_deg`` of its box's edge, from
      ``search_params`` ([pan, pitch, roll (degrees), f], the search's own parametrisation, which
      the result's horizon angles only approximate): pitch or roll, and pan unless it wraps
      (:attr:`SearchConfig.periodic_pan`) -> ``reliable = False`` with reason
      :func:`angle_edge_reason` (a camera looking down more steeply than ``pitch_range_deg``
      allows is found at the edge with a wrong focal length).

    ``finite``: the caller's batched finiteness check of the same values (the estimator checks its
    parameters, objective and rotation, from which every derived value follows finitely); None =
    check the record's values here.
    """
    if not result.ok:
        return
    if finite is None:
        values = [result.focal_px, result.hfov_deg, result.roll_deg, result.tilt_deg, result.pitch_deg,
                  result.log_likelihood]
        arrays = [result.rotation, result.vanishing_points]
        finite = all(v is not None and math.isfinite(float(v)) for v in values) and \
            all(a is not None and bool(np.isfinite(np.asarray(a, dtype=np.float64)).all()) for a in arrays)
    if not finite:
        for key in ("focal_px", "hfov_deg", "rotation", "pan_deg", "tilt_deg", "roll_deg", "pitch_deg",
                    "vanishing_points", "log_likelihood"):
            setattr(result, key, None)
        result.ok, result.reliable, result.reason = False, False, NON_FINITE_REASON
        return
    reasons = []
    if search_params is not None:
        boxes = {"pan": config.pan_range_deg, "pitch": config.pitch_range_deg, "roll": config.roll_range_deg}
        for index, (name, (low, high)) in enumerate(boxes.items()):
            if name == "pan" and config.periodic_pan:
                continue
            value = float(search_params[index])
            if high - low > 2 * edge_tolerance_deg and (value <= low + edge_tolerance_deg
                                                        or value >= high - edge_tolerance_deg):
                reasons.append(angle_edge_reason(name, low, high))
    if not known_focal:
        long_side = max(result.width, result.height)
        fov = hfov_from_focal(result.focal_px, long_side)
        low, high = config.hfov_range_deg
        if fov <= low + edge_tolerance_deg or fov >= high - edge_tolerance_deg:
            reasons.append(EDGE_REASON)
    if reasons:
        result.reliable = False
        result.reason = "; ".join(r for r in (result.reason, *reasons) if r)
