"""fR's vanishing points as a result of their own: ranked by support, and extra Atlanta families.

After the search, every estimate has the three Manhattan vanishing points ``K R[:, k]``.  This
module ranks them, and optionally finds more (the Atlanta world: further horizontal families
that share the vertical, at free azimuths; then, where none is left, families in free
directions), without touching f or R.

**Support** of a family: the length-weighted posterior mass of its segments under the mixture,
``sum_i len_i q_ik`` (pixels of segment length; ``q_ik`` the posterior of segment i for family k).
Vanishing points are ranked by it, most supported first.

**Atlanta families** (:class:`AtlantaConfig`, ``fr calibrate --atlanta``, ``fr[atlanta=on]``):
a horizontal direction at azimuth ``a`` from the first Manhattan column, ``d(a) = cos a R[:, 0] +
sin a R[:, 2]``, has its vanishing point on the horizon, ``v(a) = K d(a)``.  Greedily, up to
``max_extra`` times: every azimuth of a grid over [0, 180) deg (``step_deg``) is scored by the gain
in the length-weighted log-likelihood of adding a family at ``v(a)`` with mixture weight ``prior``
(the other components scaled by ``1 - prior``; the family's density is the horizontal Manhattan
family's, same deviation measure and lambda), ``sum_i len_i [log((1 - prior) p_i + prior h_i(a)) -
log p_i]``; azimuths within ``exclusion_deg`` of a family already in the model are not candidates
(a copy of a family always gains).  The best azimuth is kept when its gain is positive and its
support reaches ``min_support`` of the image's total segment length; the mixture then includes it
and the next family is searched.  The segments the Manhattan fit explains poorly (the background)
are the ones that gain.

**Free directions** (``free_segments`` > 0): in every step the candidates are also the
intersections of every pair of the ``free_segments`` segments the current mixture leaves most to
its background (length times background posterior); the best one (same gain, same exclusion,
measured as the angle between directions ``K^-1 v``) is refitted twice to the segments it explains
(the weighted least-squares intersection of their lines, weights length times its posterior).  It
is kept, instead of the horizontal family, when its gain is positive, its support reaches
``free_min_support`` and either no horizontal family passes or it gains more than
``free_gain_ratio`` times the best horizontal one.  Roofs, stairs, slanted objects: vanishing
points off the horizon.

The defaults of :class:`AtlantaConfig` were chosen on train splits (NYU-VP train, YUD+ train;
``results/decisions/47.md``).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, fields, replace

import torch

from fr_torch.core.exact import cross3, dot3, exact_sum, first_argmax, small_sum, top_indices
from fr_torch.core.geometry.conventions import signed_rows, vanishing_point_rows, vanishing_points
from fr_torch.errors import FRInputError
from fr_torch.core import exact_math

#: Images whose Atlanta candidates are scored at once (bounds memory: N x A deviations each).
ATLANTA_CHUNK_IMAGES = 4
#: Without Atlanta families, segments (images x N) ranked at once: a GPU batch in one pass rather
#: than a few operations per image.
RANK_CHUNK_SEGMENTS = 1 << 22


@dataclass(frozen=True)
class AtlantaConfig:
    """Extra horizontal families at free azimuths, then free directions (module docstring).

    ``max_extra``: families added at most (0 = none: only the ranking).  ``prior``: mixture weight
    of each added family, in (0, 0.5].  ``min_support``: a horizontal family is kept when its
    length-weighted posterior mass reaches this share of the image's total segment length.
    ``exclusion_deg``: no candidate within this angle (degrees) of a family already in the model.
    ``step_deg``: the azimuth grid's step (degrees).  ``free_segments``: segments whose pairs
    propose free directions (0 = horizontal families only); ``free_min_support``: the share a free
    family needs; ``free_gain_ratio``: how many times the best horizontal family's gain a free
    direction must gain to be kept instead.  Defaults: chosen on train splits (module docstring).
    """

    max_extra: int = 3
    prior: float = 0.01
    min_support: float = 0.01
    exclusion_deg: float = 5.0
    step_deg: float = 0.25
    free_segments: int = 24
    free_min_support: float = 0.03
    free_gain_ratio: float = 10.0

    def __post_init__(self) -> None:
        for name, high in (("max_extra", 10), ("free_segments", 200)):
            value = getattr(self, name)
            if not (isinstance(value, int) and 0 <= value <= high):
                raise FRInputError(f"atlanta {name} must be an integer in [0, {high}], got {value!r}")
        checks = {"prior": (0.0, 0.5), "min_support": (0.0, 1.0), "free_min_support": (0.0, 1.0),
                  "free_gain_ratio": (1.0, 1e6), "exclusion_deg": (0.0, 45.0),
                  "step_deg": (0.01, 5.0)}
        for name, (low, high) in checks.items():
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and math.isfinite(value) and low <= value <= high):
                raise FRInputError(f"atlanta {name} must be a number in [{low:g}, {high:g}], got {value!r}")
        if self.prior <= 0:
            raise FRInputError("atlanta prior must be > 0")

    @classmethod
    def parse(cls, value) -> "AtlantaConfig | None":
        """None / False / ``"off"`` -> None (no extra families); True / ``"on"`` -> the defaults;
        ``"max_extra=2:prior=0.05"`` (``:``- or ``;``-separated ``key=value``) -> the defaults with those
        overrides; an :class:`AtlantaConfig` as is.  FRInputError (one line) otherwise."""
        if value is None or value is False or isinstance(value, cls):
            return value or None
        if value is True:
            return cls()
        text = str(value).strip()
        if text.lower() in ("off", "false", "0", "no", "none", ""):
            return None
        if text.lower() in ("on", "true", "1", "yes", "default"):
            return cls()
        return replace(cls(), **overrides_from_text(cls, text, "atlanta", "on"))


def overrides_from_text(cls, text: str, setting: str, switch: str, skip: tuple[str, ...] = ()) -> dict:
    """The field overrides of dataclass ``cls`` written as ``key=value`` pairs joined by ``:`` or
    ``;`` (``"max_extra=2:prior=0.05"``): {field name: int for a field typed ``int``, else float}.
    Tokens in ``skip`` (lower case) are passed over.  FRInputError (one line, naming ``setting``
    and, for a malformed pair, the words it accepts: ``switch``, off or the pairs) otherwise."""
    kinds = {f.name: f.type for f in fields(cls)}
    overrides = {}
    for part in text.replace(";", ":").split(":"):
        if part.strip().lower() in skip:
            continue
        key, _, raw = part.partition("=")
        key = key.strip()
        if key not in kinds or not raw.strip():
            raise FRInputError(f"{setting}: expected {switch}, off or key=value pairs ({', '.join(kinds)}), "
                               f"got {part!r}")
        try:
            overrides[key] = int(raw) if kinds[key] in ("int", int) else float(raw)
        except ValueError:
            raise FRInputError(f"{setting} {key}: not a number: {raw!r}") from None
    return overrides


@dataclass
class RankedVanishingPoints:
    """Vanishing points of a batch of B images, ranked per image by support (module docstring).

    ``points``: (B, M, 3) homogeneous points (x, y, w) in pixels, ``w >= 0``; M = 3 + max_extra.
    ``support``: (B, M) pixels of segment length, descending along M; -1 where an image has fewer
    than M (those rows of ``points`` are 0).  ``family``: (B, M) int64, 0-2 = the Manhattan column
    (1 = vertical), 3.. = Atlanta families in the order they were found, -1 = none.
    ``azimuth_deg``: (B, M) azimuth of each horizontal family from ``R[:, 0]`` (degrees in
    [0, 180): 0 and 90 for the Manhattan horizontals), NaN for the vertical and empty rows.
    """

    points: torch.Tensor
    support: torch.Tensor
    family: torch.Tensor
    azimuth_deg: torch.Tensor


def rank_vanishing_points(likelihood, features, rotation: torch.Tensor, focal: torch.Tensor,
                          atlanta: AtlantaConfig | None = None, fixed_azimuth_deg: torch.Tensor | None = None,
                          fixed_weight: torch.Tensor | None = None) -> RankedVanishingPoints:
    """Rank the Manhattan VPs of B estimates by support and add extra families (module docstring).

    ``likelihood``: the :class:`~fr_torch.core.likelihood.mixture.MixtureLikelihood` of the search;
    ``features``: its :class:`~fr_torch.core.likelihood.measures.SegmentFeatures` (B, N); ``rotation``
    (B, 3, 3) world -> camera; ``focal`` (B,) pixels.  Computed in float64.

    ``fixed_azimuth_deg`` (B, S) degrees from ``R[:, 0]``, NaN = none: horizontal families the fit
    already holds (:func:`fr_torch.core.search.manhattan.fit_families`), in the mixture before any
    Atlanta family, with mixture weights ``fixed_weight`` (B, S) and the Manhattan components scaled
    by one minus their sum; they are families 3, 4, ... in that order.
    """
    if atlanta is not None and likelihood.params.model != "mixture":
        atlanta = None  # the "no probabilistic model" ablation has no mixture to add a family to
    chunk = ATLANTA_CHUNK_IMAGES if atlanta is not None or fixed_azimuth_deg is not None \
        else max(1, RANK_CHUNK_SEGMENTS // max(1, features.weight.shape[1]))
    parts = [_rank_chunk(likelihood, features.images(b, b + chunk), rotation[b:b + chunk], focal[b:b + chunk], atlanta,
                         None if fixed_azimuth_deg is None else fixed_azimuth_deg[b:b + chunk],
                         None if fixed_weight is None else fixed_weight[b:b + chunk])
             for b in range(0, rotation.shape[0], chunk)]
    return RankedVanishingPoints(*(torch.cat([getattr(p, name) for p in parts]) for name in
                                   ("points", "support", "family", "azimuth_deg")))


def _unit_directions(focal: torch.Tensor, pp: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
    """Unit camera directions (B, C, 3) ``K^-1 p`` of homogeneous pixel points p (B, C, 3) for
    focal lengths (B,) and principal points (B, 2), pixels; zero rows stay zero."""
    w = points[..., 2]
    d = torch.stack([(points[..., 0] - pp[:, None, 0] * w) / focal[:, None],
                     (points[..., 1] - pp[:, None, 1] * w) / focal[:, None], w], -1)
    return d / exact_math.sqrt(dot3(d, d))[..., None].clamp_min(1e-300)


def _pixels(focal: torch.Tensor, pp: torch.Tensor, dirs: torch.Tensor) -> torch.Tensor:
    """Homogeneous pixel points ``K d`` (B, C, 3) of camera directions d (B, C, 3), focal lengths
    (B,) and principal points (B, 2), pixels: their vanishing points
    (:func:`fr_torch.core.geometry.conventions.vanishing_points`, directions as columns)."""
    return vanishing_points(focal, pp, dirs.transpose(-1, -2)).transpose(-1, -2)


def _free_candidates(features, unexplained: torch.Tensor, count: int, focal: torch.Tensor):
    """Candidate VPs ``K d`` (B, C, 3), their unit directions d, and a validity mask (B, C): the
    intersections of every pair of the ``count`` segments with the largest ``unexplained`` weight."""
    top = top_indices(unexplained, min(count, unexplained.shape[1]), dim=1)  # (B, k)
    lines = torch.gather(features.line, 1, top[..., None].expand(-1, -1, 3))
    first, second = torch.triu_indices(top.shape[1], top.shape[1], 1, device=top.device)
    points = cross3(lines[:, first], lines[:, second])  # (B, C, 3)
    usable = (dot3(points, points) > 1e-24) & (torch.gather(unexplained, 1, top)[:, first] > 0) \
        & (torch.gather(unexplained, 1, top)[:, second] > 0)
    dirs = _unit_directions(focal, features.principal_point, points)
    return _pixels(focal, features.principal_point, dirs), dirs, usable


def horizontal_directions(rotation: torch.Tensor, azimuth: torch.Tensor) -> torch.Tensor:
    """Unit horizontal directions ``cos a R[:, 0] + sin a R[:, 2]`` (B, A, 3) at azimuths ``a`` (B, A)
    or (A,) radians from the first Manhattan column of rotations (B, 3, 3) (world -> camera)."""
    azimuth = azimuth.expand(rotation.shape[0], -1) if azimuth.dim() == 1 else azimuth
    sin, cos = exact_math.sin_cos(azimuth)
    return cos[..., None] * rotation[:, None, :, 0] + sin[..., None] * rotation[:, None, :, 2]


def horizon_points(rotation: torch.Tensor, focal: torch.Tensor, principal_point: torch.Tensor,
                   azimuth: torch.Tensor) -> torch.Tensor:
    """The vanishing points ``K d(a)`` (B, A, 3) homogeneous pixels of the horizontal directions at
    azimuths ``a`` (B, A) or (A,) radians (:func:`horizontal_directions`); ``focal`` (B,) and
    ``principal_point`` (B, 2) pixels."""
    return _pixels(focal, principal_point, horizontal_directions(rotation, azimuth))


def _rank_chunk(likelihood, features, rotation, focal, atlanta, fixed_azimuth_deg=None, fixed_weight=None):
    dtype = torch.float64
    rotation, focal = rotation.to(dtype), focal.to(dtype)
    feats = features if features.weight.dtype == dtype else _as_dtype(features, dtype)
    device = rotation.device
    batch = rotation.shape[0]
    weight = feats.weight  # (B, N), 0 for padding
    pp = feats.principal_point  # (B, 2)
    log_comp = likelihood.component_log_densities(feats, rotation[:, None], focal[:, None])[:, :, 0]  # (B, N, 4)
    comp = exact_math.exp(log_comp)
    mix = small_sum(comp, -1)  # (B, N) p_i
    extra = atlanta.max_extra if atlanta is not None else 0
    fixed = 0 if fixed_azimuth_deg is None else fixed_azimuth_deg.shape[1]
    count = 3 + fixed + extra
    points = torch.zeros(batch, count, 3, dtype=dtype, device=device)
    points[:, :3] = vanishing_point_rows(focal, feats.principal_point, rotation)
    azimuth = torch.full((batch, count), math.nan, dtype=dtype, device=device)
    azimuth[:, 0], azimuth[:, 2] = 0.0, 90.0
    present = torch.zeros(batch, count, dtype=torch.bool, device=device)
    present[:, :3] = True
    extra_density = torch.zeros(batch, weight.shape[1], fixed + extra, dtype=dtype, device=device)  # prior * h
    manhattan_scale = torch.ones(batch, dtype=dtype, device=device)  # prod (1 - prior) of added families
    if fixed:  # the fit's own families, in the mixture with the weights the fit gave them
        fixed_deg = fixed_azimuth_deg.to(device=device, dtype=dtype)
        held = torch.isfinite(fixed_deg)  # (B, S)
        fixed_w = torch.where(held, fixed_weight.to(device=device, dtype=dtype), torch.zeros_like(fixed_deg))
        fixed_points = horizon_points(rotation, focal, pp, torch.deg2rad(torch.nan_to_num(fixed_deg, nan=0.0)))
        density = fixed_w[:, None, :] * exact_math.exp(likelihood.horizontal_log_density(
            likelihood.point_deviations(feats, fixed_points, focal)))  # (B, N, S)
        manhattan_scale = 1.0 - small_sum(fixed_w, -1)
        mix = manhattan_scale[:, None] * mix + small_sum(density, -1)
        points[:, 3:3 + fixed] = torch.where(held[..., None], signed_rows(fixed_points), points[:, 3:3 + fixed])
        azimuth[:, 3:3 + fixed] = torch.remainder(fixed_deg, 180.0)
        present[:, 3:3 + fixed] = held
        extra_density[:, :, :fixed] = density
    if extra:
        step = math.radians(atlanta.step_deg)
        grid = torch.arange(0.0, math.pi, step, dtype=dtype, device=device)  # (A,)
        grid_dirs = horizontal_directions(rotation, grid)  # (B, A, 3)
        grid_points = _pixels(focal, pp, grid_dirs)  # (B, A, 3)
        grid_density = atlanta.prior * exact_math.exp(likelihood.horizontal_log_density(
            likelihood.point_deviations(feats, grid_points, focal)))  # (B, N, A)
        taken = rotation.transpose(1, 2).clone()  # (B, F, 3) unit directions of the families in the model
        if fixed:
            taken = torch.cat([taken, torch.where(held[..., None], horizontal_directions(
                rotation, torch.deg2rad(torch.nan_to_num(fixed_deg, nan=0.0))), taken[:, :1])], 1)
        total = exact_sum(weight, -1).clamp_min(1e-12)
        active = torch.ones(batch, dtype=torch.bool, device=device)
        rows = torch.arange(batch, device=device)
        cos_window = exact_math.of(exact_math.cos, math.radians(atlanta.exclusion_deg))
        prior = atlanta.prior

        def best_of(density, dirs, usable):
            """Index (B,) of the candidate with the largest gain, away from the families taken."""
            mixed = (1.0 - prior) * mix[..., None] + density  # (B, N, C)
            gain = exact_sum(exact_math.log(mixed) - exact_math.log(mix)[..., None], 1, weight=weight[..., None])  # (B, C)
            near = dot3(dirs[:, :, None, :], taken[:, None, :, :]).abs().gt(cos_window).any(-1)
            return first_argmax(gain.masked_fill(near | ~usable, -math.inf), 1)

        def score(chosen):
            """(gain (B,), support (B,), new mixture (B, N)) of adding a family of density ``chosen``."""
            mixed = (1.0 - prior) * mix + chosen
            return (exact_sum(exact_math.log(mixed) - exact_math.log(mix), -1, weight=weight),
                    exact_sum(chosen / mixed, -1, weight=weight), mixed)

        for j in range(extra):
            best = best_of(grid_density, grid_dirs, torch.ones(grid_points.shape[:2], dtype=torch.bool, device=device))
            point, chosen = grid_points[rows, best], grid_density[rows, :, best]
            gain, support, mixed = score(chosen)
            keep = active & (gain > 0) & (support >= atlanta.min_support * total)
            horizontal = keep.clone()
            if atlanta.free_segments:  # a free direction where no horizontal family passes, or one that gains far more
                background = comp[..., 3] * manhattan_scale[:, None] / mix
                free_points, free_dirs, usable = _free_candidates(feats, weight * background, atlanta.free_segments,
                                                                  focal)
                free_density = prior * exact_math.exp(likelihood.horizontal_log_density(
                    likelihood.point_deviations(feats, free_points, focal)))
                pick = best_of(free_density, free_dirs, usable)
                free_point, free_chosen = free_points[rows, pick], free_density[rows, :, pick]
                for _ in range(2):  # a pair of segments only proposes: refit to the segments it explains
                    resp = free_chosen / ((1.0 - prior) * mix + free_chosen)
                    refit = refine_points(feats, free_point[:, None], (weight * resp)[..., None])
                    free_point = _pixels(focal, pp, _unit_directions(focal, pp, refit))[:, 0]
                    free_chosen = prior * exact_math.exp(likelihood.horizontal_log_density(
                        likelihood.point_deviations(feats, free_point[:, None], focal)[..., 0]))
                free_gain, free_support, free_mixed = score(free_chosen)
                free_dir = _unit_directions(focal, pp, free_point[:, None])[:, 0]
                apart = dot3(free_dir[:, None, :], taken).abs().le(cos_window).all(-1)
                use_free = active & apart & (free_gain > 0) & (free_support >= atlanta.free_min_support * total) \
                    & (~keep | (free_gain > atlanta.free_gain_ratio * gain))
                point = torch.where(use_free[:, None], free_point, point)
                chosen = torch.where(use_free[:, None], free_chosen, chosen)
                mixed = torch.where(use_free[:, None], free_mixed, mixed)
                horizontal = horizontal & ~use_free
                keep = keep | use_free
            slot = 3 + fixed + j
            points[:, slot] = torch.where(keep[:, None], signed_rows(point), points[:, slot])
            azimuth[:, slot] = torch.where(horizontal, torch.rad2deg(grid[best]), azimuth[:, slot])
            present[:, slot] = keep
            extra_density[:, :, fixed + j] = torch.where(keep[:, None], chosen, extra_density[:, :, fixed + j])
            mix = torch.where(keep[:, None], mixed, mix)
            manhattan_scale = torch.where(keep, manhattan_scale * (1.0 - prior), manhattan_scale)
            taken = torch.cat([taken, torch.where(keep[:, None, None], _unit_directions(focal, pp, point[:, None]),
                                                  taken[:, :1])], 1)
            active = keep
    # Posterior mass of every family under the final mixture.
    family_density = torch.cat([comp[..., :3] * manhattan_scale[:, None, None], extra_density], -1)  # (B, N, M)
    support = exact_sum(family_density / mix[..., None].clamp_min(1e-300), 1, weight=weight[..., None])  # (B, M)
    support = torch.where(present, support, torch.full_like(support, -1.0))
    order = torch.argsort(support, dim=1, descending=True, stable=True)
    family = torch.arange(count, device=device).expand(batch, count)
    family = torch.where(present, family, torch.full_like(family, -1))
    azimuth[:, 1] = math.nan
    return RankedVanishingPoints(points.gather(1, order[..., None].expand(-1, -1, 3)), support.gather(1, order),
                                 family.gather(1, order), azimuth.gather(1, order))


def refine_points(features, points: torch.Tensor, weights: torch.Tensor) -> torch.Tensor:
    """Each VP moved freely to the weighted least-squares intersection of the segments' lines.

    ``points`` (B, M, 3) homogeneous pixels; ``weights`` (B, N, M) per segment and VP (e.g. length
    times posterior).  Lines are taken in coordinates centred on the principal point and scaled by
    half the long side, normalised to ``|l_xy| = 1``; the VP minimises ``sum_i w_i (l_i . v)^2``
    over unit v there (the smallest eigenvector), then goes back to pixels, signed ``w >= 0``.
    """
    scale = features.long_side / 2.0  # (B,)
    pp = features.principal_point  # (B, 2)
    line = features.line  # (B, N, 3) pixels: x' = (x - c) / s  ->  l' = (s l_x, s l_y, l . (c, 1))
    conditioned = torch.stack([scale[:, None] * line[..., 0], scale[:, None] * line[..., 1],
                               line[..., 0] * pp[:, None, 0] + line[..., 1] * pp[:, None, 1] + line[..., 2]], -1)
    planar = conditioned[..., 0] * conditioned[..., 0] + conditioned[..., 1] * conditioned[..., 1]
    conditioned = conditioned / exact_math.sqrt(planar)[..., None].clamp_min(1e-12)
    outer = conditioned[..., :, None] * conditioned[..., None, :]  # (B, N, 3, 3)
    moments = exact_sum(weights[..., None, None] * outer[:, :, None], 1)  # (B, M, 3, 3)
    _, vectors = torch.linalg.eigh(moments)
    v = vectors[..., 0]  # (B, M, 3) smallest eigenvalue
    pixels = torch.stack([scale[:, None] * v[..., 0] + pp[:, None, 0] * v[..., 2],
                          scale[:, None] * v[..., 1] + pp[:, None, 1] * v[..., 2], v[..., 2]], -1)
    return signed_rows(pixels / exact_math.sqrt(dot3(pixels, pixels))[..., None].clamp_min(1e-300))


def _as_dtype(features, dtype):
    """A copy of SegmentFeatures ``features`` with its floating tensors in ``dtype``."""
    values = {f.name: getattr(features, f.name) for f in fields(features) if f.init}
    return type(features)(**{k: v.to(dtype) if torch.is_floating_point(v) else v for k, v in values.items()})
