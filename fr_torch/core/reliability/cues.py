"""The reliability cues of an estimate.

The cues feed the error model (:mod:`fr_torch.core.reliability.model`): the paper's three (segments per
family, grid entropy, mean log-likelihood) and geometric ones of ours (focal conditioning, the focal
prior's share, the focal profile gap); the spreads (:data:`SPREAD_CUE_NAMES`: how far f and the pitch
could move before the segments notice, from the focal profile and a segment resampling) feed the
bounds of ``reliable`` (:mod:`fr_torch.core.reliability.bounds`).  The sanity checks that use
some of them are :mod:`fr_torch.core.reliability.sanity`.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Sequence

import torch

from fr_torch.core.exact import (exact_sum, first_argmax, positive_definite, small_inverse, small_matmul, small_solve,
                                 small_sum)
from fr_torch.core.geometry.params import FOCAL, from_log_focal, rotations, to_log_focal
from fr_torch.core.likelihood.measures import SegmentFeatures
from fr_torch.core.likelihood.mixture import MixtureLikelihood
from fr_torch.core.search.grid import grid_hypotheses, parameter_box, select_starts, stage1_scores
from fr_torch.core.search.passes import LATTICE
from fr_torch.core.search.refine import refine
from fr_torch.core.settings.config import FAST_REFINE_ITERATIONS, SearchConfig
from fr_torch.core import exact_math


def _quadratic_fit_matrix() -> torch.Tensor:
    """(15, 81) least-squares map from objective values on :data:`LATTICE` to the coefficients of
    ``c + g.x + x.H.x / 2`` in lattice units: [c, g (4), H_00, H_01, H_02, H_03, H_11, H_12, ..., H_33]."""
    x = LATTICE
    columns = [torch.ones(len(x), dtype=torch.float64)] + [x[:, j] for j in range(4)]
    columns += [x[:, i] * x[:, j] * (0.5 if i == j else 1.0) for i in range(4) for j in range(i, 4)]
    design = torch.stack(columns, 1)  # (81, 15): entries are multiples of 1/2, so every sum below is exact
    normal = exact_sum(design[:, :, None] * design[:, None, :], 0)
    fit, _ = small_solve(normal, design.T.contiguous())  # the pseudo-inverse (D'D)^-1 D' of a full-rank D
    return fit


#: Lattice spacing of :func:`focal_prior_share`: [pan, pitch, roll] in degrees, then log f (5 % of f).
PRIOR_SHARE_STEP = (0.5, 0.5, 0.5, 0.05)


_QUADRATIC_FIT = _quadratic_fit_matrix()
#: Column of the fit's coefficients holding H[i, j], for the 16 entries of the symmetric 4 x 4 H.
_HESSIAN_COLUMNS = torch.tensor([5 + [(a, b) for a in range(4) for b in range(a, 4)].index((min(i, j), max(i, j)))
                                 for i in range(4) for j in range(4)])


@dataclass
class LocalFit:
    """What the 3^4 lattice of :data:`PRIOR_SHARE_STEP` around each estimate says
    (:func:`local_quadratic`), [pan, pitch, roll (degrees), log f] throughout.

    ``hessian`` (B, 4, 4) float64: second derivatives of the objective (likelihood + focal prior),
    objective units per unit^2 (negative definite at a clean maximum); ``prior_curvature`` (B,):
    ``-d^2 prior / d(log f)^2`` (>= 0; 0 without a prior or inside its flat top);
    ``gradient_spread`` (B, 4, 4): ``J = n / (n - 1) sum_i (g_i - mean g)(g_i - mean g)^T`` over the
    image's n segments, ``g_i`` segment i's gradient (the spread of the summed gradient when the
    segments are resampled, :func:`resample_spreads`)."""
    hessian: torch.Tensor
    prior_curvature: torch.Tensor
    gradient_spread: torch.Tensor


def local_quadratic(likelihood: MixtureLikelihood, features: SegmentFeatures, params: torch.Tensor,
                    max_chunk_elements: int = SearchConfig.max_chunk_elements) -> LocalFit:
    """A local Laplace approximation of the objective around each estimate, and the segments' spread.

    Every segment's term ``len_i log p_i`` (:meth:`~fr_torch.core.likelihood.mixture.MixtureLikelihood.segment_log_p`)
    is scored once on the 3^4 lattice of :data:`PRIOR_SHARE_STEP` around each estimate.  Their sums
    (plus the focal prior: the objective, bit for bit) are fitted by a quadratic (the lattice
    spacing smooths the kinks of the exponential likelihood): the Hessian; the focal prior's values
    on the lattice are fitted the same way.  Each term alone is fitted the same way: its gradient,
    whose spread over the segments is ``gradient_spread``.  Images are taken
    :func:`segment_chunk_images` at a time (bounded memory; the values do not depend on it).

    Args:
        likelihood: the estimator's model (its focal prior included).
        features: the segments of B images.
        params: (B, 4) estimates [pan, pitch, roll (degrees), f (pixels)].
        max_chunk_elements: the configuration's bound on a GPU's chunks (:func:`segment_chunk_images`).

    Returns:
        :class:`LocalFit`.
    """
    device, dtype = features.weight.device, features.weight.dtype
    step = torch.tensor(PRIOR_SHARE_STEP, dtype=torch.float64, device=device)
    fit = _QUADRATIC_FIT.to(device).T  # (81, 15)
    lattice = LATTICE.to(device)
    parts = []
    chunk = segment_chunk_images(features, max_chunk_elements)
    for b in range(0, params.shape[0], chunk):
        sub = features.images(b, b + chunk)
        centre = to_log_focal(params[b:b + chunk].to(device=device, dtype=torch.float64))
        points = from_log_focal(centre[:, None, :] + lattice * step)  # (b, 81, 4)
        focal = points[..., FOCAL].to(dtype)
        log_p = likelihood.segment_log_p(sub, rotations(points.to(dtype)), focal)  # (b, N, 81)
        scores = likelihood.sum_over_segments(log_p, sub)  # (b, 81): the objective's data part
        prior_values = likelihood.focal_prior(sub, focal, derivative=False)[0] if likelihood.params.focal_prior_weight else None
        if prior_values is not None:
            scores = scores + prior_values
        hessian = lattice_fit(scores, fit)[:, _HESSIAN_COLUMNS.to(device)].view(-1, 4, 4) / (step[:, None] * step[None, :])
        if prior_values is None:
            prior = torch.zeros(len(hessian), dtype=torch.float64, device=device)
        else:  # exact for the log-normal; a flat-topped prior has none inside its band, part of it at the edge
            prior_hessian = lattice_fit(prior_values, fit[:, _HESSIAN_COLUMNS[15].item(), None])[:, 0]  # H_33
            prior = (-prior_hessian / step[3] ** 2).clamp_min(0.0)
        terms = log_p.to(torch.float64) * sub.weight.to(torch.float64)[:, :, None]  # (b, N, 81); 0 for padding
        gradient = lattice_fit(terms, fit[:, 1:5], dim=2) / step  # (b, N, 4) per degree / per log f
        weight = sub.mask.to(gradient)[..., None]
        n = weight.sum(1).clamp_min(2.0)  # a count: exact in any order
        centred = (gradient - exact_sum(gradient * weight, 1, keepdim=True) / n[:, None]) * weight
        spread = exact_sum(centred[..., :, None] * centred[..., None, :], 1) * (n / (n - 1))[..., None]
        parts.append((hessian, prior, spread))
    if not parts:
        empty = torch.zeros(0, 4, 4, dtype=torch.float64, device=device)
        return LocalFit(empty, torch.zeros(0, dtype=torch.float64, device=device), empty)
    return LocalFit(*(torch.cat([part[i] for part in parts]) for i in range(3)))


#: Products ``values x fit column`` :func:`lattice_fit` forms at once on a CPU: as many columns as
#: keep them under this many elements (at least one; on a GPU every column, the caller's chunk bounds
#: them); the coefficients do not depend on it.
LATTICE_FIT_ELEMENTS = 1 << 16


def lattice_fit(values: torch.Tensor, fit: torch.Tensor, dim: int = -1) -> torch.Tensor:
    """The fit's coefficients from lattice values: ``sum_h values[..., h, ...] fit[h, c]`` for the 81
    lattice points along ``dim`` of ``values`` and a fit (81, C); returns the other dimensions of
    ``values`` then C, float64.  Each coefficient is an exact sum over the lattice
    (:func:`fr_torch.core.exact.exact_sum`; a matrix product's order would depend on the batch), of
    as many columns at once as :data:`LATTICE_FIT_ELEMENTS` allows on a CPU, every one on a GPU (one
    exact sum per slice either way)."""
    values = values.to(torch.float64)[..., None]  # (..., 1): the columns go last
    dim = dim % (values.dim() - 1)
    shape = [1] * values.dim()
    shape[dim] = fit.shape[0]
    step = max(1, LATTICE_FIT_ELEMENTS // values.numel()) if values.device.type == "cpu" else fit.shape[1]
    return torch.cat([exact_sum(values * fit[:, c:c + step].reshape(shape[:-1] + [-1]), dim)
                      for c in range(0, fit.shape[1], step)], -1)


def focal_prior_share(likelihood: MixtureLikelihood, features: SegmentFeatures, params: torch.Tensor,
                      fitted: LocalFit | None = None) -> torch.Tensor:
    """How much of the focal length's determination comes from the focal prior (a reliability cue).

    From :func:`local_quadratic` (or ``fitted``, its output): the prior's curvature in log f, ``c_p``,
    is taken out of the fitted Hessian, leaving the likelihood's; its curvature along log f with the
    angles re-optimised (Schur complement ``-(H_ff - H_fa H_aa^-1 H_af)``) is ``c_l``.  The cue is
    ``c_p / (c_p + max(c_l, 0))``: near 0 when the segments pin f down, 1 when the likelihood is
    flat (or curves up) along f and the prior alone sets it -- e.g. a narrow view whose vanishing
    points lie far outside the image, which the prior pulls towards its centre.

    Args:
        likelihood, features, params: as for :func:`local_quadratic`.
        fitted: :func:`local_quadratic`'s output for the same arguments, when already computed.

    Returns:
        (B,) float64 in [0, 1]; 0 for every image when the model has no focal prior; 1 where the fit
        is not finite.
    """
    if not likelihood.params.focal_prior_weight:
        return torch.zeros(params.shape[0], dtype=torch.float64, device=features.weight.device)
    fitted = fitted if fitted is not None else local_quadratic(likelihood, features, params)
    hessian, prior = fitted.hessian.clone(), fitted.prior_curvature
    hessian[:, 3, 3] += prior  # the likelihood's Hessian alone
    angles, focal_row = hessian[:, :3, :3], hessian[:, :3, 3:]
    solved, solvable = small_solve(angles, focal_row)
    profile = -(hessian[:, 3, 3] - small_sum((focal_row * solved)[..., 0], -1))  # per (log f)^2
    share = prior / (prior + profile.clamp_min(0.0))
    ok = torch.isfinite(share) & solvable
    return torch.where(ok, share.clamp(0.0, 1.0) + 0.0, torch.ones_like(share))  # + 0.0: no -0.0 in the output


def focal_spread(hessian: torch.Tensor, total_length: torch.Tensor) -> torch.Tensor:
    """The focal length's spread under the local Laplace approximation (a reliability cue).

    Args:
        hessian: (B, 4, 4) from :func:`local_quadratic` ([pan, pitch, roll (deg), log f]).
        total_length: (B,) total segment length per image, pixels.

    Returns:
        (B,) float64 ``sqrt(W [-H^-1]_ff)``: the marginal spread of log f with the angles
        re-optimised, focal prior included, for the objective normalised per pixel of segment length
        (W = ``total_length``; the length-weighted sum over-counts correlated pixels, so the ranking,
        not the scale, is what the error model uses).  :data:`MAX_SPREAD` where the fit has no
        maximum along log f (or is not finite).
    """
    covariance, invertible = small_inverse(-hessian)
    variance = covariance[:, 3, 3] * total_length.to(covariance)
    ok = invertible & torch.isfinite(variance) & (variance > 0)
    return torch.where(ok, exact_math.sqrt(variance.clamp_min(0.0)), torch.full_like(variance, MAX_SPREAD)).clamp_max(MAX_SPREAD)


#: Value of :func:`focal_spread` where the objective has no maximum along log f.
MAX_SPREAD = 1e3


#: Focal lengths of :func:`focal_profile_gap`'s profile, as multiples of the estimate: about 15 % to
#: 67 % away on either side, evenly spaced in log f (narrower than the search range's 6.5x, wider
#: than the basin of a well-determined estimate, ~5 %).
PROFILE_FOCAL_RATIOS = (0.6, 0.7, 0.8, 0.87, 1.15, 1.25, 1.43, 1.67)
#: The profile points of :func:`focal_profile_spread`: the nearest on either side of the estimate
#: (13 % shorter, 15 % longer), just beyond the 10 % a reliable focal length may be off.
SPREAD_FOCAL_RATIOS = (0.87, 1.15)
#: Images profiled together by :func:`focal_profile` on a CPU (their segments are copied once per
#: ratio: 256 x 8 copies of 750 segments are about 90 MB); the profile does not depend on it.
PROFILE_CHUNK_IMAGES = 256
#: Numbers a copied segment holds in :func:`focal_profile` (about 60 bytes: the 90 MB above).
PROFILE_COPY_NUMBERS = 16
#: Coarse cells each known-focal search of :func:`focal_profile_gap`'s profile (fR's eight focal
#: lengths) keeps when stage 1 is coarse to fine (``SearchConfig.grid_coarse_factor`` s > 1): 16 of
#: the (k/s)^3 = 64 cells, so 64 + 16 x 8 = 192 hypotheses per focal length instead of k^3 = 512.
#: Chosen on the train splits (YUD, ZInD-fR, 200 NYU-VP photos; ``results/decisions/66.md``): the
#: profile's best value unchanged at 94-100 % of the focal lengths searched, no ``reliable`` flag
#: changed.  Fast-fR's two-point profile scores whole grids: there the coarse pass cost what it saved.
PROFILE_COARSE_CELLS = 16


def _images_per_chunk(features: SegmentFeatures, cpu_images: int, per_image: int, max_chunk_elements: int) -> int:
    """Images a cue takes at once: ``cpu_images`` on a CPU (cache and memory sized); on a GPU as
    many as keep ``per_image`` elements each within ``max_chunk_elements`` (the configuration's,
    :class:`~fr_torch.core.settings.config.SearchConfig`); at least one.  No value depends on it."""
    if features.weight.device.type == "cpu":
        return cpu_images
    return max(1, max_chunk_elements // max(1, per_image))


def profile_chunk_images(features: SegmentFeatures, count: int, max_chunk_elements: int) -> int:
    """How many images :func:`focal_profile` profiles at ``count`` focal lengths at once:
    :data:`PROFILE_CHUNK_IMAGES` on a CPU; on a GPU as many as keep their segments' copies
    (:data:`PROFILE_COPY_NUMBERS` numbers each) within ``max_chunk_elements``."""
    per_image = PROFILE_COPY_NUMBERS * max(1, features.weight.shape[1]) * max(1, count)
    return _images_per_chunk(features, PROFILE_CHUNK_IMAGES, per_image, max_chunk_elements)


def focal_profile(likelihood: MixtureLikelihood, features: SegmentFeatures, params: torch.Tensor,
                  config: SearchConfig, iterations: int, ratios: Sequence[float] = PROFILE_FOCAL_RATIOS,
                  coarse_cells: int | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """The objective's profile along f: the best hypothesis of a known-focal search at each
    f x ``ratios`` inside the search range.

    Each known-focal search is Fast-fR's stage 1 and refinement with the focal length fixed: the k^3
    angle grid (with ``coarse_cells``, coarse to fine as stage 1 is, keeping that many of the coarse
    cells: 192 hypotheses at :data:`PROFILE_COARSE_CELLS` and the defaults; the whole grid without,
    or with ``grid_coarse_factor`` 1), its ``top_l`` best points refined for ``iterations`` Adam steps.

    Args:
        likelihood: the estimator's model.
        features: the segments of B images.
        params: (B, 4) estimates [pan, pitch, roll (degrees), f (pixels)].
        config: the search settings (FOV range, grid, top_l).
        iterations: Adam steps per start.
        ratios: R focal lengths as multiples of the estimate's.
        coarse_cells: coarse cells kept per known-focal grid; None: the whole grid.

    Returns:
        ``(best, points)``: (B, R) float64 best objective at each ratio (-inf where f x ratio lies
        outside the FOV range: not searched) and (B, R, 4) float64 its hypothesis [pan, pitch, roll
        (degrees), f (pixels)] (the estimate where not searched).
    """
    batch, count = params.shape[0], len(ratios)
    device = features.weight.device
    chunk = profile_chunk_images(features, count, config.max_chunk_elements)
    if batch > chunk:  # each image's segments are copied once per ratio searched: bound the copies
        parts = [focal_profile(likelihood, features.images(b, b + chunk), params[b:b + chunk], config, iterations,
                               ratios, coarse_cells)
                 for b in range(0, batch, chunk)]
        return torch.cat([p[0] for p in parts]), torch.cat([p[1] for p in parts])
    ratio_t = torch.tensor(tuple(ratios), dtype=torch.float64)
    long_side = features.long_side.to("cpu", torch.float64)
    f_lo, f_hi = config.fov_range.focal_bounds(long_side)
    focal = params[:, FOCAL].to("cpu", torch.float64)[:, None] * ratio_t  # (B, R)
    inside = (focal >= f_lo[:, None]) & (focal <= f_hi[:, None])
    pairs = inside.nonzero()  # (M, 2) [image, ratio]: only focal lengths inside the range are searched
    best = torch.full((batch, count), -math.inf, dtype=torch.float64, device=device)
    points = params.to(device=device, dtype=torch.float64)[:, None, :].repeat(1, count, 1)
    if len(pairs):
        image, ratio = pairs.unbind(1)
        searched = features.take_images(image.to(device))
        long_rep, focal_rep = long_side[image], focal[image, ratio]
        hypotheses = grid_hypotheses(config, long_rep.to(device), focal_rep.to(device))  # built on the device
        grid_config = config if coarse_cells is None else replace(config, grid_coarse_cells=coarse_cells)
        _, selectable = stage1_scores(likelihood, searched, grid_config, hypotheses, long_rep, focal_rep,
                                      coarse=coarse_cells is not None)
        starts, _ = select_starts(config, selectable, hypotheses)
        lower, upper = parameter_box(config, long_rep, focal_rep)
        refined, refined_scores = refine(likelihood, searched, starts, lower.to(device), upper.to(device), iterations,
                                         fast=True, periodic_pan=config.periodic_pan)
        arg = first_argmax(refined_scores, 1)
        value = torch.gather(refined_scores.to(torch.float64), 1, arg[:, None])[:, 0]
        image, ratio = image.to(device), ratio.to(device)
        best[image, ratio] = value
        points[image, ratio] = refined[torch.arange(len(arg), device=device), arg].to(torch.float64)
    return best, points


def focal_profile_gap(likelihood: MixtureLikelihood, features: SegmentFeatures, params: torch.Tensor,
                      scores: torch.Tensor, config: SearchConfig, iterations: int,
                      profile: tuple[torch.Tensor, torch.Tensor] | None = None) -> torch.Tensor:
    """How much better the estimate scores than the best hypothesis at a clearly different focal
    length (a reliability cue): ``scores`` minus the best objective of :func:`focal_profile` over
    :data:`PROFILE_FOCAL_RATIOS` with :data:`PROFILE_COARSE_CELLS` (or ``profile``, its output when
    already computed).

    A large gap (hundreds of nats) means the segments single out the estimate's focal length; a
    small one, that another focal length explains them almost as well (two basins: the estimate
    may be the wrong one); a negative one, that the search missed a better basin.  Values are in
    objective units (nats, weighted by segment length in pixels), like ``scores``.

    Args:
        likelihood, features, params, config, iterations: as for :func:`focal_profile`.
        scores: (B,) the estimates' objectives.
        profile: :func:`focal_profile`'s output for these arguments, when already computed.

    Returns:
        (B,) float64, finite: 0 (no evidence that the estimate's focal length is singled out) where
        the gap is not finite (a non-finite estimate, or no ratio's focal length inside the range).
    """
    if params.shape[0] == 0:
        return torch.zeros(0, dtype=torch.float64, device=features.weight.device)
    if profile is None:
        profile = focal_profile(likelihood, features, params, config, iterations, coarse_cells=PROFILE_COARSE_CELLS)
    best = profile[0]
    gap = scores.to(torch.float64) - best.amax(1)
    return torch.where(torch.isfinite(gap), gap, torch.zeros_like(gap))


#: Images whose per-segment terms the cues hold at once on a CPU (81 lattice points x 750 segments x
#: 64 images in float64 are about 30 MB; :func:`segment_chunk_images`); the values do not depend on it.
SEGMENT_CHUNK_IMAGES = 64


#: Grid deviations' worth of memory one element of the cues' largest lattice tensor, (N, 81, 4)
#: float64 products, takes with the exact sum's temporaries (about six such tensors of 8 bytes
#: against a grid deviation's 7): :func:`segment_chunk_images`.
LATTICE_ELEMENT_COST = 6


def segment_chunk_images(features: SegmentFeatures, max_chunk_elements: int) -> int:
    """How many images' per-segment lattice terms a cue holds at once: :data:`SEGMENT_CHUNK_IMAGES`
    on a CPU; on a GPU as many as keep the largest of them, (N, 81, 4) per image at
    :data:`LATTICE_ELEMENT_COST` each, within ``max_chunk_elements`` (the configuration's,
    :class:`~fr_torch.core.settings.config.SearchConfig`: about 1 GB at its default)."""
    per_image = max(1, features.weight.shape[1]) * len(LATTICE) * 4 * LATTICE_ELEMENT_COST
    return _images_per_chunk(features, SEGMENT_CHUNK_IMAGES, per_image, max_chunk_elements)


def segment_objectives(likelihood: MixtureLikelihood, features: SegmentFeatures, points: torch.Tensor) -> torch.Tensor:
    """Each segment's term of the objective, ``length_i log p_i``, at each hypothesis.

    Args:
        likelihood, features: as for :func:`local_quadratic` (B images).
        points: (B, H, 4) hypotheses [pan, pitch, roll (degrees), f (pixels)].

    Returns:
        (B, H, N) float64; 0 for padding.  Summed over segments: the objective without the focal prior.
    """
    dtype = features.weight.dtype
    log_p = likelihood.segment_log_p(features, rotations(points.to(dtype)), points[..., FOCAL].to(dtype))
    terms = log_p.transpose(1, 2).to(torch.float64) * features.weight[:, None, :].to(torch.float64)
    return torch.where(features.mask[:, None, :], terms, torch.zeros_like(terms))


def _resampled_sd(differences: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Standard deviation of ``sum_i d_i`` when the segments are resampled with replacement
    (``sqrt(n / (n - 1) sum_i (d_i - mean d)^2)``), over the last axis; ``differences`` (..., N),
    ``mask`` broadcastable to it."""
    weight = mask.to(differences)
    n = weight.sum(-1).clamp_min(2.0)  # a count: exact in any order
    mean = exact_sum(differences * weight, -1) / n
    centred = (differences - mean[..., None]) * weight
    return exact_math.sqrt(exact_sum(centred * centred, -1) * n / (n - 1))


def focal_profile_spread(likelihood: MixtureLikelihood, features: SegmentFeatures, params: torch.Tensor,
                         config: SearchConfig, profile: tuple[torch.Tensor, torch.Tensor],
                         ratios: Sequence[float] = SPREAD_FOCAL_RATIOS) -> torch.Tensor:
    """How far f could move before the segments notice, from the profile next to the estimate (a
    reliability cue; the spread of log f).

    For each profile point at f x r (``profile``: :func:`focal_profile`'s output for ``ratios``), the
    segments' evidence for the estimate over that point is ``D = sum_i d_i``, with ``d_i`` segment
    i's term of the objective at the estimate minus at the point (:func:`segment_objectives`; the
    focal prior left out: it is not evidence), and ``S`` its standard deviation when the segments
    are resampled with replacement: ``z = D / S`` counts in standard errors how much better the
    estimate explains *these* segments, a self-normalised number (the objective's length weights
    over-count correlated pixels; ``S`` grows with them).  Were the objective quadratic in log f
    with spread s, ``z = |log r| / (2 s)``, so each side gives ``s_r = |log r| / (2 z)``; the cue is
    the larger of the two sides.

    Args:
        likelihood, features, params, config: as for :func:`focal_profile`.
        profile: :func:`focal_profile`'s output for these arguments and ``ratios``.
        ratios: the profile's focal ratios (default :data:`SPREAD_FOCAL_RATIOS`).

    Returns:
        (B,) float64 spread of log f (0.05 = 5 %).  :data:`MAX_SPREAD` where a point scores at least as
        well as the estimate (``z <= 0``: a search miss or a flat profile).  A side outside the FOV
        range is left out (the range rules it out); with both out, the range's own spread
        (its width in log f over sqrt(12)).
    """
    best, points = profile
    device = features.weight.device
    count = len(ratios)
    out = []
    chunk = segment_chunk_images(features, config.max_chunk_elements)
    for b in range(0, params.shape[0], chunk):
        sub = features.images(b, b + chunk)
        here = params[b:b + chunk].to(device=device, dtype=torch.float64)
        terms = segment_objectives(likelihood, sub, torch.cat([here[:, None], points[b:b + chunk]], 1))
        differences = terms[:, :1] - terms[:, 1:]  # (b, R, N)
        z = exact_sum(differences, -1) / _resampled_sd(differences, sub.mask[:, None, :]).clamp_min(1e-12)
        out.append(z)
    z = torch.cat(out) if out else torch.zeros(0, count, dtype=torch.float64, device=device)
    log_ratio = torch.tensor([abs(exact_math.of(exact_math.log, r)) for r in ratios], dtype=torch.float64, device=device)
    side = torch.where(z > 0, log_ratio / (2 * z.clamp_min(1e-12)), torch.full_like(z, MAX_SPREAD))
    inside = torch.isfinite(best)
    spread = torch.where(inside, side, torch.zeros_like(side)).amax(1)
    long_side = features.long_side.to("cpu", torch.float64)
    f_lo, f_hi = config.fov_range.focal_bounds(long_side)
    range_spread = (exact_math.log(f_hi / f_lo) / math.sqrt(12.0)).to(device)
    spread = torch.where(inside.any(1), spread, range_spread)
    return torch.where(torch.isfinite(spread), spread, torch.full_like(spread, MAX_SPREAD)).clamp_max(MAX_SPREAD)


def resample_spreads(fitted: LocalFit, known_focal: bool = False) -> dict[str, torch.Tensor]:
    """The spread of the estimate when the segments are resampled with replacement (reliability cues),
    by the infinitesimal jackknife (the "sandwich" ``H^-1 J H^-1``).

    ``H``: the likelihood's Hessian at the estimate in [pan, pitch, roll (deg), log f], from
    :func:`local_quadratic` (``fitted``) with the focal prior's curvature taken out (the spread of
    what the *segments* say: where they leave f to the prior, the spread is large).  ``J``: the
    spread of the segments' gradients over the same lattice (``fitted.gradient_spread``), i.e. of the
    summed gradient over resampled segments.  Unlike the Laplace spread (:func:`focal_spread`) it
    does not take the length-weighted objective at its word: segments that disagree widen it.

    Args:
        fitted: :func:`local_quadratic`'s output for the estimates.
        known_focal: the focal length was given: the angles alone are free (their 3 x 3 block).

    Returns:
        ``{"focal_resample_spread": (B,), "pitch_resample_spread": (B,)}`` float64: the spread of log f
        (0 for a known focal length) and of the pitch in degrees; :data:`MAX_SPREAD` where the
        likelihood has no maximum there (or the fit is not finite).
    """
    hessian = fitted.hessian.clone()
    hessian[:, 3, 3] += fitted.prior_curvature  # the likelihood's Hessian alone
    free = slice(0, 3) if known_focal else slice(0, 4)
    h, j = hessian[:, free, free], fitted.gradient_spread[:, free, free]
    inverse, invertible = small_inverse(h)
    covariance = small_matmul(small_matmul(inverse, j), inverse)
    peak = positive_definite(-0.5 * (h + h.transpose(-1, -2)))  # a maximum of the likelihood
    ok = invertible & peak

    def spread(index):
        variance = covariance[:, index, index]
        good = ok & torch.isfinite(variance) & (variance >= 0)
        return torch.where(good, exact_math.sqrt(variance.clamp_min(0.0)), torch.full_like(variance, MAX_SPREAD)).clamp_max(MAX_SPREAD)

    focal = torch.zeros(hessian.shape[0], dtype=torch.float64, device=hessian.device) if known_focal else spread(3)
    return {"focal_resample_spread": focal, "pitch_resample_spread": spread(1)}


def focal_conditioning(rotation: torch.Tensor) -> torch.Tensor:
    """How well a Manhattan frame's vanishing points constrain the focal length (a reliability cue).

    Args:
        rotation: (..., 3, 3) world->camera rotations; column i is the direction of VP i in camera
            coordinates (x right, y down, z along the optical axis), as in ``VP_i = K R[:, i]``.

    Returns:
        (...,) ``sqrt(sum_i (sin(theta_i) cos(theta_i))^2)`` in [0, sqrt(3)/2], theta_i the angle
        between VP direction i and the optical axis.  A VP sits at ``f tan(theta)`` from the
        principal point; on the principal point (theta = 0) or at infinity (theta = 90 deg) its
        position carries no information on f, and ``sin cos`` peaks at theta = 45 deg.  A camera
        panned square to a wall with level tilt (all three VPs at the centre or at infinity) gives
        0: its focal length is left to the prior.  No f enters (the directions alone decide).
    """
    squares = rotation * rotation
    norm = exact_math.sqrt(small_sum(squares, -2)).clamp_min(1e-12)  # (..., 3) column lengths
    off_axis = exact_math.sqrt(squares[..., 0, :] + squares[..., 1, :]) / norm  # sin(theta_i)
    along_axis = rotation[..., 2, :].abs() / norm  # cos(theta_i)
    product = off_axis * along_axis
    return exact_math.sqrt(small_sum(product * product, -1))


def image_cues(grid_scores, grid_counts, labels, log_p, mask, rotation) -> dict[str, torch.Tensor]:
    """The reliability cues, per image: the paper's three (§3.4) and ``focal_conditioning``.

    * ``min_family_segments``: smallest number of segments labelled (argmax posterior) with one
      of the three Manhattan families; background excluded; raw counts.
    * ``grid_entropy``: entropy (nats) of the stage-1 grid likelihoods normalised into a
      distribution, ``p_j = softmax_j(L_j / N)`` with N the number of segments the grid scored,
      ``grid_counts`` (B,) (a softmax at
      temperature N, as in the authors' code; unlike the code we do not divide the entropy by N
      a second time: the entropy of that distribution is the cue).
    * ``mean_log_likelihood``: mean over segments of log p_i at the final estimate (the
      paper's definition; the authors' MATLAB release uses the mean log max-posterior instead).
    * ``focal_conditioning``: :func:`focal_conditioning` of the final ``rotation`` (B, 3, 3).

    The fifth and sixth cues, ``focal_prior_share`` and (fR only) ``focal_profile_gap``, come
    from :func:`focal_cues`.
    """
    n = mask.sum(-1).clamp_min(1)
    counts = torch.stack([((labels == k) & mask).sum(-1) for k in range(3)], -1)
    scaled = grid_scores.to(torch.float64) / grid_counts.clamp_min(1)[:, None].to(torch.float64)
    largest = scaled.amax(-1, keepdim=True)
    log_q = scaled - largest - exact_math.log(exact_sum(exact_math.exp(scaled - largest), -1, keepdim=True))  # log softmax
    entropy = -exact_sum(exact_math.exp(log_q) * log_q, -1)
    mean_log = exact_sum(log_p * mask, -1) / n
    return {"min_family_segments": counts.min(-1).values.to(torch.float64),
            "grid_entropy": entropy.to(torch.float64),
            "mean_log_likelihood": mean_log.to(torch.float64),
            "focal_conditioning": focal_conditioning(rotation).to(torch.float64)}


#: The cues :func:`focal_cues` adds with ``spreads`` on (the bounds of ``reliable``,
#: :mod:`fr_torch.core.reliability.bounds`).
SPREAD_CUE_NAMES = ("focal_profile_spread", "focal_resample_spread", "pitch_resample_spread")


def focal_cues(likelihood: MixtureLikelihood, search: SearchConfig, features: SegmentFeatures,
               params: torch.Tensor, scores: torch.Tensor, known_focal: bool, profile_gap: bool,
               spreads: bool = False) -> dict[str, torch.Tensor]:
    """The focal cues of the estimates ``params`` (B, 4) with objectives ``scores`` (B,), each
    float64 (B,): ``focal_prior_share`` and ``focal_spread`` (:func:`focal_prior_share`,
    :func:`focal_spread`, both from one :func:`local_quadratic` fit); when ``profile_gap`` is on
    (fR's shipped model uses it), ``focal_profile_gap`` (:func:`focal_profile_gap`, each
    known-focal search refined for Fast-fR's number of steps; it costs about a Fast-fR search per
    photo, so Fast-fR and its model go without it); when ``spreads`` is on (the bounds of
    ``reliable`` use them), :data:`SPREAD_CUE_NAMES`: ``focal_profile_spread``
    (:func:`focal_profile_spread`, from the profile's two points next to the estimate: with
    ``profile_gap`` off only those two are searched) and the resampling spreads of log f and pitch
    (:func:`resample_spreads`, from the same lattice as ``focal_prior_share``).  The focal cues
    are 0 for a given focal length: the prior plays no part and there is no focal length to single
    out; the pitch's spread is still computed then."""
    zeros = torch.zeros(params.shape[0], dtype=torch.float64, device=params.device)
    names = ("focal_prior_share", "focal_spread") + (("focal_profile_gap",) if profile_gap else ())
    if known_focal:
        cues = {name: zeros for name in names}
        if spreads:
            cues.update(focal_profile_spread=zeros,
                        **resample_spreads(local_quadratic(likelihood, features, params, search.max_chunk_elements),
                                           known_focal=True))
        return cues
    fitted = local_quadratic(likelihood, features, params, search.max_chunk_elements)
    cues = {"focal_prior_share": focal_prior_share(likelihood, features, params, fitted=fitted),
            "focal_spread": focal_spread(fitted.hessian, features.total_length())}
    if profile_gap:
        profile = focal_profile(likelihood, features, params, search, FAST_REFINE_ITERATIONS,
                                coarse_cells=PROFILE_COARSE_CELLS)
        cues["focal_profile_gap"] = focal_profile_gap(likelihood, features, params, scores, search,
                                                      FAST_REFINE_ITERATIONS, profile=profile)
        near = [PROFILE_FOCAL_RATIOS.index(r) for r in SPREAD_FOCAL_RATIOS]
        near_profile = (profile[0][:, near], profile[1][:, near])
    elif spreads:
        near_profile = focal_profile(likelihood, features, params, search, FAST_REFINE_ITERATIONS, SPREAD_FOCAL_RATIOS)
    if spreads:
        cues["focal_profile_spread"] = focal_profile_spread(likelihood, features, params, search, near_profile)
        cues.update(resample_spreads(fitted))
    return cues
