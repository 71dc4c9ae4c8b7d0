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
(``log p_i = log((1 - sum_j w_j) p_i^Manhattan + sum_j w_j h_i(v_j))``, the horizontal family's
density ``h``) by the same loop (:func:`~fr_torch.core.search.refine.adam_in_box`).  Every extra
family moves with R, so its segments vote for the horizon and f.  How many families a photo has is
decided by a held-out likelihood of its own segments (:func:`held_out_gains`): families found on
one half of the segments must explain the other half.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass

import torch

from fr_torch.core.exact import exact_sum, first_argmax, small_sum
from fr_torch.core.geometry.conventions import VERTICAL_AXIS, vanishing_points
from fr_torch.core.geometry.params import FOCAL, PAN, rotations
from fr_torch.core.geometry.vanishing import AtlantaConfig, horizon_points, rank_vanishing_points
from fr_torch.core.likelihood.measures import SegmentFeatures
from fr_torch.core.likelihood.mixture import MixtureLikelihood
from fr_torch.core.search.grid import grid_hypotheses, parameter_box, select_starts, stage1_scores
from fr_torch.core.search.passes import SearchResult, subdivide_starts, sweep_focal
from fr_torch.core.search.refine import UnitBox, adam_in_box, refine_starts
from fr_torch.core.settings.config import FamiliesConfig, SearchConfig
from fr_torch.core import exact_math


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
    # coarse to fine: the k^4 grid only inside the best coarse cells (a known focal length's k^3 grid whole)
    grid_scores, selectable = stage1_scores(likelihood, grid_features, config, hypotheses, long_side, known_focal,
                                            coarse=known_focal is None)
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
#: EM steps of :func:`_fit_mixture` (weights and scales at a fixed camera: :func:`held_out_gains`, the
#: refinement's start).
FAMILY_WEIGHT_EM_STEPS = 20


@dataclass
class FamiliesFit:
    """What :func:`fit_families` returns for B images: ``params`` (B, 4) float64 rows [pan, pitch,
    roll (degrees), f (pixels)] of the chosen model (the Manhattan fit's own rows where m = 0);
    ``azimuth_deg`` (B, max_extra) float64 the extra families' azimuths from ``R[:, 0]`` (degrees),
    NaN beyond the image's count; ``weight`` (B, max_extra) their mixture weights (NaN likewise);
    ``count`` (B,) int64 m; ``scores`` (B,) float64 the chosen model's
    objective (data + focal prior); ``criterion`` (B, max_extra + 1) float64 each m's
    :func:`held_out_gains` (segment units, -inf where m had no candidates)."""

    params: torch.Tensor
    azimuth_deg: torch.Tensor
    weight: torch.Tensor
    count: torch.Tensor
    scores: torch.Tensor
    criterion: torch.Tensor


def families_objective(likelihood: MixtureLikelihood, features: SegmentFeatures, rows: torch.Tensor) -> torch.Tensor:
    """The objective (B, H) float64 of H hypotheses per image, rows (B, H, 4 + 2m) [pan, pitch,
    roll (degrees), f (pixels), a_1..a_m (degrees), w_1..w_m], under the mixture of the 3 Manhattan
    families, m extra horizontal families at azimuths a_j with weights w_j (the Manhattan components
    and the background scaled by ``1 - sum_j w_j``) and the background: ``sum_i len_i log p_i``
    (an exact sum) plus the focal prior.  Every operation is elementwise or a sum in a fixed order
    (:func:`~fr_torch.core.exact.small_sum`, :func:`~fr_torch.core.exact.exact_sum`; no
    ``logsumexp`` or ``log1p``, whose float64 roundings differ between torch's kernel sets), so a
    hypothesis's value is the same bits in any batch, padding, thread count and kernel set."""
    batch, hypotheses, width = rows.shape
    extra = (width - 4) // 2
    rotation = rotations(rows.reshape(-1, width)[:, :4]).view(batch, hypotheses, 3, 3)
    focal = rows[..., FOCAL]  # (B, H)
    density = small_sum(exact_math.exp(likelihood.component_log_densities(features, rotation, focal)), -1)  # (B, N, H)
    if extra:
        density = _with_extra_families(likelihood, features, rotation, focal, density, rows[..., 4:4 + extra],
                                       rows[..., 4 + extra:])
    value = exact_sum(exact_math.log(density), 1, weight=features.weight[..., None])
    if likelihood.params.focal_prior_weight:
        value = value + likelihood.focal_prior(features, focal, derivative=False)[0]
    return value


