"""The search with a distortion parameter: k of the division model estimated jointly with f and R.

Rows of 5 (:data:`fr_torch.core.geometry.params.DISTORTION`): ``[pan, pitch, roll, focal, k]``, k the division
model's normalised coefficient (:mod:`fr_torch.core.geometry.lens`).  Every hypothesis is scored on
its image's segments undistorted with its own k (:class:`SegmentGeometry`): hypotheses that share
a k share the undistorted segments, so each stage builds one **virtual image** per (image, k) --
the undistorted segments of that image at that k -- and scores its hypotheses with the pinhole
machinery of :mod:`fr_torch.core.search.passes` unchanged.

The stages (the pinhole search's, with k added):

1. **Grid over k** (:func:`grid_over_k`): the k^4 angle-and-focal grid
   (``SearchConfig.distortion_grid_size`` per dimension) at the plumb-line k (:func:`plumb_line`:
   the k that straightens pieces of lines, independent of f and R) and at the values of
   ``distortion_grid_k``; the ``top_l`` best of all (k, grid point) pairs start.
2. **Focal sweep** (:func:`sweep_focal_rows`): each start's focal ridge at its k
   (:func:`fr_torch.core.search.passes.sweep_focal`).
3. **Lattice passes** (:func:`subdivide_rows`): the 3^4 lattice around each start at its k and k
   one step either side (``distortion_lattice="axis"``; or the 3^5 lattice, ``"joint"``); the k step
   a third of ``distortion_k_spacing``, then a third of that.
4. **Refinement**: Adam on the five box-normalised parameters
   (:func:`fr_torch.core.search.refine.refine` with the geometry: the analytic gradient of measure b
   extends to k through d line / dk).

:func:`bend_test` asks whether a pinhole estimate's lines bend: the plumb line, and a short
division search from the estimate (at the plumb-line k: the focal sweep and lattice passes) with
its gain in nats per 1000 px of segment length (:func:`likelihood_gain`); the "lines bend" sanity
check of pinhole estimates (:func:`fr_torch.core.reliability.sanity.lines_bend_reason`) and the criterion by which
``auto`` runs this search on an image.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, replace

import torch

from fr_torch.core.exact import dot3, exact_index_sum, exact_sum, first_argmax, top_indices
from fr_torch.core.geometry.lens import normalising_radius
from fr_torch.core.geometry.params import DISTORTION, from_log_focal
from fr_torch.core.likelihood import native
from fr_torch.core.likelihood.measures import SegmentFeatures
from fr_torch.core.likelihood.mixture import MixtureLikelihood
from fr_torch.core.search.grid import (chunk_budget, grid_cell, grid_hypotheses, into_box, parameter_box, score_grid,
                                       select_starts)
from fr_torch.core.search.passes import LATTICE, SearchResult, lattice_passes, sweep_focal, tie_tolerance
from fr_torch.core.search.refine import refine_kernel_matches_torch, refine_starts
from fr_torch.core.settings.config import SearchConfig
from fr_torch.core import exact_math


@dataclass
class SegmentGeometry:
    """The photo's segments of B images, from which :class:`SegmentFeatures` follow for any k.

    ``endpoints`` (B, N, 4) photo pixels ``[x1, y1, x2, y2]``; ``mask`` (B, N); ``centre`` (B, 2) the
    distortion centre (principal point); ``radius`` (B,) the normalising radius;
    ``long_side`` (B,).  Under a hypothesis k each endpoint is undistorted
    (:func:`undistort_points`) and the likelihood's line features are those of the undistorted
    segment; its **weight stays the photo's segment length**, so the objectives of different k
    weigh the same evidence alike.  ``k_prior_weight`` (gamma >= 0): the prior on k that every
    hypothesis' objective carries, ``log p(k) = -(gamma / 2) W k^2`` with W the image's total segment
    length (:meth:`k_log_prior`; per unit of evidence, like the focal prior).
    """

    endpoints: torch.Tensor
    mask: torch.Tensor
    centre: torch.Tensor
    radius: torch.Tensor
    long_side: torch.Tensor
    k_prior_weight: float = 0.0

    @classmethod
    def from_features(cls, features: SegmentFeatures, endpoints: torch.Tensor, image_size: torch.Tensor,
                      k_prior_weight: float = 0.0):
        """The geometry of the segments behind ``features`` (their endpoints (B, N, 4) and the
        images' (B, 2) [width, height] pixels)."""
        size = image_size.to(endpoints)
        return cls(endpoints, features.mask, features.principal_point, normalising_radius(size[:, 0], size[:, 1]),
                   features.long_side, k_prior_weight)

    def k_log_prior(self, k: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The log prior on k (class docstring) and its derivative d/dk for ``k`` (B, G): two (B, G)
        tensors in ``k``'s dtype (zeros without a prior)."""
        if not self.k_prior_weight:
            return torch.zeros_like(k), torch.zeros_like(k)
        slope = self.k_prior_slope(k)[:, None] * k
        return 0.5 * slope * k, slope

    def k_prior_slope(self, like: torch.Tensor) -> torch.Tensor:
        """``-gamma W`` per image, (B,) in ``like``'s dtype and device: the prior's derivative
        (:meth:`k_log_prior`) is this times k."""
        return -self.k_prior_weight * self.total_length().to(like)

    @property
    def weight(self) -> torch.Tensor:
        """(B, N) the photo's segment lengths, 0 for padding (computed once)."""
        cached = self.__dict__.get("_weight_cache")
        if cached is None:
            d = self.endpoints[..., 2:] - self.endpoints[..., :2]
            cached = self.__dict__["_weight_cache"] = _norm2(d) * self.mask
        return cached

    def total_length(self) -> torch.Tensor:
        """(B,) float64 total segment length per image, pixels: :meth:`SegmentFeatures.total_length`
        of the photo's segments (that of every virtual image of :meth:`features`), computed once."""
        cached = self.__dict__.get("_total_length_cache")
        if cached is None:
            cached = self.__dict__["_total_length_cache"] = exact_sum(self.weight, 1)
        return cached

    def features(self, k: torch.Tensor, derivative: bool = False):
        """Features of every image under G hypotheses of k each: ``k`` (B, G) -> SegmentFeatures of
        B * G virtual images (image b's hypothesis g at row ``b * G + g``), and with ``derivative``
        also d line_along / dk, (B * G, 2N, 3)."""
        batch, groups = k.shape
        n_seg = self.endpoints.shape[1]
        dtype = self.endpoints.dtype
        k = k.to(dtype)[:, :, None]  # (B, G, 1)
        centre, offset, rho = self.offsets()  # (B, 1, 1, 2), (B, 1, 2N, 2), (B, 1, 2N)
        factor = (1.0 + k * rho).reciprocal()  # (B, G, 2N): undistorted = centre + factor * offset
        q = offset * factor[..., None]
        qa, qb = q[:, :, :n_seg], q[:, :, n_seg:]
        delta = qb - qa
        length = _norm2(delta)
        inv_length = length.clamp_min(1e-12).reciprocal()
        d = delta * inv_length[..., None]
        m = centre + (qa + qb) * 0.5
        dx, dy = d[..., 0], d[..., 1]
        mx, my = m[..., 0], m[..., 1]
        line_along = _line_along_rows([-dy, dx, dy * mx - dx * my], [dx, dy, -(dx * mx + dy * my)])
        weight, mask, principal_point, long_side, constants = self._virtual_constants(groups)
        features = SegmentFeatures(line_along[:, :n_seg], line_along[:, n_seg:], (length * 0.5).view(batch * groups, -1),
                                   weight, mask, principal_point, long_side, line_along=line_along
                                   ).sharing_constants(constants)
        if not derivative:
            return features
        d_q = offset * (-rho * factor * factor)[..., None]  # d q / dk
        d_delta = d_q[:, :, n_seg:] - d_q[:, :, :n_seg]
        d_d = (d_delta - d * _dot2(d, d_delta)[..., None]) * inv_length[..., None]
        d_m = (d_q[:, :, :n_seg] + d_q[:, :, n_seg:]) * 0.5
        ddx, ddy = d_d[..., 0], d_d[..., 1]
        dmx, dmy = d_m[..., 0], d_m[..., 1]
        d_line_along = _line_along_rows([-ddy, ddx, ddy * mx + dy * dmx - ddx * my - dx * dmy],
                                        [ddx, ddy, -(ddx * mx + dx * dmx + ddy * my + dy * dmy)])
        return features, d_line_along

    def offsets(self):
        """(centre (B, 1, 1, 2), endpoint offsets from it (B, 1, 2N, 2): first endpoints then second
        ones, their r^2 in units of the radius (B, 1, 2N)), in the endpoints' dtype, computed once:
        what :meth:`features` undistorts."""
        cached = self.__dict__.get("_offset_cache")
        if cached is None:
            dtype = self.endpoints.dtype
            centre = self.centre.to(dtype)[:, None, None, :]
            points = torch.cat([self.endpoints[..., :2], self.endpoints[..., 2:]], 1)[:, None]  # (B, 1, 2N, 2)
            offset = points - centre
            rho = _dot2(offset, offset) / (self.radius.to(dtype) ** 2)[:, None, None]
            cached = self.__dict__["_offset_cache"] = (centre, offset, rho)
        return cached

    def _virtual_constants(self, groups: int):
        """The k-independent fields of :meth:`features` for G = ``groups``: weight, mask,
        principal point, long side of the B * G virtual images, and the store of the values
        computed from them (:meth:`SegmentFeatures.sharing_constants`, seeded with the total
        length), computed once per G."""
        cache = self.__dict__.setdefault("_constants_cache", {})
        if groups not in cache:
            weight = self.weight
            mask = self.mask & (weight > 0)
            dtype = self.endpoints.dtype
            fields = tuple(x.repeat_interleave(groups, 0) for x in
                           (weight, mask, self.centre.to(dtype), self.long_side.to(dtype)))
            cache[groups] = fields + ({"total_length": self.total_length().repeat_interleave(groups, 0)},)
        return cache[groups]

    def images(self, start: int, stop: int) -> "SegmentGeometry":
        """Images ``start:stop`` (views)."""
        return SegmentGeometry(self.endpoints[start:stop], self.mask[start:stop], self.centre[start:stop],
                               self.radius[start:stop], self.long_side[start:stop], self.k_prior_weight)


# the division model's refinement kernel, checked against the torch loop once per process (native.available)
native.register_check(lambda: refine_kernel_matches_torch(SegmentGeometry.from_features), "refine_lens")




def _line_along_rows(line: list[torch.Tensor], along: list[torch.Tensor]) -> torch.Tensor:
    """The three coefficients of ``line`` and of ``along``, (B, G, N) each, as the
    :attr:`SegmentFeatures.line_along` rows of the B * G virtual images: (B * G, 2N, 3)."""
    rows = torch.cat([torch.stack(line, -1), torch.stack(along, -1)], 2)  # (B, G, 2N, 3)
    return rows.view(-1, rows.shape[2], 3)


def _dot2(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """``a_x b_x + a_y b_y`` of (..., 2) vectors (inputs broadcast), each product and the sum rounded once."""
    return a[..., 0] * b[..., 0] + a[..., 1] * b[..., 1]


def _norm2(a: torch.Tensor) -> torch.Tensor:
    """Length of (..., 2) vectors, ``sqrt(a_x^2 + a_y^2)`` rounded as :func:`_dot2` (not
    ``vector_norm``, whose kernel's order may differ between kernel sets)."""
    return exact_math.sqrt(_dot2(a, a))




#: Pieces of one line: two segments whose nearest endpoints are closer than this share of the long
#: side, whose directions differ by less than :data:`CHAIN_MAX_ANGLE_DEG`, and each of whose nearer
#: endpoint lies within :data:`CHAIN_LATERAL` (share of the long side) of the other's line.
CHAIN_GAP = 0.03
CHAIN_MAX_ANGLE_DEG = 15.0
CHAIN_LATERAL = 0.003
#: The longest segments of each image :func:`plumb_line` pairs up.
CHAIN_SEGMENTS = 200
#: Turning angles above this count as this much (pairs of pieces that are not one line).
TURN_CAP_DEG = 3.0
#: Spacing of the values of k :func:`plumb_line` tries over the k range.
PLUMB_K_STEP = 0.01
#: Elements of the chunk budget one pair test of :func:`chain_pairs` takes (its float64 direction
#: products and boolean masks alive at once, about four grid deviations' worth).
PAIR_TEST_COST = 4
#: The k spacing of :func:`bend_test`'s lattice passes (first step +-0.1).
PLUMB_K_SPACING = 0.3


@dataclass
class PlumbLine:
    """What the pieces of straight lines say about k, per image (:func:`plumb_line`): ``k`` (B,)
    the value that straightens them best; ``share`` (B,) the share of their turning it removes
    (1 - C(k) / C(0), in [0, 1]); ``pairs`` (B,) how many pairs of pieces were found."""

    k: torch.Tensor
    share: torch.Tensor
    pairs: torch.Tensor


def chain_pairs(endpoints: torch.Tensor, mask: torch.Tensor, long_side: torch.Tensor):
    """Pairs of segments that look like consecutive pieces of one line (the constants above).

    ``endpoints`` (B, M, 4) photo pixels, ``mask`` (B, M), ``long_side`` (B,).  Returns
    (image (P,), i (P,), j (P,), weight (P,)) with i < j and weight = the shorter one's length,
    in (image, i, j) order.  The direction test, the cheapest, runs on all M^2 pairs; the gap and
    lateral tests only on the C pairs that pass it (about a third), coordinates laid out (.., C)."""
    count = endpoints.shape[1]
    delta = endpoints[..., 2:] - endpoints[..., :2]
    length = _norm2(delta).clamp_min(1e-9)
    unit = delta / length[..., None]
    aligned = _dot2(unit[:, :, None, :], unit[:, None, :, :]).abs() > exact_math.of(exact_math.cos, math.radians(CHAIN_MAX_ANGLE_DEG))
    image, i, j = torch.triu(aligned & mask[:, :, None] & mask[:, None, :], diagonal=1).nonzero(as_tuple=True)
    # homogeneous unit-normal lines; |line . (x, y, 1)| = the point's distance from the segment's line
    lines = torch.stack([-unit[..., 1], unit[..., 0],
                         unit[..., 1] * endpoints[..., 0] - unit[..., 0] * endpoints[..., 1]]).view(3, -1)  # (3, B * M)
    row_i, row_j = image * count + i, image * count + j  # (C,) rows of the (B * M, ...) tensors
    ends = endpoints.reshape(-1, 4).T.contiguous()  # (4, B * M): x1, y1, x2, y2
    ends_i, ends_j = ends.index_select(1, row_i), ends.index_select(1, row_j)  # (4, C)
    x_i, y_i, x_j, y_j = ends_i[0::2], ends_i[1::2], ends_j[0::2], ends_j[1::2]  # (2, C): both endpoints
    dx, dy = x_i[:, None] - x_j[None], y_i[:, None] - y_j[None]  # (2, 2, C): i's endpoints minus j's
    gap = exact_math.sqrt((dx * dx + dy * dy).view(4, -1).amin(0))  # the nearest endpoints' distance (C,)

    def nearer_lateral(rows: torch.Tensor, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        """(C,) distance from the lines of ``rows`` (C,) of the nearer of the points ``x``, ``y``
        (2, C) (:func:`dot3` of the line and (x, y, 1), written out)."""
        line = lines.index_select(1, rows)  # (3, C)
        return (line[0] * x + line[1] * y + line[2]).abs().amin(0)

    scale = long_side.to(endpoints)[image]
    valid = (gap < CHAIN_GAP * scale) & (nearer_lateral(row_i, x_j, y_j) < CHAIN_LATERAL * scale) \
        & (nearer_lateral(row_j, x_i, y_i) < CHAIN_LATERAL * scale)
    length = length.view(-1)
    return image[valid], i[valid], j[valid], torch.minimum(length[row_i[valid]], length[row_j[valid]])


def plumb_line(geometry: "SegmentGeometry", k_range: tuple[float, float], max_chunk_elements: int) -> PlumbLine:
    """The plumb-line test: straight lines of the scene are straight in the undistorted image.

    Pairs of consecutive pieces of one line (:func:`chain_pairs`, among each image's
    :data:`CHAIN_SEGMENTS` longest segments) turn by an angle theta in a bent photo; for every k
    on a grid over ``k_range`` (spacing :data:`PLUMB_K_STEP`, 0 included) the pieces are undistorted
    and ``C(k) = sum_pairs w min(theta, cap)^2`` (w the shorter piece's length, cap
    :data:`TURN_CAP_DEG`).  Independent of f and R: a cheap estimate of k before the search
    and the evidence of the "lines bend" check.  Images are paired up in chunks within
    ``max_chunk_elements`` (:func:`~fr_torch.core.search.grid.chunk_budget`; an image costs
    CHAIN_SEGMENTS^2 pair tests of :data:`PAIR_TEST_COST` each; no value depends on the chunks).  Returns a :class:`PlumbLine`
    (k = 0, share 0 where an image has no pairs)."""
    batch = geometry.endpoints.shape[0]
    pair_cost = CHAIN_SEGMENTS ** 2 * PAIR_TEST_COST
    chunk = max(1, chunk_budget(max_chunk_elements, geometry.endpoints.device) // pair_cost)
    if batch > chunk:
        parts = [plumb_line(geometry.images(b, b + chunk), k_range, max_chunk_elements)
                 for b in range(0, batch, chunk)]
        return PlumbLine(*(torch.cat([getattr(p, name) for p in parts]) for name in ("k", "share", "pairs")))
    device = geometry.endpoints.device
    low, high = k_range
    grid = torch.arange(math.ceil(low / PLUMB_K_STEP - 1e-9), math.floor(high / PLUMB_K_STEP + 1e-9) + 1,
                        device=device, dtype=torch.float64) * PLUMB_K_STEP
    if not bool((grid == 0).any()):
        grid = torch.cat([grid, grid.new_zeros(1)])
    weight = geometry.weight
    count = min(CHAIN_SEGMENTS, weight.shape[1])
    index = top_indices(weight, count, dim=1)
    endpoints = torch.gather(geometry.endpoints, 1, index[..., None].expand(-1, -1, 4)).to(torch.float64)
    mask = torch.gather(geometry.mask & (weight > 0), 1, index)
    image, i, j, pair_weight = chain_pairs(endpoints, mask, geometry.long_side.to(torch.float64))
    # the paired pieces' directions undistorted at every k of the grid: x and y, (P, K) each
    centre = geometry.centre.to(torch.float64)[image]  # (P, 2)
    inv_r2 = (1.0 / geometry.radius.to(torch.float64) ** 2)[image, None, None]

    def directions(pieces):  # (P, 4) -> the unit directions' x and y, (P, K) each
        x, y = pieces[:, 0::2] - centre[:, :1], pieces[:, 1::2] - centre[:, 1:]  # (P, 2): both endpoints
        factor = 1.0 + grid.view(1, -1, 1) * (x * x + y * y)[:, None, :] * inv_r2  # (P, K, 2)
        x, y = x[:, None, :] / factor, y[:, None, :] / factor  # undistorted
        dx, dy = x[..., 1] - x[..., 0], y[..., 1] - y[..., 0]
        norm = exact_math.sqrt(dx * dx + dy * dy).clamp_min(1e-12)
        return dx / norm, dy / norm

    (ax, ay), (bx, by) = directions(endpoints[image, i]), directions(endpoints[image, j])
    turn = exact_math.asin((ax * by - ay * bx).abs().clamp(max=1.0))
    cost_terms = pair_weight[:, None] * turn.clamp(max=math.radians(TURN_CAP_DEG)) ** 2
    cap_cost = geometry.long_side.to(torch.float64) * math.radians(TURN_CAP_DEG) ** 2  # a pair's largest term
    cost = exact_index_sum(cost_terms, image, batch, cap_cost[:, None])
    best = first_argmax(-cost, 1)
    at_zero = cost[:, int((grid == 0).nonzero()[0, 0])]
    best_cost = cost.gather(1, best[:, None])[:, 0]
    share = torch.where(at_zero > 0, 1.0 - best_cost / at_zero.clamp_min(1e-300), torch.zeros_like(at_zero))
    pairs = torch.bincount(image, minlength=batch)
    k = torch.where(pairs > 0, grid[best], torch.zeros_like(at_zero))
    return PlumbLine(k, share.clamp(0.0, 1.0), pairs)




def angle_grid_config(config: SearchConfig) -> SearchConfig:
    """The configuration of the k^4 grid at each k: ``grid_points_per_dim`` =
    ``distortion_grid_size`` where set (the lattice passes' first step is a third of its cell);
    the lens search scores its whole grids (``grid_coarse_factor`` 1)."""
    if not config.distortion_grid_size:
        return replace(config, grid_coarse_factor=1)
    return replace(config, grid_points_per_dim=config.distortion_grid_size, grid_coarse_factor=1)


def k_values(config: SearchConfig, geometry: SegmentGeometry) -> torch.Tensor:
    """The stage-1 values of k per image, (B, K) float64: the known k; else the plumb-line k
    (:func:`plumb_line`, with ``distortion_plumb_line``) and ``distortion_grid_k``, clamped into the
    k range."""
    setting = config.distortion
    batch = geometry.endpoints.shape[0]
    if setting.known_k is not None:
        return torch.full((batch, 1), setting.known_k, dtype=torch.float64)
    low, high = setting.k_range
    values = [torch.tensor(config.distortion_grid_k, dtype=torch.float64).expand(batch, -1)]
    if config.distortion_plumb_line:
        values.insert(0, plumb_line(geometry, setting.k_range, config.max_chunk_elements).k.cpu()[:, None])
    return torch.cat(values, 1).clamp(low, high)


def k_step(config: SearchConfig) -> float:
    """The spacing of k the lattice passes start from (their first k step is a third of it):
    ``distortion_k_spacing``, 0 for a known k."""
    return 0.0 if config.distortion.known_k is not None else config.distortion_k_spacing


def parameter_box_k(config: SearchConfig, long_side: torch.Tensor, known_focal: torch.Tensor | None):
    """:func:`fr_torch.core.search.grid.parameter_box` with k's box as a fifth column: (B, 5) each."""
    lower, upper = parameter_box(config, long_side, known_focal)
    k_low, k_high = config.distortion.k_box()
    return with_k(lower, k_low), with_k(upper, k_high)


def with_k(rows: torch.Tensor, k) -> torch.Tensor:
    """Rows (..., 4) with a fifth column k (a number or a tensor broadcastable to ``rows[..., 0]``)."""
    k = torch.as_tensor(k, dtype=rows.dtype, device=rows.device).expand(rows.shape[:-1])
    return torch.cat([rows, k[..., None]], -1)


def score_rows(likelihood: MixtureLikelihood, geometry: SegmentGeometry, rows: torch.Tensor,
               max_chunk_elements: int, vertical_block: int = 1) -> torch.Tensor:
    """Objectives of rows (B, G, P, 5) whose P hypotheses of each group share k (that of the group's
    first row): one virtual image per (image, group).  Returns (B, G * P) in ``rows``' order."""
    batch, groups, points = rows.shape[:3]
    k = rows[:, :, 0, DISTORTION]
    features = geometry.features(k)
    hypotheses = rows[..., :DISTORTION].reshape(batch * groups, points, DISTORTION)
    scores = score_grid(likelihood, features, hypotheses, max_chunk_elements, vertical_block).view(batch, groups, points)
    if geometry.k_prior_weight:
        scores = scores + geometry.k_log_prior(k.to(scores.device, scores.dtype))[0][..., None]
    return scores.view(batch, groups * points)


def grid_over_k(likelihood: MixtureLikelihood, geometry: SegmentGeometry, config: SearchConfig,
                long_side: torch.Tensor, known_focal: torch.Tensor | None):
    """Stage 1 over k: the k^4 (k^3 with a known focal) grid at each of :func:`k_values`.

    Returns (starts (B, L, 5), their scores (B, L), the grid scores (B, G) at the k of the best
    start and the segments each image's grid scored (B,)) (the last two for the ``grid_entropy`` cue).
    """
    ks = k_values(config, geometry).to(geometry.endpoints.device)
    batch, count = ks.shape
    features = geometry.features(ks)  # B * K virtual images
    device = geometry.endpoints.device
    long_rep = long_side.repeat_interleave(count).to(device)
    focal_rep = None if known_focal is None else known_focal.repeat_interleave(count).to(device)
    grid_config = angle_grid_config(config)
    hypotheses = grid_hypotheses(grid_config, long_rep, focal_rep)  # (B * K, G, 4)
    scores = score_grid(likelihood, features, hypotheses, config.max_chunk_elements,
                        vertical_block=grid_config.grid_points_per_dim)
    n_grid = hypotheses.shape[1]
    if geometry.k_prior_weight:
        prior = geometry.k_log_prior(ks.to(scores))[0]  # (B, K)
        scores = (scores.view(batch, count, n_grid) + prior[..., None]).view(batch * count, n_grid)
    rows = with_k(hypotheses.view(batch, count, n_grid, 4), ks.view(batch, count, 1))
    starts, top = select_starts(config, scores.view(batch, count * n_grid), rows.view(batch, count * n_grid, 5))
    best_k = first_argmax(-(starts[:, 0, DISTORTION, None] - ks.to(starts)).abs(), -1)  # (B,)
    rows_index = torch.arange(batch, device=device) * count + best_k.to(device)
    return starts, top, scores[rows_index], features.mask.sum(-1)[rows_index]


def sweep_focal_rows(likelihood: MixtureLikelihood, geometry: SegmentGeometry, starts: torch.Tensor,
                     scores: torch.Tensor, config: SearchConfig, lower: torch.Tensor, upper: torch.Tensor):
    """:func:`fr_torch.core.search.passes.sweep_focal` of each start (B, L, 5) at its own k: returns (B, 2L, 5)
    starts (the inputs, then each one's best swept point or a copy) and their (B, 2L) scores."""
    batch, n_start = starts.shape[:2]
    features = geometry.features(starts[..., DISTORTION])
    lower4, upper4 = (x[:, :DISTORTION].repeat_interleave(n_start, 0) for x in (lower, upper))
    prior = geometry.k_log_prior(starts[..., DISTORTION].to(scores))[0]  # the same k all along a start's ridge
    swept, swept_scores = sweep_focal(likelihood, features, starts[..., :DISTORTION].reshape(-1, 1, DISTORTION),
                                      (scores - prior).reshape(-1, 1), config, lower4, upper4)
    if swept.shape[1] == 1:  # no sweep (a known focal length, or none configured)
        return starts, scores
    rows = with_k(swept.view(batch, n_start, 2, DISTORTION), starts[..., DISTORTION, None].to(swept))
    swept_scores = swept_scores.view(batch, n_start, 2) + prior[..., None].to(swept_scores)
    return (torch.cat([rows[:, :, 0], rows[:, :, 1]], 1).to(starts),
            torch.cat([swept_scores[:, :, 0], swept_scores[:, :, 1]], 1))


#: The 3^5 lattice of :func:`subdivide_rows`: k slowest (three blocks of :data:`~fr_torch.core.search.passes.LATTICE`,
#: the 3^4 lattice, pan fastest), so each block shares k and runs of 3 share the vertical VP.
LATTICE_K = torch.cat([torch.cat([LATTICE, torch.full((len(LATTICE), 1), offset, dtype=torch.float64)], 1)
                       for offset in (-1.0, 0.0, 1.0)])


def subdivide_rows(likelihood: MixtureLikelihood, geometry: SegmentGeometry, starts: torch.Tensor,
                   scores: torch.Tensor, config: SearchConfig, lower: torch.Tensor, upper: torch.Tensor,
                   k_spacing: float | None = None):
    """:func:`fr_torch.core.search.passes.subdivide_starts` in five dimensions: ``config.grid_passes`` passes
    of the 3^5 lattice :data:`LATTICE_K` around each start (B, L, 5) (k's step: a third of
    ``k_spacing``, default :func:`k_step`, then a third of that; a known k
    stays fixed), keeping the best point.  Returns (starts, scores) of the same shapes; every score
    is >= its input."""
    if config.grid_passes == 0:
        return starts, scores
    device = geometry.endpoints.device
    lower64, upper64 = lower.to(torch.float64), upper.to(torch.float64)
    cell = grid_cell(angle_grid_config(config), lower64[:, :DISTORTION], upper64[:, :DISTORTION])
    k_spacing = k_step(config) if k_spacing is None else k_spacing
    step = torch.cat([cell, torch.full_like(cell[:, :1], k_spacing)], -1)  # (B, 5)
    joint = config.distortion_lattice == "joint"
    lattice = LATTICE_K if k_spacing > 0 and joint else with_k(LATTICE, 0.0)
    k_offsets = torch.zeros(2, 5, dtype=torch.float64, device=device)
    k_offsets[:, DISTORTION] = k_offsets.new_tensor([-1.0, 1.0])
    batch, n_start = starts.shape[:2]

    def score_points(points: torch.Tensor, place):
        rows = from_log_focal(points).view(batch, n_start * (len(lattice) // len(LATTICE)), len(LATTICE), 5)
        point_scores = score_rows(likelihood, geometry, rows, config.max_chunk_elements, vertical_block=3)
        if not joint and k_spacing > 0:  # k alone, one step either side of each start
            k_points = place(k_offsets)  # (B, L, 2, 5)
            k_scores = score_rows(likelihood, geometry, from_log_focal(k_points).view(batch, 2 * n_start, 1, 5),
                                  config.max_chunk_elements)
            points = torch.cat([points, k_points], 2)
            point_scores = torch.cat([point_scores.view(batch, n_start, -1), k_scores.view(batch, n_start, 2)],
                                     2).view(batch, -1)
        return points, point_scores

    return lattice_passes(starts, scores, lattice, step, lower64, upper64, config, score_points,
                          tie_tolerance(geometry), device)




def search_with_k(likelihood: MixtureLikelihood, geometry: SegmentGeometry, features: SegmentFeatures,
                  config: SearchConfig, long_side: torch.Tensor, known_focal: torch.Tensor | None,
                  iterations: int, fast: bool) -> SearchResult:
    """The whole search with k (module docstring) for the images of ``geometry``.

    ``features``: the same images' segments as :meth:`SegmentGeometry.features` gives them at any k
    (the refinement reads their lengths); ``long_side`` (B,) pixels; ``known_focal`` (B,) or None;
    ``iterations``, ``fast``: the refinement's steps and mode.
    """
    t0 = time.perf_counter()
    starts, top_scores, grid_scores, grid_counts = grid_over_k(likelihood, geometry, config, long_side, known_focal)
    lower, upper = parameter_box_k(config, long_side, known_focal)
    starts, top_scores = sweep_focal_rows(likelihood, geometry, starts, top_scores, config, lower, upper)
    starts, top_scores = subdivide_rows(likelihood, geometry, starts, top_scores, config, lower, upper)
    grid_seconds = time.perf_counter() - t0
    params, scores, tied = refine_starts(likelihood, features, starts, top_scores, lower, upper, config, iterations,
                                         fast, geometry)
    return SearchResult(params, scores, grid_scores, grid_counts, grid_seconds, tied, lower, upper)


def likelihood_gain(scores: torch.Tensor, baseline: torch.Tensor, features: SegmentFeatures) -> torch.Tensor:
    """How much better ``scores`` explain the segments than ``baseline`` (both (B,) objectives),
    in nats per 1000 px of segment length (the photo's lengths): (B,) float64, finite (0 where
    either is not)."""
    per_kpx = features.total_length().clamp_min(1e-9) / 1000.0
    gain = (scores.to(torch.float64) - baseline.to(torch.float64)) / per_kpx
    return torch.where(torch.isfinite(gain), gain, torch.zeros_like(gain))


def bend_test(likelihood: MixtureLikelihood, geometry: SegmentGeometry, features: SegmentFeatures,
              params: torch.Tensor, scores: torch.Tensor, config: SearchConfig,
              known_focal: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
    """Do the lines of pinhole estimates bend?  A short division search from each estimate
    ``params`` (B, 4) with objective ``scores`` (B,): at the plumb-line k (:func:`plumb_line`) the
    estimate's focal ridge is swept (:func:`sweep_focal_rows`: a barrel photo's pinhole focal
    length is far from its undistorted one) and lattice passes refine f, R and k together
    (:func:`subdivide_rows`, k spacing :data:`PLUMB_K_SPACING`; a ``known_focal`` (B,) stays fixed).

    Returns float64 (B,) tensors, the cues of :data:`fr_torch.core.reliability.sanity.LINE_BEND_CUES`:
    ``line_bend_gain`` (:func:`likelihood_gain` of the best point over the pinhole estimate, >= 0),
    ``line_bend_k`` (its k), ``line_bend_plumb_k``, ``line_bend_share`` and ``line_bend_pairs`` (the
    plumb line's k, share and pairs)."""
    k_low, k_high = config.distortion.k_range
    plumb = plumb_line(geometry, config.distortion.k_range, config.max_chunk_elements)
    long_side = geometry.long_side.to("cpu", torch.float64)
    lower, upper = parameter_box(config, long_side, known_focal)
    start = into_box(params.to(torch.float64).cpu(), lower, upper, config.periodic_pan)
    lower, upper = with_k(lower, k_low), with_k(upper, k_high)
    device = geometry.endpoints.device  # the box stays on the host, as in search_with_k; the rows go to the segments
    start = with_k(start, plumb.k.to("cpu", torch.float64).clamp(k_low, k_high))[:, None].to(device)  # (B, 1, 5)
    start_scores = score_rows(likelihood, geometry, start[:, :, None], config.max_chunk_elements)
    starts, start_scores = sweep_focal_rows(likelihood, geometry, start, start_scores.to(torch.float64), config,
                                            lower, upper)
    found, found_scores = subdivide_rows(likelihood, geometry, starts, start_scores.to(torch.float64), config,
                                         lower, upper, k_spacing=PLUMB_K_SPACING)
    best = first_argmax(found_scores, 1)
    rows = torch.arange(len(best), device=best.device)
    gain = likelihood_gain(found_scores[rows, best], scores, features).clamp_min(0.0)
    return {"line_bend_gain": gain, "line_bend_k": found[rows, best, DISTORTION].to(torch.float64),
            "line_bend_plumb_k": plumb.k.to(torch.float64), "line_bend_share": plumb.share.to(torch.float64),
            "line_bend_pairs": plumb.pairs.to(torch.float64)}
