"""Stage 1 of the search: the box, the k^4 grid of hypotheses in it, their scores, the best starts.

The box: pan, pitch and roll ranges (degrees) and the focal range of the FOV range
(:class:`~fr_torch.core.settings.fov.FovRange`, across the long side), or a known focal length.
The grid: k cell centres per dimension, the focal length spaced uniformly in log f by default
(``SearchConfig.focal_grid``).  :func:`score_grid` scores every hypothesis as one batched tensor
computation (the fused kernel on a CPU stores no deviations; else cache-sized chunks on a CPU and
``max_chunk_elements`` on a GPU; no chunk size depends on the thread count), and
:func:`select_starts` keeps each image's ``top_l`` best.  With ``SearchConfig.grid_coarse_factor`` > 1,
:func:`coarse_to_fine_scores` scores the k^4 grid only inside the best cells of a coarser grid
(:func:`stage1_scores` picks one or the other).
"""
from __future__ import annotations

import functools
import math
from dataclasses import replace

import torch

from fr_torch.core.exact import top_indices
from fr_torch.core.geometry.conventions import focal_from_hfov
from fr_torch.core.geometry.params import ANGLES, FOCAL, rotations
from fr_torch.core.likelihood.measures import SegmentFeatures
from fr_torch.core.likelihood.mixture import MixtureLikelihood
from fr_torch.core.settings.config import SearchConfig
from fr_torch.core import exact_math

# Grid deviations per chunk on CPU, whatever the thread count: float32 buffers of a few MB, 32 of
# torch's 2^15-element grains (up to 32 threads share every op).  Scores are the same for any chunk
# size (results/DECISIONS.md, results/decisions/60.md).
CPU_CHUNK_ELEMENTS = 1 << 20


def _cell_centres(low: float, high: float, k: int) -> torch.Tensor:
    return low + (torch.arange(k, dtype=torch.float64) + 0.5) * (high - low) / k


@functools.lru_cache(maxsize=32)
def _grid_angles(pan_range: tuple[float, float], pitch_range: tuple[float, float], roll_range: tuple[float, float],
                 k: int, device: torch.device) -> torch.Tensor:
    """The grid's (k^3, 3) float64 [pan, pitch, roll] cell centres (degrees), pitch slowest, pan
    fastest, on ``device``; made once per setting and device (read only: the grid copies it)."""
    pan, pitch, roll = (_cell_centres(*box, k) for box in (pan_range, pitch_range, roll_range))
    return torch.cartesian_prod(pitch, roll, pan)[:, [2, 0, 1]].to(device)


def parameter_box(config: SearchConfig, long_side: torch.Tensor, known_focal: torch.Tensor | None):
    """Lower and upper bounds, (B, 4) float64, of [pan, pitch, roll, focal] per image.

    ``long_side``: (B,) the longer image side in pixels (``max(width, height)``).
    """
    f_lo, f_hi = config.fov_range.focal_bounds(long_side)
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


def log_spaced_focals(f_lo: torch.Tensor, f_hi: torch.Tensor, count: int) -> torch.Tensor:
    """``count`` focal lengths per image, (B, count) float64 pixels, at the centres of ``count``
    equal cells in log f between ``f_lo`` and ``f_hi`` ((B,) float64 pixels)."""
    fraction = (torch.arange(count, dtype=torch.float64, device=f_lo.device) + 0.5) / count
    return exact_math.exp(exact_math.log(f_lo)[:, None] + fraction * exact_math.log(f_hi / f_lo)[:, None])


