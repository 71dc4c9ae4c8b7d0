"""Stage 2 of the search: Adam inside the box, the one refinement loop every fit uses.

Parameters are stepped as u in the unit box (:class:`UnitBox`: ``u = (p' - lower') / (upper' -
lower')``, the focal length as log f, a degenerate side fixed), projected back after every step,
pan wrapped around its 90-degree box where it is periodic (:func:`adam_in_box`).  :class:`Adam`
is written in single torch operations (the same bits on every kernel set), :class:`Patience` is the
per-image stopping rule.  The Manhattan and lens fits refine the mixture likelihood
(:func:`refine`: the analytic gradient of measure b through :func:`objective_and_grad`, which
reaches the parameters by the chain rule from the vanishing points (:func:`chain_to_params`);
autograd otherwise).

Images are refined in independent slices of at most ``max_chunk_elements`` (``CPU_REFINE_ELEMENTS``
on a CPU) deviations per step, and each hypothesis' update depends only on its own gradient: a
batch gives the same answer as images one by one.  On a CPU where the fused kernels build, the
Manhattan refinement and the division model's (with k) without a stopping rule run all their steps
in one kernel call (:func:`refine_fused`, :func:`fr_torch.core.likelihood.native.measure_b_refine`):
the loop below, bit for bit, checked against it once per process (:func:`refine_kernel_matches_torch`,
with and without k).  Each mode runs its ``refine_iterations`` (fR 100 with a decaying step size,
Fast-fR 10; :data:`fr_torch.core.settings.config.MODE_PRESETS`).
"""
from __future__ import annotations

import math

import torch

from fr_torch.core.exact import dot3, exact_sum, small_matmul, small_sum
from fr_torch.core.geometry.conventions import VERTICAL_AXIS, rotation_from_cos_sin
from fr_torch.core.geometry.params import ANGLES, DISTORTION, FOCAL, PAN, from_log_focal, rotations, to_log_focal
from fr_torch.core.likelihood.measures import SegmentFeatures
from fr_torch.core.likelihood import native
from fr_torch.core.likelihood.mixture import LikelihoodParams, MixtureLikelihood
from fr_torch.core.likelihood.objective import (
    native_ok,
    measure_b_backward,
    measure_b_forward,
    measure_b_objective_and_grad,
    vp_major,
)
from fr_torch.core.search.passes import best_of_start_and_refined, tie_tolerance
from fr_torch.core.settings.config import SearchConfig
from fr_torch.core import exact_math

CPU_REFINE_ELEMENTS = 1 << 20  # deviations per refinement slice on CPU (~25 live tensors of 4 MB)


def refine(likelihood: MixtureLikelihood, features: SegmentFeatures, starts: torch.Tensor,
           lower: torch.Tensor, upper: torch.Tensor, iterations: int, fast: bool,
           max_chunk_elements: int = 1 << 24, tolerance: float = 0.0,
           patience: int = 10, periodic_pan: bool = False,
           geometry=None) -> tuple[torch.Tensor, torch.Tensor]:
    """Refine starts (B, L, 4) inside the box [lower, upper] (B, 4).  Returns (params, objective).

    With ``geometry`` (:class:`~fr_torch.core.search.lens.SegmentGeometry`, the segments of the same
    images) the rows have a fifth parameter, the division model's k (:data:`~fr_torch.core.geometry.params.DISTORTION`):
    starts (B, L, 5) inside a box (B, 5) or, per start, (B, L, 5); every hypothesis is scored on its
    segments undistorted with its own k, and k is refined with the others (``features`` then gives
    the segments' weights, the normalising length and the chunking, not the scores).

    Parameters are optimised as u = (p - lower) / (upper - lower) in [0, 1] (a degenerate box,
    e.g. a known focal length, keeps that parameter fixed); with ``periodic_pan``
    (:attr:`SearchConfig.periodic_pan`) pan wraps around its 90-degree box instead of stopping at
    its edge.  The loss of every hypothesis is its
    negative log-likelihood divided by the image's total segment length, so step sizes do not
    depend on how many segments an image has.  Images are refined in independent slices of at
    most ``max_chunk_elements`` deviations (bounded memory; same result as one big batch).

    Stopping rule (``tolerance > 0``, not in fast mode): an image stops (its parameters stay put)
    once none of its hypotheses changed its normalised objective by more than ``tolerance`` over
    the last ``patience`` steps; the loop ends when every image has stopped.  Each image's answer
    is its own, whatever else is in the batch.  Guards: the
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
                               lower[b:b + step], upper[b:b + step], iterations, fast, tol, patience, periodic_pan,
                               None if geometry is None else geometry.images(b, b + step))
                 for b in range(0, batch, step)]
        return torch.cat([p for p, _ in parts]), torch.cat([o for _, o in parts])
    return _refine_slice(likelihood, features, starts, lower, upper, iterations, fast, tol, patience, periodic_pan,
                         geometry)


def refine_starts(likelihood: MixtureLikelihood, features: SegmentFeatures, starts: torch.Tensor,
                  start_scores: torch.Tensor, lower: torch.Tensor, upper: torch.Tensor, config: SearchConfig,
                  iterations: int, fast: bool, geometry=None) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Stage 2 of a fit: :func:`refine` the starts (B, L, P) with objectives ``start_scores`` (B, L)
    inside the box under ``config``'s stopping rule and pan period, then keep each image's best of
    the starts and their refinements
    (:func:`~fr_torch.core.search.passes.best_of_start_and_refined`).  Returns (params (B, P),
    scores (B,), tied (B,) bool)."""
    refined, refined_scores = refine(likelihood, features, starts, lower, upper, iterations, fast=fast,
                                     tolerance=config.refine_tolerance, patience=config.refine_patience,
                                     periodic_pan=config.periodic_pan, geometry=geometry)
    return best_of_start_and_refined(starts, start_scores, refined, refined_scores,
                                     tie_tolerance(features if geometry is None else geometry))


