"""Two-stage search for (f, R): a k^4 grid, then batched refinement of the best l grid points.

Stage 1 scores every grid hypothesis (pan x pitch x roll x focal, k values each, cell centres
of the ranges; focal spaced uniformly in log f over the FOV range by default) as
one batched tensor computation, chunked so that at most ``max_chunk_elements`` per-segment
deviations exist at once.  Each of the best ``top_l`` grid points gains a second start, its best
point along its focal ridge (:func:`sweep_focal`: the vertical VP, the best-determined, held
fixed while f runs over the whole range); all 2l starts are then sharpened by ``grid_passes``
coarse-to-fine passes (:func:`subdivide_starts`: a 3^4 lattice at a third of the previous spacing
around each, keep the best), so refinement starts within 1/27 of a grid cell of the best lattice
point instead of half a cell.  Stage 2 refines these starts of every image together
with ``torch.optim`` (Adam on box-normalised parameters, projected back into the box after every
step), focal length included (the MATLAB release pins f to its grid value; we refine it
continuously, as the paper does).  each mode runs its ``refine_iterations`` (fR 100 with a decaying step size, Fast-fR
10; :data:`fr_torch.core.config.MODE_PRESETS`).  Each hypothesis' update depends only on its own gradient, so a
batch gives the same answer as images one by one.

Speed and memory (same math; see also :mod:`fr_torch.core.likelihood`):

* Grid: with the fused CPU kernel (:mod:`fr_torch.core.native`, which stores no deviations) the
  hypotheses of an image slice are scored in one call; on the torch path on CPU in cache-sized
  chunks (``CPU_CHUNK_ELEMENTS`` deviations, a few MB of buffers) that reuse the same buffers,
  instead of ``max_chunk_elements`` (which still bounds the chunk on GPU and caps it on CPU);
  rotations / vanishing points are built once per image slice, not per chunk.  Large batches are
  cut into image slices, so memory stays bounded for any batch size.  No chunk size depends on the
  thread count: a search takes the same path whatever threads the load leaves it
  (``FR_THREADS=auto``), in a worker process or not.
* Refinement: images are refined in independent slices of at most ``max_chunk_elements``
  (``CPU_REFINE_ELEMENTS`` on CPU) deviations per step (identical results: every image's loss and
  Adam update are its own), and the rotation is built in closed form
  (``R.T = Ry(pan) Rx(pitch) Rz(roll)``, equal to :func:`fr_torch.core.camera.rotation_from_angles`
  to rounding) with fewer, smaller autograd nodes.
  The iteration counts and step-size schedule are unchanged.
"""
from __future__ import annotations

import math

import torch

from fr_torch.core.camera import (
    VERTICAL_AXIS,
    focal_from_hfov,
    pan_from_rotation,
    rotation_from_cos_sin,
)
from fr_torch.core.config import SearchConfig
from fr_torch.core.exact import atan2, cross3, dot3, exact_sum, first_argmax, small_matmul, small_sum, top_indices
from fr_torch.core.likelihood import (
    MixtureLikelihood,
    SegmentFeatures,
    compiled_call,
    measure_b_backward,
    measure_b_forward,
    measure_b_objective_and_grad,
    vp_major,
)
from fr_torch.core.params import (
    ANGLES,
    DISTORTION,
    FOCAL,
    PAN,
    from_log_focal,
    rotations,
    to_log_focal,
)

# Grid deviations per chunk on CPU, whatever the thread count: float32 buffers of a few MB, 32 of
# torch's 2^15-element grains (up to 32 threads share every op).  Scores are the same for any chunk
# size (results/DECISIONS.md, results/decisions/60.md).
CPU_CHUNK_ELEMENTS = 1 << 20
CPU_REFINE_ELEMENTS = 1 << 20  # deviations per refinement slice on CPU (~25 live tensors of 4 MB)


def _cell_centres(low: float, high: float, k: int) -> torch.Tensor:
    return low + (torch.arange(k, dtype=torch.float64) + 0.5) * (high - low) / k


def parameter_box(config: SearchConfig, long_side: torch.Tensor, known_focal: torch.Tensor | None):
    """Lower and upper bounds, (B, 4) float64, of [pan, pitch, roll, focal] per image.

    ``long_side``: (B,) the longer image side in pixels (``max(width, height)``).
    """
    f_lo, f_hi = config.fov_range.focal_bounds(long_side)
    if known_focal is not None:
        f_lo = f_hi = known_focal.to(torch.float64)
    lo = torch.stack([torch.full_like(f_lo, config.pan_range_deg[0]), torch.full_like(f_lo, config.pitch_range_deg[0]),
                      torch.full_like(f_lo, config.roll_range_deg[0]), f_lo], -1)
    hi = torch.stack([torch.full_like(f_hi, config.pan_range_deg[1]), torch.full_like(f_hi, config.pitch_range_deg[1]),
                      torch.full_like(f_hi, config.roll_range_deg[1]), f_hi], -1)
    return lo, hi