def focal_grid(config: SearchConfig, long_side: torch.Tensor) -> torch.Tensor:
    """The k stage-1 focal values per image, (B, k) float64 pixels, at cell centres of the range,
    spaced per ``config.focal_grid`` (linear in f, in log f, or in FOV)."""
    k = config.grid_points_per_dim
    frac = (torch.arange(k, dtype=torch.float64, device=long_side.device) + 0.5) / k
    long_side = long_side.to(torch.float64)
    if config.focal_grid == "fov":
        lo, hi = config.fov_range
        fov = torch.tensor(hi, dtype=torch.float64) - frac * (hi - lo)  # wide -> narrow: f ascending
        return focal_from_hfov(fov[None, :], long_side[:, None])
    f_lo, f_hi = config.fov_range.focal_bounds(long_side)
    if config.focal_grid == "log_f":
        return log_spaced_focals(f_lo, f_hi, k)
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
    # (k^3, 3) on the device of the inputs (a GPU batch's grid is built there: 128 KB per image,
    # 0.5 GB for 4096 images, is not worth a host->device copy)
    angles = _grid_angles(config.pan_range_deg, config.pitch_range_deg, config.roll_range_deg, k, focal.device)
    batch, n_focal = focal.shape
    hyp = torch.cat([angles.expand(batch, n_focal, -1, -1),
                     focal[:, :, None, None].expand(-1, -1, angles.shape[0], 1)], -1)
    return hyp.reshape(batch, -1, 4)


def select_starts(config: SearchConfig, grid_scores: torch.Tensor, hypotheses: torch.Tensor):
    """Stage-2 starting points: the ``top_l`` best grid points, best first.

    ``grid_scores`` (B, G) and ``hypotheses`` (B, G, 4) as from :func:`grid_hypotheses` (or rows of
    5 with k, :mod:`fr_torch.core.search.lens`).
    Returns (starts (B, L, 4 or 5), their scores (B, L)), L = min(top_l, G); equal scores are
    taken in grid order (:func:`fr_torch.core.exact.top_indices`).
    """
    index = top_indices(grid_scores, min(config.top_l, grid_scores.shape[1]), dim=1)
    return (torch.gather(hypotheses, 1, index[..., None].expand(-1, -1, hypotheses.shape[-1])),
            torch.gather(grid_scores, 1, index))


def grid_cell(config: SearchConfig, lower: torch.Tensor, upper: torch.Tensor) -> torch.Tensor:
    """Size of one stage-1 grid cell per image, (B, 4) float64: [pan, pitch, roll] in degrees and
    the focal step in log f (``log(f_max / f_min) / k``, the log-f grid's spacing; 0 for a known
    focal).  ``lower``, ``upper``: (B, 4) from :func:`parameter_box`."""
    k = config.grid_points_per_dim
    angles = (upper[:, ANGLES] - lower[:, ANGLES]) / k
    log_focal = (exact_math.log(upper[:, 3:]) - exact_math.log(lower[:, 3:])) / k
    return torch.cat([angles, log_focal], -1)


def chunk_budget(max_chunk_elements: int, device: torch.device) -> int:
    """How many elements a chunk of per-segment (or per-pair) work may hold on ``device``: the
    configuration's ``max_chunk_elements`` on a GPU, at most :data:`CPU_CHUNK_ELEMENTS` on a CPU
    (a cache-sized chunk, the same at every thread count); at least 1.  Chunking never changes a
    value (every sum across a chunk's rows is exact)."""
    return max(1, max_chunk_elements if device.type != "cpu" else min(max_chunk_elements, CPU_CHUNK_ELEMENTS))


