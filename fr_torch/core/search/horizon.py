"""The horizon fit: the vertical first, then f and the horizontal directions on its horizon.

A second estimator of f and R beside fR's Manhattan mixture (:mod:`fr_torch.core.search.passes`), built
for the horizon's height on street photos, after the front end of Lee, Hebert & Kanade (CVPR
2009) and on the same segments, batch, devices and exact sums:

1. **Vertical vanishing point** (an image point; f is not needed): every pair of the
   ``vertical_proposers`` longest near-vertical segments (within ``vertical_max_deg`` of the image
   vertical) proposes the point where their lines meet; a point scores the truncated vote of the
   near-vertical segments (below), the best is refined by weighted least squares on its inliers
   (``vertical_rounds`` rounds).
2. **Focal sweep on the horizon**: for each of ``focal_steps`` focal lengths, log-spaced over the
   search box, the vertical fixes the vertical direction and so the horizon; every one of the
   ``proposers`` longest other segments meets the horizon in a candidate first horizontal vanishing
   point, orthogonality gives the second; the orthogonal triplet scores the truncated vote of the
   ``voters`` longest segments for any of its three points.  The best (f, triplet) wins.
3. **Refinement** of pan, pitch, roll and log f inside the search box (Adam, ``refine_iterations``
   steps) on the smooth form of the vote, ``sum_i l_i max_j exp(-sin^2(e_ij) / (2 sin^2(kernel)))``.

The **truncated vote** of a segment for a vanishing point is ``max(0, 1 - sin^2(e) / sin^2(inlier))``
with ``e`` the angle between the segment and the line from its midpoint to the point (deviation
measure b): a segment further than ``inlier_deg`` from every point votes nothing, so a family that
does not meet the horizon (an inclined street, a sloped roof) is left out instead of pulling the
horizon towards it, as it does through the mixture's smooth shares.

What the estimator reports from the fit (:func:`choose_fit`, ``SearchConfig.fit``) is its
**horizon**, on the camera with the Manhattan fit's focal length (more accurate than the sweep's:
3.7 % against 8.4 % mean error on YUD test) and horizontal directions (:func:`fit_on_horizon`);
``choose`` takes it where a rule learned on a train split (:class:`HorizonChooser`) finds the
photo's evidence (:func:`choice_features`) in its favour.  Settings:
:class:`fr_torch.core.settings.config.HorizonFitConfig` (the names in double back-quotes above).

Conventions: :mod:`fr_torch.core.geometry.conventions` (pixels, x right / y down; R world->camera with the
vertical, pointing down, in column 1).  The stages work in normalised coordinates
``(p - principal point) / long side``, where the vanishing point of a direction ``d`` is
``(phi d_x, phi d_y, d_z)`` with ``phi = f / long side``.  Sums over segments are
:func:`fr_torch.core.exact.exact_sum`, ties go to the lowest index: an image's fit is the same bits
in any batch, on any thread count and kernel set.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from fr_torch.core.exact import atan2, cross3, dot3, exact_sum, first_argmax, top_indices
from fr_torch.core.geometry.conventions import rotation_from_cos_sin
from fr_torch.core.geometry.params import FOCAL, PITCH, ROLL, angles_from_search_rotation
from fr_torch.core.likelihood.measures import SegmentFeatures
from fr_torch.core.search.grid import into_box, log_spaced_focals
from fr_torch.core.search.refine import UnitBox, adam_in_box, camera_vps, chain_to_params
from fr_torch.core.settings.config import HorizonFitConfig


@dataclass
class HorizonFit:
    """The horizon fit of a batch: ``params`` (B, 4) [pan, pitch, roll (degrees), f (pixels)] float64;
    ``found`` (B,) bool, False where no vertical vanishing point could be proposed (fewer than two
    near-vertical segments): ``params`` is then the box's centre.  Its smooth vote:
    :func:`horizon_vote`."""

    params: torch.Tensor
    found: torch.Tensor


def normalised_lines(features: SegmentFeatures) -> tuple[torch.Tensor, torch.Tensor]:
    """The segments' ``line`` and ``along`` (B, N, 3) in normalised coordinates
    ``(p - principal point) / long side``, float64 (first two entries unchanged)."""
    pp = features.principal_point.to(torch.float64)[:, None, :]  # (B, 1, 2)
    scale = features.long_side.to(torch.float64)[:, None]  # (B, 1)

    def convert(rows: torch.Tensor) -> torch.Tensor:
        rows = rows.to(torch.float64)
        offset = (rows[..., 0] * pp[..., 0] + rows[..., 1] * pp[..., 1] + rows[..., 2]) / scale
        return torch.stack([rows[..., 0], rows[..., 1], offset], -1)

    return convert(features.line), convert(features.along)


def truncated_vote(s: torch.Tensor, t: torch.Tensor, sin2_inlier: float) -> torch.Tensor:
    """``max(0, 1 - sin^2(e) / sin^2(inlier))`` with ``sin^2(e) = s^2 / (s^2 + t^2)`` (s, t: the
    incidences of a segment's ``line`` and ``along`` with a vanishing point); 0 where s = t = 0."""
    s2 = s * s
    total = s2 + t * t
    sin2 = torch.where(total > 0, s2 / torch.where(total > 0, total, torch.ones_like(total)), torch.ones_like(total))
    return (1.0 - sin2 / sin2_inlier).clamp_min(0.0)


def _gather(x: torch.Tensor, index: torch.Tensor) -> torch.Tensor:
    """Rows ``index`` (B, M) of x (B, N, ...) -> (B, M, ...)."""
    shaped = index.view(index.shape + (1,) * (x.dim() - 2)).expand(index.shape + x.shape[2:])
    return torch.gather(x, 1, shaped)


def unit(x: torch.Tensor) -> torch.Tensor:
    return x / torch.sqrt(dot3(x, x)).clamp_min(1e-300)[..., None]


def in_box(point: torch.Tensor, phi: torch.Tensor, lower: torch.Tensor, upper: torch.Tensor) -> torch.Tensor:
    """Whether normalised vertical points (B, Q, 3) are the vertical of a camera in the box at the
    normalised focal length ``phi`` (B, 1): roll (the angle of the point's direction from the
    principal point to the image's y axis; no f needed) and pitch (it grows with f) within the box
    ``lower`` / ``upper`` (B, 4), 1 degree of slack.  (B, Q) bool."""
    down = _vertical_direction_at(point, phi)
    roll = torch.rad2deg(atan2(down[..., 0], down[..., 1]))
    pitch = torch.rad2deg(torch.asin((-down[..., 2]).clamp(-1.0, 1.0)))
    return pitch_roll_in_box(pitch, roll, lower[:, None], upper[:, None], slack=1.0)


def pitch_roll_in_box(pitch: torch.Tensor, roll: torch.Tensor, lower: torch.Tensor, upper: torch.Tensor,
                      slack: float = 0.0) -> torch.Tensor:
    """Whether pitch and roll (degrees, any shape) lie in the box ``lower`` / ``upper`` (rows
    [pan, pitch, roll, f] broadcastable to them), widened by ``slack`` degrees either side."""
    lower, upper = lower - slack, upper + slack
    return (roll >= lower[..., ROLL]) & (roll <= upper[..., ROLL]) & (pitch >= lower[..., PITCH]) \
        & (pitch <= upper[..., PITCH])


def vertical_point(line: torch.Tensor, along: torch.Tensor, weight: torch.Tensor, mask: torch.Tensor,
                   lower: torch.Tensor, upper: torch.Tensor, long_side: torch.Tensor,
                   config: HorizonFitConfig) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Stage 1: the vertical vanishing point of each image, normalised homogeneous (B, 3) unit,
    the vote of every segment for it (B, N) and whether one was found (B,) bool.

    ``line``, ``along``: (B, N, 3) normalised (:func:`normalised_lines`); ``weight`` (B, N) pixels;
    ``lower`` / ``upper`` (B, 4) the search box (a proposed point must be the vertical of a camera
    in it at the box's shortest focal length, :func:`in_box`), ``long_side`` (B,) pixels."""
    weight = weight.to(torch.float64)
    near = mask & (along[..., 0].abs() <= math.sin(math.radians(config.vertical_max_deg)))
    sin2_inlier = math.sin(math.radians(config.inlier_deg)) ** 2
    count = min(config.vertical_proposers, line.shape[1])
    index = top_indices(torch.where(near, weight, torch.full_like(weight, -1.0)), count, dim=1)  # (B, P)
    proposer_ok = _gather(near, index)
    first, second = torch.triu_indices(count, count, 1, device=line.device)
    lines = _gather(line, index)
    points = cross3(lines[:, first], lines[:, second])  # (B, Q, 3)
    size = torch.sqrt(dot3(points, points))
    pair_ok = proposer_ok[:, first] & proposer_ok[:, second] & (size > 1e-12)
    points = points / torch.where(pair_ok, size, torch.ones_like(size))[..., None]
    phi_min = (lower[:, FOCAL] / long_side)[:, None]
    pair_ok &= in_box(points, phi_min, lower, upper)
    near_weight = weight * near
    bound = weight.amax(1)[:, None, None]  # (B, 1, 1): each image's longest segment
    voters = top_indices(torch.where(near, weight, torch.full_like(weight, -1.0)), min(config.voters, line.shape[1]),
                         dim=1)  # the longest near-vertical segments vote for the proposals
    voter_line, voter_along = _gather(line, voters)[:, None], _gather(along, voters)[:, None]
    votes = truncated_vote(dot3(voter_line, points[:, :, None]), dot3(voter_along, points[:, :, None]),
                           sin2_inlier)  # (B, Q, V)
    scores = exact_sum(votes, -1, bound=bound, weight=_gather(near_weight, voters)[:, None])
    scores = torch.where(pair_ok, scores, torch.full_like(scores, -math.inf))
    best = first_argmax(scores, 1)
    point = points.gather(1, best[:, None, None].expand(-1, 1, 3))[:, 0]  # (B, 3)
    found = pair_ok.any(1)
    for _ in range(config.vertical_rounds):  # least squares on the inliers: min sum w (line . v)^2, |v| = 1
        vote = truncated_vote(dot3(line, point[:, None]), dot3(along, point[:, None]), sin2_inlier)
        inlier_weight = near_weight * (vote > 0)
        outer = line[..., :, None] * line[..., None, :]  # (B, N, 3, 3)
        moment = exact_sum(outer, 1, bound=bound[..., None], weight=inlier_weight[..., None, None])  # (B, 3, 3)
        # the smallest eigenvector of the moment: power iteration on its adjugate (rows = cross products)
        adjugate = torch.stack([cross3(moment[:, 1], moment[:, 2]), cross3(moment[:, 2], moment[:, 0]),
                                cross3(moment[:, 0], moment[:, 1])], 1)
        candidate = point
        for _ in range(8):
            candidate = unit(torch.stack([dot3(adjugate[:, i], candidate) for i in range(3)], -1))
        usable = (inlier_weight > 0).sum(1) >= 2
        usable &= torch.isfinite(candidate).all(-1) & (dot3(candidate, candidate) > 0.5)
        point = torch.where(usable[:, None], candidate, point)
    vote = truncated_vote(dot3(line, point[:, None]), dot3(along, point[:, None]), sin2_inlier) * near
    return point, vote, found


def _vertical_direction_at(point: torch.Tensor, phi: torch.Tensor) -> torch.Tensor:
    """Unit vertical directions, pointing down (y >= 0), of normalised vertical points (B, Q, 3) at
    normalised focal lengths ``phi`` (B, 1) (-> (B, Q, 3)) or of points (B, 1, 3) at ``phi`` (B, F)
    (-> (B, F, 3))."""
    x, y = point[..., 0] / phi, point[..., 1] / phi
    d = unit(torch.stack([x, y, point[..., 2].expand_as(x)], -1))
    return torch.where(d[..., 1:2] < 0, -d, d)


def _vertical_direction(point: torch.Tensor, phi: torch.Tensor) -> torch.Tensor:
    """Unit vertical direction (B, F, 3), pointing down (y >= 0), of the normalised vertical point
    (B, 3) at normalised focal lengths ``phi`` (B, F)."""
    return _vertical_direction_at(point[:, None], phi)


def _triplets(vertical: torch.Tensor, phi: torch.Tensor, proposer_lines: torch.Tensor):
    """The orthogonal triplets proposed on each focal's horizon: (first, second) horizontal unit
    directions (B, F, P, 3).  ``vertical`` (B, F, 3), ``phi`` (B, F), ``proposer_lines`` (B, P, 3)
    normalised."""
    x_axis = torch.zeros_like(vertical)
    x_axis[..., 0] = 1.0
    e1 = unit(x_axis - vertical[..., 0:1] * vertical)
    e2 = cross3(vertical, e1)
    horizon = torch.stack([vertical[..., 0] / phi, vertical[..., 1] / phi, vertical[..., 2]], -1)  # (B, F, 3)
    meet = cross3(proposer_lines[:, None], horizon[:, :, None])  # (B, F, P, 3)
    direction = torch.stack([meet[..., 0] / phi[..., None], meet[..., 1] / phi[..., None], meet[..., 2]], -1)
    theta = torch.remainder(atan2(dot3(direction, e2[:, :, None]), dot3(direction, e1[:, :, None])), math.pi / 2)
    cos, sin = torch.cos(theta)[..., None], torch.sin(theta)[..., None]
    first = cos * e1[:, :, None] + sin * e2[:, :, None]
    second = cos * e2[:, :, None] - sin * e1[:, :, None]  # vertical x first
    return first, second


def _point_of(direction: torch.Tensor, phi: torch.Tensor) -> torch.Tensor:
    """Normalised vanishing point (..., 3) of unit directions (B, F, P, 3) at ``phi`` (B, F)."""
    phi = phi[..., None]
    return torch.stack([direction[..., 0] * phi, direction[..., 1] * phi, direction[..., 2]], -1)


def fit_horizon(features: SegmentFeatures, lower: torch.Tensor, upper: torch.Tensor,
                config: HorizonFitConfig = HorizonFitConfig(), periodic_pan: bool = False) -> HorizonFit:
    """The horizon fit (module docstring) of every image of ``features`` inside the search box
    ``lower`` / ``upper`` (B, 4) [pan, pitch, roll (degrees), f (pixels)] (a known focal length:
    equal bounds)."""
    line, along = normalised_lines(features)
    weight = features.weight.to(torch.float64)
    long_side = features.long_side.to(torch.float64)
    mask = features.mask & (weight >= config.min_length * long_side[:, None])
    weight = weight * mask
    batch = line.shape[0]
    lower64, upper64 = lower.to(line), upper.to(line)
    point, vertical_vote, found = vertical_point(line, along, weight, mask, lower64, upper64, long_side, config)
    focal = log_spaced_focals(lower64[:, FOCAL], upper64[:, FOCAL], config.focal_steps)  # (B, F)
    phi = focal / long_side[:, None]
    vertical = _vertical_direction(point, phi)
    focal_ok = in_box(point[:, None], phi, lower64, upper64)  # (B, F): the vertical's pitch in the box

    others = mask & (vertical_vote <= 0)
    proposer_count = min(config.proposers, line.shape[1])
    proposers = top_indices(torch.where(others, weight, torch.full_like(weight, -1.0)), proposer_count, dim=1)
    proposer_ok = _gather(others, proposers)  # (B, P)
    voter_count = min(config.voters, line.shape[1])
    voters = top_indices(weight, voter_count, dim=1)
    voter_line, voter_along = _gather(line, voters), _gather(along, voters)
    voter_weight, voter_vertical = _gather(weight, voters), _gather(vertical_vote, voters)
    bound = weight.amax(1)
    sweep_dtype = features.weight.dtype
    sin2_inlier = math.sin(math.radians(config.inlier_deg)) ** 2

    per_image = max(1, config.focal_steps * proposer_count * voter_count)
    step = max(1, config.chunk_elements // per_image)
    best_focal = torch.zeros(batch, dtype=torch.long, device=line.device)
    best_first = torch.zeros(batch, 3, dtype=torch.float64, device=line.device)
    best_vote = torch.zeros(batch, dtype=torch.float64, device=line.device)
    for b0 in range(0, batch, step):
        b1 = min(batch, b0 + step)
        first, second = _triplets(vertical[b0:b1], phi[b0:b1], _gather(line, proposers)[b0:b1])
        # the votes in the features' dtype (float32 by default: half the memory traffic of float64)
        rows_l = voter_line[b0:b1, None, None].to(sweep_dtype)  # (b, 1, 1, V, 3)
        rows_a = voter_along[b0:b1, None, None].to(sweep_dtype)
        votes = voter_vertical[b0:b1, None, None].to(sweep_dtype).expand(first.shape[:3] + (voter_count,))
        for direction in (first, second):
            p = _point_of(direction, phi[b0:b1])[..., None, :].to(sweep_dtype)  # (b, F, P, 1, 3)
            votes = torch.maximum(votes, truncated_vote(dot3(rows_l, p), dot3(rows_a, p), sin2_inlier))
        scores = exact_sum(votes, -1, bound=bound[b0:b1, None, None, None],
                           weight=voter_weight[b0:b1, None, None].to(sweep_dtype))
        usable = proposer_ok[b0:b1, None] & focal_ok[b0:b1, :, None]  # (b, F, P)
        scores = torch.where(usable, scores, torch.full_like(scores, -math.inf))
        flat = first_argmax(scores.flatten(1), 1)
        f_index, p_index = flat // proposer_count, flat % proposer_count
        rows = torch.arange(b1 - b0, device=line.device)
        best_focal[b0:b1] = f_index
        best_first[b0:b1] = first[rows, f_index, p_index]
        best_vote[b0:b1] = scores.flatten(1)[rows, flat]
    rows = torch.arange(batch, device=line.device)
    down = vertical[rows, best_focal]
    rotation = torch.stack([best_first, down, cross3(best_first, down)], -1)  # columns: first, vertical, second
    params = torch.cat([angles_from_search_rotation(rotation), focal[rows, best_focal][:, None]], -1)
    found = found & torch.isfinite(best_vote) & proposer_ok.any(1)
    centre = (lower64 + upper64) / 2
    params = torch.where(found[:, None], into_box(params, lower64, upper64, periodic_pan), centre)
    if config.refine_iterations:
        params = refine_horizon(features, params, lower64, upper64, config, periodic_pan)
    return HorizonFit(params, found)


def _vps(params: torch.Tensor, features: SegmentFeatures):
    """Pixel vanishing points (B, L, 3 (VP), 3 (x, y, w)) of rows (B, L, 4), with the rotation and
    the angles' cosines and sines (the refinement's chain rule, :func:`fr_torch.core.search.refine.chain_to_params`)."""
    rad = torch.deg2rad(params[..., :3])
    cos, sin = torch.cos(rad), torch.sin(rad)
    rotation = rotation_from_cos_sin(cos, sin)
    focal = params[..., FOCAL]
    vps = camera_vps(rotation, focal, features.principal_point.to(params)[:, None, :])  # (B, L, coord, VP)
    return vps, rotation, cos, sin, focal


def _kernel_terms(features: SegmentFeatures, vps: torch.Tensor, config: HorizonFitConfig, gradient: bool):
    """Smooth vote ``sum_i l_i max_j exp(-sin^2 e_ij / (2 sin^2 kernel))`` (B, L) float64, or, with
    ``gradient``, its derivative with respect to the VPs (B, L, coord, VP) instead (the refinement
    needs only that)."""
    line = features.line.to(vps.dtype)[:, None, None]  # (B, 1, 1, N, 3)
    along = features.along.to(vps.dtype)[:, None, None]
    points = vps.transpose(-1, -2)[..., None, :]  # (B, L, VP, 1, 3)
    s, t = dot3(line, points), dot3(along, points)  # (B, L, VP, N)
    total = s * s + t * t
    safe = torch.where(total > 0, total, torch.ones_like(total))
    sin2 = torch.where(total > 0, s * s / safe, torch.ones_like(total))
    width = 2.0 * math.sin(math.radians(config.kernel_deg)) ** 2
    kernel = torch.exp(-sin2 / width)
    best = first_argmax(kernel, 2)  # (B, L, N)
    weight = features.weight.to(vps.dtype)[:, None]
    bound = features.weight.to(torch.float64).amax(1)[:, None, None]  # (B, 1, 1)
    if not gradient:
        return exact_sum(kernel.gather(2, best[:, :, None]).squeeze(2), -1, bound=bound, weight=weight)
    # d sin^2 / d v = 2 s t (t line - s along) / total^2; the chosen VP of each segment only
    owner = torch.nn.functional.one_hot(best, 3).permute(0, 1, 3, 2).to(vps.dtype)  # (B, L, VP, N)
    factor = kernel * (-1.0 / width) * 2.0 * s * t / (safe * safe) * owner * (total > 0)
    terms = factor[..., None] * (t[..., None] * line - s[..., None] * along)  # (B, L, VP, N, 3)
    grad = exact_sum(terms, 3, bound=(bound / math.sin(math.radians(config.kernel_deg)) ** 2)[..., None, None],
                     weight=weight[:, :, None, :, None])  # (B, L, VP, coord)
    return grad.transpose(-1, -2)


def horizon_vote(features: SegmentFeatures, params: torch.Tensor, config: HorizonFitConfig = HorizonFitConfig()):
    """The refinement's smooth vote (:func:`_kernel_terms`) of rows ``params`` (B, L, 4), (B, L)
    float64, pixels of segment length."""
    vps = _vps(params.to(torch.float64), features)[0]
    return _kernel_terms(features, vps, config, gradient=False)


def refine_horizon(features: SegmentFeatures, params: torch.Tensor, lower: torch.Tensor, upper: torch.Tensor,
                   config: HorizonFitConfig, periodic_pan: bool) -> torch.Tensor:
    """Adam on the smooth vote from ``params`` (B, 4) inside the box (B, 4) (the refinement loop
    of every fit, :func:`~fr_torch.core.search.refine.adam_in_box`, with its own step sizes and no
    stopping rule); float64 (B, 4)."""
    box = UnitBox(lower[:, None], upper[:, None])
    u = box.to_unit(params[:, None])
    total = features.total_length().clamp_min(1e-9)[:, None]

    def gradient(u_value):
        vps, rotation, cos, sin, focal = _vps(box.to_params(u_value), features)
        grad_v = _kernel_terms(features, vps, config, gradient=True)
        return None, chain_to_params(vps, rotation, cos, sin, focal, grad_v * (-1.0 / total)[..., None, None]) * box.span

    cell = 1.0 / 8
    adam_in_box(u, box, config.refine_iterations, 0.1 * cell, 0.005 * cell, gradient, periodic_pan)
    return box.to_params(u)[:, 0]