def _horizon_deviations(likelihood, features, rotation, focal, azimuth_deg):
    """Deviations (B, N, H, m), internal units, of every segment from m horizontal families at
    azimuths (B, H, m) degrees from ``R[:, 0]`` under H hypotheses (rotations (B, H, 3, 3), focal
    lengths (B, H) pixels)."""
    batch, hypotheses, extra = azimuth_deg.shape
    points = horizon_points(rotation.reshape(-1, 3, 3), focal.reshape(-1),
                            features.principal_point.repeat_interleave(hypotheses, 0),
                            torch.deg2rad(azimuth_deg.reshape(-1, extra)))  # (B H, m, 3)
    x = likelihood.point_deviations(features, points.reshape(batch, hypotheses * extra, 3),
                                    focal.repeat_interleave(extra, 1))  # (B, N, H m)
    return x.view(batch, -1, hypotheses, extra)


def _with_extra_families(likelihood, features, rotation, focal, manhattan_density, azimuth_deg, weights):
    """The mixture density (B, N, H) ``(1 - sum_j w_j) p_i + sum_j w_j h_ij`` of the Manhattan mixture's
    density p (B, N, H) and m extra families at azimuths (B, H, m) degrees with weights (B, H, m)."""
    h = exact_math.exp(likelihood.horizontal_log_density(_horizon_deviations(likelihood, features, rotation, focal,
                                                                        azimuth_deg)))  # (B, N, H, m)
    return (1.0 - small_sum(weights, -1))[:, None] * manhattan_density + small_sum(weights[:, None] * h, -1)


def _family_deviations(likelihood, features, rotation, focal, azimuth_deg):
    """Deviations (B, N, 3 + m), internal units, of every segment from the three Manhattan vanishing
    points ``K R[:, k]`` and from m horizontal families at azimuths (B, m) degrees from ``R[:, 0]``;
    rotations (B, 3, 3), focal lengths (B,) pixels."""
    manhattan = likelihood.point_deviations(features, vanishing_points(focal, features.principal_point,
                                                                       rotation).transpose(1, 2), focal)
    extra = _horizon_deviations(likelihood, features, rotation[:, None], focal[:, None], azimuth_deg[:, None])
    return torch.cat([manhattan, extra[:, :, 0]], -1)


def _vertical_column(families: int, device) -> torch.Tensor:
    """(families,) bool: True at the vertical Manhattan family's column (``VERTICAL_AXIS``)."""
    vertical = torch.zeros(families, dtype=torch.bool, device=device)
    vertical[VERTICAL_AXIS] = True
    return vertical


def _mixture_densities(likelihood, deviations, background, scales):
    """The densities (B, N, C) of the C = 4 + m components of :func:`_fit_mixture` at ``scales``
    (B, 2) [horizontal, vertical]: the families' (``deviations`` (B, N, 3 + m); column
    ``VERTICAL_AXIS`` the vertical family's, the others horizontal) and the uniform ``background``
    (B, N)."""
    vertical = _vertical_column(deviations.shape[-1], deviations.device)
    scale = torch.where(vertical, scales[:, None, 1:], scales[:, None, :1])  # (B, 1, 3 + m)
    return torch.cat([exact_math.exp(likelihood.family_log_density(deviations, scale)), background[..., None]], -1)


