"""The fused measure-b objective: what the grid and the refinement evaluate millions of times.

:meth:`~fr_torch.core.likelihood.mixture.MixtureLikelihood.objective` takes this path for measure
b instead of the generic one, with the same terms.  Without gradients (the grid) it works in place
on reusable buffers (``workspace``) with vanishing points laid out VP-major, ``(B, N, 3 * H)``
(:func:`vp_major`), so the sum over the three families adds contiguous blocks; with gradients (the
refinement) :class:`MeasureBObjective` returns the analytic gradient with respect to the vanishing
points (``d obj / d v = sum_i [G_is l_i + G_it g_i]``), so autograd only sees the small
(B, H, 3, 3) tensors.  One deliberate detail: the exponent ``log(prior / lambda) - x / lambda`` is
clamped below at -87 (float32; -700 for float64, :data:`EXP_FLOOR`) because ``exp`` of a more
negative float32 argument takes a much slower denormal path; the clamped term (< 1e-37) is then
added to the background density (>= 0.019 for measure b), which it cannot change in float32 or
float64, so the objective is unchanged bit for bit whenever the background prior exceeds ~1e-28.
``atan2(0, 0) = 0`` as in the generic path (and the gradient there is 0, as the generic path's
guard gives).

Fused CPU kernels (float32 on a CPU, where they build: :mod:`fr_torch.core.likelihood.native`): the
grid's scores (:func:`objective_b_nograd`) and the refinement's objective with its gradient
(:func:`measure_b_objective_and_grad`) run as one C pass each, which never stores the per-segment
deviations and keeps the exact sums' integers in registers; the same operations in the same order
as the torch code here, which stays the reference (``fused=False``) and the path of every other
device, dtype and machine: the same bits either way.
"""
from __future__ import annotations

import math

import torch

from fr_torch.core.exact import angle_of, angle_of_, exact_sum, fixed_point_scale, small_sum
from fr_torch.core.geometry.conventions import VERTICAL_AXIS
from fr_torch.core.likelihood import native
from fr_torch.core.likelihood.measures import incidence
from fr_torch.core import exact_math


def family_sum(density: torch.Tensor, dim: int) -> torch.Tensor:
    """The three families' densities summed over ``dim`` (size 3, Manhattan column order) as
    ``(horizontal + horizontal) + vertical``: the order of the fused paths, which score the vertical
    VP apart (:func:`objective_b_nograd`), so every path gives the same bits."""
    first, second = [density.select(dim, k) for k in range(3) if k != VERTICAL_AXIS]
    return first + second + density.select(dim, VERTICAL_AXIS)




EXP_FLOOR = {torch.float32: -87.0, torch.float64: -700.0}  # exp() stays out of denormals above these


def vp_major(vps: torch.Tensor) -> torch.Tensor:
    """(B, H, 3 coords, 3 VPs) -> (B, 3 coords, 3 * H), columns ordered (VP, hypothesis)."""
    batch, hyp = vps.shape[:2]
    return vps.permute(0, 2, 3, 1).reshape(batch, 3, 3 * hyp)


def _take(workspace: dict | None, name: str, shape, like: torch.Tensor) -> torch.Tensor:
    """A buffer of ``shape`` from ``workspace`` (grown on demand, reused across chunks)."""
    numel = math.prod(shape)
    if workspace is None:
        return like.new_empty(shape)
    buf = workspace.get(name)
    if buf is None or buf.numel() < numel or buf.dtype != like.dtype or buf.device != like.device:
        buf = like.new_empty(numel)
        workspace[name] = buf
    return buf[:numel].view(shape)


