"""``lee2009``: orthogonal vanishing-point triplet over a focal sweep, after Lee, Hebert & Kanade 2009.

D. C. Lee, M. Hebert, T. Kanade, "Geometric reasoning for single image structure recovery",
CVPR 2009.  Their structure recovery starts from line segments and three mutually orthogonal
vanishing points found by hypothesise-and-test with supporting-line votes; the focal length comes
with the orthogonal triplet.  This is a re-implementation of that front end (the building-model
reasoning of the paper is not needed for calibration):

1. Line segments (``meta.segments`` when given, else LSD), keeping those longer than
   ``min_length_frac`` of the image diagonal.
2. Vertical VP from the near-vertical segments (within ``vertical_max_deg`` of the image
   vertical): every pair of the longest ones proposes a VP, the hypothesis with the largest summed
   length of segments within ``inlier_deg`` wins and is refined by least squares
   (:func:`fr_baselines.vp_geometry.vertical_vp`).
3. Focal sweep: ``n_focal`` focal lengths, log-spaced so that the horizontal field of view of the
   image's *long side* spans ``range`` (a :class:`~fr_torch.core.settings.fov.FovRange` or anything its ``parse`` takes) (so the sweep scales with the image size; default:
   fR's library default range, ``configs/search.json``; option ``lee2009[range=paper]`` or
   ``range=MIN:MAX``, and ``fr eval --hfov-range`` sets it for every method of a table).  For
   each focal the vertical VP fixes the horizon; every other segment's line meets the horizon in
   a candidate first horizontal VP, and orthogonality gives the second one: an orthogonal triplet
   (hypotheses from the ``max_hypothesis_segments`` longest segments, votes from the
   ``max_voting_segments`` longest, to bound the cost on cluttered images).
   A triplet scores the summed segment length supporting any of its three VPs (a segment supports
   a VP when the line from its midpoint to the VP is within ``inlier_deg`` of the segment; the
   vote decays quadratically to zero at the threshold so that nearby focals are ranked).
4. The best triplet (focal + rotation) is refined by robust least squares on the angular errors
   of its supporting segments (the VPs re-fitted to their assigned lines; this refinement is our
   addition for accuracy, the sweep alone is quantised).

Output: focal (pixels), R (vertical in column 1) and the derived roll / tilt / pitch / pan; the
three vanishing points ranked by their supporting segments (``ranked_vanishing_points``).
Failures (flagged, never raised): unusable input, fewer than ``min_segments`` segments, no
vertical VP, or no horizontal VP with at least ``min_support`` segments.
"""
from __future__ import annotations

import math

import numpy as np
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from fr_torch.core.geometry.camera import Camera
from fr_torch.core.geometry.conventions import focal_from_hfov
from fr_torch.core.settings.fov import FovRange
from fr_torch.plugins.interface import CameraEstimate, ImageMeta, TimedCalibrator

from . import vp_geometry as vg