def into_box(points: torch.Tensor, lower: torch.Tensor, upper: torch.Tensor, periodic_pan: bool) -> torch.Tensor:
    """``points`` (..., 4) [pan, pitch, roll, f or log f] moved into the box [``lower``, ``upper``]
    (broadcastable to ``points``): clamped, but for pan when ``periodic_pan``
    (:attr:`SearchConfig.periodic_pan`), which is wrapped into [lower, upper) instead."""
    boxed = torch.minimum(torch.maximum(points, lower), upper)
    if not periodic_pan:
        return boxed
    pan_low, pan_span = lower[..., :1], (upper - lower)[..., :1]
    return torch.cat([pan_low + torch.remainder(points[..., :1] - pan_low, pan_span), boxed[..., 1:]], -1)


def log_spaced_focals(f_lo: torch.Tensor, f_hi: torch.Tensor, count: int) -> torch.Tensor:
    """``count`` focal lengths per image, (B, count) float64 pixels, at the centres of ``count``
    equal cells in log f between ``f_lo`` and ``f_hi`` ((B,) float64 pixels)."""
    fraction = (torch.arange(count, dtype=torch.float64, device=f_lo.device) + 0.5) / count
    return torch.exp(f_lo.log()[:, None] + fraction * (f_hi / f_lo).log()[:, None])


def focal_grid(config: SearchConfig, long_side: torch.Tensor) -> torch.Tensor:
    """The k stage-1 focal values per image, (B, k) float64 pixels, at cell centres of the range,
    spaced per ``config.focal_grid`` (linear in f, in log f, or in FOV)."""
    k = config.grid_points_per_dim
    frac = (torch.arange(k, dtype=torch.float64, device=long_side.device) + 0.5) / k
    long_side = long_side.to(torch.float64)
    if config.focal_grid == "fov":
        lo, hi = config.fov_range
        fov = torch.tensor(hi, dtype=torch.float64) - frac * (hi - lo)  # wide -> narrow: f ascending
        return focal_from_hfov(fov[None, :], long_side[:, None])
    f_lo, f_hi = config.fov_range.focal_bounds(long_side)
    if config.focal_grid == "log_f":
        return log_spaced_focals(f_lo, f_hi, k)
    return f_lo[:, None] + frac * (f_hi - f_lo)[:, None]


def grid_hypotheses(config: SearchConfig, long_side: torch.Tensor, known_focal: torch.Tensor | None = None):
    """Grid of [pan, pitch, roll, focal] per image: (B, G, 4) float64, G = k^4 (k^3 with known f),
    on the device of ``known_focal`` if given, else of ``long_side``.

    ``long_side``: (B,) the longer image side in pixels.  Order: focal slowest, then pitch, roll,
    pan fastest -- runs of k hypotheses differing only in pan share the vertical VP (pan turns the
    camera about the vertical), which :func:`score_grid` scores once per run (``vertical_block``).
    """
    k = config.grid_points_per_dim
    if known_focal is not None:
        focal = known_focal.to(torch.float64)[:, None]
    else:
        focal = focal_grid(config, long_side)
    pan = _cell_centres(*config.pan_range_deg, k)
    pitch = _cell_centres(*config.pitch_range_deg, k)
    roll = _cell_centres(*config.roll_range_deg, k)
    # (k^3, 3) as [pan, pitch, roll], on the device of the inputs (a GPU batch's grid is built there:
    # 128 KB per image, 0.5 GB for 4096 images, is not worth a host->device copy)
    angles = torch.cartesian_prod(pitch, roll, pan)[:, [2, 0, 1]].to(focal.device)
    batch, n_focal = focal.shape
    hyp = torch.cat([angles.expand(batch, n_focal, -1, -1),
                     focal[:, :, None, None].expand(-1, -1, angles.shape[0], 1)], -1)
    return hyp.reshape(batch, -1, 4)


def select_starts(config: SearchConfig, grid_scores: torch.Tensor, hypotheses: torch.Tensor):
    """Stage-2 starting points: the ``top_l`` best grid points, best first.

    ``grid_scores`` (B, G) and ``hypotheses`` (B, G, 4) as from :func:`grid_hypotheses` (or rows of
    5 with k, :mod:`fr_torch.core.search_distortion`).
    Returns (starts (B, L, 4 or 5), their scores (B, L)), L = min(top_l, G); equal scores are
    taken in grid order (:func:`fr_torch.core.exact.top_indices`).
    """
    index = top_indices(grid_scores, min(config.top_l, grid_scores.shape[1]), dim=1)
    return (torch.gather(hypotheses, 1, index[..., None].expand(-1, -1, hypotheses.shape[-1])),
            torch.gather(grid_scores, 1, index))