#: Bound on each gradient component of the normalised loss in box units (real ones stay below ~1e4).
_GRAD_BOUND = 1e6


class Adam:
    """Adam (Kingma & Ba; torch.optim's update: ``p -= lr / (1 - b1^t) * m / (sqrt(v) / sqrt(1 - b2^t)
    + eps)``) on one tensor, its per-step scalars from ``schedule`` (:func:`adam_schedule`).

    Written in single torch operations, each rounded once: the update is the same bits on every
    kernel set and device (torch's fused Adam kernel takes fused multiply-adds on some and not on
    others, :mod:`fr_torch.core.exact`), and building no ``torch.optim`` object spares a process
    the 1-2 s import of ``torch._dynamo`` that its constructor triggers.
    """

    EPS = 1e-8  # added to the denominator

    def __init__(self, param: torch.Tensor, schedule: list[tuple[float, float]], betas: tuple[float, float],
                 eps: float = EPS):
        self.param, self.schedule, self.betas, self.eps = param, schedule, betas, eps
        self.exp_avg = torch.zeros_like(param)
        self.exp_avg_sq = torch.zeros_like(param)
        self.step_count = 0

    def step(self, grad: torch.Tensor, active: torch.Tensor | None = None) -> None:
        """One Adam update of the parameter (in place) with gradient ``grad`` (same shape), with
        the schedule's next scalars.  ``active``: broadcastable bool mask; entries outside it
        keep their parameter and moments (converged images)."""
        beta1, beta2 = self.betas
        bias, step_size = self.schedule[self.step_count]
        self.step_count += 1
        with torch.no_grad():
            exp_avg = self.exp_avg * beta1 + grad * (1.0 - beta1)
            exp_avg_sq = self.exp_avg_sq * beta2 + (grad * grad) * (1.0 - beta2)
            denom = exact_math.sqrt(exp_avg_sq) / bias + self.eps
            update = exp_avg / denom * step_size
            if active is None:
                self.exp_avg, self.exp_avg_sq = exp_avg, exp_avg_sq
                self.param.sub_(update)
            else:
                self.exp_avg = torch.where(active, exp_avg, self.exp_avg)
                self.exp_avg_sq = torch.where(active, exp_avg_sq, self.exp_avg_sq)
                self.param.sub_(torch.where(active, update, torch.zeros_like(update)))


