"""Vanishing-point geometry shared by the baselines (Lee 2009, Simon 2018, CTRL-C adapter).

Conventions are those of :mod:`fr_torch.core.geometry.conventions`: pixels x right / y down, camera x right / y down /
z forward, ``R`` world->camera with the (downward) vertical Manhattan direction in column 1 and
``det R = +1``.  Vanishing points (VPs) are homogeneous 3-vectors in *pixel* coordinates, never
dehomogenised (a VP at infinity has a zero third coordinate); lines are homogeneous 3-vectors
``l`` with ``l . x = 0`` for the points ``x`` on them.

Everything here is numpy float64; an estimate is reported as one :class:`fr_torch.core.geometry.camera.Camera`
(:func:`camera_estimate`), whose angles come from the project's torch helpers
(:func:`fr_torch.core.geometry.conventions.angles_from_rotation`), so that every method reports roll, tilt, pitch and
pan with exactly the same definitions.
"""
from __future__ import annotations

import math

import numpy as np

from fr_torch.core.geometry.camera import Camera
from fr_torch.core.geometry.conventions import (
    hfov_from_focal,
    nearest_rotation,
    principal_point_or_centre,
    rotation_angles,
)
from fr_torch.core.likelihood.segments import SegmentFilter, validate_segments
from fr_torch.detectors.registry import detect_segments
from fr_torch.errors import FRInputError
from fr_torch.plugins.interface import CameraEstimate, ImageMeta

EPS = 1e-12


# --------------------------------------------------------------------------- inputs

def image_size(image: np.ndarray | None, meta: ImageMeta) -> tuple[int, int]:
    """(width, height) in pixels from the metadata, else from the image; (0, 0) if unknown."""
    width, height = int(meta.width or 0), int(meta.height or 0)
    if (width <= 0 or height <= 0) and image is not None:
        shape = np.asarray(image).shape
        if len(shape) >= 2:
            height, width = int(shape[0]), int(shape[1])
    return width, height


def principal_point(meta: ImageMeta, width: int, height: int) -> np.ndarray:
    """Known principal point from the metadata, else the image centre ((w - 1) / 2, (h - 1) / 2)."""
    return np.array(principal_point_or_centre(meta.principal_point, width, height))


def input_segments(image: np.ndarray | None, meta: ImageMeta) -> np.ndarray:
    """Segments (N, 4) [x1, y1, x2, y2] pixels: ``meta.segments`` when given, else LSD on the image.

    Raises :class:`FRInputError` when neither is available or the input is malformed.
    """
    if meta.segments is not None:
        return validate_segments(meta.segments, f"{meta.name or 'image'}: segments")
    if image is None:
        raise FRInputError(f"{meta.name or 'image'}: neither an image nor segments were given")
    # Every LSD segment, as these methods were published (fR's working-set cap of the longest
    # segments is fR's own bound on its search time, not part of these methods).
    return detect_segments(image, segment_filter=SegmentFilter(max_segments=None))


class NoInput(Exception):
    """Why a vertical-first baseline cannot start on an image: its message is the failure's reason."""


def long_segments(image: np.ndarray | None, meta: ImageMeta, min_length_frac: float,
                  min_segments: int) -> tuple[np.ndarray, np.ndarray, int, int, np.ndarray]:
    """The input of the vertical-first baselines (Lee 2009, Simon 2018): the segments of
    :func:`input_segments` at least ``min_length_frac`` of the image diagonal long.

    Returns (segments (M, 4) pixels, their lengths (M,) pixels, width, height, principal point (2,)
    pixels).  Raises :class:`NoInput` (the failure's reason) for a malformed input, an unknown image
    size or fewer than ``min_segments`` such segments."""
    try:
        segments = input_segments(image, meta)
    except FRInputError as exc:
        raise NoInput(f"bad input: {exc}") from exc
    width, height = image_size(image, meta)
    if width <= 0 or height <= 0:
        raise NoInput("unknown image size")
    lengths = segment_lengths(segments)
    keep = lengths >= min_length_frac * math.hypot(width, height)
    if int(keep.sum()) < min_segments:
        raise NoInput(f"too few line segments ({int(keep.sum())})")
    return segments[keep], lengths[keep], width, height, principal_point(meta, width, height)


# --------------------------------------------------------------------------- lines and VPs