def grid_cell(config: SearchConfig, lower: torch.Tensor, upper: torch.Tensor) -> torch.Tensor:
    """Size of one stage-1 grid cell per image, (B, 4) float64: [pan, pitch, roll] in degrees and
    the focal step in log f (``log(f_max / f_min) / k``, the log-f grid's spacing; 0 for a known
    focal).  ``lower``, ``upper``: (B, 4) from :func:`parameter_box`."""
    k = config.grid_points_per_dim
    angles = (upper[:, ANGLES] - lower[:, ANGLES]) / k
    log_focal = (upper[:, 3:].log() - lower[:, 3:].log()) / k
    return torch.cat([angles, log_focal], -1)


def angles_from_search_rotation(rotation: torch.Tensor) -> torch.Tensor:
    """[pan, pitch, roll] in degrees, (..., 3), from world->camera R (..., 3, 3): the inverse of
    :func:`fr_torch.core.params.rotations` (``R.T = Ry(pan) Rx(pitch) Rz(roll)``) for |pitch| < 90 deg, pan folded
    into [-45, 45) (:func:`fr_torch.core.camera.pan_from_rotation`; the Manhattan frame is symmetric
    under quarter turns about the vertical)."""
    pitch = torch.rad2deg(torch.asin((-rotation[..., 2, 1]).clamp(-1.0, 1.0)))
    roll = torch.rad2deg(atan2(rotation[..., 0, 1], rotation[..., 1, 1]))
    return torch.stack([pan_from_rotation(rotation), pitch, roll], -1)


def _focal_ridge_rotations(rotation: torch.Tensor, ratio: torch.Tensor) -> torch.Tensor:
    """Rotations that keep the vertical VP's image position when f is multiplied by ``ratio``.

    ``rotation`` (..., 3, 3) world->camera (column i = world axis i in camera coordinates),
    ``ratio`` (..., m) = f_new / f.  A VP at pp + f (d_x, d_y) / d_z stays put when d_z scales
    with the ratio (a VP at infinity, d_z = 0, stays put by itself).  The vertical column is
    rescaled that way; the horizontal column whose VP lies nearer the image centre (larger |d_z|)
    is rescaled too and made orthogonal to the vertical (it moves as little as the orthogonality
    of the VPs allows); the third column completes a right-handed frame.  Returns (..., m, 3, 3).
    """
    def unit(d):
        return d / torch.sqrt(dot3(d, d))[..., None]

    def rescaled(direction):  # (..., 3) -> (..., m, 3), unit length
        d = direction[..., None, :].expand(ratio.shape + (3,))
        return unit(torch.cat([d[..., :2], d[..., 2:] * ratio[..., None]], -1))

    first_nearer = rotation[..., 2, 0].abs() >= rotation[..., 2, 2].abs()  # (...)
    horizontal = torch.where(first_nearer[..., None], rotation[..., :, 0], rotation[..., :, 2])
    vertical = rescaled(rotation[..., :, VERTICAL_AXIS])
    horizontal = rescaled(horizontal)
    horizontal = unit(horizontal - dot3(horizontal, vertical)[..., None] * vertical)
    first_nearer = first_nearer[..., None, None]
    column0 = torch.where(first_nearer, horizontal, cross3(vertical, horizontal))
    column2 = torch.where(first_nearer, cross3(horizontal, vertical), horizontal)
    return torch.stack([column0, vertical, column2], -1)