def adam_schedule(lr0: float, lr_final: float, iterations: int,
                  betas: tuple[float, float]) -> list[tuple[float, float]]:
    """Adam's two scalars at each of ``iterations`` steps whose step size decays geometrically from
    ``lr0`` at the first to ``lr_final`` at the last: ``sqrt(1 - beta2^t)`` (the second moment's
    bias correction) and ``lr_t / (1 - beta1^t)``, t from 1 (the torch loop's :class:`Adam` and the
    fused kernel's, :func:`refine_fused`)."""
    beta1, beta2 = betas
    decay = (lr_final / lr0) ** (1.0 / max(1, iterations - 1))
    schedule, lr = [], lr0
    for step_count in range(1, iterations + 1):
        schedule.append((math.sqrt(1.0 - beta2 ** step_count), lr / (1.0 - beta1 ** step_count)))
        lr = lr * decay
    return schedule


#: Adam's moment decays in the refinement (:func:`adam_in_box`).
BETAS = (0.5, 0.9)


class UnitBox:
    """Parameter rows mapped into the unit box the refinement steps in: ``u = (p' - lower') /
    (upper' - lower')`` in [0, 1], where ``'`` replaces the focal length by its log
    (:func:`~fr_torch.core.geometry.params.to_log_focal`: a step is the same relative change of f,
    and about the same change of FOV, at every zoom, as the log-spaced grid).

    ``lower``, ``upper``: the box, broadcastable to the rows (e.g. (B, 1, P) for rows (B, L, P)),
    in the rows' dtype and device.  A degenerate side (a known focal length) has ``free`` False:
    that parameter stays where it is.
    """

    def __init__(self, lower: torch.Tensor, upper: torch.Tensor):
        self.lower, upper = to_log_focal(lower), to_log_focal(upper)
        self.span = upper - self.lower
        self.free = self.span > 0
        self.span_safe = torch.where(self.free, self.span, torch.ones_like(self.span))

    def to_unit(self, params: torch.Tensor) -> torch.Tensor:
        """u of rows ``params``, clamped into [0, 1]."""
        return ((to_log_focal(params) - self.lower) / self.span_safe).clamp(0, 1)

    def to_params(self, u: torch.Tensor) -> torch.Tensor:
        """The rows at ``u`` (the inverse of :meth:`to_unit` inside the box)."""
        return from_log_focal(self.lower + u * self.span)


class Patience:
    """The refinement's stopping rule: an image stops (its parameters stay put) once none of its
    hypotheses changed its normalised objective (objective / ``total_length``, (B, 1)) by more than
    ``tolerance`` over the last ``patience`` steps.  Each image decides alone, so a batch cannot
    change its answer."""

    def __init__(self, tolerance: float, patience: int, total_length: torch.Tensor):
        self.tolerance, self.patience, self.total_length = tolerance, patience, total_length
        self.history: list[torch.Tensor] = []
        self.active: torch.Tensor | None = None  # (B, 1, 1) images still refined; None = all
        self.done = False

    def update(self, objective: torch.Tensor) -> None:
        """Record one step's objectives (B, L); :attr:`active` and :attr:`done` follow them."""
        self.history.append(objective.detach() / self.total_length)
        if len(self.history) > self.patience:
            old = self.history.pop(0)
            change = (self.history[-1] - old).abs()
            moving = ((change > self.tolerance) & torch.isfinite(change)).any(1)  # (B,)
            self.active = moving[:, None, None] if self.active is None else self.active & moving[:, None, None]
            self.done = not bool(self.active.any())


def adam_in_box(u: torch.Tensor, box: UnitBox, iterations: int, lr0: float, lr_final: float, gradient,
                periodic_pan: bool, grad_bound: float | None = None, stop: Patience | None = None) -> None:
    """The refinement loop every fit shares: ``iterations`` Adam steps (:class:`Adam`, betas (0.5,
    0.9), step size decaying geometrically from ``lr0`` to ``lr_final``, box units) on ``u``
    (B, L, P) in place, each projected back into the unit box (pan wrapped around it with
    ``periodic_pan``: u's pan is (pan - lower) / 90 deg).

    ``gradient(u)`` -> (objective (B, L) or None, d loss / d u (B, L, P)): the fit's objective and
    the gradient of its loss in box units.  The gradient is zeroed on the box's fixed sides, made
    finite (NaN, inf -> 0) and, with ``grad_bound``, clamped to +-``grad_bound``: no step makes a
    parameter non-finite.  ``stop``: the stopping rule (it reads the objectives), None = every step.
    """
    optimiser = Adam(u, adam_schedule(lr0, lr_final, iterations, BETAS), BETAS)
    all_free = bool(box.free.all())
    for _ in range(iterations):
        objective, grad = gradient(u)
        grad = grad.to(u.dtype)
        if not all_free:
            grad = torch.where(box.free, grad, torch.zeros_like(grad))
        grad = torch.nan_to_num(grad, nan=0.0, posinf=0.0, neginf=0.0)
        if grad_bound is not None:
            grad = grad.clamp_(-grad_bound, grad_bound)
        optimiser.step(grad, None if stop is None else stop.active)
        with torch.no_grad():
            if periodic_pan:
                u[..., PAN] = torch.remainder(u[..., PAN], 1.0)
            u.clamp_(0.0, 1.0)
        if stop is not None:
            stop.update(objective)
            if stop.done:
                break


