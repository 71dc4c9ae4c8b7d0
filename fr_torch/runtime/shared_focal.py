"""One focal length for many photos of one camera, and a soft prior on the focal length.

Usage::

    from fr_torch import FREstimator
    from fr_torch.runtime.shared_focal import calibrate_shared
    shared = calibrate_shared(FREstimator(), ["a.jpg", "b.jpg", "c.jpg"])
    shared.focal_px, shared.predicted_error_pct      # the camera's focal length (first image's pixels)
    shared.results[0].rotation                       # each photo's rotation at that focal length

Method (``docs/shared-focal.md``; choices in ``results/decisions/38.md``):

1. Every photo is calibrated alone (the estimator as usual; its segments and reliability kept).
2. **Focal profile** (:func:`focal_profiles`, :func:`with_estimator_prior`): for each photo, the
   best objective (the length-weighted log-likelihood plus the estimator's own focal prior, which
   corrects the likelihood's pull towards narrow views) with the focal length held at each of
   :attr:`SharedFocalSettings.grid_points` values spaced uniformly in ``log(f / L)`` over the
   search's FOV range (L = the image's long side), the rotation optimised at each: starts from the
   photo's own estimate moved along its focal ridge and from the best points of a coarse angle
   grid, refined with Fast-fR's Adam steps.
3. **Combination** (:func:`combine_profiles`): each profile is tempered into a log-likelihood of
   ``log(f / L)`` (``beta * (P - max P) / W``, W the photo's total segment length), floored at
   ``-cap`` (a photo can say "not here" at most that strongly, so a non-Manhattan photo or a wrong
   basin cannot veto the truth), optionally weighted by the reliability stage's predicted focal
   error (off by default: it tied with equal weights on train), summed over the photos, plus the log of an optional focal prior (:class:`~fr_torch.runtime.focal_prior.FocalPrior`).
   The shared ``log(f / L)`` is the sum's argmax, refined by a parabola through its neighbours.
   Photos whose profile is flat (a wall seen square on, VPs at infinity) add a constant: no drag.
4. Every photo is searched again with the focal length known (its rotation at the shared f).
5. **Principal point** (:attr:`SharedFocalSettings.principal_point`, on by default; only when the
   caller gives none): with at least ``pp_min_images`` photos of one orientation, each photo's
   objective at the shared f is scored over a grid of principal-point offsets (rotation refined
   from step 4's), tempered and floored as in step 3, summed, and the maximum of a quadratic fit
   is the group's principal point, its curvature the point's 1-sigma (:func:`shared_principal_point`);
   steps 2-4 run again at it.  Where the sum has no clear maximum the image centre is kept and
   the 1-sigma is infinite (JSON: null): rounding would otherwise decide the point.

Sizes: the shared quantity is ``f / L``, so resized copies and portrait / landscape shots of one
camera share it; a group whose usable photos differ in aspect ratio (a crop, another camera) is
refused (:class:`~fr_torch.errors.FRInputError` from :func:`calibrate_shared`).

``predicted_error_pct``: the predicted relative error of the shared focal length, 100 x
``kappa / sqrt(curvature)`` of the summed log-likelihood at its peak (in log f), ``kappa``
calibrated on train groups so that about two thirds of them fall within it (a 1-sigma value).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Sequence

import numpy as np
import torch

from fr_torch.core.exact import exact_sum
from fr_torch.core.geometry.conventions import image_centre
from fr_torch.core.geometry.params import angles_from_search_rotation, rotations
from fr_torch.core.likelihood.measures import SegmentFeatures
from fr_torch.core.likelihood.segments import SegmentBatch
from fr_torch.core.reliability.sanity import EDGE_REASON
from fr_torch.core.search.grid import grid_hypotheses, into_box, parameter_box, score_grid, select_starts
from fr_torch.core.search.passes import _focal_ridge_rotations
from fr_torch.core.search.refine import refine
from fr_torch.core.settings.fov import FovRange
from fr_torch.errors import FRInputError

#: Relative tolerance on the aspect ratio (short / long side) of the photos of one group.
ASPECT_TOLERANCE = 0.01


@dataclass(frozen=True)
class SharedFocalSettings:
    """Settings of the focal profile and of its combination (``results/decisions/38.md`` says how
    the defaults were chosen).

    ``grid_points``: focal values of the profile, uniform in log f over the FOV range.
    ``angle_grid`` / ``starts`` / ``iterations``: per focal value, the k^3 angle grid, how many of
    its best points are refined (besides the ridge start) and Adam steps per start.
    ``beta``: temperature, nats of log-likelihood per unit of mean objective per segment pixel.
    ``cap``: floor of each photo's tempered profile (nats below its own peak).
    ``error_scale_pct``: None (default: every photo weighs 1) or a photo weight
    ``1 / (1 + (e / error_scale_pct)^2)``, e the reliability stage's predicted focal error (%;
    weight 1 where a photo has none).
    ``kappa``: calibration factor of ``predicted_error_pct``.
    ``principal_point``: also estimate one principal point for the group (:func:`shared_principal_point`;
    only when the caller gives none, the group has at least ``pp_min_images`` usable photos and they
    share one orientation): ``pp_offsets`` are the offsets from the image centre tried along each
    axis (fractions of the long side; their grid is searched and a quadratic fitted to it), each
    photo's rotation refined for ``pp_iterations`` Adam steps at each.
    """
    grid_points: int = 48
    angle_grid: int = 4
    starts: int = 2
    iterations: int = 10
    beta: float = 30.0
    cap: float = 6.0
    error_scale_pct: float | None = None
    kappa: float = 1.613
    principal_point: bool = True
    pp_offsets: tuple[float, ...] = (-0.04, -0.02, 0.0, 0.02, 0.04)
    pp_iterations: int = 10
    pp_min_images: int = 5

    def __post_init__(self):
        if self.grid_points < 5 or self.angle_grid < 1 or self.starts < 1 or self.iterations < 0:
            raise FRInputError("SharedFocalSettings: grid_points >= 5, angle_grid >= 1, starts >= 1, iterations >= 0")
        if len(self.pp_offsets) < 3 or self.pp_iterations < 0 or self.pp_min_images < 2:
            raise FRInputError("SharedFocalSettings: pp_offsets needs >= 3 values, pp_iterations >= 0, "
                               "pp_min_images >= 2")
        for name in ("beta", "cap", "error_scale_pct", "kappa"):
            value = getattr(self, name)
            if value is None and name == "error_scale_pct":
                continue
            if not (math.isfinite(value) and value > 0):
                raise FRInputError(f"SharedFocalSettings.{name} must be a finite number > 0, got {value!r}")


def log_ratio_grid(fov_range: FovRange, count: int) -> np.ndarray:
    """(count,) values of ``log(f / L)`` (L the long side), uniform from the FOV range's widest view
    (smallest f) to its narrowest, endpoints included."""
    f_min, f_max = FovRange.parse(fov_range).focal_bounds(1.0)
    return np.linspace(math.log(f_min), math.log(f_max), count)


def focal_profiles(estimator, features, estimates: torch.Tensor, log_ratios: np.ndarray,
                   settings: SharedFocalSettings, chunk_images: int = 8) -> np.ndarray:
    """Best data objective of each photo with the focal length held at each grid value.

    Args:
        estimator: the :class:`~fr_torch.runtime.estimator.FREstimator` (its likelihood and search settings).
        features: :class:`~fr_torch.core.likelihood.measures.SegmentFeatures` of B photos (on the estimator's device).
        estimates: (B, 4) each photo's own estimate [pan, pitch, roll (degrees), f (pixels)].
        log_ratios: (K,) values of ``log(f / L)`` (:func:`log_ratio_grid`).
        settings: the profile's search settings.
        chunk_images: photos profiled together (each one's segments are copied K times).

    Returns:
        (B, K) float64: the length-weighted log-likelihood (objective units, without the estimator's
        focal prior) maximised over the rotation at each focal length; -inf where not finite.
    """
    likelihood, config = estimator.likelihood, estimator.search
    grid_config = replace(config, grid_points_per_dim=settings.angle_grid, top_l=settings.starts,
                          grid_coarse_factor=1)  # the whole angle grid at each focal length
    device = features.weight.device
    count = len(log_ratios)
    out = np.full((estimates.shape[0], count), -np.inf)
    ratios = torch.as_tensor(np.exp(log_ratios), dtype=torch.float64)
    for b0 in range(0, estimates.shape[0], chunk_images):
        b1 = min(estimates.shape[0], b0 + chunk_images)
        n = b1 - b0
        index = torch.arange(b0, b1, device=device).repeat_interleave(count)
        sub = features.take_images(index)
        long_side = features.long_side[b0:b1].to("cpu", torch.float64)
        focal = (long_side[:, None] * ratios[None, :]).reshape(-1)  # (n K,)
        hypotheses = grid_hypotheses(grid_config, long_side.repeat_interleave(count).to(device), focal.to(device))
        grid_scores = score_grid(likelihood, sub, hypotheses, config.max_chunk_elements,
                                 vertical_block=settings.angle_grid)
        starts, start_scores = select_starts(grid_config, grid_scores, hypotheses)
        lower, upper = parameter_box(config, long_side.repeat_interleave(count), focal)
        own = estimates[b0:b1].to(device=device, dtype=torch.float64)
        ratio = focal.view(n, count).to(device) / own[:, 3:]
        ridge = angles_from_search_rotation(_focal_ridge_rotations(rotations(own), ratio))  # (n, K, 3)
        ridge = torch.cat([ridge, focal.view(n, count, 1).to(device)], -1).view(n * count, 1, 4)
        ridge = into_box(ridge, lower[:, None].to(device), upper[:, None].to(device), config.periodic_pan)
        starts = torch.cat([ridge.to(starts), starts], 1)
        if settings.iterations:
            _, scores = refine(likelihood, sub, starts, lower.to(device), upper.to(device), settings.iterations,
                               fast=True, periodic_pan=config.periodic_pan)
            best = torch.maximum(scores.amax(1), start_scores.amax(1).to(scores))
        else:
            best = torch.maximum(score_grid(likelihood, sub, starts, config.max_chunk_elements)[:, 0],
                                 start_scores.amax(1))
        if likelihood.params.focal_prior_weight:  # the data term alone: the prior is the caller's
            best = best - likelihood.focal_prior(sub, focal.view(-1, 1).to(device), derivative=False)[0][:, 0].to(best)
        values = best.to(torch.float64).view(n, count).cpu().numpy()
        out[b0:b1] = np.where(np.isfinite(values), values, -np.inf)
    return out


@dataclass
class CombinedFocal:
    """The outcome of :func:`combine_profiles`.

    ``log_ratio``: the shared ``log(f / L)`` (nan when no photo was usable); ``predicted_error_pct``:
    its predicted 1-sigma error in percent (nan likewise); ``used``: (n,) bool, photos that entered;
    ``weights``: (n,) their weights; ``score``: (K,) the summed log-likelihood on the grid.
    """
    log_ratio: float
    predicted_error_pct: float
    used: np.ndarray
    weights: np.ndarray
    score: np.ndarray


def tempered_profiles(profiles: np.ndarray, total_length: np.ndarray, settings: SharedFocalSettings) -> np.ndarray:
    """(n, K) tempered and floored log-likelihoods of ``log(f / L)``: ``max(beta (P - max P) / W, -cap)``
    from profiles (n, K) (objective units) and total segment lengths W (n,) pixels; -cap where not finite."""
    peak = np.max(profiles, axis=1, keepdims=True)
    scaled = settings.beta * (profiles - peak) / np.maximum(total_length, 1e-9)[:, None]
    scaled = np.where(np.isfinite(scaled), scaled, -np.inf)
    return np.maximum(scaled, -settings.cap)


def combine_profiles(log_ratios: np.ndarray, profiles: np.ndarray, total_length: np.ndarray,
                     predicted_focal_pct: np.ndarray | None, settings: SharedFocalSettings,
                     prior: tuple[float, float] | None = None) -> CombinedFocal:
    """Combine per-photo focal profiles into one ``log(f / L)`` (method: module docstring, step 3).

    Args:
        log_ratios: (K,) grid of ``log(f / L)``, uniform.
        profiles: (n, K) from :func:`focal_profiles`; a row without a finite value is not used.
        total_length: (n,) total segment length per photo, pixels.
        predicted_focal_pct: (n,) the reliability stage's predicted focal error (%), or None (weight 1;
            likewise when ``settings.error_scale_pct`` is None).
        settings: temperature, floor, weights, calibration.
        prior: optional ``(log(f / L) centre, sigma in log f)``: a log-normal prior added once.

    Returns:
        :class:`CombinedFocal`.
    """
    profiles = np.asarray(profiles, dtype=np.float64).reshape(-1, len(log_ratios))
    used = np.isfinite(profiles).any(1) & np.isfinite(total_length) & (np.asarray(total_length) > 0)
    weights = np.ones(len(profiles))
    if predicted_focal_pct is not None and settings.error_scale_pct is not None:
        error = np.asarray(predicted_focal_pct, dtype=np.float64)
        weights = np.where(np.isfinite(error), 1.0 / (1.0 + (error / settings.error_scale_pct) ** 2), 1.0)
    weights = np.where(used, weights, 0.0)
    score = np.zeros(len(log_ratios))
    # each tempered profile is a log-likelihood; kappa^2 turns the sum into calibrated units
    scale = 1.0 / settings.kappa ** 2
    if used.any():
        tempered = tempered_profiles(profiles[used], np.asarray(total_length)[used], settings)
        score = score + scale * (weights[used, None] * tempered).sum(0)
    if prior is not None:
        centre, sigma = prior
        score = score - 0.5 * ((log_ratios - centre) / sigma) ** 2
    if not used.any() and prior is None:
        return CombinedFocal(math.nan, math.nan, used, weights, score)
    log_ratio, curvature = _parabolic_peak(log_ratios, score)
    error = 100.0 / math.sqrt(curvature) if curvature > 0 else math.inf
    return CombinedFocal(log_ratio, error, used, weights, score)


def _parabolic_peak(grid: np.ndarray, score: np.ndarray) -> tuple[float, float]:
    """(argmax, curvature = minus the second derivative) of ``score`` sampled on the uniform ``grid``:
    the best sample refined by the parabola through it and its neighbours (the sample itself at an end)."""
    k = int(np.argmax(score))
    step = float(grid[1] - grid[0])
    if k == 0 or k == len(grid) - 1:
        inner = 1 if k == 0 else len(grid) - 2
        curvature = -(score[inner - 1] - 2 * score[inner] + score[inner + 1]) / step ** 2
        return float(grid[k]), float(max(curvature, 0.0))
    left, mid, right = score[k - 1], score[k], score[k + 1]
    second = left - 2 * mid + right  # <= 0 at a maximum
    offset = 0.5 * (left - right) / second if second < 0 else 0.0
    return float(grid[k] + np.clip(offset, -0.5, 0.5) * step), float(-second / step ** 2)


@dataclass
class SharedFocalResult:
    """One focal length for a group of photos, and each photo's calibration at it.

    ``focal_px``: the shared focal length in the pixels of the first usable photo (photo i's own
    is ``focal_ratio * max(width_i, height_i)``, as in ``results[i].focal_px``); ``focal_ratio``:
    f / long side; ``predicted_error_pct``: predicted 1-sigma relative error of the shared focal
    length (%); ``images`` / ``images_used``: photos in the group / that entered the estimate
    (ok, with segments); ``ok`` False (and ``reason``) when no photo was usable: then ``focal_px``
    is None and ``results`` are the per-photo failures.  ``results``: one
    :class:`~fr_torch.core.result.CalibrationResult` per photo, in input order, searched with the
    focal length known (a photo that failed alone keeps its failure).  ``focal_prior``: the prior
    that entered (:meth:`fr_torch.runtime.focal_prior.FocalPrior.to_json`) or None.
    ``principal_point``: the group's estimated principal point (x, y) in the first usable photo's
    pixels, or None where it was not estimated (:attr:`SharedFocalSettings.principal_point`);
    ``principal_point_sigma_px``: its 1-sigma (x, y) in those pixels (:class:`PrincipalPointFit`;
    inf where the photos leave it open: the principal point is then the image centre).
    """
    focal_px: float | None
    focal_ratio: float | None
    predicted_error_pct: float | None
    images: int
    images_used: int
    ok: bool
    reason: str
    results: list = field(default_factory=list)
    focal_prior: dict | None = None
    principal_point: tuple[float, float] | None = None
    principal_point_sigma_px: tuple[float, float] | None = None

    def to_json(self) -> dict:
        """JSON-ready summary (no per-photo results): the ``shared_focal`` record of the CLI."""
        def clean(value):
            return None if value is None or not math.isfinite(value) else float(value)

        return {"ok": self.ok, "reason": self.reason, "focal_px": clean(self.focal_px),
                "focal_ratio": clean(self.focal_ratio), "predicted_error_pct": clean(self.predicted_error_pct),
                "images": self.images, "images_used": self.images_used,
                "principal_point": None if self.principal_point is None else [float(v) for v in self.principal_point],
                "principal_point_sigma_px": None if self.principal_point_sigma_px is None
                else [clean(v) for v in self.principal_point_sigma_px]}


def at_range_edge(log_ratios: np.ndarray, log_ratio: float) -> bool:
    """True when ``log_ratio`` lies within half a grid step of the grid's ends (the FOV range's edge)."""
    step = float(log_ratios[1] - log_ratios[0])
    return bool(log_ratio <= log_ratios[0] + 0.5 * step or log_ratio >= log_ratios[-1] - 0.5 * step)


def _mark_focal(result, predicted_error_pct: float, at_edge: bool) -> None:
    """A photo searched again at a combined focal length (in place): its predicted focal error becomes
    the combination's (when the result has predicted errors), and a focal length at the edge of the
    FOV range makes it unreliable."""
    if not result.ok:
        return
    if result.predicted_error is not None:
        result.predicted_error = dict(result.predicted_error, focal_pct=float(predicted_error_pct))
    if at_edge:
        result.reliable = False
        result.reason = "; ".join(r for r in (result.reason, EDGE_REASON) if r)


def _search_estimates(results) -> torch.Tensor:
    """(n, 4) float64 [pan, pitch, roll, f] of ok results (the search's parametrisation)."""
    rotation = torch.as_tensor(np.stack([np.asarray(r.rotation, np.float64) for r in results]))
    angles = angles_from_search_rotation(rotation)
    focal = torch.tensor([float(r.focal_px) for r in results], dtype=torch.float64)
    return torch.cat([angles, focal[:, None]], 1)


def check_group_sizes(sizes: Sequence[tuple[int, int]], names: Sequence[str]) -> None:
    """FRInputError (one line) unless every (width, height) has the same aspect ratio (short / long
    side, within :data:`ASPECT_TOLERANCE`): the shared quantity is f / long side."""
    aspects = [min(w, h) / max(w, h) for w, h in sizes]
    for size, aspect, name in zip(sizes, aspects, names):
        if abs(aspect - aspects[0]) > ASPECT_TOLERANCE * aspects[0]:
            raise FRInputError(f"shared focal length: {name} is {size[0]} x {size[1]}, {names[0]} is "
                               f"{sizes[0][0]} x {sizes[0][1]}: a group must share one aspect ratio "
                               "(resized copies and portrait/landscape are fine; crops are not)")


def profile_results(estimator, results, settings: SharedFocalSettings,
                    principal_points: Sequence | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(log_ratios (K,), profiles (n, K), total segment lengths (n,)) of ok per-photo results that
    hold their segments (``result.segments`` in the result's pixels, principal point from its camera
    unless ``principal_points`` gives one (x, y) per result)."""
    log_ratios = log_ratio_grid(estimator.search.fov_range, settings.grid_points)
    if not results:
        return log_ratios, np.zeros((0, len(log_ratios))), np.zeros(0)
    device, dtype = estimator.device, estimator.dtype
    batch = SegmentBatch.from_list([np.asarray(r.segments, np.float64) for r in results],
                                   [(r.width, r.height) for r in results], device, dtype)
    points = principal_points if principal_points is not None else [r.principal_point for r in results]
    pp = torch.tensor([list(p) for p in points], dtype=torch.float64)
    features = SegmentFeatures.from_batch(batch, pp.to(device=device, dtype=dtype))
    profiles = focal_profiles(estimator, features, _search_estimates(results), log_ratios, settings)
    return log_ratios, profiles, features.weight.sum(-1).to("cpu", torch.float64).numpy()


def with_estimator_prior(estimator, log_ratios: np.ndarray, profiles: np.ndarray, total_length: np.ndarray,
                         long_side: np.ndarray) -> np.ndarray:
    """``profiles`` (n, K) of the data term plus the estimator's own focal prior
    (:meth:`~fr_torch.core.likelihood.mixture.MixtureLikelihood.focal_prior`) at each grid value: the objective each
    photo's own estimate maximises.  ``total_length`` (n,) segment length W and ``long_side`` (n,)
    pixels, as the prior's weight and scale.  The prior corrects the likelihood's pull towards narrow
    views per photo; summed over a group it stays a per-photo correction (each profile is tempered
    and floored on its own)."""
    likelihood = estimator.likelihood
    if not likelihood.params.focal_prior_weight or len(profiles) == 0:
        return profiles

    long_side = torch.as_tensor(np.asarray(long_side, np.float64))
    lengths = exact_sum(torch.as_tensor(np.asarray(total_length, np.float64))[:, None], 1)  # as the search's W
    focal = long_side[:, None] * torch.as_tensor(np.exp(log_ratios))[None, :]
    prior = likelihood.focal_prior_of(lengths, long_side, focal)[0].numpy()
    return profiles + prior


def predicted_focal_pct(results) -> np.ndarray | None:
    """(n,) the reliability stage's predicted focal error (%) per result, nan where absent; None when
    no result has one."""
    values = [(r.predicted_error or {}).get("focal_pct", math.nan) for r in results]
    return None if all(not math.isfinite(v) for v in values) else np.asarray(values, np.float64)


def principal_point_scores(estimator, results, offsets: np.ndarray, settings: SharedFocalSettings) -> np.ndarray:
    """Best objective of each photo with the principal point moved from the image centre by each offset.

    Args:
        estimator: the :class:`~fr_torch.runtime.estimator.FREstimator` (likelihood, search box).
        results: n ok results holding their segments, searched at the group's focal length (their
            focal length is kept; their rotation is the start).
        offsets: (M, 2) offsets (x, y) from the image centre, fractions of the long side.
        settings: ``pp_iterations`` Adam steps of the rotation per offset.

    Returns:
        ``(scores, lengths)``: (n, M) float64 objective units (length-weighted log-likelihood plus the
        focal prior, which is the same at every offset; -inf where not finite) and (n,) each photo's
        total segment length, pixels (the temperature's scale, :func:`tempered_profiles`).
    """
    device, dtype = estimator.device, estimator.dtype
    config = estimator.search
    count, m = len(results), len(offsets)
    batch = SegmentBatch.from_list([np.asarray(r.segments, np.float64) for r in results],
                                   [(r.width, r.height) for r in results], device, dtype)
    long_side = torch.tensor([float(max(r.width, r.height)) for r in results], dtype=torch.float64)
    centre = torch.tensor([image_centre(r.width, r.height) for r in results], dtype=torch.float64)
    features = SegmentFeatures.from_batch(batch, centre.to(device=device, dtype=dtype))
    index = torch.arange(count).repeat_interleave(m)
    moved = centre[index] + torch.as_tensor(offsets, dtype=torch.float64).repeat(count, 1) * long_side[index, None]
    replicas = replace(features.take_images(index.to(device)), principal_point=moved.to(device=device, dtype=dtype))
    estimates = _search_estimates(results)[index]
    lower, upper = parameter_box(config, long_side[index], estimates[:, 3])
    starts = estimates[:, None].to(device)
    if settings.pp_iterations:
        _, scores = refine(estimator.likelihood, replicas, starts, lower.to(device), upper.to(device),
                           settings.pp_iterations, fast=True, periodic_pan=config.periodic_pan)
    else:
        scores = score_grid(estimator.likelihood, replicas, starts, config.max_chunk_elements)
    values = scores.amax(1).to(torch.float64).view(count, m).cpu().numpy()
    return np.where(np.isfinite(values), values, -np.inf), features.weight.sum(-1).to("cpu", torch.float64).numpy()


@dataclass(frozen=True)
class PrincipalPointFit:
    """The group's principal point from :func:`shared_principal_point`: ``offset`` (x, y) from the
    image centre in fractions of the long side (0, 0 where ``flat``), ``sigma`` (x, y) its 1-sigma
    uncertainty in the same units (from the fitted curvature; inf where ``flat``), ``flat``: the
    photos' summed scores have no clear maximum over the searched offsets (no maximum of the fitted
    quadratic, or a 1-sigma wider than the grid's half-width), so the image centre is kept rather
    than an offset that rounding would decide."""
    offset: tuple[float, float]
    sigma: tuple[float, float]
    flat: bool


def shared_principal_point(estimator, results, settings: SharedFocalSettings) -> PrincipalPointFit | None:
    """One principal-point offset from the image centre for a group of photos of one camera searched
    at their shared focal length (:class:`PrincipalPointFit`), or None (fewer than
    ``settings.pp_min_images`` photos, or photos of different orientations, whose sensor axes differ).

    Each photo's scores over the ``pp_offsets`` x ``pp_offsets`` grid (:func:`principal_point_scores`)
    are tempered and floored as the focal profiles are (:func:`tempered_profiles`: one photo moves
    the sum by at most ``cap``), summed, and a quadratic in (x, y) is fitted to the sum.  Its maximum,
    clipped to the grid, is the offset, and its curvature the 1-sigma (the sum is a log-likelihood:
    ``sigma^2 = diag(-H^-1)``).  Where it has no maximum, or the maximum is so flat that a 1-sigma
    exceeds half the grid, the fit is ``flat`` and the offset is (0, 0): the answer would otherwise
    move with the last bits of the scores.
    """
    if len(results) < settings.pp_min_images or len({r.width >= r.height for r in results}) > 1:
        return None
    axis = np.asarray(settings.pp_offsets, dtype=np.float64)
    grid = np.stack(np.meshgrid(axis, axis, indexing="xy"), -1).reshape(-1, 2)  # (M, 2)
    scores, lengths = principal_point_scores(estimator, results, grid, settings)
    total = tempered_profiles(scores, lengths, settings).sum(0)
    x, y = grid[:, 0], grid[:, 1]
    design = np.stack([np.ones_like(x), x, y, x * x, x * y, y * y], 1)
    c = np.linalg.lstsq(design, total, rcond=None)[0]
    hessian = np.array([[2 * c[3], c[4]], [c[4], 2 * c[5]]])
    half_width = 0.5 * (axis[-1] - axis[0])
    if np.all(np.isfinite(hessian)) and np.all(np.linalg.eigvalsh(hessian) < 0):
        sigma = np.sqrt(np.diag(np.linalg.inv(-hessian)))
        if np.all(sigma <= half_width):
            best = np.clip(np.linalg.solve(hessian, -c[1:3]), axis[0], axis[-1])
            return PrincipalPointFit((float(best[0]), float(best[1])), (float(sigma[0]), float(sigma[1])), False)
    return PrincipalPointFit((0.0, 0.0), (math.inf, math.inf), True)


def calibrate_shared(estimator, images: Sequence | None = None, *, segments: Sequence | None = None,
                     image_sizes: Sequence[tuple[int, int]] | None = None, names: Sequence[str] | None = None,
                     principal_point=None, focal_prior=None,
                     settings: SharedFocalSettings | None = None) -> SharedFocalResult:
    """Calibrate photos of one camera with one focal length (method: module docstring).

    Args:
        estimator: a :class:`~fr_torch.runtime.estimator.FREstimator`.
        images: file paths or arrays (as :meth:`FREstimator.calibrate_images`), or
        segments: one (N_i, 4) array per photo with ``image_sizes`` (width, height) pixels
            (as :meth:`FREstimator.calibrate_segments`).
        names: one name per photo.
        principal_point: None (image centre), one (x, y) for all, or one per photo (input pixels).
        focal_prior: None or a :class:`~fr_torch.runtime.focal_prior.FocalPrior` (input pixels of a photo of
            ``prior.image_size``, or the first usable photo's) added once to the combination.
        settings: :class:`SharedFocalSettings` (default: the chosen ones).

    Returns:
        :class:`SharedFocalResult`.  Photos that cannot be calibrated keep their per-photo failure.
        Raises FRInputError when the usable photos differ in aspect ratio.
    """
    settings = settings or SharedFocalSettings()
    if (images is None) == (segments is None):
        raise FRInputError("calibrate_shared: give images or segments (with image_sizes), not both")
    if images is not None:
        alone = estimator.calibrate_images(list(images), names=names, principal_point=principal_point)
    else:
        if image_sizes is None:
            raise FRInputError("calibrate_shared: segments need image_sizes")
        alone = estimator.calibrate_segments(list(segments), list(image_sizes), names=names,
                                             principal_point=principal_point)
    return shared_from_results(estimator, alone, focal_prior=focal_prior, settings=settings,
                               estimate_principal_point=principal_point is None)


def require_pinhole(distortion) -> None:
    """FRInputError (one line) unless the lens setting ``distortion``
    (:class:`~fr_torch.core.settings.distortion.DistortionSetting`) is the pinhole camera: the shared focal
    length's per-photo focal profiles are a pinhole camera's."""
    if distortion.estimates_k:
        raise FRInputError("a shared focal length (--shared-focal, --shared-focal-by) works with the pinhole model "
                           "only: leave out --distortion / --k, or calibrate each photo with them")


def shared_from_results(estimator, alone: Sequence, focal_prior=None,
                        settings: SharedFocalSettings | None = None,
                        estimate_principal_point: bool = True) -> SharedFocalResult:
    """Steps 2-4 of the method on per-photo results ``alone`` (each holding its segments, in the
    pixels of its photo); see :func:`calibrate_shared`.  ``estimate_principal_point`` False keeps
    each result's principal point (the caller gave it, or wants the image centre) whatever
    ``settings.principal_point`` says."""
    require_pinhole(estimator.search.distortion)
    settings = settings or SharedFocalSettings()
    if not estimate_principal_point:
        settings = replace(settings, principal_point=False)
    usable = [i for i, r in enumerate(alone) if r.ok and r.segments is not None and len(r.segments)
              and r.rotation is not None and r.focal_px is not None]
    prior_json = focal_prior.to_json() if focal_prior is not None else None
    if not usable:
        return SharedFocalResult(None, None, None, len(alone), 0, False,
                                 "no photo of the group could be calibrated (see each photo's reason)",
                                 list(alone), prior_json)
    kept = [alone[i] for i in usable]
    check_group_sizes([(r.width, r.height) for r in kept], [r.image for r in kept])
    log_ratios, combined, again = _at_shared_focal(estimator, kept, None, focal_prior, settings)
    principal_point, pp_sigma = None, None
    if settings.principal_point and all(r.ok for r in again):
        fit = shared_principal_point(estimator, again, settings)
        if fit is not None:
            long_side = max(kept[0].width, kept[0].height)
            pp_sigma = (fit.sigma[0] * long_side, fit.sigma[1] * long_side)
            if not fit.flat:
                points = [tuple(c + o * max(r.width, r.height) for c, o in zip(image_centre(r.width, r.height),
                                                                                 fit.offset)) for r in kept]
                log_ratios, combined, again = _at_shared_focal(estimator, kept, points, focal_prior, settings)
                principal_point = points[0]
            else:
                principal_point = image_centre(kept[0].width, kept[0].height)
    ratio = math.exp(combined.log_ratio)
    results = list(alone)
    at_edge = at_range_edge(log_ratios, combined.log_ratio)
    for i, result in zip(usable, again):
        _mark_focal(result, combined.predicted_error_pct, at_edge)
        results[i] = result
    return SharedFocalResult(ratio * max(kept[0].width, kept[0].height), ratio, combined.predicted_error_pct,
                             len(alone), int(combined.used.sum()), True, "", results, prior_json, principal_point,
                             pp_sigma)


def _at_shared_focal(estimator, kept: Sequence, principal_points: Sequence | None, focal_prior,
                     settings: SharedFocalSettings):
    """Steps 2-4 for the usable results ``kept`` at ``principal_points`` (one (x, y) per photo, or
    None: each result's own): (log-ratio grid, :class:`CombinedFocal`, the photos searched again at
    the shared focal length)."""
    log_ratios, profiles, lengths = profile_results(estimator, kept, settings, principal_points)
    profiles = with_estimator_prior(estimator, log_ratios, profiles, lengths, [max(r.width, r.height) for r in kept])
    prior = focal_prior.log_ratio_prior(kept[0].width, kept[0].height) if focal_prior is not None else None
    combined = combine_profiles(log_ratios, profiles, lengths, predicted_focal_pct(kept), settings, prior)
    ratio = math.exp(combined.log_ratio)
    points = principal_points if principal_points is not None else [tuple(r.principal_point) for r in kept]
    again = estimator.calibrate_segments([np.asarray(r.segments, np.float64) for r in kept],
                                         [(r.width, r.height) for r in kept], names=[r.image for r in kept],
                                         focal_px=[ratio * max(r.width, r.height) for r in kept],
                                         principal_point=[tuple(p) for p in points], apply_filter=False)
    return log_ratios, combined, again


def apply_focal_priors(estimator, alone: Sequence, priors: Sequence, settings: SharedFocalSettings | None = None
                       ) -> list:
    """Each photo alone with a soft focal prior: results of ``alone`` (per-photo results holding their
    segments) where ``priors[i]`` (a :class:`~fr_torch.runtime.focal_prior.FocalPrior` in photo i's pixels, or
    None) is set are replaced by the photo searched again at the maximum of its tempered focal
    log-likelihood plus the prior (a group of one, :func:`combine_profiles`); the others are returned
    as they are.  Returns a new list, input order."""
    settings = settings or SharedFocalSettings()
    results = list(alone)
    todo = [i for i, (r, p) in enumerate(zip(alone, priors)) if p is not None and r.ok and r.segments is not None
            and len(r.segments) and r.rotation is not None and r.focal_px is not None]
    if not todo:
        return results
    kept = [alone[i] for i in todo]
    log_ratios, profiles, lengths = profile_results(estimator, kept, settings)
    profiles = with_estimator_prior(estimator, log_ratios, profiles, lengths, [max(r.width, r.height) for r in kept])
    errors = predicted_focal_pct(kept)
    focal, errors_out, edges = [], [], []
    for j, (r, i) in enumerate(zip(kept, todo)):
        combined = combine_profiles(log_ratios, profiles[j:j + 1], lengths[j:j + 1],
                                    None if errors is None else errors[j:j + 1], settings,
                                    priors[i].log_ratio_prior(r.width, r.height))
        focal.append(math.exp(combined.log_ratio) * max(r.width, r.height))
        errors_out.append(combined.predicted_error_pct)
        edges.append(at_range_edge(log_ratios, combined.log_ratio))
    again = estimator.calibrate_segments([np.asarray(r.segments, np.float64) for r in kept],
                                         [(r.width, r.height) for r in kept], names=[r.image for r in kept],
                                         focal_px=focal, principal_point=[tuple(r.principal_point) for r in kept],
                                         apply_filter=False)
    for i, result, error, at_edge in zip(todo, again, errors_out, edges):
        _mark_focal(result, error, at_edge)
        results[i] = result
    return results
