"""The segments as the likelihood sees them (:class:`SegmentFeatures`) and the deviation measures
(a)-(e) of a segment from a vanishing point.

Shapes: B images, H hypotheses per image, N segments per image (padded; ``mask`` marks the real
ones), 3 vanishing points.  All computations use the *homogeneous* vanishing point, so a VP at
infinity (third coordinate 0) needs no special case: for a segment with unit direction d,
midpoint m and homogeneous line ``l = (-d_y, d_x, d_y m_x - d_x m_y)`` (unit normal, so
``l . (x, y, 1)`` is the signed distance of pixel (x, y) from the segment's line), and
``g = (d_x, d_y, -d . m)`` (``g . (x, y, 1)`` is the signed position of (x, y) along the segment
from its midpoint), a VP ``v`` gives

* ``s = l . v`` — v3 times the signed distance of the VP from the segment's line;
* ``t = g . v`` — v3 times the VP's position along the segment direction.

Deviation measures (internal units: radians for b and e, pixels for a, c, d):

(a) distance from the VP to the segment's line, ``|s| / |v3|`` (saturates at ``range`` px);
(b) angle between the segment and the line from its midpoint to the VP, ``atan2(|s|, |t|)`` —
    the default; a segment whose midpoint coincides with the VP gets 0;
(c) distance from an endpoint to the line through the midpoint and the VP, ``(len/2) sin(b)``;
(d) endpoint distance measured orthogonally to the segment, ``(len/2) tan(b)``;
(e) Gauss-sphere angle between the VP direction ``D = K^-1 v`` and the segment's interpretation
    plane (normal ``n = K^T l``): ``asin(|n . D| / (|n| |D|))``, where ``n . D = s`` (evaluated as
    ``atan2(|s|, sqrt(|n|^2 - s^2))``: finite value and gradient in float32 too).

s and t are written out per entry (:func:`incidence`, no matrix product), so they are the same
bits in any batch (:mod:`fr_torch.core.exact`).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import torch

from fr_torch.core.exact import angle_of, dot3, exact_sum, small_sum, top_indices
from fr_torch.core.geometry.conventions import vanishing_points
from fr_torch.core.likelihood.segments import SegmentBatch
from fr_torch.core import exact_math

MEASURES = ("a", "b", "c", "d", "e")


_TINY = 1e-30  # guards 0 / 0 in measure a
#: Measure a's background range (pixels): the default of :attr:`~fr_torch.core.likelihood.mixture.LikelihoodParams.range_px`.
RANGE_PX = 2000.0


@dataclass
class SegmentFeatures:
    """Per-segment quantities the likelihood needs, (B, N, ...) tensors (see module docstring)."""

    line: torch.Tensor  # (B, N, 3) l, unit normal
    along: torch.Tensor  # (B, N, 3) g
    half_length: torch.Tensor  # (B, N) pixels
    weight: torch.Tensor  # (B, N) length in pixels, 0 for padding
    mask: torch.Tensor  # (B, N) bool
    principal_point: torch.Tensor  # (B, 2) pixels
    long_side: torch.Tensor  # (B,) the image's longer side, pixels (the focal prior's scale)
    #: (B, 2N, 3) ``line`` then ``along`` rows: one :func:`incidence` with the VPs gives s and t
    #: (the measure-b paths).
    #: Built from ``line`` and ``along`` unless given (then ``line`` and ``along`` are its halves).
    line_along: torch.Tensor | None = field(default=None, repr=False)

    def __post_init__(self) -> None:
        if self.line_along is None:
            self.line_along = torch.cat([self.line, self.along], 1)

    @classmethod
    def from_batch(cls, batch: SegmentBatch, principal_point: torch.Tensor) -> "SegmentFeatures":
        return cls.from_endpoints(batch.endpoints, batch.mask, principal_point,
                                  batch.image_size.to(batch.endpoints).amax(-1))

    @classmethod
    def from_endpoints(cls, endpoints: torch.Tensor, mask: torch.Tensor | None,
                       principal_point: torch.Tensor, long_side: torch.Tensor | None = None) -> "SegmentFeatures":
        """``long_side`` (B,) pixels; default ``2 max(pp) + 1`` (the image's long side when the
        principal point is the image centre, :func:`fr_torch.core.geometry.conventions.image_centre`)."""
        p1, p2 = endpoints[..., :2], endpoints[..., 2:]
        delta = p2 - p1
        length = exact_math.sqrt(delta[..., 0] * delta[..., 0] + delta[..., 1] * delta[..., 1])
        if mask is None:
            mask = torch.ones_like(length, dtype=torch.bool)
        mask = mask & (length > 0)
        d = delta / length.clamp_min(1e-12).unsqueeze(-1)
        m = (p1 + p2) / 2
        line = torch.stack([-d[..., 1], d[..., 0], d[..., 1] * m[..., 0] - d[..., 0] * m[..., 1]], -1)
        along = torch.stack([d[..., 0], d[..., 1], -(d[..., 0] * m[..., 0] + d[..., 1] * m[..., 1])], -1)
        pp = principal_point.to(endpoints).expand(endpoints.shape[0], 2)
        long_side = 2 * pp.amax(-1) + 1 if long_side is None else long_side.to(endpoints).expand(endpoints.shape[0])
        return cls(line, along, length / 2, length * mask, mask, pp, long_side)

    def total_length(self) -> torch.Tensor:
        """(B,) float64 total segment length per image, pixels (an exact sum: the same bits in any
        batch, :func:`fr_torch.core.exact.exact_sum`); computed once (:meth:`constant`: the search
        asks for it at every step)."""
        return self.constant("total_length", lambda: exact_sum(self.weight, 1))

    def constant(self, key, make):
        """``make()``, computed once and kept under ``key``: for values that depend on ``weight``,
        ``mask``, ``principal_point`` and ``long_side`` alone, never on the lines (the total length,
        the objective's fixed-point grid), which the search asks for at every call.  The tensors
        must not change in place afterwards.  Features that hold the same such tensors may share
        these values (:meth:`sharing_constants`)."""
        store = self.__dict__.get("_constants")
        if store is None:
            store = self.__dict__["_constants"] = {}
        if key not in store:
            store[key] = make()
        return store[key]

    def sharing_constants(self, store: dict) -> "SegmentFeatures":
        """These features with ``store`` (a dict) as the keeper of their :meth:`constant` values:
        features built with the very same ``weight``, ``mask``, ``principal_point`` and
        ``long_side`` tensors (other lines) pass one dict, so each value is computed once for all of
        them.  Returns self."""
        self.__dict__["_constants"] = store
        return self

    def longest(self, count: int) -> "SegmentFeatures":
        """The ``count`` longest segments of each image (B, min(count, N), ...); padding stays last
        (weight 0)."""
        if count >= self.weight.shape[1]:
            return self
        return self._segments(top_indices(self.weight, count, dim=1))  # equal lengths in segment order

    def _segments(self, index: torch.Tensor, keep: torch.Tensor | None = None) -> "SegmentFeatures":
        """The segments ``index`` (B, M) int64 of each image, in that order: (B, M, ...); where
        ``keep`` (B, N) bool is given, the segments it leaves out become padding (weight 0, mask False)."""
        def take(x: torch.Tensor) -> torch.Tensor:
            shaped = index.view(index.shape + (1,) * (x.dim() - 2)).expand(index.shape + x.shape[2:])
            return torch.gather(x, 1, shaped)

        weight, mask = take(self.weight), take(self.mask)
        if keep is not None:
            mask = take(keep)
            weight = weight * mask
        return SegmentFeatures(take(self.line), take(self.along), take(self.half_length), weight, mask,
                               self.principal_point, self.long_side)

    def select(self, keep: torch.Tensor) -> "SegmentFeatures":
        """The segments where ``keep`` (B, N) bool holds, in their order, packed to the front:
        (B, M, ...) with M the largest count of an image; the rest is padding (weight 0, mask
        False)."""
        keep = keep & self.mask
        width = int(keep.sum(1).max()) if keep.numel() else 0
        return self._segments(top_indices(keep.to(torch.int8), width, dim=1), keep)  # kept first, in order

    def take_images(self, index: torch.Tensor) -> "SegmentFeatures":
        """Images ``index`` (M,) int64 of the batch, in that order, repeats allowed: (M, N, ...)
        (copies)."""
        def take(x: torch.Tensor) -> torch.Tensor:
            return x.index_select(0, index)

        return SegmentFeatures(take(self.line), take(self.along), take(self.half_length), take(self.weight),
                               take(self.mask), take(self.principal_point), take(self.long_side))

    def images(self, start: int, stop: int) -> "SegmentFeatures":
        """Images ``start:stop`` of the batch (views, no copies)."""
        if start == 0 and stop >= self.weight.shape[0]:
            return self
        return SegmentFeatures(self.line[start:stop], self.along[start:stop], self.half_length[start:stop],
                               self.weight[start:stop], self.mask[start:stop], self.principal_point[start:stop],
                               self.long_side[start:stop])


def incidence(rows: torch.Tensor, columns: torch.Tensor, out: torch.Tensor | None = None,
              tmp: torch.Tensor | None = None) -> torch.Tensor:
    """``rows @ columns`` for (B, R, 3) segment rows (``line`` or ``along`` coefficients) and (B, 3, M)
    homogeneous points: (B, R, M), every entry ``r_0 c_0 + r_1 c_1 + r_2 c_2`` with one rounding per
    product and sum (:func:`fr_torch.core.exact.dot3`'s order), not a matrix product, so a segment's
    s and t are the same bits in any batch, chunk and kernel set.  ``out`` / ``tmp``: optional
    buffers of the result's shape (the grid reuses them)."""
    if out is None:  # functional (differentiable); the same operations in the same order
        return dot3(rows[:, :, None, :], columns.transpose(1, 2)[:, None, :, :])
    torch.mul(rows[:, :, 0, None], columns[:, None, 0], out=out)
    tmp = tmp if tmp is not None else torch.empty_like(out)
    for c in (1, 2):
        out.add_(torch.mul(rows[:, :, c, None], columns[:, None, c], out=tmp))
    return out


def incidence_of(features: SegmentFeatures, rotation: torch.Tensor, focal: torch.Tensor):
    """s = l . v and t = g . v for the homogeneous VPs v = K R[:, k].

    Returns s, t with shape (B, N, H, 3) (segments before hypotheses) and v3 with shape (B, 1, H, 3).
    """
    vps = vanishing_points(focal, features.principal_point[:, None, :], rotation)  # (B, H, 3, 3)
    batch, hyp = vps.shape[:2]
    flat = vps.permute(0, 2, 1, 3).reshape(batch, 3, hyp * 3)  # (B, 3 coords, H * 3 VPs)
    s = incidence(features.line, flat).view(batch, -1, hyp, 3)
    t = incidence(features.along, flat).view(batch, -1, hyp, 3)
    return s, t, vps[:, None, :, 2, :]


def deviations_from_incidence(measure: str, s: torch.Tensor, t: torch.Tensor, v3: torch.Tensor,
                              features: SegmentFeatures, focal: torch.Tensor,
                              range_px: float = RANGE_PX) -> torch.Tensor:
    """Deviation of every segment from every VP, internal units (rad or px).

    ``s``, ``t``: (B, N, H, 3); ``v3``: (B, 1, H, 3); ``focal``: (B, H).  Returns (B, N, H, 3).
    """
    abs_s = s.abs()
    if measure == "a":
        return range_px * abs_s / (torch.maximum(abs_s, range_px * v3.abs()) + _TINY)
    if measure == "e":
        # |n| for n = K^T l: (f l_x, f l_y, l . (c, 1)) with (l_x, l_y) a unit vector; |D| = |R[:, k]| = 1.
        pp_h = torch.cat([features.principal_point, torch.ones_like(features.principal_point[:, :1])], -1)
        offset = (features.line * pp_h[:, None, :]).sum(-1)
        normal_sq = (focal[:, None, :] ** 2 + offset[:, :, None] ** 2)[..., None]  # (B, N, H, 1)
        # asin(|s| / |n|) written as atan2(|s|, sqrt(|n|^2 - s^2)): the same angle, but finite with a
        # finite gradient in float32 where |s| / |n| rounds to 1 (asin' = inf there -> NaN parameters).
        cos_part = exact_math.sqrt((normal_sq - abs_s * abs_s).clamp_min(normal_sq * 1e-12))
        return angle_of(abs_s, cos_part)
    abs_t = t.abs()
    # A midpoint exactly on the VP (s = t = 0) gets angle 0 with a finite gradient.
    angle = angle_of(abs_s, torch.where((abs_s == 0) & (abs_t == 0), torch.ones_like(abs_t), abs_t))
    if measure == "b":
        return angle
    half = features.half_length[:, :, None, None]
    if measure == "c":
        return half * exact_math.sin(angle)
    if measure == "d":
        return torch.minimum(half * exact_math.tan(angle.clamp(max=math.pi / 2 - 1e-6)), half)
    raise ValueError(f"unknown deviation measure {measure!r}")


def deviations(measure: str, endpoints: torch.Tensor, vps: torch.Tensor, focal: torch.Tensor,
               principal_point: torch.Tensor, mask: torch.Tensor | None = None,
               range_px: float = RANGE_PX) -> torch.Tensor:
    """Deviation of segments (B, N, 4) from homogeneous VPs ``vps`` (B, H, 3, 3; column k = VP k).

    ``focal`` (B, H) and ``principal_point`` (B, 2) in pixels (needed by measure e).  Returns
    (B, H, N, 3) in radians (b, e) or pixels (a, c, d).
    """
    features = SegmentFeatures.from_endpoints(endpoints, mask, principal_point)
    if measure == "e":  # normalise so that |K^-1 v| = 1, as for a column of R
        pp = features.principal_point[:, None, :, None]
        direction = torch.stack([(vps[:, :, 0] - pp[..., 0, :] * vps[:, :, 2]) / focal[..., None],
                                 (vps[:, :, 1] - pp[..., 1, :] * vps[:, :, 2]) / focal[..., None],
                                 vps[:, :, 2]], -2)
        vps = vps / exact_math.sqrt(small_sum(direction * direction, -2))[:, :, None, :]
    columns = vps.transpose(-1, -2)[:, None]  # (B, 1, H, 3 VPs, 3 coordinates)
    s = dot3(features.line[:, :, None, None, :], columns)
    t = dot3(features.along[:, :, None, None, :], columns)
    x = deviations_from_incidence(measure, s, t, vps[:, None, :, 2, :], features, focal, range_px)
    return x.transpose(1, 2)
