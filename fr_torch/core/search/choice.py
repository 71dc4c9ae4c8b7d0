"""Which fit a photo reports: the Manhattan fit's, or the horizon fit's horizon on the Manhattan
fit's camera (``SearchConfig.fit``: ``manhattan``, ``horizon`` or ``choose``).

:func:`choose_fit` runs the horizon fit (:mod:`fr_torch.core.search.horizon`) where the setting
asks for it; with ``choose`` a logistic rule learned on a train split (:class:`HorizonChooser`,
``configs/horizon_choice.json``) weighs the photo's own evidence (:func:`choice_features`,
:data:`CHOICE_FEATURES`, reported as cues ``choice_*``).  What is reported from the horizon fit is
its horizon with the Manhattan fit's focal length and horizontal directions (:func:`fit_on_horizon`).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from fr_torch.core.exact import cross3, dot3
from fr_torch.core.geometry.conventions import horizon_angles
from fr_torch.core.geometry.params import FOCAL, PITCH, ROLL, angles_from_search_rotation, rotations
from fr_torch.core.likelihood.measures import SegmentFeatures
from fr_torch.core.likelihood.mixture import MixtureLikelihood
from fr_torch.core.search.horizon import HorizonFit, fit_horizon, horizon_vote, pitch_roll_in_box, unit
from fr_torch.core.settings.config import SearchConfig

#: The evidence the choice weighs (:func:`choice_features`), in the order of the chooser's weights.
CHOICE_FEATURES = ("vote_gain", "manhattan_vote", "horizon_vote", "mixture_loss", "horizon_shift", "focal_ratio",
                   "tilt_change", "manhattan_tilt")
#: The chooser reads each piece of evidence clipped to [-EVIDENCE_CLIP, EVIDENCE_CLIP] (:func:`clean_evidence`).
EVIDENCE_CLIP = 10.0
#: Where the chooser's weights are shipped (``configs/``; ``eval/protocols/horizon_choice.py`` writes it).
CHOOSER_CONFIG = "horizon_choice.json"


@dataclass(frozen=True)
class HorizonChooser:
    """A linear rule on :data:`CHOICE_FEATURES`: the horizon is taken where
    ``sum_k coef_k (x_k - mean_k) / scale_k + intercept > 0`` (a logistic regression's decision,
    learned on a train split by ``eval/protocols/horizon_choice.py``; ``trained_on`` says which).
    Features are cleaned first (:func:`clean_evidence`)."""

    mean: tuple[float, ...]
    scale: tuple[float, ...]
    coef: tuple[float, ...]
    intercept: float
    trained_on: str = ""

    @classmethod
    def load(cls, path=None) -> "HorizonChooser":
        """The chooser of ``path`` (JSON; default the shipped ``configs/horizon_choice.json``);
        FRInputError (one line) when it is missing or malformed."""
        import json

        from fr_torch.errors import FRInputError
        from fr_torch.resources import config_path

        path = config_path(CHOOSER_CONFIG) if path is None else path
        try:
            values = json.loads(open(path).read())
            if list(values["features"]) != list(CHOICE_FEATURES):
                raise ValueError(f"features {values['features']} are not {list(CHOICE_FEATURES)}")
            chooser = cls(tuple(map(float, values["mean"])), tuple(map(float, values["scale"])),
                          tuple(map(float, values["coef"])), float(values["intercept"]), str(values.get("trained_on", "")))
        except (OSError, ValueError, KeyError, TypeError) as exc:
            raise FRInputError(f"horizon chooser {path}: not a usable chooser ({exc})") from None
        if not (len(chooser.mean) == len(chooser.scale) == len(chooser.coef) == len(CHOICE_FEATURES)):
            raise FRInputError(f"horizon chooser {path}: needs one mean, scale and coef per feature")
        return chooser

    def score(self, evidence: dict[str, torch.Tensor]) -> torch.Tensor:
        """The rule's score (B,) float64 of :func:`choice_features`' ``evidence``; > 0 takes the horizon.
        The terms are added in the features' order (the same bits everywhere)."""
        total = torch.full_like(evidence[CHOICE_FEATURES[0]], self.intercept, dtype=torch.float64)
        for name, mean, scale, coef in zip(CHOICE_FEATURES, self.mean, self.scale, self.coef):
            total = total + (clean_evidence(evidence[name]) - mean) / scale * coef
        return total


def clean_evidence(x: torch.Tensor) -> torch.Tensor:
    """Evidence (any shape) as :class:`HorizonChooser` reads it: float64, NaN -> 0, clipped to
    [-:data:`EVIDENCE_CLIP`, :data:`EVIDENCE_CLIP`]."""
    return x.to(torch.float64).nan_to_num(nan=0.0, posinf=EVIDENCE_CLIP, neginf=-EVIDENCE_CLIP).clamp(
        -EVIDENCE_CLIP, EVIDENCE_CLIP)