def segment_lengths(segments: np.ndarray) -> np.ndarray:
    """Lengths (N,) of segments (N, 4), pixels."""
    segments = np.asarray(segments, dtype=np.float64).reshape(-1, 4)
    return np.hypot(segments[:, 2] - segments[:, 0], segments[:, 3] - segments[:, 1])


def segment_midpoints(segments: np.ndarray) -> np.ndarray:
    segments = np.asarray(segments, dtype=np.float64).reshape(-1, 4)
    return 0.5 * (segments[:, :2] + segments[:, 2:])


def segment_directions(segments: np.ndarray) -> np.ndarray:
    """Unit direction vectors (N, 2) of the segments (sign arbitrary)."""
    segments = np.asarray(segments, dtype=np.float64).reshape(-1, 4)
    d = segments[:, 2:] - segments[:, :2]
    return d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), EPS)


def homogeneous_lines(segments: np.ndarray, centre=(0.0, 0.0), scale: float = 1.0) -> np.ndarray:
    """Unit homogeneous lines (N, 3) through the segments' endpoints.

    Endpoints are first mapped to ``scale * (x - centre)`` (e.g. normalised coordinates); the line
    is the cross product of the homogeneous endpoints, normalised to unit length.
    """
    segments = np.asarray(segments, dtype=np.float64).reshape(-1, 4)
    centre = np.asarray(centre, dtype=np.float64).reshape(2)
    p = np.concatenate([(segments[:, :2] - centre) * scale, np.ones((len(segments), 1))], 1)
    q = np.concatenate([(segments[:, 2:] - centre) * scale, np.ones((len(segments), 1))], 1)
    lines = np.cross(p, q)
    return lines / np.maximum(np.linalg.norm(lines, axis=1, keepdims=True), EPS)


def conditioning(width: int, height: int, pp: np.ndarray | None = None) -> np.ndarray:
    """Similarity T (3, 3) mapping pixels to centred coordinates of order 1 (for stable SVDs)."""
    pp = np.array(principal_point_or_centre(pp, width, height))
    s = 2.0 / max(width, height, 1)
    return np.array([[s, 0, -s * pp[0]], [0, s, -s * pp[1]], [0, 0, 1.0]])


def vp_least_squares(segments: np.ndarray, weights: np.ndarray | None = None,
                     transform: np.ndarray | None = None) -> np.ndarray:
    """Least-squares VP (unit homogeneous 3-vector, pixels) of the lines through ``segments``.

    Minimises ``sum_i w_i (l_i . v)^2`` over unit ``v`` (the smallest right singular vector of
    the weighted line matrix), computed in the conditioned frame ``transform`` (default: centred
    coordinates scaled by the segment spread) and mapped back to pixels.
    """
    segments = np.asarray(segments, dtype=np.float64).reshape(-1, 4)
    if len(segments) < 2:
        raise ValueError("a vanishing point needs at least two lines")
    if transform is None:
        pts = segments.reshape(-1, 2)
        centre = pts.mean(0)
        s = 1.0 / max(np.abs(pts - centre).max(), 1.0)
        transform = np.array([[s, 0, -s * centre[0]], [0, s, -s * centre[1]], [0, 0, 1.0]])
    w = np.ones(len(segments)) if weights is None else np.asarray(weights, dtype=np.float64)
    p = np.concatenate([segments[:, :2], np.ones((len(segments), 1))], 1) @ transform.T
    q = np.concatenate([segments[:, 2:], np.ones((len(segments), 1))], 1) @ transform.T
    lines = np.cross(p, q)
    lines /= np.maximum(np.linalg.norm(lines, axis=1, keepdims=True), EPS)
    _, _, vt = np.linalg.svd(lines * np.sqrt(w)[:, None], full_matrices=False)
    v = np.linalg.solve(transform, vt[-1])
    return v / np.linalg.norm(v)


def vp_from_two_lines(line_a: np.ndarray, line_b: np.ndarray) -> np.ndarray:
    """Intersection (unit homogeneous) of homogeneous lines, broadcasting over leading axes."""
    v = np.cross(line_a, line_b)
    return v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), EPS)