def _refine_slice(likelihood, features, starts, lower, upper, iterations, fast, tolerance=0.0, patience=10,
                  periodic_pan=False, geometry=None, fused=True):
    dtype, device = features.weight.dtype, features.weight.device
    if lower.dim() == 2:  # one box per image
        lower, upper = lower[:, None, :], upper[:, None, :]
    box = UnitBox(lower.to(device=device, dtype=dtype), upper.to(device=device, dtype=dtype))
    u = box.to_unit(starts.to(device=device, dtype=dtype)).detach().requires_grad_(True)
    total_length = features.total_length().clamp_min(1e-9)[:, None]  # (B, 1) float64

    def evaluate(u_value):
        params = box.to_params(u_value)
        if geometry is not None:  # one virtual image per hypothesis, its segments undistorted with its k
            batch, n_hyp = params.shape[:2]
            virtual = geometry.features(params[..., DISTORTION])
            flat = params[..., :DISTORTION].reshape(batch * n_hyp, 1, DISTORTION)
            value = likelihood.objective(virtual, rotations(flat), flat[..., FOCAL]).view(batch, n_hyp)
            return params, value + geometry.k_log_prior(params[..., DISTORTION])[0]
        rotation = rotations(params)
        return params, likelihood.objective(features, rotation, params[..., FOCAL])

    analytic = likelihood.fast_path(features)
    grad_out = (-1.0 / total_length).to(dtype)

    def gradient(u_value):
        u_value.grad = None
        if analytic:  # the same gradient in closed form, no autograd graph (see objective_and_grad)
            return objective_and_grad(likelihood, features, box.lower, box.span, u_value.detach(), grad_out, geometry)
        _, objective = evaluate(u_value)
        finite = torch.where(torch.isfinite(objective), objective, torch.zeros_like(objective))
        loss = -(finite / total_length).sum()
        loss.backward()
        return objective, u_value.grad

    # Step sizes in box units: about a quarter of a grid cell at first, decaying geometrically.
    cell = 1.0 / 8
    lr0, lr_final = 0.25 * cell, (0.02 if fast else 0.002) * cell
    if fused and analytic and tolerance <= 0 and lower.shape[1] == 1 and fused_refine_ok(features, geometry):
        refine_fused(likelihood, features, u, box, grad_out, iterations, lr0, lr_final, periodic_pan, geometry)
    else:
        adam_in_box(u, box, iterations, lr0, lr_final, gradient, periodic_pan, grad_bound=_GRAD_BOUND,
                    stop=Patience(tolerance, patience, total_length) if tolerance > 0 else None)
    with torch.no_grad():
        params, objective = evaluate(u)
        objective = torch.where(torch.isfinite(objective), objective, torch.full_like(objective, -math.inf))
    return params.detach(), objective.detach()


def fused_refine_ok(features: SegmentFeatures, geometry=None) -> bool:
    """Whether the refinement of these segments runs as one kernel call (:func:`refine_fused`):
    float32 segments on a CPU where the fused kernels and the refinement loop's check pass (with
    ``geometry``, the division model's: float32 endpoints, the ``"refine_lens"`` check)."""
    if geometry is None:
        return native_ok(features.weight) and native.available("refine")
    return native_ok(geometry.endpoints) and native_ok(features.weight) and native.available("refine_lens")


