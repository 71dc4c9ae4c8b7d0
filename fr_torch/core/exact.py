"""Arithmetic whose result does not depend on where or with what it runs.

A photo must get the same answer alone or in a batch, with any thread count, under every torch
CPU kernel set (``ATEN_CPU_CAPABILITY``), on any CPU, and run after run on a GPU.  Five kinds of
operation break that in plain torch, and the search avoids them through this module:

* **Sums in an order that depends on the layout.**  A reduction over padded segments, a matrix
  product (BLAS picks kernels, blocking and FMA by shape) or a vectorised ``sum`` (its lane count
  is the kernel set's) adds the same numbers in different orders.  :func:`exact_sum` rounds every
  term to a fixed-point grid set by a bound on the terms (not by the layout) and adds the integers
  in float64, where every partial sum is exact: the result is the same for any order, padding,
  chunking, thread count, kernel set or device.
* **Products written as BLAS calls.**  :func:`dot3` and :func:`small_matmul` spell out dot
  products with single, correctly rounded multiplications and additions (IEEE 754), in a fixed
  order; a fused multiply-add, which some kernels use and others do not, is never asked for.
* **Functions that round differently by position, kernel set or CPU.**  torch's ``atan2`` runs a
  vectorised approximation on the body of a tensor and the C library on its tail, so an element's
  value depends on where it sits; ``log1p`` and ``pow`` differ between kernel sets; and torch's
  ``exp``, ``log``, ``atan``, ``sqrt`` (and more) come from oneMKL, whose code branch, and so whose
  last bits, depend on the CPU.  The search takes its elementary functions from
  :mod:`fr_torch.core.exact_math` instead (IEEE operations in a fixed order), :func:`angle_of`
  included.
* **Linear algebra by LAPACK.**  Its solvers pick blocked kernels by CPU: :func:`small_solve`,
  :func:`small_inverse` and :func:`positive_definite` do the small systems of the cues by
  elimination, one rounding per step.
* **Ties left to a kernel.**  ``topk`` and ``argmax`` may return any of equal entries;
  :func:`top_indices` and :func:`first_argmax` take the lowest index.

``tests/test_reproducibility.py`` runs the search under every kernel set with oneMKL and numpy pinned
to what other CPUs run (``tests/conftest.py``, ``EMULATED_CPUS``), and ``fr bench --sections
reproducibility`` measures the datasets.  A GPU gives the same bits run after run but not the CPU's
(CUDA's own ``exp`` / ``log`` / ...).  Shapes: any; ``dim`` arguments as in torch.
"""
from __future__ import annotations

import math

import torch

from fr_torch.core import exact_math

#: Bits of the fixed-point grid below a term's bound: each term is kept to 2^-TERM_BITS of the
#: power of two above its bound (float32's own precision is 2^-24 of the term).
TERM_BITS = 30
#: At most 2^SUM_BITS terms per sum, so that the integers' partial sums stay below 2^53 (exact in
#: float64) even when a term exceeds its bound 2^(52 - TERM_BITS - SUM_BITS) = 4-fold.
SUM_BITS = 20
#: A bound below 2^_MIN_EXPONENT counts as 2^_MIN_EXPONENT: the scale stays a finite float32 (terms below
#: 2^-120 round to 0).
_MIN_EXPONENT = -90
#: float64 terms: bits kept below the integer grid, in a second exact sum (2^-(TERM_BITS + LOW_BITS)
#: of the bound: float64's own precision).
LOW_BITS = 22


def fixed_point_scale(bound: torch.Tensor) -> torch.Tensor:
    """The power of two that maps terms of magnitude <= ``bound`` onto integers of at most
    :data:`TERM_BITS` bits: ``2^(TERM_BITS - e)`` with ``bound < 2^e``; same shape and device as
    ``bound``, float64.  A zero bound gives ``2^TERM_BITS``; a non-finite one gives a non-finite
    scale (the sum is then non-finite, as the terms' sum would be)."""
    bound = bound.to(torch.float64)
    _, exponent = torch.frexp(bound)
    exponent = exponent.clamp_min(_MIN_EXPONENT).to(torch.float64)
    scale = exact_math.power_of_two(TERM_BITS - exponent, torch.float64)
    return torch.where(torch.isfinite(bound), scale, bound)


