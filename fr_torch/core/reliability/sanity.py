"""The sanity checks of an estimate, each a reason in ``reason`` and ``reliable = False``: too few
segments, a Manhattan family nearly empty, too little of the segment length following a Manhattan
frame (:func:`sanity_check`); the focal length or an angle at its search box's edge
(:func:`check_result`); lines that bend (:func:`lines_bend_reason`, from the cues
:data:`LINE_BEND_CUES`); and, last of all, nothing non-finite in any field (:func:`finite_record`).
"""
from __future__ import annotations

import math
from typing import Sequence

import numpy as np

from fr_torch.core.geometry.lens import border_bow_percent
from fr_torch.core.settings.config import SearchConfig
from fr_torch.core.settings.distortion import DistortionSetting

EDGE_REASON = "focal at the edge of the search range"
#: The cues of the "lines bend" check of pinhole estimates (:func:`lines_bend_reason`,
#: :func:`fr_torch.core.search.lens.bend_test`): the likelihood gain of a short division search
#: over the pinhole estimate (nats per 1000 px of segment length) and its k; the plumb line's k, the
#: share of the turning of pieces of lines it removes, and how many pairs of pieces there were.
LINE_BEND_CUES = ("line_bend_gain", "line_bend_k", "line_bend_plumb_k", "line_bend_share", "line_bend_pairs")


NON_FINITE_REASON = "non-finite estimate (NaN/inf in the parameters, objective or outputs)"


def angle_edge_reason(name: str, low: float, high: float) -> str:
    """The reason given for a ``name`` angle (pan, pitch or roll) found at the edge of its search
    box [``low``, ``high``] (degrees): the camera may lie outside it."""
    return f"{name} at the edge of the search range [{low:g}, {high:g}] deg (the camera may lie outside it)"


def check_result(result, config: SearchConfig, known_focal: bool = False,
                 edge_tolerance_deg: float = 0.25, finite: bool | None = None,
                 search_params: Sequence[float] | None = None, long_side_fov_deg: float | None = None) -> None:
    """Final checks on an estimator result (in place; ``result`` has the fields of
    :class:`fr_torch.core.result.CalibrationResult`).

    * Anything non-finite in the focal length, angles, rotation, vanishing points or objective ->
      ``ok = False``, ``reliable = False``, camera fields cleared, ``reason`` says so (a NaN is a
      failure, never a valid number).
    * An estimated focal length whose long-side FOV lies within ``edge_tolerance_deg`` of the
      search range's edge -> ``reliable = False`` with reason :data:`EDGE_REASON` (the truth may lie
      outside the range).
    * Likewise a search angle within ``edge_tolerance_deg`` of its box's edge, from
      ``search_params`` ([pan, pitch, roll (degrees), f], the search's own parametrisation, which
      the result's horizon angles only approximate): pitch or roll, and pan unless it wraps
      (:attr:`SearchConfig.periodic_pan`) -> ``reliable = False`` with reason
      :func:`angle_edge_reason` (a camera looking down more steeply than ``pitch_range_deg``
      allows is found at the edge with a wrong focal length).

    ``finite``: the caller's batched finiteness check of the same values (the estimator checks its
    parameters, objective and rotation, from which every derived value follows finitely); None =
    check the record's values here.  ``long_side_fov_deg``: the estimate's FOV across the long side
    (degrees), when the caller computed it for its batch; None = from ``result.focal_px`` here.
    """
    if not result.ok:
        return
    if finite is None:
        values = [result.focal_px, result.hfov_deg, result.roll_deg, result.tilt_deg, result.pitch_deg,
                  result.log_likelihood]
        arrays = [result.rotation, result.vanishing_points]
        finite = all(v is not None and math.isfinite(float(v)) for v in values) and \
            all(a is not None and bool(np.isfinite(np.asarray(a, dtype=np.float64)).all()) for a in arrays)
    if not finite:
        for key in ("focal_px", "hfov_deg", "rotation", "pan_deg", "tilt_deg", "roll_deg", "pitch_deg",
                    "vanishing_points", "log_likelihood"):
            setattr(result, key, None)
        result.ok, result.reliable, result.reason = False, False, NON_FINITE_REASON
        return
    reasons = []
    if search_params is not None:
        boxes = {"pan": config.pan_range_deg, "pitch": config.pitch_range_deg, "roll": config.roll_range_deg}
        for index, (name, (low, high)) in enumerate(boxes.items()):
            if name == "pan" and config.periodic_pan:
                continue
            value = float(search_params[index])
            if high - low > 2 * edge_tolerance_deg and (value <= low + edge_tolerance_deg
                                                        or value >= high - edge_tolerance_deg):
                reasons.append(angle_edge_reason(name, low, high))
    if not known_focal:
        at_edge = config.fov_range.at_edge(result.focal_px, max(result.width, result.height), edge_tolerance_deg) \
            if long_side_fov_deg is None else config.fov_range.fov_at_edge(long_side_fov_deg, edge_tolerance_deg)
        if at_edge:
            reasons.append(EDGE_REASON)
    if reasons:
        result.reliable = False
        result.reason = "; ".join(r for r in (result.reason, *reasons) if r)


# The record's fields that make up the estimate (a non-finite one fails it) and its side fields (a
# non-finite one is removed): see :func:`finite_record`.
ESTIMATE_FIELDS = ("focal_px", "hfov_deg", "principal_point", "rotation", "pan_deg", "tilt_deg", "roll_deg",
                   "pitch_deg", "vanishing_points", "log_likelihood")