def vp_angle_error(segments: np.ndarray, vps: np.ndarray) -> np.ndarray:
    """Angle (radians, in [0, pi/2]) between each segment and the line joining its midpoint to a VP.

    ``segments`` (N, 4) pixels; ``vps`` (..., 3) homogeneous pixels (finite or at infinity).
    Returns (..., N).  This is the usual consistency measure of a segment with a VP.
    """
    mid = segment_midpoints(segments)  # (N, 2)
    d = segment_directions(segments)  # (N, 2)
    vps = np.asarray(vps, dtype=np.float64)
    vx, vy, vw = vps[..., 0:1], vps[..., 1:2], vps[..., 2:3]  # (..., 1)
    # Direction from the midpoint to the VP: v_xy - w * m (valid for w = 0 too).
    ax = vx - vw * mid[:, 0]
    ay = vy - vw * mid[:, 1]
    norm = np.maximum(np.hypot(ax, ay), EPS)
    sin = np.abs(ax * d[:, 1] - ay * d[:, 0]) / norm
    return np.arcsin(np.clip(sin, 0.0, 1.0))


def is_finite_vp(vp: np.ndarray, pp: np.ndarray, limit_px: float) -> bool:
    """True when the VP lies within ``limit_px`` of the principal point (i.e. usefully finite)."""
    vp = np.asarray(vp, dtype=np.float64)
    return bool(abs(vp[2]) > EPS and np.linalg.norm(vp[:2] / vp[2] - pp) < limit_px)


def dehomogenise(vp: np.ndarray) -> np.ndarray:
    return np.asarray(vp[:2], dtype=np.float64) / vp[2]


# --------------------------------------------------------------------------- calibration

def intrinsics(focal_px: float, pp: np.ndarray) -> np.ndarray:
    return np.array([[focal_px, 0, pp[0]], [0, focal_px, pp[1]], [0, 0, 1.0]])


def focal_from_orthogonal_vps(vp_a: np.ndarray, vp_b: np.ndarray, pp: np.ndarray) -> float | None:
    """Focal length (pixels) making two finite VPs orthogonal: ``f^2 = -(a - p) . (b - p)``.

    Returns None when either VP is at infinity or the two are not compatible with orthogonality
    (the product is not negative).
    """
    if abs(vp_a[2]) < EPS or abs(vp_b[2]) < EPS:
        return None
    f2 = -float(np.dot(dehomogenise(vp_a) - pp, dehomogenise(vp_b) - pp))
    return math.sqrt(f2) if f2 > 0 else None


def direction_from_vp(vp: np.ndarray, focal_px: float, pp: np.ndarray) -> np.ndarray:
    """Unit 3-D direction (camera frame) ``K^-1 v`` of a homogeneous VP; sign arbitrary."""
    vp = np.asarray(vp, dtype=np.float64)
    d = np.array([vp[0] - pp[0] * vp[2], vp[1] - pp[1] * vp[2], focal_px * vp[2]])
    return d / max(np.linalg.norm(d), EPS)


def rotation_from_directions(vertical: np.ndarray, horizontal: np.ndarray,
                             horizontal2: np.ndarray | None = None) -> np.ndarray:
    """World->camera R (vertical in column 1, pointing down; det +1) from Manhattan directions.

    ``vertical`` and ``horizontal`` (and optionally the second horizontal direction) are camera-
    frame 3-vectors with arbitrary signs and lengths.  The vertical is signed to point down
    (positive camera y), the first horizontal to point forward (or right when it is parallel to
    the image plane); the third column is ``col0 x col1`` (det +1) and the measured second
    horizontal, if given, is averaged into it with its sign aligned.  The triplet is then
    orthogonalised by the SVD (orthogonal Procrustes), so noisy VPs give the closest rotation.
    """
    v = np.asarray(vertical, dtype=np.float64)
    v = v / max(np.linalg.norm(v), EPS)
    if v[1] < 0:
        v = -v
    h = np.asarray(horizontal, dtype=np.float64)
    h = h / max(np.linalg.norm(h), EPS)
    key = h[2] if abs(h[2]) > 1e-9 else h[0]
    if key < 0:
        h = -h
    third = np.cross(h, v)
    third /= max(np.linalg.norm(third), EPS)
    if horizontal2 is not None:
        h2 = np.asarray(horizontal2, dtype=np.float64)
        h2 = h2 / max(np.linalg.norm(h2), EPS)
        third = third + (h2 if np.dot(h2, third) >= 0 else -h2)
    return nearest_rotation(np.stack([h, v, third], axis=1))