def refine_fused(likelihood: MixtureLikelihood, features: SegmentFeatures, u: torch.Tensor, box: UnitBox,
                 grad_out: torch.Tensor, iterations: int, lr0: float, lr_final: float, periodic_pan: bool,
                 geometry=None) -> None:
    """:func:`adam_in_box` over :func:`objective_and_grad` (measure b, no stopping rule) as one call
    of the fused kernel (:func:`fr_torch.core.likelihood.native.measure_b_refine`): the same steps
    bit for bit, without a torch operator per step.

    ``u`` (B, L, P) float32 box units, stepped in place; ``box`` with sides (B, 1, P);
    ``grad_out`` (B, 1) the loss's weight of each image's objective.  With ``geometry``
    (:class:`~fr_torch.core.search.lens.SegmentGeometry`, P = 5) the kernel undistorts every
    hypothesis' segments with its k from the geometry's endpoint offsets, and the weights, the focal
    prior's constants and the distortion centre are those of the virtual images
    :meth:`~fr_torch.core.search.lens.SegmentGeometry.features` gives at any k."""
    batch, params = u.shape[0], u.shape[2]
    lens = None
    if geometry is not None:
        features = geometry.features(torch.zeros(batch, 1, dtype=u.dtype))  # the k-independent fields
        _, offset, rho = geometry.offsets()
        slope = geometry.k_prior_slope(u) if geometry.k_prior_weight else None
        lens = (offset.reshape(batch, -1, 2), rho.reshape(batch, -1), slope)
    neg_inv_scale, log_coef, background, floor, _ = likelihood._b_constants(features.weight)
    prior = None
    if likelihood.params.focal_prior_weight:  # MixtureLikelihood.focal_prior's curvature and scale
        prior = torch.stack([likelihood.focal_prior_curvature_for(features), features.long_side.to(u.dtype)], 1)
    steps = adam_schedule(lr0, lr_final, iterations, BETAS)
    data = u.detach()
    if not data.is_contiguous():
        raise ValueError("refine_fused: u must be contiguous")
    native.measure_b_refine(data, features.line_along, features.weight, neg_inv_scale, log_coef, background, floor,
                            VERTICAL_AXIS, grad_out, features.principal_point, box.lower.reshape(batch, params),
                            box.span.reshape(batch, params), prior, likelihood._prior_centre,
                            likelihood.params.focal_prior_flat_halfwidth,
                            torch.tensor(steps, dtype=torch.float64).reshape(-1, 2), BETAS, Adam.EPS, _GRAD_BOUND,
                            periodic_pan, lens)


def refine_kernel_matches_torch(geometry_from=None) -> bool:
    """The fused refinement (:func:`refine_fused`) against the torch loop on random scenes: two
    images, one with a known focal length, under the focal prior with its flat band and a periodic
    pan; and one image without the prior.  With ``geometry_from``
    (:meth:`fr_torch.core.search.lens.SegmentGeometry.from_features`, which that module registers as
    the ``"refine_lens"`` check) the division model's refinement: rows with k, the segments
    undistorted with each hypothesis' k, the prior on k in the first case.  True when every refined
    parameter has the same bits (a few hundredths of a second, once per process)."""
    generator = torch.Generator().manual_seed(66)
    cases = ((LikelihoodParams(focal_prior_weight=0.3, focal_prior_flat_halfwidth=0.2), 2, 40, 24, True, False),
             (LikelihoodParams(), 1, 30, 16, False, True))
    for params, batch, n_seg, n_start, periodic, fast in cases:
        likelihood = MixtureLikelihood(params)
        size = torch.tensor([[640.0, 480.0]]).expand(batch, 2)
        endpoints = torch.rand(batch, n_seg, 4, generator=generator) * size.repeat(1, 2)[:, None]
        features = SegmentFeatures.from_endpoints(endpoints, torch.ones(batch, n_seg, dtype=torch.bool),
                                                  torch.tensor([[319.5, 239.5]]).expand(batch, 2))
        lower = torch.tensor([[0.0, -40.0, -20.0, 200.0, -0.6]]).repeat(batch, 1)
        upper = torch.tensor([[90.0, 40.0, 20.0, 2000.0, 0.2]]).repeat(batch, 1)
        if batch > 1:  # the second image's focal length is known: a degenerate side
            upper[1, FOCAL] = lower[1, FOCAL] = 500.0
        geometry = None
        if geometry_from is not None:  # the prior on k in the first case
            geometry = geometry_from(features, endpoints, size, 3.0 if params.focal_prior_weight else 0.0)
        else:
            lower, upper = lower[:, :DISTORTION], upper[:, :DISTORTION]
        offsets = torch.rand(batch, n_start, lower.shape[1], generator=generator)
        starts = lower[:, None] + offsets * (upper - lower)[:, None]
        results = [_refine_slice(likelihood, features, starts, lower, upper, 8, fast, periodic_pan=periodic,
                                 geometry=geometry, fused=fused) for fused in (False, True)]
        for expected, got in zip(*results):
            if not torch.equal(expected.contiguous().view(torch.uint8), got.contiguous().view(torch.uint8)):
                return False
    return True