def score_grid(likelihood: MixtureLikelihood, features: SegmentFeatures, hypotheses: torch.Tensor,
               max_chunk_elements: int, vertical_block: int = 1) -> torch.Tensor:
    """Length-weighted log-likelihood of every hypothesis, (B, G) float64, in chunks of hypotheses
    and images.

    At most ``max_chunk_elements`` (``CPU_CHUNK_ELEMENTS`` on CPU, if smaller) per-segment
    deviations exist at once, in chunks that are the same at every thread count; scores do not
    depend on the chunking, the batch or the thread count,
    bit for bit (:mod:`fr_torch.core.exact`).  ``vertical_block`` = k: runs of k consecutive
    hypotheses differ only in pan (the grid of :func:`grid_hypotheses`), so their vertical VP is
    scored once (chunks hold whole runs; the same scores bit for bit).
    """
    batch, count = hypotheses.shape[:2]
    n_seg = max(1, features.weight.shape[1])
    dtype, device = features.weight.dtype, features.weight.device
    if vertical_block < 1 or count % vertical_block:
        vertical_block = 1
    # CPU: a fixed cache-sized chunk at any thread count (the fused kernel stores no deviations: no chunk)
    budget = max(1, max_chunk_elements) if likelihood.stores_no_deviations(features) and device.type == "cpu" \
        else chunk_budget(max_chunk_elements, device)
    per_hypothesis = n_seg * 3
    hyp_chunk = max(1, min(count, budget // per_hypothesis))
    hyp_chunk = max(vertical_block, hyp_chunk - hyp_chunk % vertical_block)  # whole runs
    img_chunk = max(1, min(batch, budget // (per_hypothesis * hyp_chunk)))
    scores = torch.empty(batch, count, dtype=torch.float64, device=device)
    workspace: dict = {}
    with torch.no_grad():
        for b0 in range(0, batch, img_chunk):
            b1 = min(batch, b0 + img_chunk)
            sub = features.images(b0, b1)
            # Rotations of this image slice: (b, G, 3, 3) -- small (9 numbers per hypothesis).
            part = hypotheses[b0:b1].to(device)
            rotation = rotations(part.to(dtype))
            focal = part[..., FOCAL].to(dtype)
            for h0 in range(0, count, hyp_chunk):
                h1 = min(count, h0 + hyp_chunk)
                scores[b0:b1, h0:h1] = likelihood.objective(sub, rotation[:, h0:h1], focal[:, h0:h1],
                                                            workspace=workspace, vertical_block=vertical_block)
    return scores.nan_to_num_(nan=-math.inf)  # a NaN score is never the best (topk ranks NaN first)


def _cell_members(cells: torch.Tensor, coarse_k: int, factor: int, n_focal: int) -> torch.Tensor:
    """Indices (B, M * s^D) int64 into the k^4 grid (k = ``coarse_k * factor``, order of
    :func:`grid_hypotheses`) of the points inside coarse cells ``cells`` (B, M) int64 (indices into
    the ``coarse_k`` grid); D = 4, or 3 when ``n_focal`` = 1 (a known focal).  Per cell the s^D
    points run in grid order, pan fastest: runs of s share the vertical VP."""
    s, k = factor, coarse_k * factor
    focal_c = cells // coarse_k ** 3
    pitch_c = cells // coarse_k ** 2 % coarse_k
    roll_c = cells // coarse_k % coarse_k
    pan_c = cells % coarse_k
    steps = torch.arange(s, device=cells.device)
    focal_steps = steps if n_focal > 1 else steps[:1]
    offsets = torch.cartesian_prod(focal_steps, steps, steps, steps)  # (s^D, 4) [focal, pitch, roll, pan]
    fine_focal = (focal_c * s if n_focal > 1 else focal_c)[..., None] + offsets[:, 0]
    fine_pitch = (pitch_c * s)[..., None] + offsets[:, 1]
    fine_roll = (roll_c * s)[..., None] + offsets[:, 2]
    fine_pan = (pan_c * s)[..., None] + offsets[:, 3]
    index = ((fine_focal * k + fine_pitch) * k + fine_roll) * k + fine_pan  # (B, M, s^D)
    return index.reshape(cells.shape[0], -1)


def kept_coarse_cells(config: SearchConfig, known_focal: bool = False) -> int:
    """How many coarse cells :func:`coarse_to_fine_scores` keeps per image: ``grid_coarse_cells``,
    more where fewer than ``top_l`` points would be scored, at most every cell."""
    factor = config.grid_coarse_factor
    dims = 3 if known_focal else 4
    per_cell = factor ** dims
    kept = max(config.grid_coarse_cells, -(-config.top_l // per_cell))
    return min(kept, (config.grid_points_per_dim // factor) ** dims)


def stage1_hypothesis_count(config: SearchConfig, known_focal: bool = False) -> int:
    """Hypotheses the Manhattan search's stage 1 scores per image: k^3 with a known focal length and
    k^4 for the whole grid; coarse to fine (``grid_coarse_factor`` s > 1, focal length unknown), the
    (k/s)^4 coarse cells plus the s^4 points of each kept cell (768 at the defaults)."""
    factor = config.grid_coarse_factor
    if known_focal:
        return config.grid_points_per_dim ** 3
    if factor == 1:
        return config.grid_points_per_dim ** 4
    return (config.grid_points_per_dim // factor) ** 4 + kept_coarse_cells(config) * factor ** 4


def coarse_to_fine_scores(likelihood: MixtureLikelihood, features: SegmentFeatures, config: SearchConfig,
                          hypotheses: torch.Tensor, long_side: torch.Tensor,
                          known_focal: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Stage 1 coarse to fine (``config.grid_coarse_factor`` = s > 1): the k^4 grid ``hypotheses``
    (B, G, 4) of :func:`grid_hypotheses` scored only inside the best cells of the (k/s)^4 grid.

    The coarse grid's cells are unions of s^4 cells of the k^4 grid (its cell centres and focal
    spacing nest), so the coarse grid is scored (:func:`score_grid`), each image's
    ``config.grid_coarse_cells`` best coarse cells are kept (equal scores in grid order) and the
    k^4 grid's points inside them are scored: ``(k/s)^4 + grid_coarse_cells * s^4`` hypotheses per
    image (k^3 analogues with a known focal; more cells where fewer points than ``top_l`` would be
    scored).  ``long_side`` (B,) pixels and ``known_focal`` (B,) pixels or None: as given to
    :func:`grid_hypotheses` (:class:`SearchConfig` makes sure s divides k).

    Returns (``grid_scores``, ``selectable``), both (B, G) float64 over the k^4 grid:
    ``selectable`` holds the scores of the points scored and -inf elsewhere (what
    :func:`select_starts` takes); ``grid_scores`` the same with every point not scored given its
    coarse cell's score (a stand-in for the full grid's scores, for the ``grid_entropy`` cue).
    When every coarse cell is kept, ``selectable`` equals :func:`score_grid` of the whole grid,
    bit for bit.
    """
    factor = config.grid_coarse_factor
    coarse_k = config.grid_points_per_dim // factor
    coarse_config = replace(config, grid_points_per_dim=coarse_k, grid_coarse_factor=1)
    device = hypotheses.device
    coarse = grid_hypotheses(coarse_config, long_side.to(device),
                             None if known_focal is None else known_focal.to(device))
    coarse_scores = score_grid(likelihood, features, coarse, config.max_chunk_elements, vertical_block=coarse_k)
    batch, count = hypotheses.shape[:2]
    n_focal = count // config.grid_points_per_dim ** 3
    cells = top_indices(coarse_scores, kept_coarse_cells(config, known_focal=n_focal == 1), dim=1)
    members = _cell_members(cells, coarse_k, factor, n_focal)  # (B, M s^D)
    fine = torch.gather(hypotheses, 1, members[..., None].expand(-1, -1, hypotheses.shape[-1]))
    fine_scores = score_grid(likelihood, features, fine, config.max_chunk_elements, vertical_block=factor)
    shape = (batch, n_focal // factor if n_focal > 1 else 1, coarse_k, coarse_k, coarse_k)
    upsampled = coarse_scores.view(shape)
    for dim in range(1 if n_focal > 1 else 2, 5):
        upsampled = upsampled.repeat_interleave(factor, dim)
    grid_scores = upsampled.reshape(batch, count).clone()
    grid_scores.scatter_(1, members, fine_scores)
    selectable = torch.full_like(grid_scores, -math.inf).scatter_(1, members, fine_scores)
    return grid_scores, selectable


def stage1_scores(likelihood: MixtureLikelihood, features: SegmentFeatures, config: SearchConfig,
                  hypotheses: torch.Tensor, long_side: torch.Tensor, known_focal: torch.Tensor | None = None,
                  coarse: bool = True) -> tuple[torch.Tensor, torch.Tensor]:
    """The grid ``hypotheses`` (B, G, 4) of :func:`grid_hypotheses` scored for :func:`select_starts`:
    coarse to fine (:func:`coarse_to_fine_scores`) where ``coarse`` and ``config.grid_coarse_factor``
    > 1, else the whole grid (:func:`score_grid`).  ``long_side`` (B,) and ``known_focal`` (B,) pixels
    or None: as given to :func:`grid_hypotheses`.  Returns (``grid_scores``, ``selectable``) as
    :func:`coarse_to_fine_scores` does (both the whole grid's scores when it is scored whole)."""
    if coarse and config.grid_coarse_factor > 1:
        return coarse_to_fine_scores(likelihood, features, config, hypotheses, long_side, known_focal)
    scores = score_grid(likelihood, features, hypotheses, config.max_chunk_elements,
                        vertical_block=config.grid_points_per_dim)
    return scores, scores