def _all_finite(value) -> bool:
    if value is None:
        return True
    if isinstance(value, float):  # Python and NumPy float64 scalars: most fields and every cue
        return math.isfinite(value)
    if isinstance(value, int):  # bool and int are finite (NumPy integers take the array route)
        return True
    try:
        return bool(np.isfinite(np.asarray(value, dtype=np.float64)).all())
    except (TypeError, ValueError, OverflowError):
        return False


def finite_record(result) -> None:
    """The last check of every result (in place; ``result`` has the fields of
    :class:`fr_torch.core.result.CalibrationResult`): afterwards no field holds NaN or inf.

    * A non-finite value in the estimate (:data:`ESTIMATE_FIELDS`) fails it as :func:`check_result`
      does (``ok = False``, camera and objective cleared, reason :data:`NON_FINITE_REASON`).
    * A non-finite ``manhattan_fraction`` becomes None, a non-finite cue is removed from ``cues``,
      a ``predicted_error`` with a non-finite value becomes None; an estimate that had one is not
      reliable, and ``reason`` names what was removed.  Non-finite ``runtime_s`` entries are removed.
    * The ranked vanishing points (with their support and families) are removed from a failed
      estimate and from one where any of them is non-finite.
    """
    if result.ok and not all(_all_finite(getattr(result, key)) for key in ESTIMATE_FIELDS):
        result.camera, result.log_likelihood = None, None
        result.ok, result.reliable, result.reason = False, False, NON_FINITE_REASON
    if not _all_finite(result.log_likelihood):
        result.log_likelihood = None
    if hasattr(result, "ranked_vanishing_points") and not (
            result.ok and _all_finite(result.ranked_vanishing_points) and _all_finite(result.vanishing_point_support)):
        result.ranked_vanishing_points = result.vanishing_point_support = result.vanishing_point_families = None
    removed = []
    if not _all_finite(result.manhattan_fraction):
        result.manhattan_fraction = None
        removed.append("manhattan_fraction")
    for key in [key for key, value in result.cues.items() if not _all_finite(value)]:
        del result.cues[key]
        removed.append(f"cue {key}")
    if result.predicted_error is not None and not all(_all_finite(v) for v in result.predicted_error.values()):
        result.predicted_error = None
        removed.append("predicted_error")
    result.runtime_s = {key: value for key, value in result.runtime_s.items() if _all_finite(value)}
    if removed and result.ok:
        message = f"non-finite {', '.join(removed)} removed from the record"
        result.reliable = False
        result.reason = f"{result.reason}; {message}" if result.reason else message


def lines_bend_reason(cues: dict, setting: DistortionSetting, width: float, height: float) -> str | None:
    """The "lines bend" sanity check of a pinhole estimate: the reason it is not reliable, or None.

    ``cues``: the result's cues (:data:`LINE_BEND_CUES`, computed for pinhole estimates only);
    ``width``, ``height``: the image's size (the bow of a k depends on the aspect ratio).  The lines
    bend when a division model of a k whose border bow (:func:`fr_torch.core.geometry.lens.border_bow_percent`)
    reaches ``setting.bend_min_bow_pct`` either explains the segments better by
    ``setting.bend_min_gain`` nats per 1000 px (``line_bend_gain`` at ``line_bend_k``), or
    straightens at least ``setting.bend_min_share`` of the turning of ``setting.bend_min_pairs`` or
    more pairs of pieces of lines (the plumb line, ``line_bend_plumb_k``).  The same test makes
    ``auto`` search an image with the division model."""
    def visible(k) -> bool:
        bow = border_bow_percent(float(k), width, height) if k is not None and math.isfinite(k) else math.nan
        return abs(bow) >= setting.bend_min_bow_pct

    gain, k = cues.get("line_bend_gain"), cues.get("line_bend_k")
    plumb_k, share, pairs = cues.get("line_bend_plumb_k"), cues.get("line_bend_share"), cues.get("line_bend_pairs")
    if gain is not None and gain >= setting.bend_min_gain and visible(k):
        evidence = f"k ~ {k:+.2f} fits them {gain:.0f} nats/1000 px better than a pinhole camera"
    elif share is not None and pairs is not None and share >= setting.bend_min_share \
            and pairs >= setting.bend_min_pairs and visible(plumb_k):
        k = plumb_k
        evidence = f"k ~ {k:+.2f} straightens {100 * share:.0f} % of the turning of {int(pairs)} pairs of line pieces"
    else:
        return None
    bow = border_bow_percent(float(k), width, height)
    return (f"the lines bend (a wide-angle lens: {evidence}; border lines bow ~{bow:.1f} % of the width): "
            "use --distortion division (Python: distortion='division')")


def sanity_check(r, min_segments: int, min_family_segments: int, min_manhattan_fraction: float) -> tuple[bool, str]:
    """(reliable, reason) of a result from its segment counts: fewer than ``min_segments`` segments,
    a Manhattan family with fewer than ``min_family_segments``, or less than
    ``min_manhattan_fraction`` of the segment length labelled with a family -> not reliable."""
    reasons = []
    if r.num_segments < min_segments:
        reasons.append(f"only {r.num_segments} segments (< {min_segments})")
    if r.cues.get("min_family_segments", 0) < min_family_segments:
        reasons.append(f"a Manhattan family has only {int(r.cues['min_family_segments'])} segments "
                       "(scene may not be Manhattan)")
    if r.manhattan_fraction is not None and r.manhattan_fraction < min_manhattan_fraction:
        reasons.append(f"only {100 * r.manhattan_fraction:.0f} % of the segment length follows a Manhattan "
                       "frame (scene may not be Manhattan)")
    return (not reasons), "; ".join(reasons)
