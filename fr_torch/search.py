"""Two-stage search for (f, R): a k^4 grid, then batched refinement of the best l grid points.

Stage 1 scores every grid hypothesis (pan x pitch x roll x focal, k values each, cell centres
of the ranges; focal spaced linearly in f between f(hfov_max) and f(hfov_min)) as one batched
tensor computation, chunked so that at most ``max_chunk_elements`` per-segment deviations exist at
once.  Stage 2 refines the top ``top_l`` grid points of every image together with ``torch.optim``
(Adam on box-normalised parameters, projected back into the box after every step), focal length
included (the MATLAB release pins f to its grid value; we refine it continuously, as the paper
does).  ``fr`` mode runs ``refine_iterations_fr`` steps with a decaying step size, ``fast`` mode
``refine_iterations_fast`` (10).  Each hypothesis' update depends only on its own gradient, so a
batch gives the same answer as images one by one.

Speed and memory (same math; see also :mod:`fr_torch.likelihood`):

* Grid: on CPU the hypotheses are scored in cache-sized chunks (``CPU_CHUNK_ELEMENTS`` deviations
  per intra-op thread, about 1 MB per buffer and thread) that reuse the same buffers, instead of ``max_chunk_elements`` (which
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
from dataclasses import dataclass, replace
from pathlib import Path

import torch

from .camera import focal_from_hfov, rotation_from_angles
from .likelihood import CONFIG_DIR, MixtureLikelihood, SegmentFeatures, measure_b_backward, measure_b_forward, vp_major

PARAMS = ("pan_deg", "pitch_deg", "roll_deg", "focal_px")
CPU_CHUNK_ELEMENTS = 1 << 17  # per-chunk deviations on CPU: two float32 buffers of ~0.5 MB stay in cache
CPU_REFINE_ELEMENTS = 1 << 20  # deviations per refinement slice on CPU (~25 live tensors of 4 MB)


@dataclass(frozen=True)
class SearchConfig:
    """Search settings (angles in degrees).  Defaults are the paper's; see ``configs/search.json``."""

    grid_points_per_dim: int = 8
    pan_range_deg: tuple[float, float] = (-45.0, 45.0)
    pitch_range_deg: tuple[float, float] = (-35.0, 35.0)
    roll_range_deg: tuple[float, float] = (-15.0, 15.0)
    hfov_range_deg: tuple[float, float] = (50.0, 130.0)
    top_l: int = 4
    refine_iterations_fr: int = 100
    refine_iterations_fast: int = 10
    max_chunk_elements: int = 1 << 24

    def __post_init__(self):
        low, high = self.hfov_range_deg
        if not 0 < low < high < 180:
            raise ValueError(f"horizontal FOV search range must satisfy 0 < min < max < 180 deg, got {low}, {high}")
        for key in ("pan_range_deg", "pitch_range_deg", "roll_range_deg"):
            low, high = getattr(self, key)
            if not low <= high:
                raise ValueError(f"{key} must be (min, max) with min <= max, got {low}, {high}")
        if self.grid_points_per_dim < 1 or self.top_l < 1:
            raise ValueError("grid_points_per_dim and top_l must be at least 1")

    @classmethod
    def from_config(cls, path: str | Path | None = None, **overrides) -> "SearchConfig":
        path = Path(path) if path is not None else CONFIG_DIR / "search.json"
        values = json.loads(path.read_text()) if path.exists() else {}
        values = {k: tuple(v) if isinstance(v, list) else v for k, v in values.items()}
        return replace(cls(**values), **overrides)

    def iterations(self, mode: str) -> int:
        if mode not in ("fr", "fast"):
            raise ValueError(f"mode must be 'fr' or 'fast', got {mode!r}")
        return self.refine_iterations_fr if mode == "fr" else self.refine_iterations_fast


def _cell_centres(low: float, high: float, k: int) -> torch.Tensor:
    return low + (torch.arange(k, dtype=torch.float64) + 0.5) * (high - low) / k


