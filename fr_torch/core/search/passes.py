"""Between the grid and the refinement: the focal sweep, the lattice passes, and the tie rules.

Each of the best ``top_l`` grid points gains a second start, its best point along its focal ridge
(:func:`sweep_focal`: the vertical VP, the best-determined, held fixed while f runs over the whole
range); all 2l starts are then sharpened by ``grid_passes`` coarse-to-fine passes
(:func:`lattice_passes` of the 3^4 :data:`LATTICE` at a third of the previous spacing around each,
keep the best; :func:`subdivide_starts`), so the refinement starts within 1/27 of a grid cell of
the best lattice point instead of half a cell.  The lens fit passes a lattice with k
(:func:`fr_torch.core.search.lens.subdivide_rows`) to the same :func:`lattice_passes`.

After the refinement the better of each start and its refinement wins
(:func:`best_of_start_and_refined`); two different solutions within rounding of each other
(:func:`tie_tolerance`) make the estimate ``tied``: another machine could return the other.
What a fit found is a :class:`SearchResult`.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from fr_torch.core.exact import cross3, dot3, first_argmax
from fr_torch.core.geometry.conventions import VERTICAL_AXIS
from fr_torch.core.geometry.params import (
    ANGLES,
    DISTORTION,
    FOCAL,
    PAN,
    angles_from_search_rotation,
    from_log_focal,
    rotations,
    to_log_focal,
)
from fr_torch.core.likelihood.measures import SegmentFeatures
from fr_torch.core.likelihood.mixture import MixtureLikelihood
from fr_torch.core.search.grid import grid_cell, into_box, log_spaced_focals, score_grid
from fr_torch.core.settings.config import SearchConfig
from fr_torch.core import exact_math


def _focal_ridge_rotations(rotation: torch.Tensor, ratio: torch.Tensor) -> torch.Tensor:
    """Rotations that keep the vertical VP's image position when f is multiplied by ``ratio``.

    ``rotation`` (..., 3, 3) world->camera (column i = world axis i in camera coordinates),
    ``ratio`` (..., m) = f_new / f.  A VP at pp + f (d_x, d_y) / d_z stays put when d_z scales
    with the ratio (a VP at infinity, d_z = 0, stays put by itself).  The vertical column is
    rescaled that way; the horizontal column whose VP lies nearer the image centre (larger |d_z|)
    is rescaled too and made orthogonal to the vertical (it moves as little as the orthogonality
    of the VPs allows); the third column completes a right-handed frame.  Returns (..., m, 3, 3).
    """
    def unit(d):
        return d / exact_math.sqrt(dot3(d, d))[..., None]

    def rescaled(direction):  # (..., 3) -> (..., m, 3), unit length
        d = direction[..., None, :].expand(ratio.shape + (3,))
        return unit(torch.cat([d[..., :2], d[..., 2:] * ratio[..., None]], -1))

    first_nearer = rotation[..., 2, 0].abs() >= rotation[..., 2, 2].abs()  # (...)
    horizontal = torch.where(first_nearer[..., None], rotation[..., :, 0], rotation[..., :, 2])
    vertical = rescaled(rotation[..., :, VERTICAL_AXIS])
    horizontal = rescaled(horizontal)
    horizontal = unit(horizontal - dot3(horizontal, vertical)[..., None] * vertical)
    first_nearer = first_nearer[..., None, None]
    column0 = torch.where(first_nearer, horizontal, cross3(vertical, horizontal))
    column2 = torch.where(first_nearer, cross3(horizontal, vertical), horizontal)
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
    still lie in a lower basin, so both are refined.

    ``starts`` (B, L, 4) [pan, pitch, roll, f], ``scores`` (B, L), ``lower`` / ``upper`` (B, 4)
    the parameter box (points are moved into it by :func:`into_box`).  Returns (starts, scores) of shape (B, 2L, 4)
    and (B, 2L): the L inputs, then for each the best swept point if it beats the start's score,
    else a copy of the start.  Each start is swept on its own (a batch gives the same answer as
    images one by one).  A known focal (``lower`` f == ``upper`` f) or m = 0 returns the inputs.
    """
    count = config.focal_sweep_points
    if count == 0 or bool((upper[:, FOCAL] <= lower[:, FOCAL]).all()):
        return starts, scores
    device = features.weight.device
    batch, n_start = starts.shape[:2]
    start64 = starts.to(device=device, dtype=torch.float64)
    lower64 = lower.to(device=device, dtype=torch.float64)
    upper64 = upper.to(device=device, dtype=torch.float64)
    focal = log_spaced_focals(lower64[:, FOCAL], upper64[:, FOCAL], count)[:, None, :].expand(batch, n_start, count)
    rotation = _focal_ridge_rotations(rotations(start64), focal / start64[..., FOCAL:])  # (B, L, m, 3, 3)
    angles = angles_from_search_rotation(rotation)  # (B, L, m, 3)
    pan_step = (upper64[:, PAN] - lower64[:, PAN]) / (3 * config.grid_points_per_dim)  # 1/3 of a grid cell
    pan_offsets = torch.stack([torch.zeros_like(pan_step), -pan_step, pan_step], -1)  # (B, 3)
    points = torch.cat([angles, focal[..., None]], -1)[:, :, :, None, :].repeat(1, 1, 1, 3, 1)
    points[..., PAN] += pan_offsets[:, None, None, :]  # pan fastest: runs of 3 share the vertical VP
    points = into_box(points, lower64[:, None, None, None], upper64[:, None, None, None], config.periodic_pan)
    points = points.view(batch, n_start, -1, 4)
    point_scores = score_grid(likelihood, features, points.view(batch, -1, 4), config.max_chunk_elements,
                              vertical_block=3)
    swept, swept_scores = _keep_best(starts, scores, points, point_scores, tie_tolerance(features))
    return torch.cat([starts, swept], 1), torch.cat([scores, swept_scores], 1)


