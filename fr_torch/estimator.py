"""The fR estimator: segments -> likelihood -> two-stage search -> result with reliability cues.

Usage::

    from fr_torch import FREstimator
    est = FREstimator(mode="fr")                      # or "fast" (Fast-fR)
    [result] = est.calibrate_images(["photo.jpg"])    # paths or arrays; batches welcome
    result.focal_px, result.roll_deg, result.rotation

    est.calibrate_segments([segments], image_sizes=[(640, 480)])   # your own (N, 4) segments

Conventions: see :mod:`fr_torch.camera` (pixels; degrees; R world->camera, x right / y down /
z forward, vertical Manhattan direction in column 1).
"""
from __future__ import annotations

import copy
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence

import numpy as np
import torch

from .camera import VERTICAL_AXIS, Camera, camera_record, image_centre
from .likelihood import LikelihoodParams, MixtureLikelihood, SegmentFeatures
from .search import (SearchConfig, check_result, focal_prior_share, focal_profile_gap, grid_hypotheses,
                     hypothesis_rotations, parameter_box, refine, score_grid, select_starts, subdivide_starts,
                     sweep_focal)
from . import image_io, validate
from .segments import FRInputError, SegmentBatch, SegmentFilter, get_detector, validate_segments

BACKGROUND_LABEL = 3


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


SEARCH_CHUNK_IMAGES = 4096  # images searched together (bounds host and device memory for any batch)

# CalibrationResult.to_json: its keys, in order (the CLI's output schema)
JSON_KEYS = ("image", "width", "height", "ok", "reliable", "reason", "focal_px", "hfov_deg", "principal_point",
             "rotation", "vertical_axis", "pan_deg", "tilt_deg", "roll_deg", "pitch_deg", "vanishing_points",
             "log_likelihood", "num_segments", "manhattan_fraction", "cues", "predicted_error", "error_bound",
             "runtime_s")


@camera_record
@dataclass
class CalibrationResult:
    """Everything fR says about one image.  Angles in degrees, lengths in pixels.

    ``camera`` is the estimate (:class:`fr_torch.camera.Camera`: focal length, principal point,
    rotation); ``focal_px``, ``hfov_deg``, ``principal_point``, ``rotation`` (3, 3) world->camera,
    ``pan_deg`` / ``tilt_deg`` / ``roll_deg`` / ``pitch_deg`` and ``vanishing_points`` (3, 3; row i
    = homogeneous VP i (x, y, w), w >= 0) are read-only views of it (:func:`fr_torch.camera.camera_record`).
    ``ok`` is False when no estimate could be made (then ``camera`` and those fields are None and
    ``reason`` says why).  ``reliable`` is False when the estimate exists but should not be
    trusted (too few segments, a Manhattan family nearly empty, or predicted errors above the
    threshold once a reliability model is loaded); ``reason`` lists why.
    """

    image: str
    width: int
    height: int
    ok: bool = True
    reliable: bool = False
    reason: str = ""
    camera: Camera | None = None
    vertical_axis: int = VERTICAL_AXIS
    log_likelihood: float | None = None
    num_segments: int = 0
    manhattan_fraction: float | None = None  # share of total segment length labelled with a family
    segments: np.ndarray | None = None  # (N, 4) the segments used
    labels: np.ndarray | None = None  # (N,) 0, 1, 2 = Manhattan column (1 = vertical), 3 = background
    cues: dict[str, float] = field(default_factory=dict)
    predicted_error: dict[str, float] | None = None
    # what `reliable` promises (fr_torch.reliability_bounds): {"coverage", "focal_pct", "tilt_deg" (the
    # bounds), "limits": {...}}; None without a reliability promise
    error_bound: dict[str, Any] | None = None
    # seconds per image: detect, grid (the k^4 grid, the focal sweep and the lattice passes), refine, cues, total
    runtime_s: dict[str, float] = field(default_factory=dict)

    def to_json(self, include_segments: bool = False) -> dict[str, Any]:
        """JSON-ready dict (the CLI's output schema, keys :data:`JSON_KEYS`; arrays become nested lists)."""
        out = {key: copy.deepcopy(getattr(self, key)) for key in JSON_KEYS}
        for key in ("rotation", "vanishing_points"):
            if out[key] is not None:
                out[key] = np.asarray(out[key]).tolist()
        if include_segments and self.segments is not None:
            out["segments"] = self.segments.tolist()
            out["labels"] = self.labels.tolist()
        if self.labels is not None:
            out["segments_per_family"] = np.bincount(self.labels, minlength=4).tolist()
        return out