def rotation_from_vps(vertical_vp: np.ndarray, horizontal_vp: np.ndarray, focal_px: float,
                      pp: np.ndarray, horizontal_vp2: np.ndarray | None = None) -> np.ndarray:
    """World->camera R from homogeneous pixel VPs and the focal length (see rotation_from_directions).

    Column 0 is the horizontal direction closer to the camera x axis when both are given.
    """
    dv = direction_from_vp(vertical_vp, focal_px, pp)
    dh = direction_from_vp(horizontal_vp, focal_px, pp)
    dh2 = None if horizontal_vp2 is None else direction_from_vp(horizontal_vp2, focal_px, pp)
    if dh2 is not None and abs(dh2[0]) > abs(dh[0]):
        dh, dh2 = dh2, dh
    return rotation_from_directions(dv, dh, dh2)


def positive_w(points) -> np.ndarray:
    """Homogeneous VPs (M, 3) float64, each negated where ``w < 0`` so that ``w >= 0``."""
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    return points * np.where(points[:, 2:] < 0, -1.0, 1.0)


def rank_by_support(points, support) -> np.ndarray:
    """Homogeneous VPs (M, 3) signed so that ``w >= 0``, sorted by ``support`` (M,), largest first
    (ties keep the given order): a method's ``ranked_vanishing_points``."""
    points = positive_w(points)
    order = np.argsort(-np.asarray(support, dtype=np.float64).reshape(-1), kind="stable")
    return points[order]


def pick_zenith(points: np.ndarray, pp: np.ndarray, max_angle_deg: float, min_distance_px: float) -> int | None:
    """Index of the first of ranked VPs (M, 3) that can be the zenith: seen from the principal
    point within ``max_angle_deg`` of the image vertical, and at infinity or farther than
    ``min_distance_px`` from it; None when none is."""
    cos_limit = math.cos(math.radians(max_angle_deg))
    for i, vp in enumerate(np.asarray(points, dtype=np.float64).reshape(-1, 3)):
        offset = vp[:2] - pp * vp[2]
        norm = float(np.linalg.norm(offset))
        if norm < EPS or abs(offset[1]) < cos_limit * norm:
            continue
        if abs(vp[2]) > EPS and norm / abs(vp[2]) <= min_distance_px:
            continue
        return i
    return None


def orthogonal_pair(hvps: list[dict], zvp: np.ndarray, pp: np.ndarray, diag: float,
                    focal_bounds: tuple[float, float], finite_limit: float, zenith_tol_deg: float):
    """The focal length from the best pair of horizontal VPs: ``(f, vp_i, vp_j)`` or None.

    ``hvps``: candidates ``{"vp": (3,) homogeneous pixels, "significance": score}``.  A pair counts
    when both VPs lie within ``finite_limit * diag`` of the principal point, their orthogonality
    gives ``f^2 = -(v_i - p) . (v_j - p) > 0`` with f within half the lower and twice the upper of
    ``focal_bounds`` (pixels), and, when the zenith ``zvp`` is finite, both directions are within
    ``zenith_tol_deg`` of perpendicular to it under that f.  The pair with the largest summed
    significance wins (Simon 2018's rule; CONSAC's f uses it too).
    """
    f_lo, f_hi = focal_bounds
    zenith_finite = is_finite_vp(zvp, pp, 1e6 * diag)
    tol = math.sin(math.radians(zenith_tol_deg))
    best = None
    for i in range(len(hvps)):
        for j in range(i + 1, len(hvps)):
            vi, vj = hvps[i], hvps[j]
            if not (is_finite_vp(vi["vp"], pp, finite_limit * diag) and is_finite_vp(vj["vp"], pp, finite_limit * diag)):
                continue
            f = focal_from_orthogonal_vps(vi["vp"], vj["vp"], pp)
            if f is None or not (0.5 * f_lo <= f <= 2.0 * f_hi):
                continue
            if zenith_finite:
                dz = direction_from_vp(zvp, f, pp)
                if any(abs(dz @ direction_from_vp(v["vp"], f, pp)) > tol for v in (vi, vj)):
                    continue
            score = vi["significance"] + vj["significance"]
            if best is None or score > best[0]:
                best = (score, f, vi, vj)
    return None if best is None else best[1:]


def camera_estimate(method: str, camera: Camera, runtime_s: float = float("nan"),
                    ranked_vanishing_points: np.ndarray | None = None, **extra) -> CameraEstimate:
    """A successful CameraEstimate of ``camera``: every angle and the hfov derived by the Camera;
    ``ranked_vanishing_points`` (M, 3) as :func:`rank_by_support` gives them."""
    return CameraEstimate(method=method, camera=camera, runtime_s=runtime_s, extra=dict(extra),
                          ranked_vanishing_points=ranked_vanishing_points)