def sweep_focal(likelihood: MixtureLikelihood, features: SegmentFeatures, starts: torch.Tensor,
                scores: torch.Tensor, config: SearchConfig, lower: torch.Tensor, upper: torch.Tensor):
    """Add to each start its best point along its focal ridge: the best of
    ``config.focal_sweep_points`` focal values with the vertical VP held fixed.

    Focal length and pitch trade off along a ridge of the objective: the vertical VP (the family
    with the most segments and the smallest deviations) is pinned down well, its distance from
    the principal point, f / tan(pitch), much less its f and pitch apart.  A k^4 grid samples that
    ridge coarsely, so all ``top_l`` starts can sit on the wrong part of it (a 120 deg view found
    at 90 deg with 12 deg more pitch).  For every start this scores m focal values spaced
    uniformly in log f over the whole range, each with the start's vertical VP held fixed and
    its nearer horizontal VP moved as little as orthogonality allows
    (:func:`_focal_ridge_rotations`), at pan offsets 0 and +-1/3 of a grid cell.

    The swept points are added, not swapped in: a point that scores higher than its start can
    still lie in a lower basin, so both are refined.

    ``starts`` (B, L, 4) [pan, pitch, roll, f], ``scores`` (B, L), ``lower`` / ``upper`` (B, 4)
    the parameter box (points are moved into it by :func:`into_box`).  Returns (starts, scores) of shape (B, 2L, 4)
    and (B, 2L): the L inputs, then for each the best swept point if it beats the start's score,
    else a copy of the start.  Each start is swept on its own (a batch gives the same answer as
    images one by one).  A known focal (``lower`` f == ``upper`` f) or m = 0 returns the inputs.
    """
    count = config.focal_sweep_points
    if count == 0 or bool((upper[:, FOCAL] <= lower[:, FOCAL]).all()):
        return starts, scores
    device = features.weight.device
    batch, n_start = starts.shape[:2]
    start64 = starts.to(device=device, dtype=torch.float64)
    lower64 = lower.to(device=device, dtype=torch.float64)
    upper64 = upper.to(device=device, dtype=torch.float64)
    focal = log_spaced_focals(lower64[:, FOCAL], upper64[:, FOCAL], count)[:, None, :].expand(batch, n_start, count)
    rotation = _focal_ridge_rotations(rotations(start64), focal / start64[..., FOCAL:])  # (B, L, m, 3, 3)
    angles = angles_from_search_rotation(rotation)  # (B, L, m, 3)
    pan_step = (upper64[:, PAN] - lower64[:, PAN]) / (3 * config.grid_points_per_dim)  # 1/3 of a grid cell
    pan_offsets = torch.stack([torch.zeros_like(pan_step), -pan_step, pan_step], -1)  # (B, 3)
    points = torch.cat([angles, focal[..., None]], -1)[:, :, :, None, :].repeat(1, 1, 1, 3, 1)
    points[..., PAN] += pan_offsets[:, None, None, :]  # pan fastest: runs of 3 share the vertical VP
    points = into_box(points, lower64[:, None, None, None], upper64[:, None, None, None], config.periodic_pan)
    points = points.view(batch, n_start, -1, 4)
    point_scores = score_grid(likelihood, features, points.view(batch, -1, 4), config.max_chunk_elements,
                              vertical_block=3)
    swept, swept_scores = _keep_best(starts, scores, points, point_scores, tie_tolerance(features))
    return torch.cat([starts, swept], 1), torch.cat([scores, swept_scores], 1)


#: Scores of one image closer than this many nats per pixel of its segment length are ties.  The
#: objective's float32 terms differ by a few ulps between CPU families and devices (its sums are
#: exact, :mod:`fr_torch.core.exact`), which moves a score by well under this; a choice between tied
#: candidates follows their order, not their last bits.
TIE_NATS_PER_PX = 2.0 ** -20
#: Two solutions of one image are different answers (not the same basin reached twice) when their
#: focal lengths differ by more than this share or an angle by more than SOLUTION_ANGLE_DEG.
SOLUTION_FOCAL = 0.01
SOLUTION_ANGLE_DEG = 0.5


def tie_tolerance(segments) -> torch.Tensor:
    """(B,) float64: the score difference below which two hypotheses of an image are tied, nats
    (:data:`TIE_NATS_PER_PX` times the image's total segment length).  ``segments``: a
    :class:`~fr_torch.core.likelihood.SegmentFeatures` or a
    :class:`~fr_torch.core.search_distortion.SegmentGeometry` (their (B, N) ``weight``, pixels)."""
    return exact_sum(segments.weight, 1) * TIE_NATS_PER_PX


def near_best(scores: torch.Tensor, tolerance: torch.Tensor) -> torch.Tensor:
    """(..., C) bool: the candidates of ``scores`` (..., C) within ``tolerance`` (broadcastable to
    ``scores[..., 0]``) of the best along the last dimension (NaN scores never are)."""
    best = torch.where(torch.isnan(scores), -math.inf, scores).amax(-1, keepdim=True)
    return scores >= best - tolerance.to(best)[..., None]


def first_near_best(scores: torch.Tensor, tolerance: torch.Tensor) -> torch.Tensor:
    """Index along the last dimension of ``scores`` (..., C) of the first candidate within
    ``tolerance`` (broadcastable to ``scores[..., 0]``) of the best: int64 (...).  The choice does
    not move with the scores' last bits unless a candidate sits right at the tolerance's edge."""
    return first_argmax(near_best(scores, tolerance).to(torch.int8), -1)