def objective_b_nograd(line_along, weight, flat, neg_inv_scale, log_coef, background, floor, log_bound,
                       workspace: dict | None = None, vertical_block: int = 1, per_segment: bool = False,
                       fused: bool = True, grid: tuple[torch.Tensor, torch.Tensor] | None = None) -> torch.Tensor:
    """Measure-b objective (B, H) float64 for VP-major vanishing points ``flat`` (B, 3, 3H), no autograd;
    with ``per_segment`` each segment's log p_i instead, (B, N, H) in the segments' dtype (a view of
    the ``workspace`` buffer when one is given).

    Every pass is in place on reusable buffers: [s; t] (:func:`incidence`); x = atan(|s / t|)
    (:func:`fr_torch.core.exact.angle_of_`); log(prior/lambda) - x/lambda, clamped at ``floor``;
    exp; the 3 families and the background added as ``(horizontal + horizontal) + vertical +
    background`` (:func:`family_sum`'s order); log; the length-weighted sum over segments, exact
    (:func:`fr_torch.core.exact.exact_sum`, bounded per image by ``log_bound`` times the longest
    segment).

    ``vertical_block`` = k > 1: runs of k consecutive hypotheses share the vertical VP (column
    ``VERTICAL_AXIS``), so only every k-th one is scored and added to its run: (2 + 1/k) H VP
    columns instead of 3 H, the same sums bit for bit.  H must be a multiple of k.

    ``fused``: the objective of float32 CPU tensors comes from the fused kernel of
    :mod:`fr_torch.core.likelihood.native` where it is available (the same bits, the deviations never stored);
    False always takes the torch path written here, the reference the kernel is checked against.
    ``grid``: :func:`sum_grid` of ``weight`` and ``log_bound`` when the caller keeps it (the fused
    kernel's input; formed here when None).
    """
    batch, n_seg = weight.shape
    hyp = flat.shape[2] // 3
    if vertical_block > 1 and hyp % vertical_block:
        raise ValueError(f"vertical_block {vertical_block} does not divide the {hyp} hypotheses")
    if fused and not per_segment and vertical_block <= native.TILE and native_ok(weight):
        factor, scale = sum_grid(weight, log_bound) if grid is None else grid
        return native.measure_b_scores(line_along, factor, scale, flat, neg_inv_scale, log_coef, background, floor,
                                       VERTICAL_AXIS, vertical_block)
    block = max(1, vertical_block)
    columns = flat.view(batch, 3, 3, hyp)
    h_cols = _without_vertical(columns, 2).reshape(batch, 3, 2 * hyp)
    v_cols = columns[:, :, VERTICAL_AXIS, ::block]  # (B, 3, H / k): one per run
    h = _family_density(line_along, h_cols, _without_vertical(neg_inv_scale, 0), _without_vertical(log_coef, 0),
                        floor, workspace, "h", groups=2).view(batch, n_seg, 2, hyp)
    v = _family_density(line_along, v_cols, neg_inv_scale[VERTICAL_AXIS], log_coef[VERTICAL_AXIS], floor,
                        workspace, "v")
    p = torch.add(h[:, :, 0], h[:, :, 1], out=_take(workspace, "p", (batch, n_seg, hyp), weight))
    p.view(batch, n_seg, hyp // block, block).add_(v[..., None])
    p.copy_(exact_math.log(p.add_(background)))
    if per_segment:
        return p
    return exact_sum(p, 1, bound=log_sum_bound(weight, log_bound), weight=weight[:, :, None])


def native_ok(weight: torch.Tensor) -> bool:
    """Whether segments of ``weight``'s dtype and device take the fused kernels (:mod:`fr_torch.core.likelihood.native`)."""
    return weight.dtype == torch.float32 and weight.device.type == "cpu" and native.available()


def sum_grid(weight: torch.Tensor, log_bound: float) -> tuple[torch.Tensor, torch.Tensor]:
    """The fixed-point grid of the objective's exact sum over segments, as
    :func:`fr_torch.core.exact.exact_sum` forms it from the bound :func:`log_sum_bound`: each
    segment's factor ``weight * scale`` (B, N) in ``weight``'s dtype and the scale (B,) float64."""
    scale = fixed_point_scale(log_sum_bound(weight, log_bound))  # (B, 1, 1)
    factor = weight[:, :, None] * scale.to(weight.dtype)
    return factor[..., 0], scale.view(-1)


def log_sum_bound(weight: torch.Tensor, log_bound: float) -> torch.Tensor:
    """(B, 1, 1) bound on ``|len_i log p_i|`` per image: its longest segment times ``log_bound``
    (a bound on |log p_i| for any hypothesis), the same whatever the batch."""
    return (weight.amax(1) * log_bound)[:, None, None] if weight.shape[1] else weight.new_zeros(weight.shape[0], 1, 1)


def _family_density(line_along, columns, neg_inv_scale, log_coef, floor, workspace, name, groups=1):
    """prior/lambda exp(-x/lambda) of every segment for VP columns (B, 3, M): (B, N, M), in place
    in the ``workspace`` buffer named ``name`` (a view of it is returned).  ``line_along`` (B, 2N, 3)
    as in :class:`SegmentFeatures`.  The columns form ``groups`` equal blocks (VPs) with constants
    ``neg_inv_scale`` = -1/lambda and ``log_coef`` = log(prior/lambda) of shape (groups, 1);
    exponents are clamped at ``floor``."""
    batch, n_seg = line_along.shape[0], line_along.shape[1] // 2
    width = columns.shape[2]
    shape = (batch, 2 * n_seg, width)
    st = incidence(line_along, columns, out=_take(workspace, name, shape, line_along),
                   tmp=_take(workspace, "incidence", shape, line_along))
    s = angle_of_(st[:, :n_seg], st[:, n_seg:])  # x = atan(|s / t|), in the s half
    s.view(batch, n_seg, groups, width // groups).mul_(neg_inv_scale).add_(log_coef)
    return s.copy_(exact_math.exp(s.clamp_min_(floor)))


def _without_vertical(x: torch.Tensor, dim: int) -> torch.Tensor:
    """``x`` without index ``VERTICAL_AXIS`` along ``dim`` (the two horizontal families), from two
    slices: indexing a GPU tensor with a Python list copies the index to the device and waits for
    it, once per grid chunk."""
    return torch.cat([x.narrow(dim, 0, VERTICAL_AXIS), x.narrow(dim, VERTICAL_AXIS + 1, 2 - VERTICAL_AXIS)], dim)


def measure_b_forward(line_along, weight, flat, neg_inv_scale, log_coef, background, floor, log_bound):
    """Measure-b objective (B, H) float64 and what :func:`measure_b_backward` needs (no autograd
    graph); the same terms and sum as :func:`objective_b_nograd`, bit for bit.

    ``line_along`` (B, 2N, 3) as in :class:`SegmentFeatures`, ``weight`` (B, N), ``flat`` (B, 3, 3H)
    VP-major vanishing points (:func:`vp_major`)."""
    batch, n_seg = weight.shape
    hyp = flat.shape[2] // 3
    st = incidence(line_along, flat)
    s, t = st[:, :n_seg], st[:, n_seg:]
    theta = angle_of(s, t).view(batch, n_seg, 3, hyp)
    e = exact_math.exp((theta * neg_inv_scale).add_(log_coef).clamp_min_(floor))  # prior/lambda exp(-x/lambda)
    p = family_sum(e, 2).add_(background)
    objective = exact_sum(exact_math.log(p), 1, bound=log_sum_bound(weight, log_bound), weight=weight[:, :, None])
    return objective, (line_along, weight, s, t, e, p, neg_inv_scale)


def measure_b_objective_and_grad(line_along, weight, flat, constants, grad_out, fused: bool = True):
    """Measure-b objective (B, H) float64 and its gradient with respect to the VP-major vanishing
    points ``flat`` (B, 3, 3H), float64, for the upstream gradient ``grad_out`` (broadcastable to
    (B, H)): :func:`measure_b_forward` then :func:`measure_b_backward`, or for float32 CPU tensors
    the fused kernel of :mod:`fr_torch.core.likelihood.native` (the same bits in one pass; ``fused`` = False
    always takes the torch path).  ``constants``: :meth:`MixtureLikelihood._b_constants`."""
    batch, hyp = weight.shape[0], flat.shape[2] // 3
    if fused and native_ok(weight):
        neg_inv_scale, log_coef, background, floor, log_bound = constants
        factor, scale = sum_grid(weight, log_bound)
        return native.measure_b_grad(line_along, weight, factor, scale, flat, neg_inv_scale, log_coef, background,
                                     floor, VERTICAL_AXIS, grad_out.to(weight.dtype))
    objective, saved = measure_b_forward(line_along, weight, flat, *constants)
    return objective, measure_b_backward(saved, grad_out.to(weight.dtype).expand(batch, hyp).contiguous())


def measure_b_backward(saved, grad_out, flat: torch.Tensor | None = None):
    """d objective / d flat (B, 3, 3H) float64 for the upstream gradient ``grad_out`` (B, H).

    With ``flat`` (the forward pass's VP-major vanishing points) also d objective / d line_along,
    (B, 2N, 3): ``d obj / d l_i = sum_v G_is v``, ``d obj / d g_i = sum_v G_it v`` (the distortion
    parameter's chain, :mod:`fr_torch.core.geometry.lens`).  Returns the one tensor, or the pair.
    Sums over segments are exact (:func:`fr_torch.core.exact.exact_sum`), those over the VPs
    written out: the same bits in any batch."""
    line_along, weight, s, t, e, p, neg_inv_scale = saved
    batch, n_seg, hyp = p.shape
    line, along = line_along[:, :n_seg], line_along[:, n_seg:]
    # d obj / d x_ik = w_i / p_i * (-e_ik / lambda_k);  x = atan2(|s|, |t|):
    # dx/ds = sign(s) |t| / r2 = q t / r2, dx/dt = -sign(t) |s| / r2 = -q s / r2, with
    # r2 = s^2 + t^2 and q = sign(s) sign(t) (both 0 at s = 0 or t = 0; r2 > 0 guards 0 / 0).
    g = (weight[:, :, None] / p).mul_(grad_out.to(p.dtype)[:, None, :])  # (B, N, H)
    r2 = (s * s).add_(t * t).clamp_min_(torch.finfo(s.dtype).tiny)
    q = torch.sign(s * t)
    common = (e * neg_inv_scale).mul_(g[:, :, None, :]).view(batch, n_seg, 3 * hyp).mul_(q).div_(r2)
    if flat is not None:  # terms below float's normal range (< 1e-38) are 0 to the sums, but subnormal
        # operands slow the CPU's products several times over: drop them
        common.masked_fill_(common.abs() < torch.finfo(common.dtype).tiny, 0.0)
    grad_s = common * t  # d obj / d s
    grad_t = common.mul_(s).neg_()  # d obj / d t
    # d obj / d flat[c] = sum_i line_ic grad_s_i + along_ic grad_t_i, one exact sum per coordinate, its
    # fixed-point grid set by the image's largest term (one reduction over the whole image: a reduction
    # over the segment axis alone, with a few hypotheses inside it, is several times slower)
    sums = []
    for c in range(3):
        terms = line[:, :, c, None] * grad_s + along[:, :, c, None] * grad_t
        bound = terms.detach().abs().flatten(1).amax(1)[:, None, None] if terms.numel() else None
        sums.append(exact_sum(terms, 1, bound=bound))
    grad_flat = torch.stack(sums, 1)
    if flat is None:
        return grad_flat
    columns = flat.to(grad_s.dtype).transpose(1, 2)  # (B, 3H, 3)
    per_segment = [small_sum(grad[:, :, :, None] * columns[:, None], 2) for grad in (grad_s, grad_t)]
    return grad_flat, torch.cat(per_segment, 1)


class MeasureBObjective(torch.autograd.Function):
    """Measure-b objective with an analytic gradient w.r.t. the VP-major vanishing points."""

    @staticmethod
    def forward(ctx, line_along, weight, flat, neg_inv_scale, log_coef, background, floor, log_bound):
        objective, saved = measure_b_forward(line_along, weight, flat, neg_inv_scale, log_coef, background, floor,
                                             log_bound)
        ctx.save_for_backward(*saved)
        ctx.flat_dtype = flat.dtype
        return objective

    @staticmethod
    def backward(ctx, grad_out):
        grad_flat = measure_b_backward(ctx.saved_tensors, grad_out)
        return None, None, grad_flat.to(ctx.flat_dtype), None, None, None, None, None