def exact_sum(x: torch.Tensor, dim: int, bound: torch.Tensor | None = None, keepdim: bool = False,
              weight: torch.Tensor | None = None) -> torch.Tensor:
    """Sum of ``x`` (or of ``weight * x``) over ``dim`` in float64, independent of the order of the terms.

    Every term is rounded to a multiple of ``1 / scale`` (:func:`fixed_point_scale` of ``bound``,
    default the largest ``|x|`` of the slice), i.e. to 2^-:data:`TERM_BITS` of the bound's power
    of two (float64 terms: 2^-(TERM_BITS + LOW_BITS), through a second sum of their remainders);
    the rounded terms are integers in units of ``1 / scale``, so float64 adds them without error in
    any order, and the result is the sum of the rounded terms, bit for bit, on any device.
    Padding with zeros, splitting the batch, thread counts and kernel sets cannot change it.

    Args:
        x: float32 or float64 terms.
        dim: the dimension summed over (at most 2^:data:`SUM_BITS` long).
        bound: an upper bound on the terms' magnitude per slice, broadcastable to
            ``x.sum(dim, keepdim=True)`` (e.g. one per image); it must not depend on how the slices
            are laid out.  Terms above it by more than 4x may make the sum inexact (still finite and
            nearly order-free).  None = the slice's own largest term magnitude (one more pass).
        keepdim: keep ``dim`` with size 1.
        weight: optional factors broadcastable to ``x``: the terms are ``weight * x``, each product
            rounded once in ``x``'s dtype (``bound`` then bounds the products).

    Returns:
        float64 sums, shape of ``x.sum(dim, keepdim=keepdim)``.  NaN or inf among the terms gives a
        non-finite sum.  Differentiable: the gradient is a plain sum's (rounding has none).
    """
    if x.shape[dim] > (1 << SUM_BITS):
        raise ValueError(f"exact_sum: {x.shape[dim]} terms exceed its limit of 2^{SUM_BITS}")
    if bound is None:
        terms = x if weight is None else x * weight
        bound = terms.detach().abs().amax(dim, keepdim=True) if terms.numel() else x.new_zeros(())
    scale = fixed_point_scale(bound)
    work = x if x.dtype == torch.float32 else x.to(torch.float64)  # scaled in float32 (exact: a power of two)
    factor = scale.to(work.dtype) if weight is None else weight.to(work.dtype) * scale.to(work.dtype)
    scaled = work * factor
    high = scaled.round()
    # integers in float64: any order of addition is exact (and .double().sum is ~10x faster than sum(dtype=))
    total = high.to(torch.float64).sum(dim, keepdim=True)
    if work.dtype == torch.float64:  # float64 terms keep 2^-LOW_BITS more: their rounded-off parts, summed apart
        low = (scaled - high).mul_(2.0 ** LOW_BITS).round_()  # scaled - high is exact
        total = total + low.sum(dim, keepdim=True) / 2.0 ** LOW_BITS
    total = total / scale
    if torch.is_grad_enabled() and (x.requires_grad or (weight is not None and weight.requires_grad)):
        # the exact value with the gradient of a plain sum (adding p - p = 0 leaves the bits alone)
        plain = (x if weight is None else x * weight).sum(dim, keepdim=True, dtype=torch.float64)
        total = total.detach() + (plain - plain.detach())
    return total if keepdim else total.squeeze(dim)