def different_solutions(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """(...) bool: parameter rows a, b (..., 4 or 5) [pan, pitch, roll (deg), f (px), k] are different
    answers (:data:`SOLUTION_FOCAL`, :data:`SOLUTION_ANGLE_DEG`; pan compared modulo 90 deg, k by
    0.02)."""
    angles = (a[..., ANGLES] - b[..., ANGLES]).abs()
    pan = torch.remainder(angles[..., 0], 90.0)
    angles = torch.cat([torch.minimum(pan, 90.0 - pan)[..., None], angles[..., 1:]], -1)
    apart = (angles > SOLUTION_ANGLE_DEG).any(-1) | ((a[..., FOCAL] / b[..., FOCAL]).log().abs() > SOLUTION_FOCAL)
    if a.shape[-1] > DISTORTION:
        apart = apart | ((a[..., DISTORTION] - b[..., DISTORTION]).abs() > 0.02)
    return apart


def _keep_best(starts: torch.Tensor, scores: torch.Tensor, points: torch.Tensor, point_scores: torch.Tensor,
               tolerance: torch.Tensor):
    """Each start's best candidate where it scores higher than the start by more than ``tolerance``,
    else the start.

    ``starts`` (B, L, 4) with ``scores`` (B, L); ``points`` (B, L, P, 4) candidates per start with
    their ``point_scores`` (B, L * P) from :func:`score_grid`; ``tolerance`` (B,) nats
    (:func:`tie_tolerance`): the first candidate within it of the best is taken.  Returns (starts,
    scores), same shapes and dtypes as the inputs.
    """
    candidate_scores = point_scores.view(scores.shape + (-1,))
    tolerance = tolerance.to(candidate_scores)[:, None]  # (B, 1)
    best = first_near_best(candidate_scores, tolerance)
    best_scores = torch.gather(candidate_scores, -1, best[..., None])[..., 0]
    better = best_scores > scores + tolerance
    chosen = torch.gather(points, 2, best[..., None, None].expand(-1, -1, 1, points.shape[-1]))[:, :, 0]
    return torch.where(better[..., None], chosen.to(starts), starts), torch.where(better, best_scores, scores)


def best_of_start_and_refined(starts: torch.Tensor, start_scores: torch.Tensor, refined: torch.Tensor,
                              refined_scores: torch.Tensor, tolerance: torch.Tensor):
    """Each image's best of {its best start, its refined points}, ties (:func:`first_near_best`
    within ``tolerance`` (B,) nats) going to the earlier candidate.

    ``starts`` (B, L, D) with ``start_scores`` (B, L), the first of each image its best; ``refined``
    (B, R, D) with ``refined_scores`` (B, R).  Returns (params (B, D) float64, scores (B,) in
    ``refined_scores``' dtype, tied (B,) bool: another candidate within the tolerance is a
    different answer (:func:`different_solutions`), so rounding could choose it elsewhere)."""
    candidates = torch.cat([starts[:, :1].to(refined), refined], 1).to(torch.float64)
    candidate_scores = torch.cat([start_scores[:, :1].to(refined_scores), refined_scores], 1)
    near = near_best(candidate_scores.to(torch.float64), tolerance)
    best = first_argmax(near.to(torch.int8), -1)
    rows = torch.arange(len(best), device=best.device)
    chosen = candidates[rows, best]
    tied = (near & different_solutions(candidates, chosen[:, None])).any(1)
    return chosen, candidate_scores[rows, best], tied


#: The 3^4 lattice offsets of a subdivision pass, [pan, pitch, roll, log f], pan varying fastest
#: (runs of 3 share the vertical VP: ``score_grid(..., vertical_block=3)``); the centre is included.
LATTICE = torch.cartesian_prod(*[torch.tensor([-1.0, 0.0, 1.0], dtype=torch.float64)] * 4)[:, [3, 1, 2, 0]]


def subdivide_starts(likelihood: MixtureLikelihood, features: SegmentFeatures, starts: torch.Tensor,
                     scores: torch.Tensor, config: SearchConfig, lower: torch.Tensor, upper: torch.Tensor):
    """Coarse-to-fine passes around the stage-1 starts: ``config.grid_passes`` times, score the
    3^4 lattice around each start (offsets -h, 0, +h per parameter; focal in log f) and move the
    start to the best point if it beats the start's score; h is a third of a grid cell in the
    first pass and a third of the previous h after that (the lattice subdivides the cell around
    the start).

    ``starts`` (B, L, 4) [pan, pitch, roll, f] and their ``scores`` (B, L); ``lower`` / ``upper``
    (B, 4) the parameter box (points are moved into it by :func:`into_box`; a known focal stays fixed).  Returns
    (starts, scores) of the same shapes; every score is >= its input score.  Each start moves on
    its own, so a batch gives the same answer as images one by one.
    """
    if config.grid_passes == 0:
        return starts, scores
    lower64, upper64 = lower.to(torch.float64), upper.to(torch.float64)
    step = grid_cell(config, lower64, upper64)

    def score_points(points: torch.Tensor, place):
        hypotheses = from_log_focal(points).view(points.shape[0], -1, 4)
        return points, score_grid(likelihood, features, hypotheses, config.max_chunk_elements, vertical_block=3)

    return lattice_passes(starts, scores, LATTICE, step, lower64, upper64, config, score_points,
                          tie_tolerance(features), features.weight.device)


def lattice_passes(starts: torch.Tensor, scores: torch.Tensor, lattice: torch.Tensor, step: torch.Tensor,
                   lower: torch.Tensor, upper: torch.Tensor, config: SearchConfig, score_points,
                   tolerance: torch.Tensor, device: torch.device) -> tuple[torch.Tensor, torch.Tensor]:
    """The coarse-to-fine pass loop of :func:`subdivide_starts`, for D parameters [pan, pitch, roll,
    f (, k)]: ``config.grid_passes`` passes; each places ``lattice`` (P, D) float64 offsets, times
    ``step`` (B, D) (in log f for the focal length) divided by 3 per pass, around every start,
    moves the points into the box [``lower``, ``upper``] (B, D) (:func:`into_box`), scores them and
    keeps each start's best point where it beats the start (:func:`_keep_best`, ``tolerance`` (B,)).

    ``score_points(points, place)``: the pass's lattice points (B, L, P, D) in log f, and
    ``place(offsets)``, which places other offsets (Q, D) around the starts as the lattice was
    placed (scaled by the pass's step, moved into the box) -> (candidates (B, L, P', D), their
    scores (B, L * P')) (a lens search adds candidates of its own that way,
    :func:`fr_torch.core.search_distortion.subdivide_rows`).  ``starts`` (B, L, D) [pan, pitch,
    roll, f (pixels)(, k)] and ``scores`` (B, L); returns both, the same shapes; the points live on
    ``device``.
    """
    log_lower = to_log_focal(lower.to(torch.float64))[:, None, None, :].to(device)
    log_upper = to_log_focal(upper.to(torch.float64))[:, None, None, :].to(device)
    step = step[:, None, None, :].to(device)  # (B, 1, 1, D)
    lattice = lattice.to(device)
    current = to_log_focal(starts.to(device=device, dtype=torch.float64))
    fraction = 1.0
    for _ in range(config.grid_passes):
        fraction /= 3.0

        def place(offsets: torch.Tensor, around: torch.Tensor = current, scale: torch.Tensor = step * fraction):
            return into_box(around[:, :, None, :] + offsets * scale, log_lower, log_upper, config.periodic_pan)

        points, point_scores = score_points(place(lattice), place)  # lattice points (B, L, P, D)
        current, scores = _keep_best(current, scores, points, point_scores, tolerance)
    return from_log_focal(current).to(starts), scores


def score_grid(likelihood: MixtureLikelihood, features: SegmentFeatures, hypotheses: torch.Tensor,
               max_chunk_elements: int, vertical_block: int = 1) -> torch.Tensor:
    """Length-weighted log-likelihood of every hypothesis, (B, G) float64, in chunks of hypotheses
    and images.

    At most ``max_chunk_elements`` (``CPU_CHUNK_ELEMENTS`` on CPU, if smaller) per-segment
    deviations exist at once, in chunks that are the same at every thread count; scores do not
    depend on the chunking, the batch or the thread count,
    bit for bit (:mod:`fr_torch.core.exact`).  ``vertical_block`` = k: runs of k consecutive
    hypotheses differ only in pan (the grid of :func:`grid_hypotheses`), so their vertical VP is
    scored once (chunks hold whole runs; the same scores bit for bit).
    """
    batch, count = hypotheses.shape[:2]
    n_seg = max(1, features.weight.shape[1])
    dtype, device = features.weight.dtype, features.weight.device
    if vertical_block < 1 or count % vertical_block:
        vertical_block = 1
    # CPU: a fixed cache-sized chunk at any thread count (the fused kernel stores no deviations: no chunk)
    cpu_budget = max_chunk_elements if likelihood.stores_no_deviations(features) else CPU_CHUNK_ELEMENTS
    budget = max(1, max_chunk_elements if device.type != "cpu" else min(max_chunk_elements, cpu_budget))
    per_hypothesis = n_seg * 3
    hyp_chunk = max(1, min(count, budget // per_hypothesis))
    hyp_chunk = max(vertical_block, hyp_chunk - hyp_chunk % vertical_block)  # whole runs
    img_chunk = max(1, min(batch, budget // (per_hypothesis * hyp_chunk)))
    scores = torch.empty(batch, count, dtype=torch.float64, device=device)
    workspace: dict = {}
    with torch.no_grad():
        for b0 in range(0, batch, img_chunk):
            b1 = min(batch, b0 + img_chunk)
            sub = features.images(b0, b1)
            # Rotations of this image slice: (b, G, 3, 3) -- small (9 numbers per hypothesis).
            part = hypotheses[b0:b1].to(device)
            rotation = rotations(part.to(dtype))
            focal = part[..., FOCAL].to(dtype)
            for h0 in range(0, count, hyp_chunk):
                h1 = min(count, h0 + hyp_chunk)
                scores[b0:b1, h0:h1] = likelihood.objective(sub, rotation[:, h0:h1], focal[:, h0:h1],
                                                            workspace=workspace, vertical_block=vertical_block)
    return scores.nan_to_num_(nan=-math.inf)  # a NaN score is never the best (topk ranks NaN first)


def refine(likelihood: MixtureLikelihood, features: SegmentFeatures, starts: torch.Tensor,
           lower: torch.Tensor, upper: torch.Tensor, iterations: int, fast: bool,
           max_chunk_elements: int = 1 << 24, tolerance: float = 0.0,
           patience: int = 10, periodic_pan: bool = False,
           geometry=None) -> tuple[torch.Tensor, torch.Tensor]:
    """Refine starts (B, L, 4) inside the box [lower, upper] (B, 4).  Returns (params, objective).

    With ``geometry`` (:class:`~fr_torch.core.search_distortion.SegmentGeometry`, the segments of the same
    images) the rows have a fifth parameter, the division model's k (:data:`~fr_torch.core.params.DISTORTION`):
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


#: Bound on each gradient component of the normalised loss in box units (real ones stay below ~1e4).
_GRAD_BOUND = 1e6


class Adam:
    """Adam (Kingma & Ba; torch.optim's update: ``p -= lr / (1 - b1^t) * m / (sqrt(v) / sqrt(1 - b2^t)
    + eps)``) on one tensor, with a step size that decays by ``gamma`` after every step.

    Written in single torch operations, each rounded once: the update is the same bits on every
    kernel set and device (torch's fused Adam kernel takes fused multiply-adds on some and not on
    others, :mod:`fr_torch.core.exact`), and building no ``torch.optim`` object spares a process
    the 1-2 s import of ``torch._dynamo`` that its constructor triggers.
    """

    def __init__(self, param: torch.Tensor, lr: float, gamma: float, betas: tuple[float, float], eps: float = 1e-8):
        self.param, self.lr, self.gamma, self.betas, self.eps = param, lr, gamma, betas, eps
        self.exp_avg = torch.zeros_like(param)
        self.exp_avg_sq = torch.zeros_like(param)
        self.step_count = 0

    def step(self, grad: torch.Tensor, active: torch.Tensor | None = None) -> None:
        """One Adam update of the parameter (in place) with gradient ``grad`` (same shape), then
        the step size decays by ``gamma``.  ``active``: broadcastable bool mask; entries outside it
        keep their parameter and moments (converged images)."""
        beta1, beta2 = self.betas
        self.step_count += 1
        with torch.no_grad():
            exp_avg = self.exp_avg * beta1 + grad * (1.0 - beta1)
            exp_avg_sq = self.exp_avg_sq * beta2 + (grad * grad) * (1.0 - beta2)
            denom = exp_avg_sq.sqrt() / math.sqrt(1.0 - beta2 ** self.step_count) + self.eps
            update = exp_avg / denom * (self.lr / (1.0 - beta1 ** self.step_count))
            if active is None:
                self.exp_avg, self.exp_avg_sq = exp_avg, exp_avg_sq
                self.param.sub_(update)
            else:
                self.exp_avg = torch.where(active, exp_avg, self.exp_avg)
                self.exp_avg_sq = torch.where(active, exp_avg_sq, self.exp_avg_sq)
                self.param.sub_(torch.where(active, update, torch.zeros_like(update)))
        self.lr = self.lr * self.gamma


def _refine_slice(likelihood, features, starts, lower, upper, iterations, fast, tolerance=0.0, patience=10,
                  periodic_pan=False, geometry=None):
    dtype, device = features.weight.dtype, features.weight.device
    # The focal length is refined as log f: a step is the same relative change of f (and about the
    # same change of FOV) at every zoom, matching the log-spaced stage-1 grid.
    if lower.dim() == 2:  # one box per image
        lower, upper = lower[:, None, :], upper[:, None, :]
    lower = to_log_focal(lower.to(device=device, dtype=dtype))
    upper = to_log_focal(upper.to(device=device, dtype=dtype))
    starts = to_log_focal(starts.to(device=device, dtype=dtype))
    span = (upper - lower)
    free = span > 0
    span_safe = torch.where(free, span, torch.ones_like(span))
    u = ((starts - lower) / span_safe).clamp(0, 1).detach().requires_grad_(True)
    total_length = features.total_length().clamp_min(1e-9)[:, None]  # (B, 1) float64
    # Step sizes in box units: about a quarter of a grid cell at first, decaying geometrically.
    cell = 1.0 / 8
    lr0 = 0.25 * cell
    lr_final = (0.02 if fast else 0.002) * cell
    gamma = (lr_final / lr0) ** (1.0 / max(1, iterations - 1))
    optimiser = Adam(u, lr0, gamma, betas=(0.5, 0.9))
    all_free = bool(free.all())
    history: list[torch.Tensor] = []
    active = None  # (B, 1, 1) images still refined under the stopping rule

    def evaluate(u_value):
        params = from_log_focal(lower + u_value * span)
        if geometry is not None:  # one virtual image per hypothesis, its segments undistorted with its k
            batch, n_hyp = params.shape[:2]
            virtual = geometry.features(params[..., DISTORTION])
            flat = params[..., :DISTORTION].reshape(batch * n_hyp, 1, DISTORTION)
            value = likelihood.objective(virtual, rotations(flat), flat[..., FOCAL]).view(batch, n_hyp)
            return params, value + geometry.k_log_prior(params[..., DISTORTION])[0]
        rotation = rotations(params)
        return params, likelihood.objective(features, rotation, params[..., FOCAL])

    analytic = likelihood._fast_path(features)
    grad_out = (-1.0 / total_length).to(dtype)
    for _ in range(iterations):
        u.grad = None
        if analytic and geometry is not None:
            objective, grad = objective_and_grad(likelihood, features, lower, span, u.detach(), grad_out, geometry)
        elif analytic:  # same gradient in closed form, no autograd graph (see objective_and_grad)
            result = (compiled_call(objective_and_grad, likelihood, likelihood, features, lower, span, u.detach(),
                                    grad_out) if likelihood.compiled else None)
            objective, grad = result or objective_and_grad(likelihood, features, lower, span, u.detach(), grad_out)
        else:
            _, objective = evaluate(u)
            finite = torch.where(torch.isfinite(objective), objective, torch.zeros_like(objective))
            loss = -(finite / total_length).sum()
            loss.backward()
            grad = u.grad
        grad = grad.to(dtype)
        if not all_free:
            grad = torch.where(free, grad, torch.zeros_like(grad))
        # A finite, bounded gradient keeps Adam's moments and so every parameter finite.
        optimiser.step(torch.nan_to_num(grad, nan=0.0, posinf=0.0, neginf=0.0).clamp_(-_GRAD_BOUND, _GRAD_BOUND),
                       active)
        with torch.no_grad():
            if periodic_pan:  # u's pan is (pan - lower) / 90 deg: wrap it into [0, 1)
                u[..., PAN] = torch.remainder(u[..., PAN], 1.0)
            u.clamp_(0.0, 1.0)
        if tolerance > 0:  # an image stops once none of its hypotheses moves its objective any more
            history.append(objective.detach() / total_length)
            if len(history) > patience:
                old = history.pop(0)
                change = (history[-1] - old).abs()
                moving = ((change > tolerance) & torch.isfinite(change)).any(1)  # (B,)
                active = moving[:, None, None] if active is None else active & moving[:, None, None]
                if not bool(active.any()):
                    break
    with torch.no_grad():
        params, objective = evaluate(u)
        objective = torch.where(torch.isfinite(objective), objective, torch.full_like(objective, -math.inf))
    return params.detach(), objective.detach()


def objective_and_grad(likelihood: MixtureLikelihood, features: SegmentFeatures, lower: torch.Tensor,
                       span: torch.Tensor, u: torch.Tensor, grad_out: torch.Tensor,
                       geometry=None):
    """Measure-b objective (B, L) at ``params = lower + u * span`` and the gradient of
    ``sum(grad_out * objective)`` with respect to u (B, L, 4), without autograd.

    With ``geometry`` the rows have a fifth parameter, k: each hypothesis is scored on its images'
    segments undistorted with its k (:meth:`~fr_torch.core.search_distortion.SegmentGeometry.features`, one
    virtual image per hypothesis), and d obj / dk = sum_i (d obj / d line_along_i) . (d line_along_i / dk)
    (:func:`fr_torch.core.likelihood.measure_b_backward` with the VPs); u is then (B, L, 5).

    ``params`` = [pan, pitch, roll (degrees), log f (f in pixels)], the refinement's coordinates.

    ``lower``, ``span``: (B, 1, 4); ``grad_out``: broadcastable to (B, L).  The chain is written
    out: G = d obj / d V for the VPs V = K R from :func:`fr_torch.core.likelihood.measure_b_backward`;
    ``dV/df = [R_0; R_1; 0]``; and for the angles, with ``R.T = Ry(pan) Rx(pitch) Rz(roll)``
    (:func:`fr_torch.core.params.rotations`), ``dR/d angle = -R [w]_x`` for the axis ``w`` = e_y (pan),
    ``Ry(pan) e_x`` (pitch) and ``R.T e_z`` (roll), so ``d obj / d angle = -w . axial(V.T G)``
    (``<G, K dR> = <K.T G, -R [w]_x> = -<R.T K.T G, [w]_x>``; axial(M) = (M21 - M12, M02 - M20,
    M10 - M01)).  Equal to the autograd gradient of the same objective to rounding (tests); used
    by the refinement, where autograd's per-step overhead dominated at small batches.
    """
    params = lower + u * span
    batch, n_hyp = params.shape[:2]
    rad = torch.deg2rad(params[..., ANGLES])
    cos, sin = torch.cos(rad), torch.sin(rad)
    rotation = rotation_from_cos_sin(cos, sin)  # (B, L, 3, 3)
    focal = torch.exp(params[..., FOCAL])
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
    with ``R.T = Ry(pan) Rx(pitch) Rz(roll)`` (:func:`fr_torch.core.params.rotations`), ``cos`` /
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