#: Scores of one image closer than this many nats per pixel of its segment length are ties.  The
#: objective's float32 terms differ by a few ulps between CPU families and devices (its sums are
#: exact, :mod:`fr_torch.core.exact`), which moves a score by well under this; a choice between tied
#: candidates follows their order, not their last bits.
TIE_NATS_PER_PX = 2.0 ** -20
#: Two solutions of one image are different answers (not the same basin reached twice) when their
#: focal lengths differ by more than this share or an angle by more than SOLUTION_ANGLE_DEG.
SOLUTION_FOCAL = 0.01
SOLUTION_ANGLE_DEG = 0.5


def tie_tolerance(segments) -> torch.Tensor:
    """(B,) float64: the score difference below which two hypotheses of an image are tied, nats
    (:data:`TIE_NATS_PER_PX` times the image's total segment length).  ``segments``: a
    :class:`~fr_torch.core.likelihood.measures.SegmentFeatures` or a
    :class:`~fr_torch.core.search.lens.SegmentGeometry` (their ``total_length()``, pixels)."""
    return segments.total_length() * TIE_NATS_PER_PX


def near_best(scores: torch.Tensor, tolerance: torch.Tensor) -> torch.Tensor:
    """(..., C) bool: the candidates of ``scores`` (..., C) within ``tolerance`` (broadcastable to
    ``scores[..., 0]``) of the best along the last dimension (NaN scores never are)."""
    best = torch.where(torch.isnan(scores), -math.inf, scores).amax(-1, keepdim=True)
    return scores >= best - tolerance.to(best)[..., None]


def first_near_best(scores: torch.Tensor, tolerance: torch.Tensor) -> torch.Tensor:
    """Index along the last dimension of ``scores`` (..., C) of the first candidate within
    ``tolerance`` (broadcastable to ``scores[..., 0]``) of the best: int64 (...).  The choice does
    not move with the scores' last bits unless a candidate sits right at the tolerance's edge."""
    return first_argmax(near_best(scores, tolerance).to(torch.int8), -1)