def failure_estimate(method: str, reason: str, extra: dict,
                     ranked_vanishing_points: np.ndarray | None = None) -> CameraEstimate:
    """A failed CameraEstimate (``reason``) that still carries ``extra`` and the method's ranked
    vanishing points (M, 3), when it found them but could not turn them into f and R."""
    estimate = CameraEstimate.failure(method, reason)
    estimate.extra.update(extra)
    estimate.ranked_vanishing_points = ranked_vanishing_points
    return estimate


def roll_from_zenith(zenith_vp: np.ndarray, pp: np.ndarray) -> float:
    """Roll (degrees, paper definition) from the vertical VP alone; it needs no focal length.

    With c = K^-1 z the up direction in the y-up camera frame, roll = atan(-c_x / c_y) and the
    focal length cancels in the ratio.
    """
    z = np.asarray(zenith_vp, dtype=np.float64)
    dx, dy = z[0] - pp[0] * z[2], z[1] - pp[1] * z[2]
    # y-up frame: c = (dx, -dy, .) up to a common sign, which cancels in the ratio.
    if abs(dy) < EPS:
        return 90.0 if dx > 0 else -90.0
    return math.degrees(math.atan(-dx / -dy))


# --------------------------------------------------------------------------- vertical VP

def near_vertical_mask(segments: np.ndarray, max_angle_deg: float) -> np.ndarray:
    """Segments within ``max_angle_deg`` of the image vertical."""
    d = segment_directions(segments)
    return np.abs(d[:, 1]) >= math.cos(math.radians(max_angle_deg))


def vertical_vp(segments: np.ndarray, max_angle_deg: float = 30.0, inlier_deg: float = 1.5,
                max_hypothesis_segments: int = 80) -> tuple[np.ndarray, np.ndarray] | None:
    """Vertical VP (unit homogeneous, pixels) from the near-vertical segments, hypothesise-and-test.

    Every pair among the (longest ``max_hypothesis_segments``) near-vertical segments proposes a
    VP; a hypothesis scores the summed length of the near-vertical segments within ``inlier_deg``
    of it (:func:`vp_angle_error`).  The best one is refined by least squares on its inliers
    (twice).  Returns ``(vp, inlier mask over all segments)`` or None with fewer than two
    near-vertical segments.
    """
    segments = np.asarray(segments, dtype=np.float64).reshape(-1, 4)
    cand = np.flatnonzero(near_vertical_mask(segments, max_angle_deg))
    if len(cand) < 2:
        return None
    lengths = segment_lengths(segments)
    cand_sorted = cand[np.argsort(-lengths[cand])][:max_hypothesis_segments]
    lines = homogeneous_lines(segments[cand_sorted], centre=segments.reshape(-1, 2).mean(0),
                              scale=1.0 / max(np.abs(segments).max(), 1.0))
    i, j = np.triu_indices(len(cand_sorted), 1)
    hyp_c = vp_from_two_lines(lines[i], lines[j])  # conditioned frame
    centre = segments.reshape(-1, 2).mean(0)
    s = 1.0 / max(np.abs(segments).max(), 1.0)
    T = np.array([[s, 0, -s * centre[0]], [0, s, -s * centre[1]], [0, 0, 1.0]])
    hyp = np.linalg.solve(T, hyp_c.T).T  # back to pixels
    err = vp_angle_error(segments[cand], hyp)  # (H, Nv)
    thr = math.radians(inlier_deg)
    score = ((err < thr) * lengths[cand]).sum(1)
    # Two collinear candidate segments meet in no point (the zero vector): never a hypothesis.
    norms = np.linalg.norm(hyp, axis=1)
    usable = np.isfinite(norms) & (norms > 0)
    if not usable.any():
        return None
    best_index = int(np.argmax(np.where(usable, score, -np.inf)))
    vp = hyp[best_index] / norms[best_index]
    for _ in range(2):
        inl = cand[vp_angle_error(segments[cand], vp) < thr]
        if len(inl) < 2:
            break
        vp = vp_least_squares(segments[inl], lengths[inl])
    inliers = np.zeros(len(segments), bool)
    inliers[cand] = vp_angle_error(segments[cand], vp) < thr
    return vp, inliers
