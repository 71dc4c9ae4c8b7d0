"""Deviation measures (a)-(e) and the 4-way mixture likelihood of line segments.

Every segment is explained by one of the three Manhattan families (vanishing point i = K R[:, i];
column 1 is the vertical) or by a uniform background.  Shapes: B images, H hypotheses per image,
N segments per image (padded; ``mask`` marks the real ones), 3 vanishing points.

All computations use the *homogeneous* vanishing point, so a VP at infinity (third coordinate
0) needs no special case: for a segment with unit direction d, midpoint m and homogeneous line
``l = (-d_y, d_x, d_y m_x - d_x m_y)`` (unit normal, so ``l . (x, y, 1)`` is the signed distance
of pixel (x, y) from the segment's line), and ``g = (d_x, d_y, -d . m)`` (``g . (x, y, 1)`` is the
signed position of (x, y) along the segment from its midpoint), a VP ``v`` gives

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

Likelihoods: exponential ``exp(-x / lambda) / lambda`` for a, b, c, e; half-normal (a central
Gaussian on the signed deviation, sigma = 1 px by default) for d; background uniform over the
measure's range (pi/2 for b and e, ``range`` px for a, the half length for c and d; measures are
clamped to their range).  Objective: ``sum_i len_i * log p_i``.

The vertical parameters (lambda and prior) go on the world-up column (column 1), as in the
paper.  The authors' MATLAB release attaches them to a horizontal column instead; we follow the
paper.

Speed (measure b, the default): :meth:`MixtureLikelihood.objective` evaluates the same mixture
with a fused path instead of the generic one.  Without gradients (the grid) it works in place
on reusable buffers (``workspace``) with vanishing points laid out VP-major, ``(B, N, 3 * H)``,
so the sum over the three families adds contiguous blocks; with gradients (the refinement) a
custom autograd function returns the analytic gradient with respect to the vanishing points
(``d obj / d v = sum_i [G_is l_i + G_it g_i]``), so autograd only sees the small (B, H, 3, 3)
tensors.  One deliberate detail: the exponent ``log(prior / lambda) - x / lambda`` is clamped
below at -87 (float32; -700 for float64) because ``exp`` of a more negative float32 argument
takes a much slower denormal path; the clamped term (< 1e-37) is then added to the background
density (>= 0.019 for measure b), which it cannot change in float32 or float64, so the objective
is unchanged bit for bit whenever the background prior exceeds ~1e-28.  ``atan2(0, 0) = 0`` as in
the generic path (and the gradient there is 0, as the generic path's guard gives).

Fused CPU kernels (float32 on a CPU, where they build: :mod:`fr_torch.core.native`): the grid's
scores (:func:`objective_b_nograd`) and the refinement's objective with its gradient
(:func:`measure_b_objective_and_grad`) run as one C pass each, which never stores the per-segment
deviations and keeps the exact sums' integers in registers; the same operations in the same
order as the torch code here, which stays the reference (``fused=False``) and the path of every
other device, dtype and machine: the same bits either way.

One photo, one answer: s and t are written out per entry (:func:`incidence`, no matrix product),
the angle is ``atan(|s / t|)``, the families are added in one order on every path
(:func:`_family_sum`) and every sum over segments is exact
(:func:`fr_torch.core.exact.exact_sum`), so an image's objective (float64) is the same bits in
any batch, chunk, thread count and CPU kernel set (:mod:`fr_torch.core.exact`).

Compiled search (opt-in, ``MixtureLikelihood(compiled=True)``, ``SearchConfig.compile_search``,
``--compile``): the no-gradient measure-b sums are written as broadcast elementwise ops and one
reduction over segments (:func:`objective_b_elementwise`), which ``torch.compile`` turns into one
fused kernel (C++ on CPU, Triton on CUDA) that never stores the (B, 2N, 3H) deviations; the
refinement's closed-form objective and gradient (:func:`fr_torch.core.search.objective_and_grad`) are
compiled too, which removes most of its per-step operator overhead.  Compilation happens once per
process (:func:`compiled_call`); where it fails (no C++ compiler, no Triton)
the estimator warns once and keeps the eager paths.
"""
from __future__ import annotations

import json
import math
import warnings
from dataclasses import dataclass, field, replace
from pathlib import Path

import torch

from fr_torch.core.camera import (
    VERTICAL_AXIS,
    focal_from_hfov,
    vanishing_points,
)
from fr_torch.core import native
from fr_torch.core.config import Mode
from fr_torch.core.exact import angle_of, angle_of_, dot3, exact_sum, fixed_point_scale, small_sum, top_indices
from fr_torch.core.fov import FOV_LIMITS_DEG, FovRange
from fr_torch.core.segments import SegmentBatch
from fr_torch.resources import config_dir

MEASURES = ("a", "b", "c", "d", "e")
MODELS = ("mixture", "nomixture")
CONFIG_DIR = config_dir()  # the shipped configs/ folder (fr_torch/resources.py)
DEFAULT_LIKELIHOOD_CONFIG = CONFIG_DIR / "likelihood.json"
_TINY = 1e-30  # guards 0 / 0 in measure a


def likelihood_config_path(name_or_path: str | Path | None) -> Path:
    """Resolve a likelihood configuration: None -> ``configs/likelihood.json`` (the default);
    a bare name such as ``paper`` or ``fitted`` -> ``configs/likelihood_<name>.json``; else a path."""
    if name_or_path is None:
        return DEFAULT_LIKELIHOOD_CONFIG
    named = CONFIG_DIR / f"likelihood_{name_or_path}.json"
    path = named if named.is_file() else Path(name_or_path)
    if not path.is_file():
        known = sorted(p.stem.removeprefix("likelihood_") for p in CONFIG_DIR.glob("likelihood_*.json"))
        raise ValueError(f"likelihood config {str(name_or_path)!r} not found (names: {', '.join(known)}, or a JSON path)")
    return path