def _fit_mixture(likelihood, deviations, background, weight, prior, iterations=FAMILY_WEIGHT_EM_STEPS):
    """The mixture of the three Manhattan families, m extra horizontal families and the uniform
    background that best explains the segments of ``weight`` (B, N) (lengths; 0: not counted),
    by EM: every component's weight and the two scales (horizontal families, the vertical one)
    fitted to the photo.  ``deviations`` (B, N, 3 + m) (:func:`_family_deviations`), ``background``
    (B, N) the background's density; the start: the likelihood's priors and scales, each extra
    family at ``prior``.  Returns (shares (B, 4 + m) [Manhattan 0..2, extras, background], scales
    (B, 2) [horizontal, vertical], internal units); the scales stay within a factor 4 of the
    likelihood's."""
    params = likelihood.params
    batch, _, families = deviations.shape
    extra = families - 3
    start = [params.prior_horizontal] * 3 + [0.0] * extra + [params.prior_background]
    start[VERTICAL_AXIS] = params.prior_vertical
    share = torch.tensor(start, dtype=deviations.dtype, device=deviations.device) * (1.0 - extra * prior)
    share[3:3 + extra] = prior
    share = share.expand(batch, -1)
    configured = torch.tensor([params.scale_horizontal, params.scale_vertical], dtype=deviations.dtype,
                              device=deviations.device)
    scales = configured.expand(batch, -1)
    vertical = _vertical_column(families, deviations.device)
    total = exact_sum(weight, 1).clamp_min(1e-12)
    for _ in range(iterations):
        parts = share[:, None, :] * _mixture_densities(likelihood, deviations, background, scales)  # (B, N, C)
        resp = parts / small_sum(parts, -1)[..., None]
        share = exact_sum(resp, 1, weight=weight[..., None]) / total[:, None]
        held = weight[..., None] * resp[..., :families]  # (B, N, 3 + m)
        fitted = [likelihood.fitted_scale(deviations[..., columns].transpose(1, 2).reshape(batch, -1),
                                          held[..., columns].transpose(1, 2).reshape(batch, -1))
                  for columns in (~vertical, vertical)]
        scales = torch.minimum(torch.maximum(torch.stack(fitted, 1), configured / 4), configured * 4)
    return share, scales


def held_out_gains(likelihood: MixtureLikelihood, features: SegmentFeatures, manhattan: torch.Tensor,
                   config: FamiliesConfig) -> torch.Tensor:
    """How much m = 0..``max_extra`` extra horizontal families explain segments they were not found
    on: (B, max_extra + 1) float64, segment units (log-likelihood times N / W); column 0 is 0, -inf
    where either half of the photo had fewer than m candidates.

    The segments are split in two halves by their index's parity (a fixed rule: the same halves in
    any batch).  On each half, the Atlanta search (:func:`rank_vanishing_points`, ``config``'s
    prior, support and exclusion) proposes azimuths at the Manhattan fit ``manhattan`` (B, 4); the
    mixture of the three Manhattan families, the first m proposed families and the uniform
    background is fitted there by EM (:func:`_fit_mixture`: every weight and the families' two
    scales), for each m including 0; the other half scores each fit, ``sum_i len_i log p_i`` over
    its segments, and the gain of m is its score less that of m = 0.  The two halves' gains add up.

    Why the weights and scales are fitted to the photo in this test: with the search's fixed
    background prior (a few percent) and one scale per family, a family at any azimuth explains
    part of the clutter better than the background does, and a family beside a real one explains
    that family's deviations' tails, on both halves.  Fitted, an extra family gains on the other
    half only where segments meet the horizon at its azimuth more often than the rest of the model
    explains: the search over azimuths is priced by the photo's own evidence, with no penalty
    constant."""
    rotation, focal = rotations(manhattan), manhattan[:, FOCAL]
    batch, most = manhattan.shape[0], config.max_extra
    background = likelihood.background_density(features)  # (B, N)
    parity = torch.arange(features.weight.shape[1], device=features.weight.device) % 2
    atlanta = AtlantaConfig(max_extra=most, prior=config.prior, min_support=config.min_support,
                            exclusion_deg=config.exclusion_deg, free_segments=0)
    gains = torch.zeros(batch, most + 1, dtype=manhattan.dtype, device=manhattan.device)
    for half in (0, 1):
        found_on = features.mask & (parity == half)
        scored_on = features.weight * (features.mask & (parity != half))
        candidates = _candidate_azimuths(rank_vanishing_points(likelihood, features.select(found_on), rotation, focal,
                                                               atlanta), most)
        deviations = _family_deviations(likelihood, features, rotation, focal, torch.nan_to_num(candidates, nan=0.0))
        scores = []
        for m in range(most + 1):
            x = deviations[..., :3 + m]
            share, scales = _fit_mixture(likelihood, x, background, features.weight * found_on, config.prior)
            density = small_sum(share[:, None, :] * _mixture_densities(likelihood, x, background, scales), -1)
            scores.append(exact_sum(exact_math.log(density), 1, weight=scored_on))
            if m:
                held = torch.isfinite(candidates[:, :m]).all(1)
                gains[:, m] = gains[:, m] + torch.where(held, scores[m] - scores[0], torch.full_like(scores[m], -math.inf))
    count_n = features.mask.sum(1).to(gains.dtype).clamp_min(1.0)
    return gains * (count_n / features.total_length().clamp_min(1e-9))[:, None]