def different_solutions(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """(...) bool: parameter rows a, b (..., 4 or 5) [pan, pitch, roll (deg), f (px), k] are different
    answers (:data:`SOLUTION_FOCAL`, :data:`SOLUTION_ANGLE_DEG`; pan compared modulo 90 deg, k by
    0.02)."""
    angles = (a[..., ANGLES] - b[..., ANGLES]).abs()
    pan = torch.remainder(angles[..., 0], 90.0)
    angles = torch.cat([torch.minimum(pan, 90.0 - pan)[..., None], angles[..., 1:]], -1)
    apart = (angles > SOLUTION_ANGLE_DEG).any(-1) | (exact_math.log(a[..., FOCAL] / b[..., FOCAL]).abs() > SOLUTION_FOCAL)
    if a.shape[-1] > DISTORTION:
        apart = apart | ((a[..., DISTORTION] - b[..., DISTORTION]).abs() > 0.02)
    return apart


def _keep_best(starts: torch.Tensor, scores: torch.Tensor, points: torch.Tensor, point_scores: torch.Tensor,
               tolerance: torch.Tensor):
    """Each start's best candidate where it scores higher than the start by more than ``tolerance``,
    else the start.

    ``starts`` (B, L, 4) with ``scores`` (B, L); ``points`` (B, L, P, 4) candidates per start with
    their ``point_scores`` (B, L * P) from :func:`score_grid`; ``tolerance`` (B,) nats
    (:func:`tie_tolerance`): the first candidate within it of the best is taken.  Returns (starts,
    scores), same shapes and dtypes as the inputs.
    """
    candidate_scores = point_scores.view(scores.shape + (-1,))
    tolerance = tolerance.to(candidate_scores)[:, None]  # (B, 1)
    best = first_near_best(candidate_scores, tolerance)
    best_scores = torch.gather(candidate_scores, -1, best[..., None])[..., 0]
    better = best_scores > scores + tolerance
    chosen = torch.gather(points, 2, best[..., None, None].expand(-1, -1, 1, points.shape[-1]))[:, :, 0]
    return torch.where(better[..., None], chosen.to(starts), starts), torch.where(better, best_scores, scores)


def best_of_start_and_refined(starts: torch.Tensor, start_scores: torch.Tensor, refined: torch.Tensor,
                              refined_scores: torch.Tensor, tolerance: torch.Tensor):
    """Each image's best of {its best start, its refined points}, ties (:func:`first_near_best`
    within ``tolerance`` (B,) nats) going to the earlier candidate.

    ``starts`` (B, L, D) with ``start_scores`` (B, L), the first of each image its best; ``refined``
    (B, R, D) with ``refined_scores`` (B, R).  Returns (params (B, D) float64, scores (B,) in
    ``refined_scores``' dtype, tied (B,) bool: another candidate within the tolerance is a
    different answer (:func:`different_solutions`), so rounding could choose it elsewhere)."""
    candidates = torch.cat([starts[:, :1].to(refined), refined], 1).to(torch.float64)
    candidate_scores = torch.cat([start_scores[:, :1].to(refined_scores), refined_scores], 1)
    near = near_best(candidate_scores.to(torch.float64), tolerance)
    best = first_argmax(near.to(torch.int8), -1)
    rows = torch.arange(len(best), device=best.device)
    chosen = candidates[rows, best]
    tied = (near & different_solutions(candidates, chosen[:, None])).any(1)
    return chosen, candidate_scores[rows, best], tied


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
    lower64, upper64 = lower.to(torch.float64), upper.to(torch.float64)
    step = grid_cell(config, lower64, upper64)

    def score_points(points: torch.Tensor, place):
        hypotheses = from_log_focal(points).view(points.shape[0], -1, 4)
        return points, score_grid(likelihood, features, hypotheses, config.max_chunk_elements, vertical_block=3)

    return lattice_passes(starts, scores, LATTICE, step, lower64, upper64, config, score_points,
                          tie_tolerance(features), features.weight.device)


def lattice_passes(starts: torch.Tensor, scores: torch.Tensor, lattice: torch.Tensor, step: torch.Tensor,
                   lower: torch.Tensor, upper: torch.Tensor, config: SearchConfig, score_points,
                   tolerance: torch.Tensor, device: torch.device) -> tuple[torch.Tensor, torch.Tensor]:
    """The coarse-to-fine pass loop of :func:`subdivide_starts`, for D parameters [pan, pitch, roll,
    f (, k)]: ``config.grid_passes`` passes; each places ``lattice`` (P, D) float64 offsets, times
    ``step`` (B, D) (in log f for the focal length) divided by 3 per pass, around every start,
    moves the points into the box [``lower``, ``upper``] (B, D) (:func:`into_box`), scores them and
    keeps each start's best point where it beats the start (:func:`_keep_best`, ``tolerance`` (B,)).

    ``score_points(points, place)``: the pass's lattice points (B, L, P, D) in log f, and
    ``place(offsets)``, which places other offsets (Q, D) around the starts as the lattice was
    placed (scaled by the pass's step, moved into the box) -> (candidates (B, L, P', D), their
    scores (B, L * P')) (a lens search adds candidates of its own that way,
    :func:`fr_torch.core.search.lens.subdivide_rows`).  ``starts`` (B, L, D) [pan, pitch,
    roll, f (pixels)(, k)] and ``scores`` (B, L); returns both, the same shapes; the points live on
    ``device``.
    """
    log_lower = to_log_focal(lower.to(torch.float64))[:, None, None, :].to(device)
    log_upper = to_log_focal(upper.to(torch.float64))[:, None, None, :].to(device)
    step = step[:, None, None, :].to(device)  # (B, 1, 1, D)
    lattice = lattice.to(device)
    current = to_log_focal(starts.to(device=device, dtype=torch.float64))
    fraction = 1.0
    for _ in range(config.grid_passes):
        fraction /= 3.0

        def place(offsets: torch.Tensor, around: torch.Tensor = current, scale: torch.Tensor = step * fraction):
            return into_box(around[:, :, None, :] + offsets * scale, log_lower, log_upper, config.periodic_pan)

        points, point_scores = score_points(place(lattice), place)  # lattice points (B, L, P, D)
        current, scores = _keep_best(current, scores, points, point_scores, tolerance)
    return from_log_focal(current).to(starts), scores


@dataclass
class SearchResult:
    """What a fit's search (:func:`~fr_torch.core.search.manhattan.search_manhattan`,
    :func:`~fr_torch.core.search.lens.search_with_k`) found for B images.

    ``params`` (B, P) the estimates (P = 4: [pan, pitch, roll (degrees), f (pixels)]; 5 with the
    division model's k) and ``scores`` (B,) their objectives; ``grid_scores`` (B, G) and
    ``grid_counts`` (B,) the stage-1 scores and the segments each image's grid scored (the
    ``grid_entropy`` cue); ``grid_seconds``: the time of the stages before the refinement (all
    images); ``tied`` (B,) bool: another solution scored within rounding of the estimate
    (:func:`best_of_start_and_refined`); ``lower``, ``upper`` (B, P): the search box.
    """

    params: torch.Tensor
    scores: torch.Tensor
    grid_scores: torch.Tensor
    grid_counts: torch.Tensor
    grid_seconds: float
    tied: torch.Tensor
    lower: torch.Tensor
    upper: torch.Tensor