@dataclass
class FitChoice:
    """What :func:`choose_fit` returns: ``params`` (B, 4) float64 the chosen rows and ``scores`` (B,)
    float64 their mixture objective (NaN where the Manhattan fit was kept: its own score stands),
    ``horizon`` (B,) bool where the horizon was chosen, ``tied`` (B,) bool where the choice's score
    is zero to within rounding (another machine could choose the other), ``evidence`` the
    :data:`CHOICE_FEATURES` (B,) float64 each (empty when the horizon fit did not run)."""

    params: torch.Tensor
    scores: torch.Tensor
    horizon: torch.Tensor
    tied: torch.Tensor
    evidence: dict


def border_heights(params: torch.Tensor, principal_point: torch.Tensor, image_size: torch.Tensor) -> torch.Tensor:
    """Where the horizons of rows (B, 4) cross the borders ``x = 0`` and ``x = w - 1``: y (B, 2)
    float64 pixels (``principal_point`` (B, 2), ``image_size`` (B, 2) [width, height] pixels)."""
    params = params.to(torch.float64)
    down = rotations(params)[..., :, 1]
    pp = principal_point.to(torch.float64)
    focal = params[:, FOCAL]
    # l = K^-T d: (d_x / f, d_y / f, d_z - (c_x d_x + c_y d_y) / f)
    a, b = down[:, 0] / focal, down[:, 1] / focal
    c = down[:, 2] - (pp[:, 0] * down[:, 0] + pp[:, 1] * down[:, 1]) / focal
    columns = torch.stack([torch.zeros_like(a), image_size[:, 0].to(torch.float64) - 1.0], -1)
    return -(a[:, None] * columns + c[:, None]) / b[:, None]


def mixture_loss(manhattan_scores: torch.Tensor, held_scores: torch.Tensor, total_length: torch.Tensor) -> torch.Tensor:
    """``log(1 + |L_m - L_h| / W)`` (B,) float64: how much the mixture objective loses between the
    Manhattan fit's camera (``manhattan_scores``) and the camera on the horizon (``held_scores``),
    per unit of the images' segment length ``total_length`` W (pixels).  Written ``log(1 + x)``:
    ``torch.log1p``'s kernels round differently under the default CPU kernel set than under AVX2,
    ``log``'s do not (:mod:`fr_torch.core.exact`)."""
    return torch.log(1.0 + (manhattan_scores.to(torch.float64) - held_scores).abs() / total_length)


def choice_features(features: SegmentFeatures, manhattan: torch.Tensor, manhattan_scores: torch.Tensor,
                    fit: "HorizonFit", held: torch.Tensor, held_scores: torch.Tensor, votes: torch.Tensor,
                    image_size: torch.Tensor) -> dict[str, torch.Tensor]:
    """The evidence of the choice (:data:`CHOICE_FEATURES`, (B,) float64 each): ``vote_gain`` the
    horizon fit's smooth vote minus the Manhattan fit's, ``manhattan_vote`` / ``horizon_vote`` the
    two votes (all per unit segment length); ``mixture_loss`` ``log(1 + |L_m - L_h| / total length)``
    of the mixture objective of the Manhattan fit and of the camera on the horizon (10 where that
    camera leaves the box); ``horizon_shift`` the larger border distance between the two horizons
    (share of the height); ``focal_ratio`` ``log(f_sweep / f_manhattan)``; ``tilt_change`` and
    ``manhattan_tilt`` in degrees."""
    total = features.total_length().clamp_min(1e-9)
    loss = mixture_loss(manhattan_scores, held_scores, total)
    shift = (border_heights(held, features.principal_point, image_size)
             - border_heights(manhattan, features.principal_point, image_size)).abs().amax(-1)
    tilt_m = horizon_angles(rotations(manhattan))["tilt_deg"]
    tilt_h = horizon_angles(rotations(held))["tilt_deg"]
    return {"vote_gain": (votes[:, 1] - votes[:, 0]) / total, "manhattan_vote": votes[:, 0] / total,
            "horizon_vote": votes[:, 1] / total,
            "mixture_loss": torch.where(torch.isfinite(held_scores), loss, torch.full_like(loss, 10.0)),
            "horizon_shift": shift / image_size[:, 1].to(torch.float64),
            "focal_ratio": torch.log(fit.params[:, FOCAL] / manhattan[:, FOCAL]),
            "tilt_change": (tilt_h - tilt_m).abs(), "manhattan_tilt": tilt_m.abs()}