def focal_conditioning(rotation: torch.Tensor) -> torch.Tensor:
    """How well a Manhattan frame's vanishing points constrain the focal length (a reliability cue).

    Args:
        rotation: (..., 3, 3) world->camera rotations; column i is the direction of VP i in camera
            coordinates (x right, y down, z along the optical axis), as in ``VP_i = K R[:, i]``.

    Returns:
        (...,) ``sqrt(sum_i (sin(theta_i) cos(theta_i))^2)`` in [0, sqrt(3)/2], theta_i the angle
        between VP direction i and the optical axis.  A VP sits at ``f tan(theta)`` from the
        principal point; on the principal point (theta = 0) or at infinity (theta = 90 deg) its
        position carries no information on f, and ``sin cos`` peaks at theta = 45 deg.  A camera
        panned square to a wall with level tilt (all three VPs at the centre or at infinity) gives
        0: its focal length is left to the prior.  No f enters (the directions alone decide).
    """
    columns = rotation / rotation.norm(dim=-2, keepdim=True).clamp_min(1e-12)
    off_axis = columns[..., :2, :].norm(dim=-2)  # sin(theta_i), (..., 3)
    along_axis = columns[..., 2, :].abs()  # cos(theta_i)
    return (off_axis * along_axis).square().sum(-1).sqrt()