def _candidate_azimuths(ranked, most: int) -> torch.Tensor:
    """The Atlanta families' azimuths (B, most) degrees in the order they were found, NaN where an
    image has fewer."""
    if not most:
        return ranked.azimuth_deg[:, :0]
    found = torch.stack([torch.where(ranked.family == 3 + j, ranked.azimuth_deg, torch.full_like(
        ranked.azimuth_deg, -math.inf)).amax(1) for j in range(most)], 1)
    return torch.where(torch.isfinite(found), found, torch.full_like(found, math.nan))


#: The central differences' step of the extra families' refinement, in unit-box coordinates
#: (:func:`_refine_families`).
DIFFERENCE_STEP = 1e-6


def _refine_families(likelihood, features, rows, lower, upper, iterations):
    """Rows (B, P = 4 + 2m) refined by :func:`adam_in_box` in the box ``lower`` / ``upper`` (B, P)
    on :func:`families_objective` per unit segment length; returns (rows, objective (B,)).

    The gradient is the central difference of the objective (step :data:`DIFFERENCE_STEP` in box
    units), its 2P + 1 points scored as hypotheses of one call: every value is an exact sum over the
    segments, so the step is the same bits in any batch, thread count and kernel set (autograd's
    backward sums over the segments in an order that depends on all three)."""
    box = UnitBox(lower[:, None], upper[:, None])
    u = box.to_unit(rows[:, None]).detach()
    total = features.total_length().clamp_min(1e-9)[:, None]
    width = rows.shape[1]
    offsets = torch.eye(width, dtype=u.dtype, device=u.device) * DIFFERENCE_STEP  # (P, P)

    def gradient(u_value):
        points = torch.cat([u_value, u_value + offsets, u_value - offsets], 1)  # (B, 2P + 1, P)
        value = families_objective(likelihood, features, box.to_params(points)) / total
        slope = (value[:, 1:1 + width] - value[:, 1 + width:]) / (2 * DIFFERENCE_STEP)  # (B, P)
        return value[:, :1], -slope[:, None]

    cell = 1.0 / 8
    with torch.no_grad():
        adam_in_box(u, box, iterations, 0.25 * cell, 0.002 * cell, gradient, periodic_pan=False, grad_bound=1e6)
        refined = box.to_params(u)[:, 0]
        return refined, families_objective(likelihood, features, refined[:, None])[:, 0]


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

    How many (m in 0..``max_extra``): the largest :func:`held_out_gains` (m = 0 on ties, and where
    no m gains).  Then, for a photo with m > 0, the first m candidates of the Atlanta search on all
    its segments, their weights (EM at the Manhattan fit, within :data:`WEIGHT_RANGE`) and the
    camera are refined together (pan within ``window_deg`` of its start, each azimuth within
    ``window_deg`` or half the distance to the nearest other family, pitch, roll and f within the
    search box) on :func:`families_objective`; if fewer than m candidates reach the support on all
    segments, m is that number.  Each photo is refined alone with its own m (the same bits in any
    batch).  Computed in float64."""
    dtype = torch.float64
    feats = SegmentFeatures(*(getattr(features, name).to(dtype) if torch.is_floating_point(getattr(features, name))
                              else getattr(features, name) for name in
                              ("line", "along", "half_length", "weight", "mask", "principal_point", "long_side")))
    manhattan, lower, upper = manhattan.to(dtype), lower.to(dtype), upper.to(dtype)
    batch, most = manhattan.shape[0], config.max_extra
    device = manhattan.device
    criterion = held_out_gains(likelihood, feats, manhattan, config) if most else \
        torch.zeros(batch, 1, dtype=dtype, device=device)
    atlanta = AtlantaConfig(max_extra=max(1, most), prior=config.prior, min_support=config.min_support,
                            exclusion_deg=config.exclusion_deg, free_segments=0)
    rotation, focal = rotations(manhattan), manhattan[:, FOCAL]
    choice = first_argmax(criterion, 1)  # (B,) m
    candidates = torch.full((batch, most), math.nan, dtype=dtype, device=device)
    searched = torch.nonzero(choice > 0)[:, 0]  # the Atlanta search on all segments, where a family is kept
    if len(searched):
        candidates[searched] = _candidate_azimuths(rank_vanishing_points(
            likelihood, feats.take_images(searched), rotation[searched], focal[searched], atlanta), most)
    choice = torch.minimum(choice, torch.isfinite(candidates).sum(1))  # found in order: a prefix
    rows = manhattan.clone()
    azimuth = torch.full((batch, most), math.nan, dtype=dtype, device=device)
    weight = torch.full((batch, most), math.nan, dtype=dtype, device=device)
    with torch.no_grad():
        scores = families_objective(likelihood, feats, manhattan[:, None])[:, 0]
    low_w, high_w = WEIGHT_RANGE
    for m in range(1, most + 1):
        index = torch.nonzero(choice == m)[:, 0]
        if not len(index):
            continue
        part = feats.take_images(index)
        start_rows, start = manhattan[index], candidates[index, :m]
        deviations = _family_deviations(likelihood, part, rotation[index], focal[index], start)
        weights = _fit_mixture(likelihood, deviations, likelihood.background_density(part), part.weight,
                               config.prior)[0][:, 3:3 + m] \
            .clamp(*WEIGHT_RANGE)  # the start: the extra families' shares fitted at the Manhattan camera
        half = _azimuth_windows(start, config.window_deg)
        low = torch.cat([lower[index], start - half, torch.full_like(start, low_w)], 1)
        high = torch.cat([upper[index], start + half, torch.full_like(start, high_w)], 1)
        low[:, PAN], high[:, PAN] = start_rows[:, PAN] - config.window_deg, start_rows[:, PAN] + config.window_deg
        refined, value = _refine_families(likelihood, part, torch.cat([start_rows, start, weights], 1), low, high,
                                          iterations)
        rows[index] = refined[:, :4]
        azimuth[index, :m] = torch.remainder(refined[:, 4:4 + m], 180.0)
        weight[index, :m] = refined[:, 4 + m:]
        scores[index] = value
    return FamiliesFit(rows, azimuth, weight, choice, scores, criterion)