@dataclass(frozen=True)
class LikelihoodParams:
    """Mixture parameters for one deviation measure, in internal units (radians or pixels).

    ``scale_vertical`` / ``scale_horizontal``: exponential mean lambda (or Gaussian sigma for d).
    ``range_px``: background range for measure a (pixels).  Priors sum to 1.
    ``model``: ``mixture`` (the fR objective) or ``nomixture``, the paper's "no probabilistic model"
    ablation: each segment scores the log of its smallest deviation from the three VPs,
    ``objective = -sum_i len_i log(min_k x_ik + eps)`` with ``eps = scale_horizontal / 100`` (keeps
    the log finite for a segment exactly through a VP); no priors, no background.
    ``focal_prior_weight`` (gamma >= 0) and ``focal_prior_hfov_deg`` (degrees): a log-normal prior
    on the focal length relative to the image's long side L,
    ``log p(f) = -(gamma / 2) * (W + W0) * (log(f / L) - log(f0 / L))^2``, with f0 the focal length
    whose FOV across the long side is ``focal_prior_hfov_deg``, W the image's total segment length
    and W0 = ``focal_prior_pseudo_length`` * L (pixels).  The W part acts per unit of evidence, like
    the length-weighted likelihood it is added to; W0 is evidence the prior always has, so an image
    with few segments (a blank wall) leans on it more than one with many.  It counters the
    likelihood's pull towards narrow fields of view when the image barely constrains f (the
    f -> infinity bias the paper describes: far VPs make the horizontal families nearly parallel,
    which fits noisy or non-Manhattan segments slightly better).  The shipped centre and gamma are
    in ``configs/likelihood.json`` (``results/DECISIONS.md`` says how they were chosen); gamma = 0 =
    no prior.
    ``focal_prior_flat_halfwidth`` (h >= 0, in log f): a flat top, no pull while f is within a
    factor e^h of f0; outside, the same quadratic in the distance to that band,
    ``log p(f) = -(gamma / 2) * (W + W0) * max(0, |log(f / f0)| - h)^2`` (h = 0: the log-normal).
    The config's ``focal_prior`` block may hold per-mode overrides (``"fr": {...}``, ``"fast":
    {...}``; :meth:`from_dict`): fR's shipped prior is the flat-topped one.
    """

    measure: str = "b"
    scale_vertical: float = math.radians(0.57)
    scale_horizontal: float = math.radians(1.46)
    prior_vertical: float = 0.45
    prior_horizontal: float = 0.26
    prior_background: float = 0.03
    range_px: float = 2000.0
    model: str = "mixture"
    focal_prior_weight: float = 0.0
    focal_prior_hfov_deg: float = 82.0
    focal_prior_pseudo_length: float = 0.0
    focal_prior_flat_halfwidth: float = 0.0

    def __post_init__(self) -> None:
        """Explicit parameters are checked too (no NaN, zero or negative scale; priors in [0, 1])."""
        for name in ("scale_vertical", "scale_horizontal", "range_px"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
                raise ValueError(f"LikelihoodParams.{name} must be a finite number > 0, got {value!r}")
        for name in ("prior_vertical", "prior_horizontal", "prior_background"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and math.isfinite(value) and 0 <= value <= 1):
                raise ValueError(f"LikelihoodParams.{name} must be in [0, 1], got {value!r}")
        if not self.prior_background > 0:
            raise ValueError("LikelihoodParams.prior_background must be > 0 (the background keeps p_i > 0)")
        if not (math.isfinite(self.focal_prior_weight) and self.focal_prior_weight >= 0):
            raise ValueError(f"focal_prior_weight must be a finite number >= 0, got {self.focal_prior_weight}")
        low, high = FOV_LIMITS_DEG
        if not (math.isfinite(self.focal_prior_hfov_deg) and low <= self.focal_prior_hfov_deg <= high):
            raise ValueError(f"focal_prior_hfov_deg must be in [{low:g}, {high:g}] degrees, got "
                             f"{self.focal_prior_hfov_deg}")
        if not (math.isfinite(self.focal_prior_pseudo_length) and self.focal_prior_pseudo_length >= 0):
            raise ValueError("focal_prior_pseudo_length must be a finite number >= 0, got "
                             f"{self.focal_prior_pseudo_length}")
        if not (math.isfinite(self.focal_prior_flat_halfwidth) and 0 <= self.focal_prior_flat_halfwidth <= 3):
            raise ValueError("focal_prior_flat_halfwidth must be in [0, 3] (log f), got "
                             f"{self.focal_prior_flat_halfwidth}")
        if self.model not in MODELS:
            raise ValueError(f"unknown likelihood model {self.model!r}; choose one of {', '.join(MODELS)}")

    def with_prior_in_range(self, fov_range: FovRange) -> "LikelihoodParams":
        """A copy whose focal-prior centre lies in the search range ``(min, max)`` (degrees, FOV
        across the long side): unchanged when it does, else the range's midpoint in log f (a user
        who searches a range that excludes the learned centre knows more about the camera than the
        train splits do)."""
        if fov_range.min_deg <= self.focal_prior_hfov_deg <= fov_range.max_deg:
            return self
        return replace(self, focal_prior_hfov_deg=fov_range.log_focal_midpoint_deg())

    @classmethod
    def from_config(cls, measure: str | None = None, path: str | Path | None = None,
                    mode: str | None = None) -> "LikelihoodParams":
        """Read ``configs/likelihood.json`` (or ``path``: a file or a name, see
        :func:`likelihood_config_path`); angles there are in degrees.  ``mode`` (``"fr"`` /
        ``"fast"``): apply that mode's focal-prior overrides (:meth:`from_dict`)."""
        source = likelihood_config_path(path)
        try:
            config = json.loads(source.read_text())
        except (OSError, UnicodeDecodeError, ValueError) as exc:
            raise ValueError(f"likelihood config {source}: not a readable JSON file ({exc})") from None
        return cls.from_dict(config, measure, str(source), mode)

    @classmethod
    def from_dict(cls, config, measure: str | None = None, source: str = "likelihood config",
                  mode: str | None = None) -> "LikelihoodParams":
        """Validate a likelihood config (the JSON's content) and build the parameters.

        Schema: ``{"default_measure": "a".."e" (optional), "measures": {m: {"unit": "deg"|"px",
        "lambda_vertical": > 0, "lambda_horizontal": > 0, "range_px": > 0 (a), "sigma": > 0 (d)}},
        "priors": {"vertical": >= 0, "horizontal": >= 0, "background": > 0}}`` (priors are
        normalised so that vertical + 2 horizontal + background = 1), and optionally
        ``"focal_prior": {"weight": >= 0, "hfov_deg": [1, 179], "pseudo_length": >= 0,
        "flat_halfwidth": [0, 3], "fr": {...}, "fast": {...}}``: a mode's block overrides any of the
        four for that ``mode``.  Every violation raises a ValueError naming the field.
        """
        def fail(message: str):
            raise ValueError(f"{source}: {message}")

        def number(value, name: str, low: float, high: float, low_inclusive: bool = False) -> float:
            if isinstance(value, bool) or not isinstance(value, (int, float)):
                fail(f"{name} must be a number, got {value!r}")
            try:
                value = float(value)
            except OverflowError:
                fail(f"{name} is too large")
            if not math.isfinite(value) or value < low or (value == low and not low_inclusive) or value > high:
                fail(f"{name} must be in {'[' if low_inclusive else '('}{low:g}, {high:g}], got {value!r}")
            return value

        if not isinstance(config, dict):
            fail(f"expected a JSON object with 'measures' and 'priors', got {type(config).__name__}")
        measure = measure or config.get("default_measure", "b")
        if measure not in MEASURES:
            raise ValueError(f"unknown deviation measure {measure!r}; choose one of {', '.join(MEASURES)}")
        measures = config.get("measures")
        if not isinstance(measures, dict) or not isinstance(measures.get(measure), dict):
            fail(f"'measures' must be an object with an entry for measure {measure!r}")
        entry = measures[measure]
        unit = entry.get("unit", "deg" if measure in ("b", "e") else "px")
        if unit not in ("deg", "px"):
            fail(f"measures.{measure}.unit must be 'deg' or 'px', got {unit!r}")
        top = 90.0 if unit == "deg" else 1e6  # an angle deviation cannot exceed 90 deg
        to_internal = math.radians if unit == "deg" else float
        if measure == "d":
            scale_v = scale_h = number(entry.get("sigma", 1.0), f"measures.{measure}.sigma", 0.0, top)
        else:
            for key in ("lambda_vertical", "lambda_horizontal"):
                if key not in entry:
                    fail(f"measures.{measure}.{key} is missing")
            scale_v = to_internal(number(entry["lambda_vertical"], f"measures.{measure}.lambda_vertical", 0.0, top))
            scale_h = to_internal(number(entry["lambda_horizontal"], f"measures.{measure}.lambda_horizontal", 0.0, top))
        range_px = number(entry.get("range_px", cls.range_px), f"measures.{measure}.range_px", 0.0, 1e9)
        priors = config.get("priors")
        if not isinstance(priors, dict):
            fail("'priors' must be an object with vertical, horizontal and background")
        for key in ("vertical", "horizontal", "background"):
            if key not in priors:
                fail(f"priors.{key} is missing")
        vertical = number(priors["vertical"], "priors.vertical", 0.0, 1e6, low_inclusive=True)
        horizontal = number(priors["horizontal"], "priors.horizontal", 0.0, 1e6, low_inclusive=True)
        background = number(priors["background"], "priors.background", 0.0, 1e6)
        if vertical + horizontal == 0:
            fail("priors.vertical and priors.horizontal are both 0: no Manhattan family can be explained")
        focal_prior = config.get("focal_prior", {})
        if not isinstance(focal_prior, dict):
            fail(f"'focal_prior' must be an object like {{\"weight\": 0.3, \"hfov_deg\": 82}}, got {focal_prior!r}")
        def prior_settings(block: dict, where: str) -> tuple[float, float, float, float]:
            return (number(block.get("weight", 0.0), f"{where}.weight", 0.0, 100.0, low_inclusive=True),
                    number(block.get("hfov_deg", cls.focal_prior_hfov_deg), f"{where}.hfov_deg", *FOV_LIMITS_DEG,
                           low_inclusive=True),
                    number(block.get("pseudo_length", 0.0), f"{where}.pseudo_length", 0.0, 1e6, low_inclusive=True),
                    number(block.get("flat_halfwidth", 0.0), f"{where}.flat_halfwidth", 0.0, 3.0, low_inclusive=True))

        settings = {None: prior_settings(focal_prior, "focal_prior")}
        for name in map(str, Mode):  # every mode's overrides are checked, whichever mode asks
            overrides = focal_prior.get(name, {})
            if not isinstance(overrides, dict):
                fail(f"focal_prior.{name} must be an object of overrides for mode {name!r}")
            settings[name] = prior_settings(dict(focal_prior, **overrides), f"focal_prior.{name}")
        gamma, prior_hfov, pseudo, flat = settings[str(mode) if mode in set(Mode) else None]
        total = vertical + 2 * horizontal + background
        return cls(measure=measure, scale_vertical=scale_v, scale_horizontal=scale_h, focal_prior_weight=gamma,
                   focal_prior_hfov_deg=prior_hfov, focal_prior_pseudo_length=pseudo, focal_prior_flat_halfwidth=flat,
                   prior_vertical=vertical / total, prior_horizontal=horizontal / total,
                   prior_background=background / total, range_px=range_px)


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
        principal point is the image centre, :func:`fr_torch.core.camera.image_centre`)."""
        p1, p2 = endpoints[..., :2], endpoints[..., 2:]
        delta = p2 - p1
        length = torch.sqrt(delta[..., 0] * delta[..., 0] + delta[..., 1] * delta[..., 1])
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
        batch, :func:`fr_torch.core.exact.exact_sum`); computed once per object (the search asks
        for it at every step), so the tensors must not change in place afterwards."""
        cached = self.__dict__.get("_total_length")
        if cached is None:
            cached = self.__dict__["_total_length"] = exact_sum(self.weight, 1)
        return cached

    def longest(self, count: int) -> "SegmentFeatures":
        """The ``count`` longest segments of each image (B, min(count, N), ...); padding stays last
        (weight 0)."""
        if count >= self.weight.shape[1]:
            return self
        index = top_indices(self.weight, count, dim=1)  # (B, count), equal lengths in segment order

        def take(x: torch.Tensor) -> torch.Tensor:
            shaped = index.view(index.shape + (1,) * (x.dim() - 2)).expand(index.shape + x.shape[2:])
            return torch.gather(x, 1, shaped)

        return SegmentFeatures(take(self.line), take(self.along), take(self.half_length), take(self.weight),
                               take(self.mask), self.principal_point, self.long_side)

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


