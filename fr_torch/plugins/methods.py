"""fR and Fast-fR behind the common :class:`~fr_torch.plugins.interface.Calibrator` interface.

Registered names: ``fr``, ``fast-fr`` (image in, LSD or another detector), and ``oracle-fr``
(fR run on the segments given in ``ImageMeta.segments``, e.g. a dataset's hand-labelled lines: the
upper bound of a line-based method).  Options select configurations:
``fr[measure=a]`` ... ``fr[measure=e]`` (deviation measure), ``fr[detector=mcmlsd]``,
``fr[likelihood=paper]`` (likelihood config by name or path, see
:func:`fr_torch.core.likelihood.mixture.likelihood_config_path`), ``fr[range=paper]`` / ``fr[range=40:130]``
(the FOV search range across the long side, anything :meth:`fr_torch.core.settings.fov.FovRange.parse`
accepts: ``paper`` = [50, 130], ``default`` = [30, 120]), ``fr[model=nomixture]`` (the paper's "no
probabilistic model" ablation, see :class:`fr_torch.core.likelihood.mixture.LikelihoodParams`),
``fr[atlanta=on]`` (extra horizontal vanishing points at free azimuths, ranked with the Manhattan
three; f and R unchanged; ``atlanta=max_extra=2:prior=0.05`` sets its parameters, see
:class:`fr_torch.core.geometry.vanishing.AtlantaConfig`).  Every estimate carries fR's vanishing points
ranked by support (``CameraEstimate.ranked_vanishing_points``).  ``fr[distortion=division]`` /
``fr[distortion=auto]`` (radial distortion estimated, see :mod:`fr_torch.core.geometry.lens`) and
``fr[k=-0.2]`` (a known k); ``fr[families=auto]`` (extra horizontal families inside the likelihood,
:class:`fr_torch.core.settings.config.FamiliesConfig`); ``fr[working_long_side=640]`` /
``fr[working_long_side=input]`` (the cap on the long side the lines are detected at,
:func:`fr_torch.images.io.parse_working_long_side`).
"""
from __future__ import annotations

import time
from dataclasses import replace

import numpy as np

from fr_torch.core.likelihood.mixture import LikelihoodParams
from fr_torch.core.result import CalibrationResult
from fr_torch.core.settings.config import SearchConfig
from fr_torch.plugins.interface import CameraEstimate, ImageMeta, register
from fr_torch.registry import format_method_spec
from fr_torch.runtime.estimator import FREstimator


def estimate_from_result(method: str, result: CalibrationResult, runtime_s: float) -> CameraEstimate:
    """Convert an fR result into the common estimate record."""
    if not result.ok:
        return CameraEstimate.failure(method, result.reason, runtime_s)
    horizon = result.horizon
    return CameraEstimate(
        method=method, camera=result.camera,
        predicted_error=result.predicted_error, reliable=result.reliable, runtime_s=runtime_s, reason=result.reason,
        extra={"cues": result.cues, "num_segments": result.num_segments, "log_likelihood": result.log_likelihood,
               "stage_runtime_s": result.runtime_s, "vanishing_point_support": result.vanishing_point_support,
               "vanishing_point_families": result.vanishing_point_families,
               "distortion": result.distortion, "horizon_bound_pct": None if horizon is None else horizon.bound_pct,
               "model": result.model},
        ranked_vanishing_points=result.ranked_vanishing_points,
    )


class FRCalibrator:
    """fR / Fast-fR as a Calibrator.

    Segments given in ``meta.segments`` are used instead of detecting them on the image (as the
    baselines do; ``fr eval``'s ``@labelled`` suffix relies on it).  ``use_meta_segments``: they are
    required (the oracle); without them the estimate fails with "n/a (no segments supplied)".
    """

    def __init__(self, mode: str = "fr", measure: str | None = None, detector: str = "lsd", device: str = "cpu",
                 likelihood: str | None = None, use_meta_segments: bool = False, name: str | None = None,
                 range=None, model: str | None = None, atlanta=None, distortion: str | None = None, k=None,
                 families=None, **estimator_kwargs):
        for value, setting in ((range, SearchConfig.with_fov_range), (families, SearchConfig.with_families)):
            if value is not None:
                base = estimator_kwargs.get("search_config") or SearchConfig.from_config()
                estimator_kwargs["search_config"] = setting(base, value)
        if model is not None:
            params = (estimator_kwargs.get("likelihood_params")
                      or LikelihoodParams.from_config(measure, likelihood, mode=mode))
            estimator_kwargs["likelihood_params"] = replace(params, model=model)
        self.estimator = FREstimator(mode=mode, measure=measure, detector=detector, device=device,
                                     likelihood=likelihood, atlanta=atlanta, distortion=distortion,
                                     k=None if k is None else float(k), **estimator_kwargs)
        self.use_meta_segments = use_meta_segments
        base = name or ("fr" if mode == "fr" else "fast-fr")
        self.name = format_method_spec(base, {
            "measure": measure or None, "detector": detector if detector != "lsd" else None,
            "likelihood": likelihood or None, "range": range if isinstance(range, str) else None, "model": model,
            "atlanta": atlanta if self.estimator.atlanta is not None else None, "distortion": distortion, "k": k,
            "families": families, "working_long_side": estimator_kwargs.get("working_long_side")})

    def estimate(self, image: np.ndarray | None, meta: ImageMeta) -> CameraEstimate:
        start = time.perf_counter()
        if self.use_meta_segments and meta.segments is None:
            return CameraEstimate.failure(self.name, "n/a (no segments supplied)")
        if meta.segments is not None:
            [result] = self.estimator.calibrate_segments([meta.segments], [(meta.width, meta.height)],
                                                         names=[meta.name], focal_px=meta.focal_px,
                                                         principal_point=meta.principal_point)
        else:
            [result] = self.estimator.calibrate_images([image], names=[meta.name], focal_px=meta.focal_px,
                                                       principal_point=meta.principal_point)
        return estimate_from_result(self.name, result, time.perf_counter() - start)


@register("fr")
def make_fr(**kwargs) -> FRCalibrator:
    return FRCalibrator(mode="fr", **kwargs)


@register("fast-fr")
def make_fast_fr(**kwargs) -> FRCalibrator:
    return FRCalibrator(mode="fast", **kwargs)


@register("oracle-fr")
def make_oracle_fr(**kwargs) -> FRCalibrator:
    return FRCalibrator(mode="fr", use_meta_segments=True, name="oracle-fr", **kwargs)
