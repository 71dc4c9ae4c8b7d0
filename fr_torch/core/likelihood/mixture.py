"""The 4-way mixture likelihood of line segments and its parameters.

Every segment is explained by one of the three Manhattan families (vanishing point i = K R[:, i];
column 1 is the vertical) or by a uniform background.  The deviation of a segment from a
vanishing point is one of the measures (a)-(e) of :mod:`fr_torch.core.likelihood.measures`.

Likelihoods: exponential ``exp(-x / lambda) / lambda`` for a, b, c, e; half-normal (a central
Gaussian on the signed deviation, sigma = 1 px by default) for d; background uniform over the
measure's range (pi/2 for b and e, ``range`` px for a, the half length for c and d; measures are
clamped to their range).  Objective: ``sum_i len_i * log p_i``, plus the focal prior
(:class:`LikelihoodParams`).

The vertical parameters (lambda and prior) go on the world-up column (column 1), as in the
paper.  The authors' MATLAB release attaches them to a horizontal column instead; we follow the
paper.

Speed (measure b, the default): :meth:`MixtureLikelihood.objective` evaluates the same mixture
with the fused path of :mod:`fr_torch.core.likelihood.objective` (and its C kernels on a CPU,
checked bit for bit against the torch path once per process by :func:`kernels_match_torch`).

One photo, one answer: s and t are written out per entry, the angle is ``atan(|s / t|)``, the
families are added in one order on every path
(:func:`~fr_torch.core.likelihood.objective.family_sum`) and every sum over segments is exact
(:func:`fr_torch.core.exact.exact_sum`), so an image's objective (float64) is the same bits in
any batch, chunk, thread count and CPU kernel set (:mod:`fr_torch.core.exact`).
"""
from __future__ import annotations

import json
import math
from dataclasses import dataclass, replace
from pathlib import Path

import torch

from fr_torch.core.exact import exact_sum, small_sum
from fr_torch.core.geometry.conventions import VERTICAL_AXIS, focal_from_hfov, vanishing_points
from fr_torch.core.likelihood import native
from fr_torch.core.likelihood.measures import (
    MEASURES,
    RANGE_PX,
    SegmentFeatures,
    deviations_from_incidence,
    incidence,
    incidence_of,
)
from fr_torch.core.likelihood.objective import (
    EXP_FLOOR,
    MeasureBObjective,
    family_sum,
    log_sum_bound,
    measure_b_objective_and_grad,
    native_ok,
    objective_b_nograd,
    sum_grid,
    vp_major,
)
from fr_torch.core.settings.config import Mode
from fr_torch.core.settings.fov import FOV_LIMITS_DEG, FovRange
from fr_torch.resources import config_dir
from fr_torch.core import exact_math

MODELS = ("mixture", "nomixture")
CONFIG_DIR = config_dir()  # the shipped configs/ folder (fr_torch/resources.py)
DEFAULT_LIKELIHOOD_CONFIG = CONFIG_DIR / "likelihood.json"


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
    range_px: float = RANGE_PX
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