def _incidence(features: SegmentFeatures, rotation: torch.Tensor, focal: torch.Tensor):
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
                              range_px: float = LikelihoodParams.range_px) -> torch.Tensor:
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
        cos_part = torch.sqrt((normal_sq - abs_s * abs_s).clamp_min(normal_sq * 1e-12))
        return angle_of(abs_s, cos_part)
    abs_t = t.abs()
    # A midpoint exactly on the VP (s = t = 0) gets angle 0 with a finite gradient.
    angle = angle_of(abs_s, torch.where((abs_s == 0) & (abs_t == 0), torch.ones_like(abs_t), abs_t))
    if measure == "b":
        return angle
    half = features.half_length[:, :, None, None]
    if measure == "c":
        return half * torch.sin(angle)
    if measure == "d":
        return torch.minimum(half * torch.tan(angle.clamp(max=math.pi / 2 - 1e-6)), half)
    raise ValueError(f"unknown deviation measure {measure!r}")


def deviations(measure: str, endpoints: torch.Tensor, vps: torch.Tensor, focal: torch.Tensor,
               principal_point: torch.Tensor, mask: torch.Tensor | None = None,
               range_px: float = LikelihoodParams.range_px) -> torch.Tensor:
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
        vps = vps / torch.sqrt(small_sum(direction * direction, -2))[:, :, None, :]
    columns = vps.transpose(-1, -2)[:, None]  # (B, 1, H, 3 VPs, 3 coordinates)
    s = dot3(features.line[:, :, None, None, :], columns)
    t = dot3(features.along[:, :, None, None, :], columns)
    x = deviations_from_incidence(measure, s, t, vps[:, None, :, 2, :], features, focal, range_px)
    return x.transpose(1, 2)