native.register_check(refine_kernel_matches_torch, "refine")


def objective_and_grad(likelihood: MixtureLikelihood, features: SegmentFeatures, lower: torch.Tensor,
                       span: torch.Tensor, u: torch.Tensor, grad_out: torch.Tensor,
                       geometry=None):
    """Measure-b objective (B, L) at ``params = lower + u * span`` and the gradient of
    ``sum(grad_out * objective)`` with respect to u (B, L, 4), without autograd.

    With ``geometry`` the rows have a fifth parameter, k: each hypothesis is scored on its images'
    segments undistorted with its k (:meth:`~fr_torch.core.search.lens.SegmentGeometry.features`, one
    virtual image per hypothesis), and d obj / dk = sum_i (d obj / d line_along_i) . (d line_along_i / dk)
    (:func:`fr_torch.core.likelihood.objective.measure_b_backward` with the VPs); u is then (B, L, 5).

    ``params`` = [pan, pitch, roll (degrees), log f (f in pixels)], the refinement's coordinates.

    ``lower``, ``span``: (B, 1, 4); ``grad_out``: broadcastable to (B, L).  The chain is written
    out: G = d obj / d V for the VPs V = K R from :func:`fr_torch.core.likelihood.objective.measure_b_backward`;
    ``dV/df = [R_0; R_1; 0]``; and for the angles, with ``R.T = Ry(pan) Rx(pitch) Rz(roll)``
    (:func:`fr_torch.core.geometry.params.rotations`), ``dR/d angle = -R [w]_x`` for the axis ``w`` = e_y (pan),
    ``Ry(pan) e_x`` (pitch) and ``R.T e_z`` (roll), so ``d obj / d angle = -w . axial(V.T G)``
    (``<G, K dR> = <K.T G, -R [w]_x> = -<R.T K.T G, [w]_x>``; axial(M) = (M21 - M12, M02 - M20,
    M10 - M01)).  Equal to the autograd gradient of the same objective to rounding (tests); used
    by the refinement, where autograd's per-step overhead dominated at small batches.
    """
    params = lower + u * span
    batch, n_hyp = params.shape[:2]
    rad = torch.deg2rad(params[..., ANGLES])
    sin, cos = exact_math.sin_cos(rad)
    rotation = rotation_from_cos_sin(cos, sin)  # (B, L, 3, 3)
    focal = exact_math.exp(params[..., FOCAL])
    if geometry is not None:
        features, d_line_along = geometry.features(params[..., DISTORTION], derivative=True)  # B * L images
    pp = features.principal_point[:, None, :]  # (B, 1, 2)
    if geometry is not None:
        pp = pp.view(batch, n_hyp, 2)
    vps = camera_vps(rotation, focal, pp)  # (B, L, 3, 3)
    constants = likelihood._b_constants(features.weight)
    if geometry is None:
        objective, grad_flat = measure_b_objective_and_grad(features.line_along, features.weight, vp_major(vps),
                                                            constants, grad_out)
        grad_v = grad_flat.view(batch, 3, 3, n_hyp).permute(0, 3, 1, 2)  # (B, L, coord, VP)
    else:
        flat = vp_major(vps.reshape(batch * n_hyp, 1, 3, 3))  # (B * L, 3, 3): one hypothesis per virtual image
        objective, saved = measure_b_forward(features.line_along, features.weight, flat, *constants)
        objective = objective.view(batch, n_hyp)
        grad_flat, grad_line_along = measure_b_backward(saved, grad_out.expand(batch, n_hyp).reshape(-1, 1).contiguous(),
                                                        flat)
        grad_v = grad_flat.view(batch, n_hyp, 3, 3)  # (B, L, coord, VP)
        grad_k = exact_sum(small_sum(grad_line_along * d_line_along, -1), 1).view(batch, n_hyp)
        if geometry.k_prior_weight:  # the prior on k (SegmentGeometry.k_log_prior)
            k_prior, d_k_prior = geometry.k_log_prior(params[..., DISTORTION])
            objective = objective + k_prior
            grad_k = grad_k + grad_out * d_k_prior
    focal_prior_grad = None
    if likelihood.params.focal_prior_weight:  # the focal prior of MixtureLikelihood.objective
        if geometry is None:
            prior, d_prior = likelihood.focal_prior(features, focal)
        else:
            prior, d_prior = (x.view(batch, n_hyp) for x in likelihood.focal_prior(features, focal.reshape(-1, 1)))
        objective = objective + prior
        focal_prior_grad = grad_out * d_prior
    grad_p = chain_to_params(vps, rotation, cos, sin, focal, grad_v, focal_prior_grad)
    if geometry is not None:
        grad_p = torch.cat([grad_p, grad_k[..., None]], -1)
    return objective, grad_p * span