class MixtureLikelihood:
    """The fR mixture model for one deviation measure; all methods are batched tensor ops.

    Hypotheses come as rotations (B, H, 3, 3) and focal lengths (B, H) in pixels.
    """

    def __init__(self, params: LikelihoodParams | None = None):
        self.params = params or LikelihoodParams.from_config()
        # log(f0 / L): the focal prior's centre as a focal length per pixel of the long side
        self._prior_centre = exact_math.of(exact_math.log, focal_from_hfov(self.params.focal_prior_hfov_deg, 1.0))

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
            return x.new_full((1, 1, 1, 1), exact_math.of(exact_math.log, p.prior_background / (math.pi / 2)))
        if p.measure == "a":
            return x.new_full((1, 1, 1, 1), exact_math.of(exact_math.log, p.prior_background / p.range_px))
        half = features.half_length.clamp_min(1e-6)[:, :, None, None]  # c, d: uniform on [0, len/2]
        return exact_math.of(exact_math.log, p.prior_background) - exact_math.log(half)

    def background_density(self, features: SegmentFeatures) -> torch.Tensor:
        """The uniform background's density (without its prior) at every segment, (B, N), in
        ``features.weight``'s dtype: the last column of :meth:`component_log_densities`, whose
        value depends on the segments alone."""
        x = features.weight[..., None, None]  # (B, N, 1, 1)
        log_prior_density = self._log_background(x, features).expand_as(x)[..., 0, 0]
        return exact_math.exp(log_prior_density) / self.params.prior_background

    def _deviations(self, features, rotation, focal) -> torch.Tensor:
        s, t, v3 = incidence_of(features, rotation, focal)
        return deviations_from_incidence(self.params.measure, s, t, v3, features, focal, self.params.range_px)

    def _component_log_densities(self, x: torch.Tensor, features: SegmentFeatures) -> torch.Tensor:
        """log(prior * density) of the 3 families and the background, (B, N, H, 4)."""
        prior, scale = self._family_constants(x)
        if self.params.measure == "d":
            family = exact_math.log(prior * math.sqrt(2 / math.pi) / scale) - 0.5 * (x / scale) ** 2
        else:
            family = exact_math.log(prior / scale) - x / scale
        background = self._log_background(x, features).expand_as(x[..., :1])
        return torch.cat([family, background], -1)

    def component_log_densities(self, features: SegmentFeatures, rotation: torch.Tensor,
                                focal: torch.Tensor) -> torch.Tensor:
        """log(prior * density) of the 3 families and the background for every segment under every
        hypothesis (rotations (B, H, 3, 3), focal lengths (B, H)), (B, N, H, 4); column 3 = background."""
        return self._component_log_densities(self._deviations(features, rotation, focal), features)

    def point_deviations(self, features: SegmentFeatures, vps: torch.Tensor, focal: torch.Tensor) -> torch.Tensor:
        """Deviation of every segment from A homogeneous VPs ``vps`` (B, A, 3) in pixels, (B, N, A),
        internal units; ``focal`` (B,) or (B, A) pixels (measure e: each VP's camera).  For measure
        e the VPs must be ``K d`` with unit directions ``d``, as a column of R gives."""
        flat = vps.transpose(1, 2).to(features.line.dtype)  # (B, 3, A)
        s = incidence(features.line, flat)[..., None]  # (B, N, A, 1)
        t = incidence(features.along, flat)[..., None]
        v3 = flat[:, None, 2, :, None]  # (B, 1, A, 1)
        focal = focal.to(flat.dtype)
        focal = focal[:, None].expand(-1, flat.shape[-1]) if focal.dim() == 1 else focal
        return deviations_from_incidence(self.params.measure, s, t, v3, features, focal, self.params.range_px)[..., 0]

    def horizontal_log_density(self, x: torch.Tensor) -> torch.Tensor:
        """log density (without the prior) of a horizontal family at deviations ``x`` (internal units)."""
        return self.family_log_density(x, self.params.scale_horizontal)

    def family_log_density(self, x: torch.Tensor, scale) -> torch.Tensor:
        """log density (without the prior) of a family at deviations ``x`` (internal units) whose
        scale is ``scale`` (a number, or a tensor broadcastable to ``x``): exponential with mean
        ``scale``, or for measure d half-normal with sigma ``scale``."""
        half_normal = self.params.measure == "d"
        if torch.is_tensor(scale):
            log_norm = (exact_math.of(exact_math.log, math.sqrt(2 / math.pi)) if half_normal else 0.0) - exact_math.log(scale)
        else:
            log_norm = exact_math.of(exact_math.log, math.sqrt(2 / math.pi) / scale) if half_normal else -exact_math.of(exact_math.log, scale)
        return log_norm - 0.5 * (x / scale) ** 2 if half_normal else log_norm - x / scale

    def fitted_scale(self, x: torch.Tensor, weight: torch.Tensor) -> torch.Tensor:
        """The scale of :meth:`family_log_density` that maximises ``sum weight log density(x)``
        (the last dimension summed, exactly): the weighted mean of x, or for measure d the root
        of the weighted mean of x^2.  ``x``, ``weight`` (..., N); returns (...)."""
        total = exact_sum(weight, -1).clamp_min(1e-300)
        if self.params.measure == "d":
            return exact_math.sqrt(exact_sum(x * x, -1, weight=weight) / total)
        return exact_sum(x, -1, weight=weight) / total

    def segment_log_likelihood(self, features: SegmentFeatures, rotation: torch.Tensor,
                               focal: torch.Tensor) -> torch.Tensor:
        """log p_i of every segment under every hypothesis, (B, N, H).

        Fast path: the background term keeps p_i >= prior_bg * density_bg > 0, so the mixture is
        summed directly, without a log-sum-exp.
        """
        x = self._deviations(features, rotation, focal)
        prior, scale = self._family_constants(x)
        if self.params.measure == "d":
            density = exact_math.exp(-0.5 * (x / scale) ** 2) * (prior * math.sqrt(2 / math.pi) / scale)
        else:
            density = exact_math.exp(x * (-1.0 / scale)) * (prior / scale)
        background = exact_math.exp(self._log_background(density, features))[..., 0]
        return exact_math.log(family_sum(density, -1) + background)

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
            value = value + self.focal_prior(features, focal, derivative=False)[0]
        return value

    def focal_prior(self, features: SegmentFeatures, focal: torch.Tensor,
                    derivative: bool = True) -> tuple[torch.Tensor, torch.Tensor | None]:
        """The log focal prior (see :class:`LikelihoodParams`) and its derivative d/df (per pixel)
        of the images of ``features`` (:meth:`focal_prior_of`; their curvature
        :meth:`focal_prior_curvature` is kept with the features, :meth:`SegmentFeatures.constant`).

        ``focal`` (B, H) pixels.  Returns two (B, H) tensors in ``features.weight``'s dtype (the
        derivative None without ``derivative``).
        """
        dtype = features.weight.dtype
        return self._focal_prior_at(self.focal_prior_curvature_for(features), features.long_side, focal.to(dtype),
                                    derivative)

    def focal_prior_curvature_for(self, features: SegmentFeatures) -> torch.Tensor:
        """:meth:`focal_prior_curvature` of the images of ``features``, (B,) in ``features.weight``'s
        dtype, computed once per features (:meth:`SegmentFeatures.constant`)."""
        dtype, params = features.weight.dtype, self.params
        return features.constant(
            ("focal_prior_curvature", dtype, params.focal_prior_weight, params.focal_prior_pseudo_length),
            lambda: self.focal_prior_curvature(features.total_length().to(dtype), features.long_side))

    def focal_prior_of(self, total_length: torch.Tensor, long_side: torch.Tensor,
                       focal: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The log focal prior and its derivative d/df (per pixel) of images whose segments add up
        to ``total_length`` (B,) pixels (float64, :meth:`SegmentFeatures.total_length`: an exact
        sum, the same in any batch) and whose long side is ``long_side`` (B,) pixels.

        ``focal`` (B, H) pixels.  Returns two (B, H) tensors in ``focal``'s dtype.
        """
        return self._focal_prior_at(self.focal_prior_curvature(total_length.to(focal.dtype), long_side), long_side,
                                    focal)

    def _focal_prior_at(self, curvature: torch.Tensor, long_side: torch.Tensor, focal: torch.Tensor,
                        derivative: bool = True) -> tuple[torch.Tensor, torch.Tensor | None]:
        """:meth:`focal_prior_of` from the images' :meth:`focal_prior_curvature` (B,) in ``focal``'s
        dtype; the derivative None without ``derivative``."""
        weight = curvature[:, None]  # (B, 1)
        offset = exact_math.log(focal / long_side[:, None]) - self._prior_centre
        flat = self.params.focal_prior_flat_halfwidth
        if flat:  # the distance to the flat band |log(f / f0)| <= h, signed
            offset = torch.sign(offset) * (offset.abs() - flat).clamp_min(0.0)
        return -0.5 * weight * offset ** 2, (-weight * offset / focal) if derivative else None

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
        if self.fast_path(features):
            vps = vanishing_points(focal, features.principal_point[:, None, :], rotation)  # (B, H, 3, 3)
            flat = vp_major(vps)
            constants = self._b_constants(features.weight)
            if torch.is_grad_enabled() and vps.requires_grad:
                return MeasureBObjective.apply(features.line_along, features.weight, flat, *constants)
            with torch.no_grad():
                grid = self.b_sum_grid(features) if native_ok(features.weight) else None  # the fused kernel's input
                return objective_b_nograd(features.line_along, features.weight, flat, *constants,
                                          workspace=workspace, vertical_block=vertical_block, grid=grid)
        if self.params.model == "nomixture":
            x = self._deviations(features, rotation, focal).amin(-1)  # (B, N, H)
            log_x = exact_math.log(x + self.params.scale_horizontal / 100)
            return -exact_sum(log_x, 1, weight=features.weight[:, :, None])
        log_p = self.segment_log_likelihood(features, rotation, focal)
        return exact_sum(log_p, 1, weight=features.weight[:, :, None])

    def segment_log_p(self, features: SegmentFeatures, rotation: torch.Tensor, focal: torch.Tensor) -> torch.Tensor:
        """log p_i of every segment under every hypothesis, (B, N, H) in the segments' dtype, no
        autograd: the terms whose length-weighted sum (:meth:`sum_over_segments`) is the data part of
        :meth:`objective`, bit for bit (the fused path for measure b, else
        :meth:`segment_log_likelihood`)."""
        with torch.no_grad():
            if self.fast_path(features):
                flat = vp_major(vanishing_points(focal, features.principal_point[:, None, :], rotation))
                return objective_b_nograd(features.line_along, features.weight, flat, *self._b_constants(features.weight),
                                          per_segment=True)
            return self.segment_log_likelihood(features, rotation, focal)

    def sum_over_segments(self, log_p: torch.Tensor, features: SegmentFeatures) -> torch.Tensor:
        """``sum_i len_i log p_i`` of per-segment terms (B, N, H) from :meth:`segment_log_p`: (B, H)
        float64, the data part of :meth:`objective` bit for bit (the same exact sum and bound)."""
        bound = log_sum_bound(features.weight, self._b_constants(features.weight)[-1]) \
            if self.fast_path(features) else None
        return exact_sum(log_p, 1, bound=bound, weight=features.weight[:, :, None])

    def stores_no_deviations(self, features: SegmentFeatures) -> bool:
        """True when scoring without gradients runs the fused kernel (:mod:`fr_torch.core.likelihood.native`),
        which keeps no per-segment deviations: the grid needs no chunking for memory then."""
        return self.fast_path(features) and native_ok(features.weight)

    def fast_path(self, features: SegmentFeatures) -> bool:
        return (self.params.measure == "b" and self.params.model == "mixture" and features.weight.dtype in EXP_FLOOR
                and not (features.line.requires_grad or features.along.requires_grad
                         or features.weight.requires_grad)
                and self.params.prior_background > 1e-20)

    def b_sum_grid(self, features: SegmentFeatures) -> tuple[torch.Tensor, torch.Tensor]:
        """The fixed-point grid of the fused measure-b objective's exact sum over the segments of
        ``features`` (:func:`fr_torch.core.likelihood.objective.sum_grid`: each segment's factor
        (B, N), the scale (B,)), computed once per features (:meth:`SegmentFeatures.constant`)."""
        log_bound = self._b_constants(features.weight)[-1]
        return features.constant(("sum_grid", log_bound), lambda: sum_grid(features.weight, log_bound))

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
            log_bound = max(abs(exact_math.of(exact_math.log, background)), abs(exact_math.of(exact_math.log, peak)))
            cached = ((-1.0 / scale)[:, None].contiguous(), exact_math.log(prior / scale)[:, None].contiguous(),
                      background, EXP_FLOOR[like.dtype], log_bound)
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
        log_p = (largest + exact_math.log(small_sum(exact_math.exp(log_components - largest), -1)[..., None]))[..., 0]
        return exact_math.exp(log_components - log_p[..., None]).transpose(1, 2), log_p.transpose(1, 2)


def kernels_match_torch() -> bool:
    """The fused kernels (:mod:`fr_torch.core.likelihood.native`) against the torch path on random scenes (segments through a VP, VPs at
    infinity, no segments, several tiles and MKL calls, ``vertical_block`` 1 to 3): True when every
    score, objective and gradient has the same bits (about 0.1 s, once per process)."""
    generator = torch.Generator().manual_seed(60)
    constants = MixtureLikelihood()._b_constants(torch.zeros(1))
    for batch, n_seg, hyp, block in ((2, 37, 10, 1), (1, 5, 9, 3), (2, 300, 6, 3), (1, 12, 300, 3), (2, 0, 4, 2)):
        line = torch.randn(batch, n_seg, 3, generator=generator)
        line[..., :2] /= exact_math.sqrt(line[..., 0:1] * line[..., 0:1] + line[..., 1:2] * line[..., 1:2])
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