class Lee2009(TimedCalibrator):
    """Orthogonal VP triplet + focal sweep (Lee, Hebert & Kanade, CVPR 2009)."""

    name = "lee2009"

    def __init__(self, n_focal: int = 64, range=None,
                 inlier_deg: float = 2.0, vertical_max_deg: float = 30.0, min_length_frac: float = 0.02,
                 min_segments: int = 8, min_support: int = 3, refine: bool = True,
                 theta_step_deg: float = 0.25, max_hypothesis_segments: int = 200,
                 max_voting_segments: int = 1000):
        self.n_focal = int(n_focal)
        self.fov_range = FovRange.parse(range)
        self.inlier_deg = float(inlier_deg)
        self.vertical_max_deg = float(vertical_max_deg)
        self.min_length_frac = float(min_length_frac)
        self.min_segments = int(min_segments)
        self.min_support = int(min_support)
        self.refine = bool(refine)
        self.theta_step_deg = float(theta_step_deg)
        self.max_hypothesis_segments = int(max_hypothesis_segments)
        self.max_voting_segments = int(max_voting_segments)

    # ------------------------------------------------------------------ steps
    def focal_sweep(self, width: int, height: int) -> np.ndarray:
        """Focal lengths (pixels) of the sweep: long-side hfov over ``range`` (a :class:`~fr_torch.core.settings.fov.FovRange` or anything its ``parse`` takes), log-spaced."""
        long_side = max(width, height)
        low, high = self.fov_range
        return np.geomspace(focal_from_hfov(high, long_side), focal_from_hfov(low, long_side), self.n_focal)

    def _estimate(self, image, meta: ImageMeta) -> CameraEstimate:
        try:
            segments, lengths, width, height, pp = vg.long_segments(image, meta, self.min_length_frac,
                                                                    self.min_segments)
        except vg.NoInput as exc:
            return CameraEstimate.failure(self.name, str(exc))

        found = vg.vertical_vp(segments, self.vertical_max_deg, self.inlier_deg)
        if found is None:
            return CameraEstimate.failure(self.name, "no vertical vanishing point (too few near-vertical segments)")
        zvp, vertical_inliers = found

        best = self._sweep(segments, lengths, zvp, vertical_inliers, pp, width, height)
        if best is None:
            return CameraEstimate.failure(self.name, "no orthogonal vanishing-point triplet")
        focal, rotation, score = best
        if self.refine:
            focal, rotation = self._refine(segments, lengths, focal, rotation, pp)
        support = self._support(segments, focal, rotation, pp)
        horizontal_support = sorted((int(support[0]), int(support[2])), reverse=True)
        if horizontal_support[0] < self.min_support:
            return CameraEstimate.failure(self.name, "no horizontal vanishing point with enough support")
        camera = Camera(width, height, focal, pp, rotation)
        return vg.camera_estimate(self.name, camera, score=float(score), support=[int(s) for s in support],
                                  ranked_vanishing_points=vg.rank_by_support(camera.vanishing_points, support))

    def _sweep(self, segments, lengths, zvp, vertical_inliers, pp, width, height):
        """Best (focal, R, score) over the focal sweep and the line-proposed horizontal VPs."""
        thr = math.radians(self.inlier_deg)
        others = np.flatnonzero(~vertical_inliers)
        if len(others) < 1:
            return None
        # Hypotheses come from the longest non-vertical segments, votes from the longest segments
        # (caps keep the sweep fast on cluttered images; short segments carry little weight).
        proposers = segments[others[np.argsort(-lengths[others])][: self.max_hypothesis_segments]]
        lines = vg.homogeneous_lines(proposers)
        voters = np.argsort(-lengths)[: self.max_voting_segments]
        segments, lengths = segments[voters], lengths[voters]
        err_v = vg.vp_angle_error(segments, zvp)
        best = (-1.0, None, None)
        step = math.radians(self.theta_step_deg)
        for focal in self.focal_sweep(width, height):
            K = vg.intrinsics(focal, pp)
            K_inv = np.linalg.inv(K)
            dv = vg.direction_from_vp(zvp, focal, pp)
            e1 = np.array([1.0, 0.0, 0.0]) - dv[0] * dv
            if np.linalg.norm(e1) < 1e-6:
                e1 = np.array([0.0, 0.0, 1.0]) - dv[2] * dv
            e1 /= np.linalg.norm(e1)
            e2 = np.cross(dv, e1)
            horizon = K_inv.T @ dv  # line of the VPs of all horizontal directions
            cand = np.cross(lines, horizon)  # (M, 3) candidate horizontal VPs
            d = cand @ K_inv.T
            theta = np.mod(np.arctan2(d @ e2, d @ e1), math.pi / 2)
            theta = np.unique(np.round(theta / step)) * step  # dedupe on a fine grid
            d1 = np.cos(theta)[:, None] * e1 + np.sin(theta)[:, None] * e2
            d2 = -np.sin(theta)[:, None] * e1 + np.cos(theta)[:, None] * e2
            err = np.minimum(vg.vp_angle_error(segments, d1 @ K.T), vg.vp_angle_error(segments, d2 @ K.T))
            err = np.minimum(err, err_v[None, :])
            vote = np.clip(1.0 - (err / thr) ** 2, 0.0, None) * lengths
            scores = vote.sum(1)
            k = int(np.argmax(scores))
            if scores[k] > best[0]:
                best = (float(scores[k]), focal, vg.rotation_from_directions(dv, d1[k], d2[k]))
        if best[1] is None:
            return None
        return best[1], best[2], best[0]

    def _assign(self, segments, focal, rotation, pp, thr):
        """VP index (0, 1, 2) of each segment, or -1 when none is within ``thr`` radians."""
        vps = (vg.intrinsics(focal, pp) @ rotation).T  # (3, 3): row i = VP i
        err = vg.vp_angle_error(segments, vps)  # (3, N)
        label = np.argmin(err, 0)
        label[err.min(0) >= thr] = -1
        return label

    def _support(self, segments, focal, rotation, pp):
        label = self._assign(segments, focal, rotation, pp, math.radians(self.inlier_deg))
        return [int((label == i).sum()) for i in range(3)]

    def _refine(self, segments, lengths, focal, rotation, pp):
        """Robust least squares on (log f, small rotation) of the supporting segments' errors."""
        mid = vg.segment_midpoints(segments)
        dirs = vg.segment_directions(segments)
        for _ in range(2):
            label = self._assign(segments, focal, rotation, pp, 1.5 * math.radians(self.inlier_deg))
            used = label >= 0
            if used.sum() < 4:
                break
            m, dd, lab, w = mid[used], dirs[used], label[used], np.sqrt(lengths[used])
            r0, f0 = rotation, focal

            def residuals(x, m=m, dd=dd, lab=lab, w=w, r0=r0, f0=f0):
                f = f0 * math.exp(x[0])
                r = Rotation.from_rotvec(x[1:]).as_matrix() @ r0
                vps = (vg.intrinsics(f, pp) @ r)[:, lab]  # (3, M) VP of each segment
                ax = vps[0] - vps[2] * m[:, 0]
                ay = vps[1] - vps[2] * m[:, 1]
                norm = np.maximum(np.hypot(ax, ay), vg.EPS)
                return w * (ax * dd[:, 1] - ay * dd[:, 0]) / norm  # signed sine of the angle error

            sol = least_squares(residuals, np.zeros(4), loss="soft_l1",
                                f_scale=math.sin(math.radians(0.5 * self.inlier_deg)) * float(np.median(w)))
            new_focal = f0 * math.exp(sol.x[0])
            if not np.isfinite(new_focal) or new_focal <= 0:
                break
            focal = new_focal
            rotation = vg.nearest_rotation(Rotation.from_rotvec(sol.x[1:]).as_matrix() @ r0)
        # Column 1 stays the vertical (the refinement rotates all columns together); re-impose the
        # sign convention (vertical down, det +1).
        return focal, vg.rotation_from_directions(rotation[:, 1], rotation[:, 0], rotation[:, 2])