def focal_bounds(config: SearchConfig, width: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(f_min, f_max) in pixels for each image width (B,): f(hfov_max), f(hfov_min)."""
    width = width.to(torch.float64)
    return focal_from_hfov(torch.tensor(config.hfov_range_deg[1], dtype=torch.float64), width), \
        focal_from_hfov(torch.tensor(config.hfov_range_deg[0], dtype=torch.float64), width)


def parameter_box(config: SearchConfig, width: torch.Tensor, known_focal: torch.Tensor | None):
    """Lower and upper bounds, (B, 4) float64, of [pan, pitch, roll, focal] per image."""
    f_lo, f_hi = focal_bounds(config, width)
    if known_focal is not None:
        f_lo = f_hi = known_focal.to(torch.float64)
    lo = torch.stack([torch.full_like(f_lo, config.pan_range_deg[0]), torch.full_like(f_lo, config.pitch_range_deg[0]),
                      torch.full_like(f_lo, config.roll_range_deg[0]), f_lo], -1)
    hi = torch.stack([torch.full_like(f_hi, config.pan_range_deg[1]), torch.full_like(f_hi, config.pitch_range_deg[1]),
                      torch.full_like(f_hi, config.roll_range_deg[1]), f_hi], -1)
    return lo, hi


def grid_hypotheses(config: SearchConfig, width: torch.Tensor, known_focal: torch.Tensor | None = None):
    """Grid of [pan, pitch, roll, focal] per image: (B, G, 4) float64, G = k^4 (k^3 with known f).

    Order: focal slowest, then pitch, pan, roll fastest.
    """
    k = config.grid_points_per_dim
    pan = _cell_centres(*config.pan_range_deg, k)
    pitch = _cell_centres(*config.pitch_range_deg, k)
    roll = _cell_centres(*config.roll_range_deg, k)
    angles = torch.cartesian_prod(pitch, pan, roll)[:, [1, 0, 2]]  # (k^3, 3) as [pan, pitch, roll]
    if known_focal is not None:
        focal = known_focal.to(torch.float64)[:, None]
    else:
        f_lo, f_hi = focal_bounds(config, width)
        focal = f_lo[:, None] + (torch.arange(k, dtype=torch.float64) + 0.5) * (f_hi - f_lo)[:, None] / k
    batch, n_focal = focal.shape
    hyp = torch.cat([angles.expand(batch, n_focal, -1, -1),
                     focal[:, :, None, None].expand(-1, -1, angles.shape[0], 1)], -1)
    return hyp.reshape(batch, -1, 4)


def hypothesis_rotations(params: torch.Tensor) -> torch.Tensor:
    """World->camera R (..., 3, 3) from [pan, pitch, roll, focal] parameters (..., 4)."""
    return rotation_from_angles(params[..., 0], params[..., 1], params[..., 2])


def score_grid(likelihood: MixtureLikelihood, features: SegmentFeatures, hypotheses: torch.Tensor,
               max_chunk_elements: int) -> torch.Tensor:
    """Length-weighted log-likelihood of every hypothesis, (B, G), in chunks of hypotheses and images.

    At most ``max_chunk_elements`` (``CPU_CHUNK_ELEMENTS`` on CPU, if smaller) per-segment
    deviations exist at once; scores do not depend on the chunking.
    """
    batch, count = hypotheses.shape[:2]
    n_seg = max(1, features.weight.shape[1])
    dtype, device = features.weight.dtype, features.weight.device
    # CPU: a cache-sized chunk per intra-op thread.  A fixed 2^17 chunk capped every op at 4 threads
    # (torch's GRAIN_SIZE 2^15 elements per thread), so more cores did not help.
    cpu_budget = CPU_CHUNK_ELEMENTS * max(1, torch.get_num_threads())
    budget = max(1, max_chunk_elements if device.type != "cpu" else min(max_chunk_elements, cpu_budget))
    per_hypothesis = n_seg * 3
    hyp_chunk = max(1, min(count, budget // per_hypothesis))
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
                                                            workspace=workspace)
    return scores


def fast_rotations(params: torch.Tensor) -> torch.Tensor:
    """World->camera R (..., 3, 3) from [pan, pitch, roll, ...] (degrees), closed form.

    ``R.T = Ry(pan) Rx(pitch) Rz(roll)`` -- the same rotation as :func:`hypothesis_rotations`
    (kornia quaternion route) up to rounding, in fewer operations; differentiable.
    """
    rad = torch.deg2rad(params[..., :3])
    cos, sin = torch.cos(rad), torch.sin(rad)
    cp, ct, cr = cos.unbind(-1)
    sp, st, sr = sin.unbind(-1)
    spst, cpst = sp * st, cp * st
    # Columns of R.T are the rows of R; build R row by row (row i of R = column i of R.T).
    rows = torch.stack([cp * cr + spst * sr, ct * sr, cpst * sr - sp * cr,
                        spst * cr - cp * sr, ct * cr, sp * sr + cpst * cr,
                        sp * ct, -st, cp * ct], -1)
    return rows.view(params.shape[:-1] + (3, 3))



def refine(likelihood: MixtureLikelihood, features: SegmentFeatures, starts: torch.Tensor,
           lower: torch.Tensor, upper: torch.Tensor, iterations: int, fast: bool,
           max_chunk_elements: int = 1 << 24) -> tuple[torch.Tensor, torch.Tensor]:
    """Refine starts (B, L, 4) inside the box [lower, upper] (B, 4).  Returns (params, objective).

    Parameters are optimised as u = (p - lower) / (upper - lower) in [0, 1] (a degenerate box,
    e.g. a known focal length, keeps that parameter fixed).  The loss of every hypothesis is its
    negative log-likelihood divided by the image's total segment length, so step sizes do not
    depend on how many segments an image has.  Images are refined in independent slices of at
    most ``max_chunk_elements`` deviations (bounded memory; same result as one big batch).
    """
    batch, n_start = starts.shape[:2]
    n_seg = max(1, features.weight.shape[1])
    if features.weight.device.type == "cpu":
        max_chunk_elements = min(max_chunk_elements, CPU_REFINE_ELEMENTS)
    step = max(1, max_chunk_elements // (n_seg * n_start * 3))
    if batch > step:
        parts = [_refine_slice(likelihood, features.images(b, b + step), starts[b:b + step],
                               lower[b:b + step], upper[b:b + step], iterations, fast)
                 for b in range(0, batch, step)]
        return torch.cat([p for p, _ in parts]), torch.cat([o for _, o in parts])
    return _refine_slice(likelihood, features, starts, lower, upper, iterations, fast)


def _refine_slice(likelihood, features, starts, lower, upper, iterations, fast):
    dtype, device = features.weight.dtype, features.weight.device
    lower = lower.to(device=device, dtype=dtype)[:, None, :]
    upper = upper.to(device=device, dtype=dtype)[:, None, :]
    span = (upper - lower)
    free = span > 0
    span_safe = torch.where(free, span, torch.ones_like(span))
    u = ((starts.to(device=device, dtype=dtype) - lower) / span_safe).clamp(0, 1).detach().requires_grad_(True)
    total_length = features.weight.sum(-1).clamp_min(1e-9)[:, None]
    # Step sizes in box units: about a quarter of a grid cell at first, decaying geometrically.
    cell = 1.0 / 8
    lr0 = 0.25 * cell
    lr_final = (0.02 if fast else 0.002) * cell
    gamma = (lr_final / lr0) ** (1.0 / max(1, iterations - 1))
    optimiser = torch.optim.Adam([u], lr=lr0, betas=(0.5, 0.9))
    schedule = torch.optim.lr_scheduler.ExponentialLR(optimiser, gamma)
    all_free = bool(free.all())

    def evaluate(u_value):
        params = lower + u_value * span
        rotation = fast_rotations(params)
        return params, likelihood.objective(features, rotation, params[..., 3])

    analytic = likelihood._fast_path(features)
    for _ in range(iterations):
        optimiser.zero_grad(set_to_none=True)
        if analytic:  # same gradient in closed form, no autograd graph (see objective_and_grad)
            u.grad = objective_and_grad(likelihood, features, lower, span, u.detach(), -1.0 / total_length)[1]
        else:
            _, objective = evaluate(u)
            loss = -(objective / total_length).sum()
            loss.backward()
        if not all_free:
            u.grad = torch.where(free, u.grad, torch.zeros_like(u.grad))
        optimiser.step()
        schedule.step()
        with torch.no_grad():
            u.clamp_(0.0, 1.0)
    with torch.no_grad():
        params, objective = evaluate(u)
    return params.detach(), objective.detach()


def objective_and_grad(likelihood: MixtureLikelihood, features: SegmentFeatures, lower: torch.Tensor,
                       span: torch.Tensor, u: torch.Tensor, grad_out: torch.Tensor):
    """Measure-b objective (B, L) at ``params = lower + u * span`` and the gradient of
    ``sum(grad_out * objective)`` with respect to u (B, L, 4), without autograd.

    ``lower``, ``span``: (B, 1, 4); ``grad_out``: broadcastable to (B, L).  The chain is written
    out: d obj / d VPs from :func:`fr_torch.likelihood.measure_b_backward`, then ``V = K R``
    (``dV/df = [R_0; R_1; 0]``, ``dV/dR = K``) and the closed-form derivatives of
    :func:`fast_rotations` with respect to pan, pitch and roll (degrees).  Equal to the autograd
    gradient of the same objective to rounding (tests); used by the refinement, where autograd's
    per-step overhead dominated at small batches.
    """
    params = lower + u * span
    batch, n_hyp = params.shape[:2]
    rad = torch.deg2rad(params[..., :3])
    cos, sin = torch.cos(rad), torch.sin(rad)
    cp, ct, cr = cos.unbind(-1)
    sp, st, sr = sin.unbind(-1)
    spst, cpst = sp * st, cp * st
    zero = torch.zeros_like(cp)
    rotation = torch.stack([cp * cr + spst * sr, ct * sr, cpst * sr - sp * cr,
                            spst * cr - cp * sr, ct * cr, sp * sr + cpst * cr,
                            sp * ct, -st, cp * ct], -1).view(batch, n_hyp, 3, 3)
    d_pan = torch.stack([cpst * sr - sp * cr, zero, -spst * sr - cp * cr,
                         cpst * cr + sp * sr, zero, cp * sr - spst * cr,
                         cp * ct, zero, -sp * ct], -1)
    d_pitch = torch.stack([sp * ct * sr, -st * sr, cp * ct * sr,
                           sp * ct * cr, -st * cr, cp * ct * cr,
                           -spst, -ct, -cpst], -1)
    d_roll = torch.stack([spst * cr - cp * sr, ct * cr, cpst * cr + sp * sr,
                          -spst * sr - cp * cr, -ct * sr, sp * cr - cpst * sr,
                          zero, zero, zero], -1)
    focal = params[..., 3]
    pp = features.principal_point[:, None, :]  # (B, 1, 2)
    # V = K R: rows 0, 1 = f R_j + c_j R_2, row 2 = R_2.
    top = focal[..., None, None] * rotation[..., :2, :] + pp[..., None] * rotation[..., 2:, :]
    vps = torch.cat([top, rotation[..., 2:, :]], -2)  # (B, L, 3, 3)
    objective, saved = measure_b_forward(features.line, features.along, features.weight, vp_major(vps),
                                         *likelihood._b_constants(features.weight))
    grad_flat = measure_b_backward(saved, grad_out.expand(batch, n_hyp).contiguous())
    grad_v = grad_flat.view(batch, 3, 3, n_hyp).permute(0, 3, 1, 2)  # (B, L, coord, VP)
    # dObj/dR = K^T G: rows 0, 1 scaled by f; row 2 gets c . G[:2] + G[2].
    grad_r = torch.cat([focal[..., None, None] * grad_v[..., :2, :],
                        (pp[..., None] * grad_v[..., :2, :]).sum(-2, keepdim=True) + grad_v[..., 2:, :]], -2)
    grad_r = grad_r.reshape(batch, n_hyp, 9)
    grad_f = (grad_v[..., :2, :] * rotation[..., :2, :]).sum((-1, -2))
    grad_p = torch.stack([(grad_r * d_pan).sum(-1), (grad_r * d_pitch).sum(-1), (grad_r * d_roll).sum(-1)], -1)
    grad_p = torch.cat([grad_p * (math.pi / 180), grad_f[..., None]], -1)
    return objective, grad_p * span
