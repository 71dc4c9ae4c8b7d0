"""The Manhattan fit (fR, Fast-fR): the engine's stages on the mixture likelihood of a pinhole camera.

Stage 1 scores the k^4 grid over pan, pitch, roll and the focal length (:mod:`~fr_torch.core.search.grid`,
each image's ``grid_segments`` longest segments; with ``grid_coarse_factor`` > 1 only inside the best
cells of a coarser grid), keeps the best ``top_l`` points, adds each one's
best point along its focal ridge and sharpens them by lattice passes
(:mod:`~fr_torch.core.search.passes`); stage 2 refines them all with Adam inside the box
(:mod:`~fr_torch.core.search.refine`), and the better of each start and its refinement wins.  The lens
fit (:mod:`~fr_torch.core.search.lens`) runs the same stages with k as a fifth parameter.

**Extra horizontal families** (:func:`fit_families`, ``SearchConfig.families``, opt-in): an Atlanta
world inside the likelihood.  After the Manhattan fit, up to ``max_extra`` horizontal families with
vanishing points on the horizon, ``v_j = K (cos a_j R[:, 0] + sin a_j R[:, 2])``, join the mixture;
candidates ``a_j`` come from the Atlanta search of
:func:`fr_torch.core.geometry.vanishing.rank_vanishing_points` (a 1-D search over azimuth among the
segments the Manhattan mixture leaves to its background), then f, R and the azimuths are refined
together under the mixture of 3 + m families and the background
(``log p_i = log((1 - m prior) p_i^Manhattan + prior sum_j h_i(v_j))``, the horizontal family's
density ``h``) by the same loop (:func:`~fr_torch.core.search.refine.adam_in_box`).  Every extra
family moves with R, so its segments vote for the horizon and f.  Each photo keeps the count m of
the largest penalised likelihood (BIC, :class:`~fr_torch.core.settings.config.FamiliesConfig`).
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass

import torch

from fr_torch.core.exact import exact_sum, first_argmax
from fr_torch.core.geometry.params import FOCAL, PAN, rotations
from fr_torch.core.geometry.vanishing import AtlantaConfig, horizon_points, rank_vanishing_points
from fr_torch.core.likelihood.measures import SegmentFeatures
from fr_torch.core.likelihood.mixture import MixtureLikelihood
from fr_torch.core.search.grid import (
    coarse_to_fine_scores,
    grid_hypotheses,
    parameter_box,
    score_grid,
    select_starts,
)
from fr_torch.core.search.passes import SearchResult, subdivide_starts, sweep_focal
from fr_torch.core.search.refine import UnitBox, adam_in_box, refine_starts
from fr_torch.core.settings.config import FamiliesConfig, SearchConfig


def search_manhattan(likelihood: MixtureLikelihood, features: SegmentFeatures, config: SearchConfig,
                     long_side: torch.Tensor, known_focal: torch.Tensor | None, iterations: int,
                     fast: bool) -> SearchResult:
    """The whole search (module docstring) for the images of ``features``.

    ``long_side`` (B,) pixels (the FOV range is on the long side); ``known_focal`` (B,) pixels or
    None; ``iterations``, ``fast``: the refinement's steps and mode.  Returns rows
    [pan, pitch, roll, f] (B, 4).
    """
    t0 = time.perf_counter()
    device = features.weight.device
    hypotheses = grid_hypotheses(config, long_side.to(device), None if known_focal is None else known_focal.to(device))
    grid_features = features.longest(config.grid_segments) if config.grid_segments else features
    if config.grid_coarse_factor > 1:  # coarse to fine: the k^4 grid only inside the best coarse cells
        grid_scores, selectable = coarse_to_fine_scores(likelihood, grid_features, config, hypotheses,
                                                        long_side, known_focal)
    else:
        grid_scores = selectable = score_grid(likelihood, grid_features, hypotheses, config.max_chunk_elements,
                                              vertical_block=config.grid_points_per_dim)
    grid_counts = grid_features.mask.sum(-1)
    starts, top_scores = select_starts(config, selectable, hypotheses)
    lower, upper = parameter_box(config, long_side, known_focal)
    starts, top_scores = sweep_focal(likelihood, features, starts, top_scores, config, lower, upper)
    starts, top_scores = subdivide_starts(likelihood, features, starts, top_scores, config, lower, upper)
    grid_seconds = time.perf_counter() - t0
    params, scores, tied = refine_starts(likelihood, features, starts, top_scores, lower, upper, config, iterations,
                                         fast)
    return SearchResult(params, scores, grid_scores, grid_counts, grid_seconds, tied, lower, upper)

#: The range of an extra family's mixture weight in the joint refinement (:func:`fit_families`).
WEIGHT_RANGE = (0.002, 0.4)


@dataclass
class FamiliesFit:
    """What :func:`fit_families` returns for B images: ``params`` (B, 4) float64 rows [pan, pitch,
    roll (degrees), f (pixels)] of the chosen model (the Manhattan fit's own rows where m = 0);
    ``azimuth_deg`` (B, max_extra) float64 the extra families' azimuths from ``R[:, 0]`` (degrees),
    NaN beyond the image's count; ``weight`` (B, max_extra) their mixture weights (NaN likewise);
    ``count`` (B,) int64 m; ``scores`` (B,) float64 the chosen model's
    objective (data + focal prior); ``criterion`` (B, max_extra + 1) float64 the penalised gain of
    each m (segment units, -inf where m had no candidates)."""

    params: torch.Tensor
    azimuth_deg: torch.Tensor
    weight: torch.Tensor
    count: torch.Tensor
    scores: torch.Tensor
    criterion: torch.Tensor


def families_objective(likelihood: MixtureLikelihood, features: SegmentFeatures, rows: torch.Tensor) -> torch.Tensor:
    """The objective (B,) float64 of rows (B, 4 + 2m) [pan, pitch, roll (degrees), f (pixels),
    a_1..a_m (degrees), w_1..w_m] under the mixture of the 3 Manhattan families, m extra horizontal
    families at azimuths a_j with weights w_j (the Manhattan components and the background scaled
    by ``1 - sum_j w_j``) and the background: ``sum_i len_i log p_i`` (exact sum, the gradient of a
    plain one) plus the focal prior.  Differentiable in ``rows`` (the generic path of
    :class:`MixtureLikelihood`)."""
    extra = (rows.shape[-1] - 4) // 2
    rotation = rotations(rows[:, :4])  # (B, 3, 3)
    focal = rows[:, FOCAL]
    log_p = torch.logsumexp(likelihood.component_log_densities(features, rotation[:, None], focal[:, None])[:, :, 0],
                            -1)  # (B, N)
    if extra:
        points = horizon_points(rotation, focal, features.principal_point, torch.deg2rad(rows[:, 4:4 + extra]))
        log_h = likelihood.horizontal_log_density(likelihood.point_deviations(features, points, focal))  # (B, N, m)
        weights = rows[:, 4 + extra:]
        log_p = torch.logsumexp(torch.cat([log_p[..., None] + torch.log1p(-weights.sum(1))[:, None, None],
                                           log_h + torch.log(weights)[:, None, :]], -1), -1)
    value = exact_sum(log_p, 1, weight=features.weight)
    if likelihood.params.focal_prior_weight:
        value = value + likelihood.focal_prior(features, focal[:, None], derivative=False)[0][:, 0]
    return value


def _refine_families(likelihood, features, rows, lower, upper, iterations):
    """Rows (B, 4 + 2m) refined by :func:`adam_in_box` in the box ``lower`` / ``upper`` (B, 4 + 2m)
    on :func:`families_objective` per unit segment length; returns (rows, objective (B,))."""
    box = UnitBox(lower[:, None], upper[:, None])
    u = box.to_unit(rows[:, None]).detach()
    total = features.total_length().clamp_min(1e-9)

    def gradient(u_value):
        with torch.enable_grad():
            u_value = u_value.detach().requires_grad_(True)
            objective = families_objective(likelihood, features, box.to_params(u_value)[:, 0])
            finite = torch.where(torch.isfinite(objective), objective, torch.zeros_like(objective))
            (grad,) = torch.autograd.grad(-(finite / total).sum(), u_value)
        return objective.detach()[:, None], grad

    cell = 1.0 / 8
    adam_in_box(u, box, iterations, 0.25 * cell, 0.002 * cell, gradient, periodic_pan=False, grad_bound=1e6)
    with torch.no_grad():
        refined = box.to_params(u)[:, 0]
        return refined, families_objective(likelihood, features, refined)


def _azimuth_windows(candidates: torch.Tensor, window: float) -> torch.Tensor:
    """Half-widths (B, m) degrees of each candidate azimuth's refinement box: ``window``, or half
    the distance (modulo 180 degrees) to the nearest other family (the Manhattan ones at 0 and 90,
    the other candidates) where that is less, so that no family can become a copy of another."""
    others = torch.cat([torch.zeros_like(candidates[:, :1]), torch.full_like(candidates[:, :1], 90.0), candidates], 1)
    gap = torch.remainder(candidates[:, :, None] - others[:, None, :], 180.0)
    gap = torch.minimum(gap, 180.0 - gap)  # (B, m, 2 + m)
    self_index = torch.arange(candidates.shape[1], device=candidates.device) + 2
    gap[:, torch.arange(candidates.shape[1]), self_index] = math.inf
    return torch.clamp(gap.amin(-1) / 2, max=window)


def fit_families(likelihood: MixtureLikelihood, features: SegmentFeatures, manhattan: torch.Tensor,
                 lower: torch.Tensor, upper: torch.Tensor, config: FamiliesConfig, iterations: int) -> FamiliesFit:
    """Extra horizontal families inside the likelihood (module docstring) for the images of
    ``features`` after the Manhattan fit ``manhattan`` (B, 4) rows [pan, pitch, roll, f], inside the
    search box ``lower`` / ``upper`` (B, 4); ``iterations``: refinement steps.

    Candidates: the Atlanta search (horizontal families only, ``config``'s prior, support and
    exclusion) at the Manhattan fit.  For m = 1..``max_extra`` the first m candidates, their weights
    (from ``prior``, within [:data:`WEIGHT_RANGE`]) and the camera are refined together (pan within
    ``window_deg`` of its start, each azimuth within ``window_deg`` or half the distance to the
    nearest other family, pitch, roll and f within the search box); the photo keeps the m of the
    largest ``(L_m - L_0) N / W - penalty m log N`` (BIC with two parameters per family, azimuth
    and weight; L: :func:`families_objective`, W: the total segment length, N: the segment count),
    m = 0 on ties.  Computed in float64."""
    dtype = torch.float64
    feats = SegmentFeatures(*(getattr(features, name).to(dtype) if torch.is_floating_point(getattr(features, name))
                              else getattr(features, name) for name in
                              ("line", "along", "half_length", "weight", "mask", "principal_point", "long_side")))
    manhattan, lower, upper = manhattan.to(dtype), lower.to(dtype), upper.to(dtype)
    batch, most = manhattan.shape[0], config.max_extra
    atlanta = AtlantaConfig(max_extra=max(1, most), prior=config.prior, min_support=config.min_support,
                            exclusion_deg=config.exclusion_deg, free_segments=0)
    ranked = rank_vanishing_points(likelihood, feats, rotations(manhattan), manhattan[:, FOCAL], atlanta)
    candidates = torch.stack([torch.where(ranked.family == 3 + j, ranked.azimuth_deg, torch.full_like(
        ranked.azimuth_deg, -math.inf)).amax(1) for j in range(most)], 1) if most else manhattan[:, :0]
    candidates = torch.where(torch.isfinite(candidates), candidates, torch.full_like(candidates, math.nan))
    count_n = feats.mask.sum(1).to(dtype).clamp_min(1.0)
    per_segment = count_n / feats.total_length().clamp_min(1e-9)
    with torch.no_grad():
        base = families_objective(likelihood, feats, manhattan)
    criterion = torch.full((batch, most + 1), -math.inf, dtype=dtype, device=manhattan.device)
    criterion[:, 0] = 0.0
    fits, scores = [manhattan], [base]
    low_w, high_w = WEIGHT_RANGE
    for m in range(1, most + 1):
        start = torch.nan_to_num(candidates[:, :m], nan=0.0)
        held = torch.isfinite(candidates[:, :m]).all(1)
        half = _azimuth_windows(start, config.window_deg)
        weights = torch.full_like(start, config.prior)
        rows = torch.cat([manhattan, start, weights], 1)
        low = torch.cat([lower, start - half, torch.full_like(start, low_w)], 1)
        high = torch.cat([upper, start + half, torch.full_like(start, high_w)], 1)
        low[:, PAN], high[:, PAN] = manhattan[:, PAN] - config.window_deg, manhattan[:, PAN] + config.window_deg
        refined, value = _refine_families(likelihood, feats, rows, low, high, iterations)
        gain = (value - base) * per_segment - config.penalty * m * torch.log(count_n)
        criterion[:, m] = torch.where(held & torch.isfinite(gain), gain, criterion[:, m])
        fits.append(refined)
        scores.append(value)
    choice = first_argmax(criterion, 1)  # (B,) m
    rows = torch.zeros(batch, 4, dtype=dtype, device=manhattan.device)
    azimuth = torch.full((batch, most), math.nan, dtype=dtype, device=manhattan.device)
    weight = torch.full((batch, most), math.nan, dtype=dtype, device=manhattan.device)
    chosen_scores = torch.zeros(batch, dtype=dtype, device=manhattan.device)
    for m, (fit, value) in enumerate(zip(fits, scores)):
        pick = choice == m
        rows = torch.where(pick[:, None], fit[:, :4], rows)
        if m:
            azimuth[:, :m] = torch.where(pick[:, None], torch.remainder(fit[:, 4:4 + m], 180.0), azimuth[:, :m])
            weight[:, :m] = torch.where(pick[:, None], fit[:, 4 + m:], weight[:, :m])
        chosen_scores = torch.where(pick, value, chosen_scores)
    return FamiliesFit(rows, azimuth, weight, choice, chosen_scores, criterion)