class MixtureLikelihood:
    """The fR mixture model for one deviation measure; all methods are batched tensor ops.

    Hypotheses come as rotations (B, H, 3, 3) and focal lengths (B, H) in pixels.
    """

    def __init__(self, params: LikelihoodParams | None = None, compiled: bool = False):
        """``compiled``: score no-gradient measure-b hypotheses (grid, sweep, passes, cue lattice)
        with :func:`objective_b_elementwise` under ``torch.compile``, and let the refinement
        compile its step (module docstring); turned off, with one warning, where that fails."""
        self.params = params or LikelihoodParams.from_config()
        self.compiled = bool(compiled)
        # log(f0 / L): the focal prior's centre as a focal length per pixel of the long side
        self._prior_centre = math.log(focal_from_hfov(self.params.focal_prior_hfov_deg, 1.0))

    def _family_constants(self, like: torch.Tensor):
        """Per-family prior and scale, (3,) tensors, vertical parameters on column 1."""
        p = self.params
        scale = like.new_tensor([p.scale_horizontal] * 3)
        scale[VERTICAL_AXIS] = p.scale_vertical
        prior = like.new_tensor([p.prior_horizontal] * 3)
        prior[VERTICAL_AXIS] = p.prior_vertical
        return prior, scale

    def _log_background(self, x: torch.Tensor, features: SegmentFeatures) -> torch.Tensor:
        """log(prior * uniform density) of the background, broadcastable to (B, N, H, 1)."""
        p = self.params
        if p.measure in ("b", "e"):
            return x.new_full((1, 1, 1, 1), math.log(p.prior_background / (math.pi / 2)))
        if p.measure == "a":
            return x.new_full((1, 1, 1, 1), math.log(p.prior_background / p.range_px))
        half = features.half_length.clamp_min(1e-6)[:, :, None, None]  # c, d: uniform on [0, len/2]
        return math.log(p.prior_background) - torch.log(half)

    def _deviations(self, features, rotation, focal) -> torch.Tensor:
        s, t, v3 = _incidence(features, rotation, focal)
        return deviations_from_incidence(self.params.measure, s, t, v3, features, focal, self.params.range_px)

    def _component_log_densities(self, x: torch.Tensor, features: SegmentFeatures) -> torch.Tensor:
        """log(prior * density) of the 3 families and the background, (B, N, H, 4)."""
        prior, scale = self._family_constants(x)
        if self.params.measure == "d":
            family = torch.log(prior * math.sqrt(2 / math.pi) / scale) - 0.5 * (x / scale) ** 2
        else:
            family = torch.log(prior / scale) - x / scale
        background = self._log_background(x, features).expand_as(x[..., :1])
        return torch.cat([family, background], -1)

    def component_log_densities(self, features: SegmentFeatures, rotation: torch.Tensor,
                                focal: torch.Tensor) -> torch.Tensor:
        """log(prior * density) of the 3 families and the background for every segment under every
        hypothesis (rotations (B, H, 3, 3), focal lengths (B, H)), (B, N, H, 4); column 3 = background."""
        return self._component_log_densities(self._deviations(features, rotation, focal), features)

    def point_deviations(self, features: SegmentFeatures, vps: torch.Tensor, focal: torch.Tensor) -> torch.Tensor:
        """Deviation of every segment from A homogeneous VPs ``vps`` (B, A, 3) in pixels, (B, N, A),
        internal units; ``focal`` (B,) pixels (measure e).  For measure e the VPs must be ``K d``
        with unit directions ``d``, as a column of R gives."""
        flat = vps.transpose(1, 2).to(features.line.dtype)  # (B, 3, A)
        s = incidence(features.line, flat)[..., None]  # (B, N, A, 1)
        t = incidence(features.along, flat)[..., None]
        v3 = flat[:, None, 2, :, None]  # (B, 1, A, 1)
        focal = focal.to(flat.dtype)[:, None].expand(-1, flat.shape[-1])
        return deviations_from_incidence(self.params.measure, s, t, v3, features, focal, self.params.range_px)[..., 0]

    def horizontal_log_density(self, x: torch.Tensor) -> torch.Tensor:
        """log density (without the prior) of a horizontal family at deviations ``x`` (internal units)."""
        scale = self.params.scale_horizontal
        if self.params.measure == "d":
            return math.log(math.sqrt(2 / math.pi) / scale) - 0.5 * (x / scale) ** 2
        return -math.log(scale) - x / scale

    def segment_log_likelihood(self, features: SegmentFeatures, rotation: torch.Tensor,
                               focal: torch.Tensor) -> torch.Tensor:
        """log p_i of every segment under every hypothesis, (B, N, H).

        Fast path: the background term keeps p_i >= prior_bg * density_bg > 0, so the mixture is
        summed directly, without a log-sum-exp.
        """
        x = self._deviations(features, rotation, focal)
        prior, scale = self._family_constants(x)
        if self.params.measure == "d":
            density = torch.exp(-0.5 * (x / scale) ** 2) * (prior * math.sqrt(2 / math.pi) / scale)
        else:
            density = torch.exp(x * (-1.0 / scale)) * (prior / scale)
        background = torch.exp(self._log_background(density, features))[..., 0]
        return torch.log(_family_sum(density, -1) + background)

    def objective(self, features: SegmentFeatures, rotation: torch.Tensor, focal: torch.Tensor,
                  workspace: dict | None = None, vertical_block: int = 1) -> torch.Tensor:
        """Length-weighted log-likelihood sum_i len_i log p_i plus the focal prior
        (:meth:`focal_prior`), (B, H).

        ``vertical_block`` = k > 1 promises that runs of k consecutive hypotheses share the
        vertical VP (same f and ``R[:, 1]``: the grid, where pan varies fastest and leaves the
        vertical direction unchanged); the fused measure-b path then scores that VP once per run.
        """
        value = self._data_objective(features, rotation, focal, workspace, vertical_block)
        if self.params.focal_prior_weight:
            value = value + self.focal_prior(features, focal)[0]
        return value

    def focal_prior(self, features: SegmentFeatures, focal: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The log focal prior (see :class:`LikelihoodParams`) and its derivative d/df (per pixel)
        of the images of ``features`` (:meth:`focal_prior_of`).

        ``focal`` (B, H) pixels.  Returns two (B, H) tensors in ``features.weight``'s dtype.
        """
        return self.focal_prior_of(features.total_length(), features.long_side, focal.to(features.weight.dtype))

    def focal_prior_of(self, total_length: torch.Tensor, long_side: torch.Tensor,
                       focal: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The log focal prior and its derivative d/df (per pixel) of images whose segments add up
        to ``total_length`` (B,) pixels (float64, :meth:`SegmentFeatures.total_length`: an exact
        sum, the same in any batch) and whose long side is ``long_side`` (B,) pixels.

        ``focal`` (B, H) pixels.  Returns two (B, H) tensors in ``focal``'s dtype.
        """
        weight = self.focal_prior_curvature(total_length.to(focal.dtype), long_side)[:, None]  # (B, 1)
        offset = torch.log(focal / long_side[:, None]) - self._prior_centre
        flat = self.params.focal_prior_flat_halfwidth
        if flat:  # the distance to the flat band |log(f / f0)| <= h, signed
            offset = torch.sign(offset) * (offset.abs() - flat).clamp_min(0.0)
        return -0.5 * weight * offset ** 2, -weight * offset / focal

    def focal_prior_curvature(self, total_length: torch.Tensor, long_side: torch.Tensor) -> torch.Tensor:
        """``gamma * (W + W0)`` per image, (B,): minus the second derivative of the log focal prior
        with respect to log f outside its flat band (the same at every such f; 0 inside the band and
        without a prior), in objective units per (log f)^2, directly comparable with the curvature
        of the length-weighted likelihood.  ``total_length`` W (B,) and ``long_side`` (B,) pixels
        (W0 = the pseudo-length per pixel of the long side times it)."""
        params = self.params
        evidence = total_length + params.focal_prior_pseudo_length * long_side  # W + W0
        return params.focal_prior_weight * evidence

    def _data_objective(self, features: SegmentFeatures, rotation: torch.Tensor, focal: torch.Tensor,
                        workspace: dict | None = None, vertical_block: int = 1) -> torch.Tensor:
        """Length-weighted log-likelihood sum_i len_i log p_i, (B, H) float64: the sum over segments
        is exact (:func:`fr_torch.core.exact.exact_sum`), so an image scores the same in any batch.

        Measure b in float32/float64 takes the fused path (module docstring); ``workspace`` (a
        dict, reused across calls of the same shape) lets the grid avoid fresh allocations.
        """
        if self._fast_path(features):
            vps = vanishing_points(focal, features.principal_point[:, None, :], rotation)  # (B, H, 3, 3)
            flat = vp_major(vps)
            constants = self._b_constants(features.weight)
            if torch.is_grad_enabled() and vps.requires_grad:
                return _MeasureBObjective.apply(features.line_along, features.weight, flat, *constants)
            with torch.no_grad():
                if self.compiled:
                    value = compiled_call(objective_b_elementwise, self, features.line_along, features.weight,
                                          flat.contiguous(), *constants)
                    if value is not None:
                        return value
                return objective_b_nograd(features.line_along, features.weight, flat, *constants,
                                          workspace=workspace, vertical_block=vertical_block)
        if self.params.model == "nomixture":
            x = self._deviations(features, rotation, focal).amin(-1)  # (B, N, H)
            log_x = torch.log(x + self.params.scale_horizontal / 100)
            return -exact_sum(log_x, 1, weight=features.weight[:, :, None])
        log_p = self.segment_log_likelihood(features, rotation, focal)
        return exact_sum(log_p, 1, weight=features.weight[:, :, None])

    def segment_log_p(self, features: SegmentFeatures, rotation: torch.Tensor, focal: torch.Tensor) -> torch.Tensor:
        """log p_i of every segment under every hypothesis, (B, N, H) in the segments' dtype, no
        autograd: the terms whose length-weighted sum (:meth:`sum_over_segments`) is the data part of
        :meth:`objective`, bit for bit (the fused path for measure b, else
        :meth:`segment_log_likelihood`)."""
        with torch.no_grad():
            if self._fast_path(features):
                flat = vp_major(vanishing_points(focal, features.principal_point[:, None, :], rotation))
                return objective_b_nograd(features.line_along, features.weight, flat, *self._b_constants(features.weight),
                                          per_segment=True)
            return self.segment_log_likelihood(features, rotation, focal)

    def sum_over_segments(self, log_p: torch.Tensor, features: SegmentFeatures) -> torch.Tensor:
        """``sum_i len_i log p_i`` of per-segment terms (B, N, H) from :meth:`segment_log_p`: (B, H)
        float64, the data part of :meth:`objective` bit for bit (the same exact sum and bound)."""
        bound = _log_sum_bound(features.weight, self._b_constants(features.weight)[-1]) \
            if self._fast_path(features) else None
        return exact_sum(log_p, 1, bound=bound, weight=features.weight[:, :, None])

    def stores_no_deviations(self, features: SegmentFeatures) -> bool:
        """True when scoring without gradients runs the fused kernel (:mod:`fr_torch.core.native`),
        which keeps no per-segment deviations: the grid needs no chunking for memory then."""
        return self._fast_path(features) and not self.compiled and _native_ok(features.weight)

    def _fast_path(self, features: SegmentFeatures) -> bool:
        return (self.params.measure == "b" and self.params.model == "mixture" and features.weight.dtype in _EXP_FLOOR
                and not (features.line.requires_grad or features.along.requires_grad
                         or features.weight.requires_grad)
                and self.params.prior_background > 1e-20)

    def _b_constants(self, like: torch.Tensor):
        """(-1 / lambda (3, 1), log(prior / lambda) (3, 1), background density, exponent floor,
        bound on |log p_i|) of the fused measure-b path."""
        key = (like.dtype, like.device)
        cached = self.__dict__.setdefault("_constants_cache", {}).get(key)
        if cached is None:
            prior, scale = self._family_constants(like)
            p = self.params
            background = p.prior_background / (math.pi / 2)
            # p_i lies between the background density and the background plus every family's peak
            peak = background + float((prior / scale).sum())
            log_bound = max(abs(math.log(background)), abs(math.log(peak)))
            cached = ((-1.0 / scale)[:, None].contiguous(), torch.log(prior / scale)[:, None].contiguous(),
                      background, _EXP_FLOOR[like.dtype], log_bound)
            self._constants_cache[key] = cached
        return cached

    def posteriors(self, features: SegmentFeatures, rotation: torch.Tensor, focal: torch.Tensor,
                   max_chunk_elements: int = 1 << 22):
        """(posterior over the 4 components (B, H, N, 4), log p_i (B, H, N)); column 3 = background.

        Images are processed in slices of at most ``max_chunk_elements`` deviations (bounded memory);
        the log-sum-exp over the 4 components is written out (largest term, then the 4 exponentials
        added in component order), so every value is the same bits in any batch.
        """
        batch, n_seg = features.weight.shape
        step = max(1, max_chunk_elements // max(1, n_seg * rotation.shape[1] * 3))
        if batch > step:
            parts = [self.posteriors(features.images(b, b + step), rotation[b:b + step], focal[b:b + step],
                                     max_chunk_elements) for b in range(0, batch, step)]
            return torch.cat([q for q, _ in parts]), torch.cat([lp for _, lp in parts])
        log_components = self._component_log_densities(self._deviations(features, rotation, focal), features)
        largest = log_components.amax(-1, keepdim=True)
        log_p = (largest + torch.log(small_sum(torch.exp(log_components - largest), -1)[..., None]))[..., 0]
        return torch.exp(log_components - log_p[..., None]).transpose(1, 2), log_p.transpose(1, 2)


def _family_sum(density: torch.Tensor, dim: int) -> torch.Tensor:
    """The three families' densities summed over ``dim`` (size 3, Manhattan column order) as
    ``(horizontal + horizontal) + vertical``: the order of the fused paths, which score the vertical
    VP apart (:func:`objective_b_nograd`), so every path gives the same bits."""
    first, second = [density.select(dim, k) for k in range(3) if k != VERTICAL_AXIS]
    return first + second + density.select(dim, VERTICAL_AXIS)


# --------------------------------------------------------------------------- fused measure-b path

_EXP_FLOOR = {torch.float32: -87.0, torch.float64: -700.0}  # exp() stays out of denormals above these


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
                       fused: bool = True) -> torch.Tensor:
    """Measure-b objective (B, H) float64 for VP-major vanishing points ``flat`` (B, 3, 3H), no autograd;
    with ``per_segment`` each segment's log p_i instead, (B, N, H) in the segments' dtype (a view of
    the ``workspace`` buffer when one is given).

    Every pass is in place on reusable buffers: [s; t] (:func:`incidence`); x = atan(|s / t|)
    (:func:`fr_torch.core.exact.angle_of_`); log(prior/lambda) - x/lambda, clamped at ``floor``;
    exp; the 3 families and the background added as ``(horizontal + horizontal) + vertical +
    background`` (:func:`_family_sum`'s order); log; the length-weighted sum over segments, exact
    (:func:`fr_torch.core.exact.exact_sum`, bounded per image by ``log_bound`` times the longest
    segment).

    ``vertical_block`` = k > 1: runs of k consecutive hypotheses share the vertical VP (column
    ``VERTICAL_AXIS``), so only every k-th one is scored and added to its run: (2 + 1/k) H VP
    columns instead of 3 H, the same sums bit for bit.  H must be a multiple of k.

    ``fused``: the objective of float32 CPU tensors comes from the fused kernel of
    :mod:`fr_torch.core.native` where it is available (the same bits, the deviations never stored);
    False always takes the torch path written here, the reference the kernel is checked against.
    """
    batch, n_seg = weight.shape
    hyp = flat.shape[2] // 3
    if vertical_block > 1 and hyp % vertical_block:
        raise ValueError(f"vertical_block {vertical_block} does not divide the {hyp} hypotheses")
    if fused and not per_segment and vertical_block <= native.TILE and _native_ok(weight):
        factor, scale = _sum_grid(weight, log_bound)
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
    p.add_(background).log_()
    if per_segment:
        return p
    return exact_sum(p, 1, bound=_log_sum_bound(weight, log_bound), weight=weight[:, :, None])


def _native_ok(weight: torch.Tensor) -> bool:
    """Whether segments of ``weight``'s dtype and device take the fused kernels (:mod:`fr_torch.core.native`)."""
    return weight.dtype == torch.float32 and weight.device.type == "cpu" and native.available()


def _sum_grid(weight: torch.Tensor, log_bound: float) -> tuple[torch.Tensor, torch.Tensor]:
    """The fixed-point grid of the objective's exact sum over segments, as
    :func:`fr_torch.core.exact.exact_sum` forms it from the bound :func:`_log_sum_bound`: each
    segment's factor ``weight * scale`` (B, N) in ``weight``'s dtype and the scale (B,) float64."""
    scale = fixed_point_scale(_log_sum_bound(weight, log_bound))  # (B, 1, 1)
    factor = weight[:, :, None] * scale.to(weight.dtype)
    return factor[..., 0], scale.view(-1)


def _log_sum_bound(weight: torch.Tensor, log_bound: float) -> torch.Tensor:
    """(B, 1, 1) bound on ``|len_i log p_i|`` per image: its longest segment times ``log_bound``
    (a bound on |log p_i| for any hypothesis), the same whatever the batch."""
    return (weight.amax(1) * log_bound)[:, None, None] if weight.shape[1] else weight.new_zeros(weight.shape[0], 1, 1)


def objective_b_elementwise(line_along, weight, flat, neg_inv_scale, log_coef, background, floor,
                            log_bound=None) -> torch.Tensor:
    """Measure-b objective (B, H) of :func:`objective_b_nograd` (``vertical_block`` = 1, same
    arguments and terms), written for a compiler: s and t of each VP as broadcast products
    (B, N, 1) x (B, 1, H) instead of buffers, the mixture elementwise, one weighted reduction over
    the N segments.  Eager, this materialises more than the buffered path; under ``torch.compile``
    (:func:`compiled_call`) it is one kernel reading only the segments and the VPs, whose sums the
    compiler orders (equal to :func:`objective_b_nograd` to float rounding, not bit for bit).
    ``flat`` (B, 3, 3H) VP-major and contiguous (:func:`vp_major`).
    """
    batch, n_seg = weight.shape
    hyp = flat.shape[2] // 3
    line, along = line_along[:, :n_seg, :, None], line_along[:, n_seg:, :, None]  # (B, N, 3, 1)
    vps = flat.view(batch, 1, 3, 3, hyp)  # (B, 1, coordinate, VP, H)
    densities = []
    for k in range(3):
        v = vps[:, :, :, k]  # (B, 1, 3, H)
        s = line[:, :, 0] * v[:, :, 0] + line[:, :, 1] * v[:, :, 1] + line[:, :, 2] * v[:, :, 2]
        t = along[:, :, 0] * v[:, :, 0] + along[:, :, 1] * v[:, :, 1] + along[:, :, 2] * v[:, :, 2]
        densities.append(torch.exp(torch.clamp_min(angle_of(s, t) * neg_inv_scale[k] + log_coef[k], floor)))
    mixture = _family_sum(torch.stack(densities, -1), -1)
    return (weight[:, :, None] * torch.log(mixture + background)).to(torch.float64).sum(1)


_COMPILED: dict = {}  # function -> its torch.compile wrapper, one per process


def compiled_call(fn, owner, *args):
    """``fn(*args)`` through ``torch.compile(fn, dynamic=True)`` (compiled on the first call, one
    compilation per process and device serves every batch, segment and hypothesis count).

    ``owner`` (a :class:`MixtureLikelihood`) has ``compiled`` set to False, with one warning, when
    compiling or running the kernel fails (no C++ compiler, no Triton, an unsupported backend);
    the call then returns None and the caller takes its eager path.
    """
    compiled = _COMPILED.get(fn)
    if compiled is None:
        compiled = _COMPILED[fn] = torch.compile(fn, dynamic=True)
    try:
        return compiled(*args)
    except Exception as exc:
        owner.compiled = False
        first_line = (str(exc).strip().splitlines() or [""])[0][:200]
        warnings.warn(f"fR: compiled search unavailable ({type(exc).__name__}: {first_line}); running without it",
                      RuntimeWarning, stacklevel=3)
        return None


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
    return s.clamp_min_(floor).exp_()


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
    e = (theta * neg_inv_scale).add_(log_coef).clamp_min_(floor).exp_()  # prior/lambda exp(-x/lambda)
    p = _family_sum(e, 2).add_(background)
    objective = exact_sum(torch.log(p), 1, bound=_log_sum_bound(weight, log_bound), weight=weight[:, :, None])
    return objective, (line_along, weight, s, t, e, p, neg_inv_scale)


def measure_b_objective_and_grad(line_along, weight, flat, constants, grad_out, fused: bool = True):
    """Measure-b objective (B, H) float64 and its gradient with respect to the VP-major vanishing
    points ``flat`` (B, 3, 3H), float64, for the upstream gradient ``grad_out`` (broadcastable to
    (B, H)): :func:`measure_b_forward` then :func:`measure_b_backward`, or for float32 CPU tensors
    the fused kernel of :mod:`fr_torch.core.native` (the same bits in one pass; ``fused`` = False
    always takes the torch path).  ``constants``: :meth:`MixtureLikelihood._b_constants`."""
    batch, hyp = weight.shape[0], flat.shape[2] // 3
    if fused and _native_ok(weight):
        neg_inv_scale, log_coef, background, floor, log_bound = constants
        factor, scale = _sum_grid(weight, log_bound)
        return native.measure_b_grad(line_along, weight, factor, scale, flat, neg_inv_scale, log_coef, background,
                                     floor, VERTICAL_AXIS, grad_out.to(weight.dtype))
    objective, saved = measure_b_forward(line_along, weight, flat, *constants)
    return objective, measure_b_backward(saved, grad_out.to(weight.dtype).expand(batch, hyp).contiguous())


def measure_b_backward(saved, grad_out, flat: torch.Tensor | None = None):
    """d objective / d flat (B, 3, 3H) float64 for the upstream gradient ``grad_out`` (B, H).

    With ``flat`` (the forward pass's VP-major vanishing points) also d objective / d line_along,
    (B, 2N, 3): ``d obj / d l_i = sum_v G_is v``, ``d obj / d g_i = sum_v G_it v`` (the distortion
    parameter's chain, :mod:`fr_torch.core.distortion`).  Returns the one tensor, or the pair.
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


def kernels_match_torch() -> bool:
    """The fused kernels (:mod:`fr_torch.core.native`) against the torch path on random scenes (segments through a VP, VPs at
    infinity, no segments, several tiles and MKL calls, ``vertical_block`` 1 to 3): True when every
    score, objective and gradient has the same bits (about 0.1 s, once per process)."""
    generator = torch.Generator().manual_seed(60)
    constants = MixtureLikelihood()._b_constants(torch.zeros(1))
    for batch, n_seg, hyp, block in ((2, 37, 10, 1), (1, 5, 9, 3), (2, 300, 6, 3), (1, 12, 300, 3), (2, 0, 4, 2)):
        line = torch.randn(batch, n_seg, 3, generator=generator)
        line[..., :2] /= line[..., :2].norm(dim=-1, keepdim=True)
        along = torch.randn(batch, n_seg, 3, generator=generator) * 300
        along[:, :3] = 0.0  # t = 0: s / t infinite
        line[:, 3:4] = 0.0  # with t = 0 too: s / t = 0 / 0
        along[:, 3:4] = 0.0
        line_along = torch.cat([line, along], 1)
        weight = torch.rand(batch, n_seg, generator=generator) * 100
        flat = torch.randn(batch, 3, 3 * hyp, generator=generator) * torch.tensor([[400.0], [400.0], [1.0]])
        flat[0, 2, :hyp] = 0.0  # VPs at infinity
        expected = objective_b_nograd(line_along, weight, flat, *constants, vertical_block=block, fused=False)
        got = objective_b_nograd(line_along, weight, flat, *constants, vertical_block=block)
        grad_out = -1.0 / (1.0 + torch.rand(batch, 1, generator=generator) * 1000)
        expected_pair = measure_b_objective_and_grad(line_along, weight, flat, constants, grad_out, fused=False)
        got_pair = measure_b_objective_and_grad(line_along, weight, flat, constants, grad_out)
        for a, b in ((expected, got), *zip(expected_pair, got_pair)):
            if not torch.equal(a.view(torch.int64), b.view(torch.int64)):
                return False
    return True


native.register_check(kernels_match_torch)


class _MeasureBObjective(torch.autograd.Function):
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