class FREstimator:
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
    ``reliability``: the error predictor stage (:mod:`fr_torch.reliability`): ``"default"`` (the
    shipped model of this mode, when installed), a model object, a path to a model ``.npz``, or None
    (off).  When on, every estimate gets ``predicted_error`` and ``reliable = False`` above the
    thresholds of ``configs/reliability.json``.
    ``profile_gap``: compute the ``focal_profile_gap`` cue (:meth:`_focal_cues`; a quarter of fR's
    time per photo, half of its batch throughput): None (default) when the reliability model uses
    it (fR's shipped model does; with ``reliability=None`` it is skipped), True always (records
    for training a model), False never (a model that uses it is then an error).
    """

    def __init__(self, mode: str = "fr", measure: str | None = None, detector="lsd", device: str = "cpu",
                 dtype: torch.dtype = torch.float32, likelihood_params: LikelihoodParams | None = None,
                 likelihood: str | None = None,
                 search_config: SearchConfig | None = None, segment_filter: SegmentFilter | None = None,
                 min_segments: int = 10, min_family_segments: int = 2, min_manhattan_fraction: float = 0.6,
                 reliability="default", profile_gap: bool | None = None):
        self.mode = mode
        self.search = search_config or SearchConfig.from_config()
        self.iterations = self.search.iterations(mode)
        params = likelihood_params or LikelihoodParams.from_config(measure, likelihood, mode=mode)
        self.likelihood = MixtureLikelihood(params.with_prior_in_range(self.search.hfov_range_deg),
                                            compiled=self.search.compile_search)
        self.detector = get_detector(detector)
        self.device = validate.resolve_device(device)
        self.working_long_side = image_io.WORKING_LONG_SIDE
        self.dtype = dtype
        self.segment_filter = segment_filter or SegmentFilter(max_segments=self.search.max_segments(mode))
        self.min_segments = min_segments
        self.min_family_segments = min_family_segments
        self.min_manhattan_fraction = min_manhattan_fraction
        from .reliability import ReliabilityModel

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

    # ------------------------------------------------------------------ public API

    def calibrate_images(self, images: Sequence, names: Sequence[str] | None = None, focal_px=None,
                         principal_point=None) -> list[CalibrationResult]:
        """Calibrate images given as file paths or arrays (grey, BGR, BGRA; 8/16-bit or float).

        ``focal_px``: None (unknown), a number for all images, or one value (or None) per image.
        ``principal_point``: None (image centre), an (x, y) pair for all, or one per image.
        A bad image yields a result with ``ok=False`` and the reason; the others are unaffected.
        """
        from .pipeline import calibrate_paths  # decode + detect + search; also with worker processes

        return [r for _, batch in calibrate_paths(self, images, max(1, len(images)), 0, focal_px, principal_point,
                                                  names) for r in batch]

    def calibrate_segments(self, segments: Sequence, image_sizes: Sequence[tuple[int, int]],
                           names: Sequence[str] | None = None, focal_px=None, principal_point=None,
                           apply_filter: bool = True) -> list[CalibrationResult]:
        """Calibrate from user-supplied segments: one (N_i, 4) array [x1, y1, x2, y2] per image.

        ``image_sizes``: (width, height) per image, pixels.  Segments are filtered like detected
        ones unless ``apply_filter`` is False.
        """
        if len(segments) != len(image_sizes):
            raise FRInputError(f"got {len(segments)} segment sets but {len(image_sizes)} image sizes")
        names = list(names) if names is not None else [f"image{i}" for i in range(len(segments))]
        focal_list = validate.per_image(focal_px, len(segments), "focal_px")
        pp_list = validate.per_image(principal_point, len(segments), "principal_point", width=2)
        items = []
        for i, seg in enumerate(segments):
            size = tuple(image_sizes[i])
            try:
                if len(size) != 2 or not all(np.isfinite(size)) or min(size) <= 0:
                    raise FRInputError(f"{names[i]}: image size must be (width, height) > 0, got {size}")
                checked = validate_segments(seg, f"{names[i]} segments")
                validate.check_camera(focal_list[i], pp_list[i], size, names[i])
                items.append(_Image(names[i], size, checked))
            except FRInputError as exc:
                shown = size if len(size) == 2 and all(np.isfinite(size)) else (0, 0)
                items.append(_Image(names[i], shown, np.zeros((0, 4)), error=str(exc)))
        if apply_filter:  # the whole batch in one pass
            valid = [item for item in items if item.error is None]
            for item, kept in zip(valid, self.segment_filter.many([v.segments for v in valid],
                                                                  [v.size for v in valid])):
                item.segments = kept
        return self._calibrate(items, focal_list, pp_list)

    def calibrate_detections(self, detections: Sequence, names: Sequence[str], focal_px=None,
                             principal_point=None) -> list[CalibrationResult]:
        """Calibrate images that were already decoded and detected, one
        :class:`fr_torch.pipeline.Detection` each (from :func:`fr_torch.pipeline.iter_detections`,
        possibly in worker processes).

        A detection holds its segments in *working* pixels (the image brought to a long side of at
        most :attr:`working_long_side`) and ``scale``, input pixels per working pixel.
        ``focal_px`` / ``principal_point`` are in the **input** image's pixels (None, one value for
        all, or one per image), and so is every result: they are brought to working pixels for the
        search and the results back to the input's pixels.  A detection with ``error`` set, or an
        image whose focal length / principal point is invalid, gives ``ok=False`` with the reason.
        """
        count = len(detections)
        names = list(names)
        if len(names) != count:
            raise FRInputError(f"got {count} detections but {len(names)} names")
        focal_list = validate.per_image(focal_px, count, "focal_px")
        pp_list = validate.per_image(principal_point, count, "principal_point", width=2)
        items, focal_work, pp_work = [], [], []
        for d, name, f, pp in zip(detections, names, focal_list, pp_list):
            item = _Image(name, d.size, d.segments, error=d.error, detect_s=d.seconds)
            if item.error is None:
                try:  # checked in the input's pixels, so the message quotes the user's numbers
                    validate.check_camera(f, pp, d.input_size, name)
                    f, pp = image_io.focal_and_pp_to_working(f, pp, d.scale)
                except FRInputError as exc:
                    item.error, f, pp = str(exc), None, None
            items.append(item)
            focal_work.append(f)
            pp_work.append(pp)
        results = self._calibrate(items, focal_work, pp_work)
        for result, d in zip(results, detections):
            image_io.result_to_input_pixels(result, d.scale, d.input_size)
        return results

    # ------------------------------------------------------------------ internals

    def _calibrate(self, items: list[_Image], focal_list: list, pp_list: list) -> list[CalibrationResult]:
        """Search ``items`` (their sizes and segments in working pixels); ``focal_list`` /
        ``pp_list``: one focal length / principal point (or None) per item, in working pixels,
        already checked by the public entry that built the items (in the user's pixels)."""
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
        if self.reliability is not None:  # the last stage: predicted errors, reliable above thresholds
            self.reliability.annotate_many(results, mode=self.mode,
                                           focal_known=[item.focal_px is not None for item in items])
        return results

    def _search_group(self, group: list[_Image], known_focal: bool):
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

        t0 = time.perf_counter()
        long_side = torch.maximum(width, height)  # the FOV range is on the long side (portrait = landscape)
        hypotheses = grid_hypotheses(self.search, long_side.to(device), None if focal is None else focal.to(device))
        # Stage 1 scores each image's longest segments only (they carry the evidence); stage 2 all.
        grid_count = self.search.grid_segment_count(self.mode)
        grid_features = features.longest(grid_count) if grid_count else features
        grid_scores = score_grid(self.likelihood, grid_features, hypotheses, self.search.max_chunk_elements,
                                 vertical_block=self.search.grid_points_per_dim)
        starts, top_scores = select_starts(self.search, grid_scores, hypotheses)
        lower, upper = parameter_box(self.search, long_side, focal)
        starts, top_scores = sweep_focal(self.likelihood, features, starts, top_scores, self.search, lower, upper)
        starts, top_scores = subdivide_starts(self.likelihood, features, starts, top_scores, self.search,
                                              lower, upper)
        t1 = time.perf_counter()

        refined, refined_scores = refine(self.likelihood, features, starts, lower, upper, self.iterations,
                                         fast=self.mode == "fast", tolerance=self.search.refine_tolerance,
                                         patience=self.search.refine_patience,
                                         periodic_pan=self.search.periodic_pan)
        # Keep the best of {best grid point, refined points}.
        candidates = torch.cat([starts[:, :1].to(refined), refined], 1)
        candidate_scores = torch.cat([top_scores[:, :1], refined_scores], 1)
        best = candidate_scores.argmax(1)
        rows = torch.arange(len(group), device=device)
        best_params = candidates[rows, best].to(torch.float64)
        best_scores = candidate_scores[rows, best]
        t2 = time.perf_counter()

        rotation = hypothesis_rotations(best_params)  # float64 (B, 3, 3)
        posterior, log_p = self.likelihood.posteriors(features, rotation[:, None].to(dtype), best_params[:, None, 3].to(dtype))
        labels = posterior[:, 0].argmax(-1)
        cues = self._cues(grid_scores, grid_features.mask.sum(-1), labels, log_p[:, 0], batch.mask, rotation)
        cues.update(self._focal_cues(features, best_params, best_scores, known_focal))
        t3 = time.perf_counter()

        timing = {"grid": (t1 - t0) / len(group), "refine": (t2 - t1) / len(group), "cues": (t3 - t2) / len(group)}
        # One device->host transfer per tensor, not one per image (keeps large batches O(B)).
        counts_all = batch.mask.sum(-1).cpu().numpy()
        lengths_all = batch.lengths.cpu().numpy()
        labels_all = labels.cpu().numpy()
        rotation_all = rotation.cpu().numpy()
        params_all = best_params.cpu().numpy()
        scores_all = best_scores.to(torch.float64).cpu().numpy()
        cues_all = {key: value.cpu().numpy() for key, value in cues.items()}
        family = labels_all != BACKGROUND_LABEL
        manhattan = (lengths_all * family).sum(-1) / np.maximum(lengths_all.sum(-1), 1e-12)
        cameras = Camera.many(size_np[:, 0], size_np[:, 1], params_all[:, 3], pp_np, rotation_all)
        # Finite parameters, objective and rotation give finite hfov, angles and VPs (f > 0 in the box).
        finite = np.isfinite(params_all).all(-1) & np.isfinite(scores_all) & np.isfinite(rotation_all).all((-1, -2))
        for j, item in enumerate(group):
            n = int(counts_all[j])
            r = item.result
            r.camera = cameras[j]
            r.log_likelihood = float(scores_all[j])
            r.num_segments = n
            r.segments = item.segments
            r.labels = labels_all[j, :n]
            r.manhattan_fraction = float(manhattan[j])
            r.cues = {key: float(value[j]) for key, value in cues_all.items()}
            r.runtime_s = dict(timing, total=(time.perf_counter() - start_all) / len(group))
            r.reliable, r.reason = self._sanity(r)
            # non-finite -> ok=False; focal or an angle at its range's edge -> unreliable
            check_result(r, self.search, known_focal, finite=bool(finite[j]), search_params=params_all[j])

    def _cues(self, grid_scores, grid_counts, labels, log_p, mask, rotation) -> dict[str, torch.Tensor]:
        """The reliability cues, per image: the paper's three (§3.4) and ``focal_conditioning``.

        * ``min_family_segments``: smallest number of segments labelled (argmax posterior) with one
          of the three Manhattan families; background excluded; raw counts.
        * ``grid_entropy``: entropy (nats) of the stage-1 grid likelihoods normalised into a
          distribution, ``p_j = softmax_j(L_j / N)`` with N the number of segments the grid scored,
          ``grid_counts`` (B,) (a softmax at
          temperature N, as in the authors' code; unlike the code we do not divide the entropy by N
          a second time: the entropy of that distribution is the cue).
        * ``mean_log_likelihood``: mean over segments of log p_i at the final estimate (the
          paper's definition; the authors' MATLAB release uses the mean log max-posterior instead).
        * ``focal_conditioning``: :func:`focal_conditioning` of the final ``rotation`` (B, 3, 3).

        The fifth and sixth cues, ``focal_prior_share`` and (fR only) ``focal_profile_gap``, come
        from :meth:`_focal_cues`.
        """
        n = mask.sum(-1).clamp_min(1)
        counts = torch.stack([((labels == k) & mask).sum(-1) for k in range(3)], -1)
        log_q = torch.log_softmax(grid_scores / grid_counts.clamp_min(1)[:, None].to(grid_scores), -1)
        entropy = -(log_q.exp() * log_q).sum(-1)
        mean_log = (log_p * mask).sum(-1) / n
        return {"min_family_segments": counts.min(-1).values.to(torch.float64),
                "grid_entropy": entropy.to(torch.float64),
                "mean_log_likelihood": mean_log.to(torch.float64),
                "focal_conditioning": focal_conditioning(rotation).to(torch.float64)}

    def _focal_cues(self, features: SegmentFeatures, params: torch.Tensor, scores: torch.Tensor,
                    known_focal: bool) -> dict[str, torch.Tensor]:
        """The focal cues of the estimates ``params`` (B, 4) with objectives ``scores`` (B,), each
        float64 (B,): ``focal_prior_share`` (:func:`fr_torch.search.focal_prior_share`) and, when
        ``profile_gap`` is on (fR's shipped model uses it), ``focal_profile_gap``
        (:func:`fr_torch.search.focal_profile_gap`, each known-focal search refined for Fast-fR's
        number of steps; ~25 ms per photo, over half of Fast-fR's time, so Fast-fR and its model go
        without it).  0 for a given focal length: the prior plays no
        part and there is no focal length to single out."""
        names = ("focal_prior_share", "focal_profile_gap") if self.profile_gap else ("focal_prior_share",)
        if known_focal:
            return {name: torch.zeros(params.shape[0], dtype=torch.float64, device=params.device) for name in names}
        cues = {"focal_prior_share": focal_prior_share(self.likelihood, features, params,
                                                       self.search.max_chunk_elements)}
        if self.profile_gap:
            cues["focal_profile_gap"] = focal_profile_gap(self.likelihood, features, params, scores, self.search,
                                                          self.search.iterations("fast"))
        return cues

    def _sanity(self, r: CalibrationResult) -> tuple[bool, str]:
        reasons = []
        if r.num_segments < self.min_segments:
            reasons.append(f"only {r.num_segments} segments (< {self.min_segments})")
        if r.cues.get("min_family_segments", 0) < self.min_family_segments:
            reasons.append(f"a Manhattan family has only {int(r.cues['min_family_segments'])} segments "
                           "(scene may not be Manhattan)")
        if r.manhattan_fraction is not None and r.manhattan_fraction < self.min_manhattan_fraction:
            reasons.append(f"only {100 * r.manhattan_fraction:.0f} % of the segment length follows a Manhattan "
                           "frame (scene may not be Manhattan)")
        return (not reasons), "; ".join(reasons)


def calibrate(inputs: Sequence, mode: str = "fr", **kwargs) -> list[CalibrationResult]:
    """One-call API: calibrate images (paths or arrays) with fR (``mode="fr"``) or Fast-fR (``"fast"``).

    Keyword arguments go to :class:`FREstimator` (measure, detector, device, dtype, ...) or to
    :meth:`FREstimator.calibrate_images` (focal_px, principal_point, names).
    """
    call_keys = {"focal_px", "principal_point", "names"}
    call_kwargs = {k: kwargs.pop(k) for k in list(kwargs) if k in call_keys}
    return FREstimator(mode=mode, **kwargs).calibrate_images(inputs, **call_kwargs)