def choose_fit(likelihood: MixtureLikelihood, features: SegmentFeatures, manhattan: torch.Tensor,
               manhattan_scores: torch.Tensor, lower: torch.Tensor, upper: torch.Tensor, image_size: torch.Tensor,
               search: SearchConfig, chooser: HorizonChooser | None = None) -> FitChoice:
    """The fit ``search.fit`` asks for, per image of ``features``: ``manhattan`` (B, 4) the Manhattan
    fit's rows and ``manhattan_scores`` (B,) their mixture objective, ``lower`` / ``upper`` (B, 4)
    the search box, ``image_size`` (B, 2) [width, height] pixels.

    ``horizon``: wherever the horizon fit finds a vertical, its horizon with the Manhattan fit's
    focal length and horizontal directions (:func:`fit_on_horizon`); ``choose``: the same where,
    besides, ``chooser`` (default the shipped one, :meth:`HorizonChooser.load`) scores the
    evidence (:func:`choice_features`) above 0; ``manhattan``: the Manhattan fit (the horizon fit
    does not run).  A camera on the horizon that leaves the box keeps the Manhattan fit."""
    manhattan = manhattan.to(torch.float64)
    batch = manhattan.shape[0]
    none = torch.zeros(batch, dtype=torch.bool, device=manhattan.device)
    kept = torch.full((batch,), math.nan, dtype=torch.float64, device=manhattan.device)
    if search.fit == "manhattan":
        return FitChoice(manhattan, kept, none, none, {})
    fit = fit_horizon(features, lower, upper, search.horizon, search.periodic_pan)
    votes = horizon_vote(features, torch.stack([manhattan, fit.params], 1), search.horizon)
    held, scores = fit_on_horizon(likelihood, features, fit.params, manhattan, lower, upper)
    evidence = choice_features(features, manhattan, manhattan_scores, fit, held, scores, votes, image_size)
    use = fit.found & torch.isfinite(scores)  # a horizon no camera in the box has: the Manhattan fit stays
    tied = none
    if search.fit == "choose":
        score = (chooser or HorizonChooser.load()).score(evidence)
        tied = use & (score.abs() <= 1e-9)
        use = use & (score > 0)
    return FitChoice(torch.where(use[:, None], held, manhattan), torch.where(use, scores, kept), use, tied, evidence)


def horizon_of(params: torch.Tensor, long_side: torch.Tensor) -> torch.Tensor:
    """The horizon lines (B, 3) float64 of rows (B, 4), in normalised coordinates (module docstring):
    ``K^-T R[:, 1]`` with ``K = diag(phi, phi, 1)``."""
    params = params.to(torch.float64)
    down = rotations(params)[..., :, 1]
    phi = params[:, FOCAL] / long_side.to(torch.float64)
    return torch.stack([down[:, 0] / phi, down[:, 1] / phi, down[:, 2]], -1)


def fit_on_horizon(likelihood: MixtureLikelihood, features: SegmentFeatures, horizon_params: torch.Tensor,
                   manhattan: torch.Tensor, lower: torch.Tensor, upper: torch.Tensor):
    """The camera with the horizon of ``horizon_params`` (B, 4) and the focal length of
    ``manhattan`` (B, 4), the Manhattan fit (its f is the more accurate, the horizon fit's horizon
    the more precise): the vertical is the horizon's pole ``K^T h`` at that f, the first horizontal
    direction the Manhattan fit's projected on the plane normal to it (the least rotation of the
    Manhattan fit's frame that puts its horizon on the horizon fit's).  Returns (params (B, 4)
    float64; their mixture objective (:meth:`MixtureLikelihood.objective`, B,) float64, -inf where
    pitch or roll leaves the box ``lower`` / ``upper`` (B, 4))."""
    long_side = features.long_side.to(torch.float64)
    horizon = horizon_of(horizon_params, long_side)
    manhattan = manhattan.to(torch.float64)
    focal = manhattan[:, FOCAL]
    phi = (focal / long_side)[:, None]
    down = unit(torch.cat([phi * horizon[:, :2], horizon[:, 2:]], -1))  # K^T h: the vertical
    down = torch.where(down[..., 1:2] < 0, -down, down)
    frame = rotations(manhattan)
    first = frame[..., 0] - dot3(frame[..., 0], down)[:, None] * down
    other = frame[..., 2] - dot3(frame[..., 2], down)[:, None] * down
    first = unit(torch.where((dot3(first, first) >= dot3(other, other))[:, None], first, cross3(other, down)))
    rotation = torch.stack([first, down, cross3(first, down)], -1)
    angles = angles_from_search_rotation(rotation)
    params = torch.cat([angles, focal[:, None]], -1)
    lower64, upper64 = lower.to(torch.float64), upper.to(torch.float64)
    inside = pitch_roll_in_box(angles[:, PITCH], angles[:, ROLL], lower64, upper64)
    dtype = features.weight.dtype
    value = likelihood.objective(features, rotations(params)[:, None].to(dtype), focal[:, None].to(dtype))[:, 0]
    return params, torch.where(inside, value.double(), torch.full_like(focal, -math.inf))