def dot3(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """``a[..., 0] b[..., 0] + a[..., 1] b[..., 1] + a[..., 2] b[..., 2]`` (inputs broadcast), in
    that order, each product and sum rounded once: the same bits on every kernel set and device."""
    return a[..., 0] * b[..., 0] + a[..., 1] * b[..., 1] + a[..., 2] * b[..., 2]


def small_matmul(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Batched product ``a @ b`` of small matrices (..., n, m) x (..., m, k) -> (..., n, k), every
    entry ``a_i0 b_0j + a_i1 b_1j + ...`` with one rounding per product and sum, left to right (for
    m = 3 the order of :func:`dot3`): the same bits in any batch, kernel set and device."""
    return small_sum(a[..., :, :, None] * b[..., None, :, :], -2)


def cross3(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Cross product of (..., 3) vectors, each entry ``a_i b_j - a_j b_i`` rounded twice (no fused
    multiply-add, module docstring)."""
    a0, a1, a2 = a.unbind(-1)
    b0, b1, b2 = b.unbind(-1)
    return torch.stack([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0], -1)


def small_sum(x: torch.Tensor, dim: int) -> torch.Tensor:
    """Sum over a short dimension (a handful of entries) from left to right, one rounding per
    addition: the same bits for every layout, kernel set and device."""
    parts = x.unbind(dim)
    total = parts[0]
    for part in parts[1:]:
        total = total + part
    return total


def first_argmax(x: torch.Tensor, dim: int) -> torch.Tensor:
    """Index of the largest entry along ``dim``, the lowest index among equal largest entries
    (int64; NaN never wins unless the whole slice is NaN, then 0).  torch's ``argmax`` leaves the
    tie to its kernel."""
    cleaned = torch.where(torch.isnan(x), torch.full_like(x, -math.inf), x) if x.is_floating_point() else x
    best = cleaned.amax(dim, keepdim=True)
    index = torch.arange(x.shape[dim], device=x.device).view([-1 if d == dim % x.dim() else 1 for d in range(x.dim())])
    return torch.where(cleaned == best, index, x.shape[dim]).amin(dim).clamp_max(x.shape[dim] - 1)


def top_indices(x: torch.Tensor, count: int, dim: int = -1) -> torch.Tensor:
    """Indices of the ``count`` largest entries along ``dim``, largest first, equal entries in index
    order (a stable sort; torch's ``topk`` leaves the order of ties to its kernel)."""
    return torch.sort(x, dim=dim, descending=True, stable=True).indices.narrow(dim, 0, count)


def small_solve(a: torch.Tensor, b: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Solutions ``x`` of ``a x = b`` for batches of small systems, ``a`` (..., n, n), ``b`` (..., n,
    m): Gauss-Jordan elimination with partial pivoting (the largest ``|pivot|``, the lowest row among
    equal ones), every step an elementwise product, difference or quotient rounded once.  LAPACK's
    solvers (``torch.linalg``) pick blocked kernels by CPU and so round differently from one CPU to
    another; this gives the same bits anywhere.  Meant for n up to a few dozen.

    Returns:
        (x (..., n, m), ok (...,) bool): ok is False where a pivot is 0 or not finite (a singular or
        non-finite system; x is then not meaningful).
    """
    n = a.shape[-1]
    batch = a.shape[:-2]
    aug = torch.cat([a, b.to(a.dtype)], -1).reshape(-1, n, n + b.shape[-1])
    ok = torch.ones(aug.shape[0], dtype=torch.bool, device=a.device)
    rows = torch.arange(n, device=a.device)
    for col in range(n):
        below = first_argmax(aug[:, col:, col].abs(), -1) + col  # (B,) the pivot's row
        order = rows.expand(aug.shape[0], n).clone()
        order[:, col] = below
        order.scatter_(1, below[:, None], col)
        aug = aug.gather(1, order[:, :, None].expand_as(aug))
        pivot = aug[:, col, col]
        ok &= (pivot != 0) & torch.isfinite(pivot)
        row = aug[:, col, :] / pivot[:, None]
        factor = aug[:, :, col].clone()
        factor[:, col] = 0.0
        aug = aug - factor[:, :, None] * row[:, None, :]
        aug[:, col, :] = row
    return aug[:, :, n:].reshape(*batch, n, b.shape[-1]), ok.reshape(batch)


def small_inverse(a: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Inverses of small square matrices (..., n, n) by :func:`small_solve` against the identity:
    (inverse, ok) as there."""
    eye = torch.eye(a.shape[-1], dtype=a.dtype, device=a.device).expand_as(a)
    return small_solve(a, eye)


def positive_definite(a: torch.Tensor) -> torch.Tensor:
    """(...,) bool: True where the symmetric matrices ``a`` (..., n, n) are positive definite, i.e.
    every pivot of their symmetric elimination (no pivoting; Sylvester's criterion) is positive and
    finite.  Elementwise steps only: the same verdict on any CPU (an eigensolver's is LAPACK's)."""
    m = a.reshape(-1, *a.shape[-2:]).clone()
    ok = torch.ones(m.shape[0], dtype=torch.bool, device=a.device)
    for col in range(m.shape[-1]):
        pivot = m[:, col, col]
        ok &= (pivot > 0) & torch.isfinite(pivot)
        column = m[:, :, col] / pivot[:, None]
        m = m - column[:, :, None] * m[:, col, None, :]
    return ok.reshape(a.shape[:-2])


def angle_of(s: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    """``atan2(|s|, |t|)`` in [0, pi/2] radians, elementwise (``s``, ``t`` of one shape and dtype),
    as ``atan(|s / t|)``: 0 where s = t = 0, pi/2 where t = 0 alone.  torch's ``atan2`` is avoided
    (module docstring)."""
    return exact_math.atan(torch.div(s, t).abs_().nan_to_num_(nan=0.0))


def angle_of_(s: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    """:func:`angle_of` written into ``s`` (in place; returns ``s``)."""
    return s.copy_(exact_math.atan(s.div_(t).abs_().nan_to_num_(nan=0.0)))


def atan2(y: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    """torch's ``atan2(y, x)`` in (-pi, pi] radians, elementwise, through :func:`angle_of` (the same
    bits at every position and kernel set); ``atan2(0, x) = 0`` for x >= 0 and pi for x < 0."""
    angle = angle_of(y, x)
    angle = torch.where(x < 0, math.pi - angle, angle)
    return torch.where(y < 0, -angle, angle)


def exact_index_sum(values: torch.Tensor, index: torch.Tensor, count: int,
                    bound: torch.Tensor | None = None) -> torch.Tensor:
    """Sums of ``values`` (P, ...) into ``count`` bins by ``index`` (P,) int64: (count, ...) float64,
    independent of the order of the P entries (``index_add_`` adds in its own order, atomically on a
    GPU).  ``bound``: an upper bound on the values' magnitude per bin, broadcastable to (count, ...)
    (as for :func:`exact_sum`); default each bin's own largest ``|value|``.  Each value is rounded
    to its bin's fixed-point grid."""
    values = values.to(torch.float64)
    shape = (count,) + tuple(values.shape[1:])
    if bound is None:
        expanded = index.view((-1,) + (1,) * (values.dim() - 1)).expand_as(values)
        bound = values.new_zeros(shape).scatter_reduce_(0, expanded, values.abs(), "amax")
    scale = fixed_point_scale(bound).expand(shape)
    integers = (values * scale.index_select(0, index)).round_()
    return torch.zeros(shape, dtype=torch.float64, device=values.device).index_add_(0, index, integers) / scale