def camera_vps(rotation: torch.Tensor, focal: torch.Tensor, principal_point: torch.Tensor) -> torch.Tensor:
    """The vanishing points ``V = K R`` (..., 3, 3) (rows x, y, w in pixels; column j the VP of
    world axis j) of rotations (..., 3, 3), focal lengths (...) and principal points broadcastable
    to (..., 2), pixels: rows 0, 1 = ``f R_j + c R_2``, row 2 = ``R_2``, each product rounded once."""
    top = focal[..., None, None] * rotation[..., :2, :] + principal_point[..., None] * rotation[..., 2:, :]
    return torch.cat([top, rotation[..., 2:, :]], -2)


def chain_to_params(vps: torch.Tensor, rotation: torch.Tensor, cos: torch.Tensor, sin: torch.Tensor,
                    focal: torch.Tensor, grad_v: torch.Tensor, grad_f_extra: torch.Tensor | None = None) -> torch.Tensor:
    """The gradient (..., 4) with respect to [pan, pitch, roll (per degree), log f] of a function of
    the vanishing points ``V = K R`` whose gradient with respect to V is ``grad_v`` (..., coord, VP).

    ``vps`` (..., 3, 3) = K R (rows x, y, w; columns the VPs), ``rotation`` (..., 3, 3) world->camera
    with ``R.T = Ry(pan) Rx(pitch) Rz(roll)`` (:func:`fr_torch.core.geometry.params.rotations`), ``cos`` /
    ``sin`` (..., 3) of the angles, ``focal`` (...) pixels; ``grad_f_extra`` (...) is added to the
    derivative with respect to f (a prior on f).  ``dV/df = [R_0; R_1; 0]`` and
    ``dR/d angle = -R [w]_x`` for the axis ``w`` = e_y (pan), ``Ry(pan) e_x`` (pitch) and ``R.T e_z``
    (roll), so ``d / d angle = -w . axial(V.T G)`` (axial(M) = (M21 - M12, M02 - M20, M10 - M01));
    every product written out (:mod:`fr_torch.core.exact`)."""
    grad_v = grad_v.to(rotation.dtype)
    grad_f = small_sum(small_sum(grad_v[..., :2, :] * rotation[..., :2, :], -1), -1)
    if grad_f_extra is not None:
        grad_f = grad_f + grad_f_extra
    m = small_matmul(vps.transpose(-1, -2), grad_v)  # R.T K.T G (..., 3, 3)
    anti = m - m.transpose(-1, -2)
    axial = torch.stack([anti[..., 2, 1], anti[..., 0, 2], anti[..., 1, 0]], -1)  # (..., 3)
    grad_pitch = cos[..., 0] * axial[..., 0] - sin[..., 0] * axial[..., 2]  # w = Ry e_x = (cos pan, 0, -sin pan)
    grad_roll = dot3(rotation[..., 2, :], axial)  # w = R.T e_z = row 2 of R
    grad_angles = torch.stack([axial[..., 1], grad_pitch, grad_roll], -1) * (-math.pi / 180)  # per degree
    return torch.cat([grad_angles, (grad_f * focal)[..., None]], -1)  # d/d log f = f d/df
