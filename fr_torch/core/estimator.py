"""The fR estimator: segments -> likelihood -> two-stage search -> result with reliability cues.

Usage::

    from fr_torch import FREstimator
    est = FREstimator(mode="fr")                      # or "fast" (Fast-fR)
    [result] = est.calibrate_images(["photo.jpg"])    # paths or arrays; batches welcome
    result.focal_px, result.roll_deg, result.rotation

    est.calibrate_segments([segments], image_sizes=[(640, 480)])   # your own (N, 4) segments

Conventions: see :mod:`fr_torch.core.geometry.conventions` (pixels; degrees; R world->camera, x right / y down /
z forward, vertical Manhattan direction in column 1).
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np
import torch

from fr_torch.core.exact import first_argmax
from fr_torch.core.geometry.camera import Camera
from fr_torch.core.geometry.conventions import hfov_from_focal, image_centre
from fr_torch.core.geometry.params import DISTORTION, FOCAL, CameraParams, rotations
from fr_torch.core.geometry.vanishing import AtlantaConfig, rank_vanishing_points
from fr_torch.core.likelihood.measures import SegmentFeatures
from fr_torch.core.likelihood.mixture import LikelihoodParams, MixtureLikelihood
from fr_torch.core.likelihood.segments import SegmentBatch, SegmentFilter, drop_absurd_segments, validate_segments
from fr_torch.core.reliability.cues import focal_cues, image_cues
from fr_torch.core.reliability.model import ReliabilityModel
from fr_torch.core.reliability.sanity import (
    LINE_BEND_CUES,
    check_result,
    finite_record,
    lines_bend_reason,
    sanity_check,
)
from fr_torch.core.result import CalibrationResult
from fr_torch.core.search.lens import SegmentGeometry, bend_test, search_with_k
from fr_torch.core.search.manhattan import fit_families, search_manhattan
from fr_torch.core.settings.checks import (
    MAX_REACH_IMAGE_SIZES,
    check_camera,
    check_image_size,
    image_names,
    per_image,
    resolve_device,
    segment_sets,
)
from fr_torch.core.settings.checks import image_sizes as checked_image_sizes
from fr_torch.core.settings.config import Mode, SearchConfig
from fr_torch.core.settings.distortion import DistortionMode
from fr_torch.errors import FRInputError

BACKGROUND_LABEL = 3
#: The reason of an estimate that another, different solution matched within rounding
#: (:func:`fr_torch.core.search.passes.best_of_start_and_refined`).
TIE_REASON = ("another solution scores the same to within rounding (the photo has two answers: another machine "
              "could return the other)")


@dataclass
class _Image:
    """One image on its way through the estimator: its inputs, then its result."""

    name: str
    size: tuple[int, int]  # (width, height), pixels; (0, 0) when the image could not be read
    segments: np.ndarray  # (N, 4) filtered segments
    error: str | None = None  # why it cannot be calibrated (bad input)
    detect_s: float | None = None  # seconds spent decoding + detecting (images only)
    focal_px: float | None = None  # known focal length, pixels
    principal_point: tuple[float, float] | None = None  # None: image centre
    result: CalibrationResult | None = None
    dropped: int = 0  # segments dropped as absurd (drop_absurd_segments)


def absurd_segments_note(dropped: int) -> str:
    """The reason part of a result that lost ``dropped`` segments to :func:`drop_absurd_segments`."""
    return (f"{dropped} segment(s) with non-finite coordinates or beyond {MAX_REACH_IMAGE_SIZES} image sizes "
            "from the image dropped")


def keep_sane_segments(segments: np.ndarray, size: tuple, name: str) -> tuple[np.ndarray, int]:
    """:func:`drop_absurd_segments`, and an FRInputError for ``name`` when it drops every segment."""
    kept, dropped = drop_absurd_segments(segments, size)
    if dropped and not len(kept):
        raise FRInputError(f"{name}: all {dropped} segments have non-finite coordinates or lie beyond "
                           f"{MAX_REACH_IMAGE_SIZES} image sizes from the image: cannot calibrate")
    return kept, dropped


SEARCH_CHUNK_IMAGES = 4096  # images searched together (bounds host and device memory for any batch)


class SegmentEstimator:
    """fR / Fast-fR (Qian & Elder, ECCV 2022) on CPU or CUDA, batched over images.

    ``mode``: ``"fr"`` (refine to convergence) or ``"fast"`` (10 refinement iterations).
    ``measure``: deviation measure a-e (default from ``configs/likelihood.json``: b).
    ``detector``: name of a registered detector (``lsd`` default) or a detector object.
    ``likelihood``: likelihood config, a name (``paper``, ``fitted``) or a JSON path (default
    ``configs/likelihood.json``); ``likelihood_params`` overrides it with explicit parameters.
    ``dtype``: float32 (default) or float64 (reference).
    ``segment_filter``: default ``SegmentFilter`` keeping each image's longest
    ``search_config.max_segments(mode)`` segments (fR 750, Fast-fR 500; ``configs/search.json``).
    ``min_segments``: fewer segments than this -> ``reliable = False``; likewise when a Manhattan
    family has fewer than ``min_family_segments`` segments, or when less than
    ``min_manhattan_fraction`` of the total segment length is labelled with a Manhattan family
    (random texture, nature scenes: real built scenes measure 0.75-0.95 with LSD).
    ``reliability``: the error predictor stage (:mod:`fr_torch.core.reliability`): ``"default"`` (the
    shipped model of this mode, when installed), a model object, a path to a model ``.npz``, or None
    (off).  When on, every estimate gets ``predicted_error``, ``error_bound`` and ``reliable = False``
    when a bound exceeds its limit (the promise of ``configs/reliability.json``,
    :mod:`fr_torch.core.reliability.bounds`; with ``"enforce": false``: a predicted error above its
    threshold).
    ``profile_gap``: compute the ``focal_profile_gap`` cue (:meth:`_focal_cues`; a quarter of fR's
    time per photo, half of its batch throughput): None (default) when the reliability model uses
    it (fR's shipped model does; with ``reliability=None`` it is skipped), True always (records
    for training a model), False never (a model that uses it is then an error).
    ``spreads``: compute the cues the bounds of ``reliable`` rest on
    (:data:`fr_torch.core.reliability.cues.SPREAD_CUE_NAMES`): None (default) when the reliability stage holds
    such bounds (the shipped one does), True always (records), False never.
    ``atlanta``: extra vanishing points beyond the Manhattan three after the fit
    (:class:`fr_torch.core.geometry.vanishing.AtlantaConfig` or anything its ``parse`` takes; None = off);
    they join ``ranked_vanishing_points`` and change neither f nor R.
    ``distortion``: the lens model, ``pinhole`` (default), ``division`` (k of the division model
    estimated with f and R) or ``auto`` (:class:`~fr_torch.core.settings.distortion.DistortionSetting`);
    ``k``: a known k (normalised by half the image diagonal, :mod:`fr_torch.core.geometry.lens`),
    which implies ``division``.  Both override ``search_config.distortion``.
    """

    def __init__(self, mode: Mode | str = Mode.FR, measure: str | None = None, device: str = "cpu",
                 dtype: torch.dtype = torch.float32, likelihood_params: LikelihoodParams | None = None,
                 likelihood: str | None = None,
                 search_config: SearchConfig | None = None, segment_filter: SegmentFilter | None = None,
                 min_segments: int = 10, min_family_segments: int = 2, min_manhattan_fraction: float = 0.6,
                 reliability="default", profile_gap: bool | None = None, spreads: bool | None = None,
                 atlanta=None, distortion: str | None = None, k: float | None = None):
        self.mode = Mode.parse(mode)
        self.atlanta = AtlantaConfig.parse(atlanta)
        self.search = (search_config or SearchConfig.from_config()).resolve(self.mode)
        if distortion is not None or k is not None:
            self.search = self.search.with_distortion(distortion, k)
        self.iterations = self.search.refine_iterations
        params = likelihood_params or LikelihoodParams.from_config(measure, likelihood, mode=self.mode)
        # the likelihood as given (the reliability model's scope is checked against it)
        self.likelihood_params = params
        self.likelihood_name = "custom parameters" if likelihood_params is not None else str(likelihood or "default")
        self.likelihood = MixtureLikelihood(params.with_prior_in_range(self.search.fov_range))
        self.device = resolve_device(device)
        self.dtype = dtype
        self.segment_filter = segment_filter or SegmentFilter(max_segments=self.search.max_segments)
        self.min_segments = min_segments
        self.min_family_segments = min_family_segments
        self.min_manhattan_fraction = min_manhattan_fraction

        if isinstance(reliability, str) and reliability == "default":
            reliability = ReliabilityModel.load_default(mode)
        elif isinstance(reliability, (str, Path)):
            reliability = ReliabilityModel.load(reliability)
        self.reliability = reliability
        model_cues = getattr(reliability, "cue_names", ())  # () without a model
        if profile_gap is False and "focal_profile_gap" in model_cues:
            raise FRInputError("the reliability model uses the focal_profile_gap cue: profile_gap=False "
                               "needs reliability=None or a model without it")
        self.profile_gap = "focal_profile_gap" in model_cues if profile_gap is None else bool(profile_gap)
        # the spread cues that the bounds of `reliable` rest on (fr_torch.core.reliability.bounds)
        self.spreads = getattr(reliability, "needs_spreads", False) if spreads is None else bool(spreads)

    # ------------------------------------------------------------------ public API

    def calibrate_segments(self, segments: Sequence, image_sizes: Sequence[tuple[int, int]],
                           names: Sequence[str] | None = None, focal_px=None, principal_point=None,
                           apply_filter: bool = True) -> list[CalibrationResult]:
        """Calibrate from user-supplied segments: one (N_i, 4) array [x1, y1, x2, y2] per image.

        ``segments``: a sequence (list, tuple, (B, N, 4) array or tensor) of one (N_i, 4) array,
        nested list or tensor per image; counts may differ.  ``image_sizes``: one (width, height)
        pair of numbers per image, pixels.  ``names``: one per image (default ``image0``, ...).
        ``focal_px`` / ``principal_point``: None, one value for all images or one per image
        (:func:`fr_torch.core.settings.checks.per_image`).  An argument of the wrong form or length is an
        FRInputError naming it; a bad value of one image (its segments, size, focal length or
        principal point) fails only that image (``ok=False`` and the reason).  Rows with non-finite
        coordinates fail their image; rows beyond :data:`~fr_torch.core.settings.checks.MAX_REACH_IMAGE_SIZES`
        image sizes from the image are dropped (the result is then not reliable and its reason
        says how many).  Segments are filtered like detected ones unless ``apply_filter`` is False.
        """
        segments = segment_sets(segments)
        count = len(segments)
        sizes = checked_image_sizes(image_sizes, count)
        names = image_names(names, count, [f"image{i}" for i in range(count)])
        focal_list = per_image(focal_px, count, "focal_px")
        pp_list = per_image(principal_point, count, "principal_point", width=2)
        items = []
        for i, seg in enumerate(segments):
            size = sizes[i]
            try:
                check_image_size(size, names[i])
            except FRInputError as exc:
                items.append(_Image(names[i], (0, 0), np.zeros((0, 4)), error=str(exc)))
                continue
            try:
                checked = validate_segments(seg, f"{names[i]} segments")
                check_camera(focal_list[i], pp_list[i], size, names[i])
                kept, dropped = keep_sane_segments(checked, size, names[i])
                items.append(_Image(names[i], size, kept, dropped=dropped))
            except FRInputError as exc:
                items.append(_Image(names[i], size, np.zeros((0, 4)), error=str(exc)))
        if apply_filter:  # the whole batch in one pass
            valid = [item for item in items if item.error is None]
            for item, kept in zip(valid, self.segment_filter.many([v.segments for v in valid],
                                                                  [v.size for v in valid])):
                item.segments = kept
        return self._calibrate(items, focal_list, pp_list)

    # ------------------------------------------------------------------ internals

    def _calibrate(self, items: list[_Image], focal_list: list, pp_list: list,
                   detected: bool = False) -> list[CalibrationResult]:
        """Search ``items`` (their sizes and segments in working pixels); ``focal_list`` /
        ``pp_list``: one focal length / principal point (or None) per item, in working pixels,
        already checked by the public entry that built the items (in the user's pixels).
        ``detected``: the segments come from this estimator's detector (the reliability model's
        scope then includes it, :meth:`reliability_scope_gap`)."""
        for item, f, pp in zip(items, focal_list, pp_list):
            item.focal_px, item.principal_point = f, pp
            r = item.result = CalibrationResult(image=item.name, width=int(item.size[0]), height=int(item.size[1]))
            if item.error is not None:
                r.ok, r.reason = False, item.error
            elif len(item.segments) == 0:
                r.ok, r.reason = False, "no line segments found: cannot calibrate"
                r.segments, r.labels = np.zeros((0, 4)), np.zeros(0, int)
        todo = [item for item in items if item.result.ok]
        # Images with and without a known focal length are searched separately (4-D vs 3-D grid).
        # A large batch is searched SEARCH_CHUNK_IMAGES images at a time: memory stays bounded (the
        # grid's hypotheses alone are 128 KB per image) and the answers are those of one big batch.
        for known in (False, True):
            group = [item for item in todo if (item.focal_px is not None) == known]
            for start in range(0, len(group), SEARCH_CHUNK_IMAGES):
                self._search_group(group[start:start + SEARCH_CHUNK_IMAGES], known)
        results = [item.result for item in items]
        for item in items:
            if item.detect_s is not None:
                item.result.runtime_s["detect"] = item.detect_s
                item.result.runtime_s["total"] = item.result.runtime_s.get("total", 0.0) + item.detect_s
        for item in items:
            if item.dropped and item.result.ok:
                item.result.reliable = False
                item.result.reason = "; ".join(r for r in (item.result.reason, absurd_segments_note(item.dropped)) if r)
        if self.reliability is not None:  # predicted errors, bounds, reliable = the promise
            scope_gap = self.reliability_scope_gap(detected)
            if scope_gap is None:
                self.reliability.annotate_many(results, mode=self.mode,
                                               focal_known=[item.focal_px is not None for item in items])
            else:  # the model knows nothing of this setting: no prediction, not reliable
                for result in results:
                    if result.ok:
                        result.predicted_error, result.reliable = None, False
                        result.reason = "; ".join(r for r in (result.reason, scope_gap) if r)
        for result in results:  # the last stage: no NaN / inf in any field
            finite_record(result)
        return results

    def reliability_scope_gap(self, detected: bool) -> str | None:
        """Why the reliability model does not apply to this estimator's results, or None when it
        does: it was trained on another deviation measure or likelihood
        (:meth:`fr_torch.core.reliability.model.ReliabilityModel.scope_gap`), or -- for segments from
        this estimator's detector (``detected``), not the caller's -- on another detector."""
        scope_gap = getattr(self.reliability, "scope_gap", None)
        if scope_gap is None:  # a model object without a declared scope
            return None
        detector = getattr(self, "detector", None) if detected else None
        detector_name = None if detector is None else str(getattr(detector, "name", type(detector).__name__))
        return scope_gap(self.likelihood_params, self.likelihood_name, detector_name, mode=self.mode)

    def _search_group(self, group: list[_Image], known_focal: bool, lens: str | None = None):
        """Search ``group`` (images with segments; all with or all without a known focal length)
        and fill their results.  ``lens``: ``pinhole`` or ``division``; None = the setting's
        (``auto``: pinhole, then the division search for the images whose lines bend,
        :func:`fr_torch.core.reliability.sanity.lines_bend_reason`'s criterion)."""
        setting = self.search.distortion
        auto = lens is None and setting.mode is DistortionMode.AUTO and setting.known_k is None
        if lens is None:
            lens = "pinhole" if setting.mode is DistortionMode.PINHOLE or auto else "division"
        start_all = time.perf_counter()
        device, dtype = self.device, self.dtype
        batch = SegmentBatch.from_list([g.segments for g in group], [g.size for g in group], device, dtype)
        size_np = np.array([g.size for g in group], dtype=np.float64).reshape(-1, 2)
        pp_np = np.array([g.principal_point if g.principal_point is not None else (np.nan, np.nan) for g in group],
                         dtype=np.float64).reshape(-1, 2)
        pp_np = np.where(np.isnan(pp_np), np.stack(image_centre(size_np[:, 0], size_np[:, 1]), -1), pp_np)
        width = torch.from_numpy(size_np[:, 0].copy())
        height = torch.from_numpy(size_np[:, 1].copy())
        pp = torch.from_numpy(pp_np)
        features = SegmentFeatures.from_batch(batch, pp.to(device=device, dtype=dtype))
        focal = torch.tensor([float(g.focal_px) for g in group], dtype=torch.float64) if known_focal else None

        long_side = torch.maximum(width, height)  # the FOV range is on the long side (portrait = landscape)
        geometry = SegmentGeometry.from_features(features, batch.endpoints, batch.image_size,
                                                 setting.k_prior_weight if lens == "division" else 0.0)
        k_estimate = None  # (B,) k of the division estimates
        extra_azimuth = extra_weight = extra_count = None  # (B, m) degrees and (B,) of the extra families (SearchConfig.families)
        fast = self.mode == "fast"
        t0 = time.perf_counter()
        if lens == "division":  # the lens fit: k with f and R
            found = search_with_k(self.likelihood, geometry, features, self.search, long_side, focal, self.iterations,
                                  fast)
        else:  # the Manhattan fit
            found = search_manhattan(self.likelihood, features, self.search, long_side, focal, self.iterations, fast)
        t1 = t0 + found.grid_seconds
        params, best_scores, tied = found.params, found.scores, found.tied
        grid_scores, grid_counts = found.grid_scores, found.grid_counts
        if lens == "division":
            k_estimate = params[:, DISTORTION]
            estimate = CameraParams(params[:, :DISTORTION].contiguous())
            features = geometry.features(params[:, DISTORTION, None])  # the segments as the estimate sees them
        else:
            if self.search.families is not None:  # extra horizontal families inside the likelihood
                families = fit_families(self.likelihood, features, params, found.lower, found.upper,
                                        self.search.families, self.iterations)
                extra = families.count > 0
                params = torch.where(extra[:, None], families.params.to(params.dtype), params)
                # the Manhattan mixture's objective at the camera (what the cues compare against)
                manhattan_scores = self.likelihood.objective(features, rotations(params)[:, None].to(dtype),
                                                             params[:, FOCAL, None].to(dtype))[:, 0]
                best_scores = torch.where(extra, manhattan_scores.to(best_scores.dtype), best_scores)
                extra_azimuth, extra_weight, extra_count = families.azimuth_deg, families.weight, families.count
            estimate = CameraParams(params)
        t2 = time.perf_counter()

        rotation = estimate.rotation()  # float64 (B, 3, 3)
        posterior, log_p = self.likelihood.posteriors(features, rotation[:, None].to(dtype),
                                                      estimate.focal_px[:, None].to(dtype))
        labels = first_argmax(posterior[:, 0], -1)
        ranked = rank_vanishing_points(self.likelihood, features, rotation, estimate.focal_px, self.atlanta,
                                       extra_azimuth, extra_weight)
        cues = image_cues(grid_scores, grid_counts, labels, log_p[:, 0], batch.mask, rotation)
        if extra_count is not None:
            cues["extra_families"] = extra_count.to(torch.float64)
        cues.update(focal_cues(self.likelihood, self.search, features, estimate.data, best_scores, known_focal,
                               self.profile_gap, self.spreads))
        if lens == "pinhole":  # do the lines bend?  (a sanity check of pinhole estimates; auto's criterion)
            cues.update(bend_test(self.likelihood, geometry, features, estimate.data, best_scores, self.search, focal))
        t3 = time.perf_counter()

        timing = {"grid": (t1 - t0) / len(group), "refine": (t2 - t1) / len(group), "cues": (t3 - t2) / len(group)}
        # One device->host transfer per tensor, not one per image (keeps large batches O(B)).
        counts_all = batch.mask.sum(-1).cpu().numpy()
        lengths_all = batch.lengths.cpu().numpy()
        labels_all = labels.cpu().numpy()
        rotation_all = rotation.cpu().numpy()
        params_all = estimate.data.cpu().numpy()
        scores_all = best_scores.to(torch.float64).cpu().numpy()
        tied_all = tied.cpu().numpy()
        cues_all = {key: value.cpu().numpy() for key, value in cues.items()}
        ranked_points, ranked_support, ranked_family = (ranked.points.cpu().numpy(), ranked.support.cpu().numpy(),
                                                        ranked.family.cpu().numpy())
        cameras = Camera.many(size_np[:, 0], size_np[:, 1], params_all[:, FOCAL], pp_np, rotation_all)
        long_side_fov_all = hfov_from_focal(torch.from_numpy(params_all[:, FOCAL].astype(np.float64)),
                                            torch.from_numpy(size_np.max(1))).numpy()
        k_all = None if k_estimate is None else k_estimate.to(torch.float64).cpu().numpy()
        # Finite parameters, objective and rotation give finite hfov, angles and VPs (f > 0 in the box).
        finite = np.isfinite(params_all).all(-1) & np.isfinite(scores_all) & np.isfinite(rotation_all).all((-1, -2))
        bent = []  # with auto: the images whose lines bend, searched again with the division model below
        for j, item in enumerate(group):
            n = int(counts_all[j])
            r = item.result
            r.camera = cameras[j]
            r.log_likelihood = float(scores_all[j])
            r.num_segments = n
            r.segments = item.segments
            r.labels = labels_all[j, :n]
            found = ranked_family[j] >= 0
            r.ranked_vanishing_points = ranked_points[j][found]
            r.vanishing_point_support = ranked_support[j][found]
            r.vanishing_point_families = ranked_family[j][found]
            lengths = lengths_all[j, :n]  # the image's own segments: the same sums in any batch
            r.manhattan_fraction = float((lengths * (r.labels != BACKGROUND_LABEL)).sum() / max(lengths.sum(), 1e-12))
            r.cues = {key: float(value[j]) for key, value in cues_all.items()}
            r.runtime_s = dict(timing, total=(time.perf_counter() - start_all) / len(group))
            if k_all is not None:
                r.distortion_model, r.distortion_k = "division", float(k_all[j])
            r.model = "manhattan"
            r.reliable, r.reason = sanity_check(r, self.min_segments, self.min_family_segments,
                                                 self.min_manhattan_fraction)
            bend = lines_bend_reason(r.cues, setting, r.width, r.height) if lens == "pinhole" else None
            if bend:
                r.reliable, r.reason = False, "; ".join(x for x in (r.reason, bend) if x)
            if tied_all[j]:
                r.reliable, r.reason = False, "; ".join(x for x in (r.reason, TIE_REASON) if x)
            # non-finite -> ok=False; focal or an angle at its range's edge -> unreliable
            check_result(r, self.search, known_focal, finite=bool(finite[j]), search_params=params_all[j],
                         long_side_fov_deg=float(long_side_fov_all[j]))
            if auto and bend and r.ok:
                bent.append(item)
        if bent:  # the division search for the images whose lines bend; they keep the check's cues and time
            first = {id(item): (dict(item.result.runtime_s), {key: item.result.cues[key] for key in LINE_BEND_CUES})
                     for item in bent}
            self._search_group(bent, known_focal, lens="division")
            for item in bent:
                runtime, bend_cues = first[id(item)]
                item.result.cues.update(bend_cues)
                item.result.runtime_s = {key: item.result.runtime_s.get(key, 0.0) + runtime.get(key, 0.0)
                                         for key in set(runtime) | set(item.result.runtime_s)}
