"""``simon2018``: a-contrario horizon-first VP detection, after Simon, Fond & Berger, ECCV 2018.

G. Simon, A. Fond, M.-O. Berger, "A-contrario horizon-first vanishing point detection using
second-order grouping laws", ECCV 2018.  Re-implemented from the paper (the authors' code is
AGPL; nothing is copied from it).  Steps:

1. Line segments (``meta.segments`` when given, else LSD) longer than ``min_length_frac`` of the
   image diagonal.
2. **Zenith** from the near-vertical segments (hypothesise-and-test over pairs, least-squares
   refinement: :func:`fr_baselines.vp_geometry.vertical_vp`).  The *zenith line* joins the principal
   point to the zenith; the horizon line (HL) is perpendicular to it, so a HL candidate is a
   single offset along the zenith line.
3. **HL candidates.**  (a) The paper's second-order grouping: a horizontal segment at the height
   of the camera centre projects onto the HL, so segments oriented like the HL (within
   ``align_deg``) accumulate at the HL offset; the meaningful modes (a-contrario, binomial NFA
   against a uniform background, NFA < 1) of the histogram of their offsets are candidates.
   (b) Because the HL is often outside the image, candidates are also drawn from a prior: the
   offsets implied by the zenith for a log-spaced sweep of focal lengths (the HL offset o and the
   zenith distance z satisfy o z = -f^2), plus a uniform grid when the zenith is at infinity.
   (The paper samples its prior from a learned offset distribution; ours is uninformative.)
4. **hVP detection on each candidate.**  Every non-vertical segment's line meets the HL; the
   intersections are mapped to the azimuth angle on the horizon (exact when the zenith is finite,
   since the candidate offset then fixes the focal length) and histogrammed over the circle.  The
   meaningful modes of this histogram (maximal intervals with binomial NFA < ``nfa_eps`` against
   a uniform background, chosen greedily by significance) are the horizontal VPs; each is re-fitted
   by least squares to its supporting segments.  The HL candidate with the largest summed
   significance (-log10 NFA) of its hVPs wins; its offset is then re-estimated from its two most
   significant hVPs and the detection is run once more.
5. **Focal and rotation.**  The focal length comes from the most significant *pair of finite*
   hVPs compatible with orthogonality (``f^2 = -(v_i - p).(v_j - p) > 0``) and, when the zenith
   is finite, orthogonal to it within ``zenith_tol_deg`` under that focal; R is the orthogonalised
   (zenith, v_i, v_j) triplet (:func:`fr_baselines.vp_geometry.rotation_from_vps`).

**Failures.**  When no such pair exists (e.g. one horizontal VP at infinity, or a single
horizontal family) the method has no focal length and therefore no tilt (tilt needs f), so the
estimate is a *flagged failure* (``ok=False``, reason "no orthogonal pair of finite horizontal
VPs"); the roll, which the zenith alone determines, and the detected VPs are kept in ``extra``
(``extra["roll_deg"]``, ``extra["zenith"]``, ``extra["hvps"]``).  Every estimate that found a zenith,
failed or not, ranks it and the hVPs by their supporting segments (``ranked_vanishing_points``).  The tables therefore count the
share of images with a valid (focal + rotation) result, as the brief requires.  Bad input, too few
segments and no zenith are flagged failures too.

**Focal range.**  Long-side FOV in ``range`` (a :class:`~fr_torch.core.settings.fov.FovRange` or anything its ``parse`` takes) (default: fR's library default range,
``configs/search.json``; option ``simon2018[range=paper]`` or ``range=MIN:MAX``; ``fr eval
--hfov-range`` sets it for every method of a table).
"""
from __future__ import annotations

import math

import numpy as np
from scipy.stats import binom

from fr_torch.core.geometry.camera import Camera
from fr_torch.core.settings.fov import FovRange
from fr_torch.plugins.interface import CameraEstimate, ImageMeta, TimedCalibrator

from . import vp_geometry as vg


def meaningful_modes(counts: np.ndarray, circular: bool = False, max_width: int | None = None,
                     eps: float = 1.0, prior: np.ndarray | None = None) -> list[tuple[int, int, float]]:
    """Meaningful modes of a 1-D histogram against a background model (a-contrario).

    An interval of bins [a, b] holding k of the M counts, whose background probability is p (the
    sum of ``prior`` over the interval; uniform by default), has ``NFA = N_tests * P[Bin(M, p) >= k]``
    with ``N_tests = L (L + 1) / 2`` intervals.  Modes are the intervals with ``NFA < eps`` chosen
    greedily by increasing NFA among those not overlapping an already chosen one (a simple
    version of the maximal meaningful modes).  Returns ``[(start_bin, width, log10_nfa), ...]``
    (start may wrap around when ``circular``).
    """
    counts = np.asarray(counts, dtype=np.float64)
    n_bins = len(counts)
    total = counts.sum()
    if total <= 0 or n_bins == 0:
        return []
    prior = np.full(n_bins, 1.0 / n_bins) if prior is None else np.asarray(prior, np.float64) / np.sum(prior)
    max_width = n_bins // 2 if max_width is None else min(max_width, n_bins)
    log10_tests = math.log10(n_bins * (n_bins + 1) / 2.0)
    ext_counts = np.concatenate([counts, counts]) if circular else np.concatenate([counts, np.zeros(n_bins)])
    ext_prior = np.concatenate([prior, prior]) if circular else np.concatenate([prior, np.zeros(n_bins)])
    csum_c = np.concatenate([[0.0], np.cumsum(ext_counts)])
    csum_p = np.concatenate([[0.0], np.cumsum(ext_prior)])
    starts = np.arange(n_bins)
    widths = np.arange(1, max_width + 1)
    s, w = np.meshgrid(starts, widths, indexing="ij")
    if not circular:
        valid = s + w <= n_bins
    else:
        valid = np.ones_like(s, bool)
    k = csum_c[s + w] - csum_c[s]
    p = np.clip(csum_p[s + w] - csum_p[s], 1e-12, 1.0 - 1e-12)
    over = k > p * total  # only over-dense intervals can be modes
    log10_nfa = np.full(s.shape, np.inf)
    ok = valid & over
    log10_nfa[ok] = log10_tests + binom.logsf(k[ok] - 1, total, p[ok]) / math.log(10.0)
    order = np.argsort(log10_nfa, axis=None)
    taken = np.zeros(n_bins, bool)
    modes = []
    log10_eps = math.log10(eps)
    for flat in order:
        value = log10_nfa.flat[flat]
        if not value < log10_eps:
            break
        start, width = int(s.flat[flat]), int(w.flat[flat])
        bins = np.arange(start, start + width) % n_bins
        if taken[bins].any():
            continue
        taken[bins] = True
        modes.append((start, width, float(value)))
    return modes


class Simon2018(TimedCalibrator):
    """A-contrario horizon-first VP detection (Simon, Fond & Berger, ECCV 2018) + focal from hVPs."""

    name = "simon2018"

    def __init__(self, vertical_max_deg: float = 30.0, inlier_deg: float = 1.5, align_deg: float = 2.0,
                 min_length_frac: float = 0.02, min_segments: int = 8, n_offset_bins: int = 64,
                 n_angle_bins: int = 180, max_mode_deg: float = 10.0, n_prior: int = 48,
                 range=None, finite_limit: float = 20.0,
                 zenith_tol_deg: float = 5.0, nfa_eps: float = 1.0, min_support: int = 3,
                 n_refine: int = 3, n_fine: int = 9):
        self.vertical_max_deg = float(vertical_max_deg)
        self.inlier_deg = float(inlier_deg)
        self.align_deg = float(align_deg)
        self.min_length_frac = float(min_length_frac)
        self.min_segments = int(min_segments)
        self.n_offset_bins = int(n_offset_bins)
        self.n_angle_bins = int(n_angle_bins)
        self.max_mode_deg = float(max_mode_deg)
        self.n_prior = int(n_prior)
        self.fov_range = FovRange.parse(range)
        self.finite_limit = float(finite_limit)
        self.zenith_tol_deg = float(zenith_tol_deg)
        self.nfa_eps = float(nfa_eps)
        self.min_support = int(min_support)
        self.n_refine = int(n_refine)
        self.n_fine = int(n_fine)

    # ------------------------------------------------------------------ main
    def _estimate(self, image, meta: ImageMeta) -> CameraEstimate:
        try:
            segments, lengths, width, height, pp = vg.long_segments(image, meta, self.min_length_frac,
                                                                    self.min_segments)
        except vg.NoInput as exc:
            return CameraEstimate.failure(self.name, str(exc))
        diag = math.hypot(width, height)

        found = vg.vertical_vp(segments, self.vertical_max_deg, self.inlier_deg)
        if found is None:
            return CameraEstimate.failure(self.name, "no zenith (too few near-vertical segments)")
        zvp, vertical = found
        # Zenith line: through the principal point and the zenith; n = its unit image direction,
        # signed to point up in the image; the HL is {x : (x - p) . n = offset}.
        a = zvp[:2] - pp * zvp[2]
        if np.linalg.norm(a) < 1e-9:
            return CameraEstimate.failure(self.name, "zenith at the principal point (camera looking straight up/down)")
        n = a / np.linalg.norm(a)
        if n[1] > 0:
            n = -n
        zenith_dist = float(a @ n / zvp[2]) if abs(zvp[2]) > vg.EPS else math.inf  # signed, along n
        horizontal = ~vertical
        if horizontal.sum() < 2:
            return CameraEstimate.failure(self.name, "no horizontal line segments")
        seg_h, len_h = segments[horizontal], lengths[horizontal]
        lines_h = vg.homogeneous_lines(seg_h)

        def evaluate(offsets):
            out = []
            for offset in offsets:
                found_vps = self._hvps_on_hl(offset, seg_h, len_h, lines_h, pp, n, zenith_dist, diag)
                if found_vps is not None:
                    out.append((sum(v["significance"] for v in found_vps), float(offset), found_vps))
            return out

        candidates = np.unique(np.asarray(self._hl_candidates(seg_h, pp, n, zenith_dist, width, height)))
        scored = evaluate(candidates)
        # Local refinement: a fine grid around the best few candidates (half-way to the neighbours).
        for _, offset, _ in sorted(scored, key=lambda c: -c[0])[: self.n_refine]:
            k = int(np.searchsorted(candidates, offset))
            lo = candidates[k - 1] if k > 0 else offset - 0.05 * diag
            hi = candidates[k + 1] if k + 1 < len(candidates) else offset + 0.05 * diag
            scored += evaluate(np.linspace(0.5 * (lo + offset), 0.5 * (offset + hi), self.n_fine))
        best = max(scored, key=lambda c: c[0]) if scored else None
        roll = vg.roll_from_zenith(zvp, pp)
        extra = {"zenith": zvp.tolist(), "roll_deg": roll}
        zenith_support = int(vertical.sum())
        if best is None:
            return vg.failure_estimate(self.name, "no horizontal vanishing point on any horizon candidate", extra,
                                       vg.rank_by_support([zvp], [zenith_support]))
        # Second pass on the horizon through the most significant finite hVPs.
        score, offset, hvps = best
        finite = [v for v in hvps if vg.is_finite_vp(v["vp"], pp, self.finite_limit * diag)]
        if finite:
            top = sorted(finite, key=lambda v: -v["significance"])[:2]
            new_offset = float(np.mean([(vg.dehomogenise(v["vp"]) - pp) @ n for v in top]))
            again = self._hvps_on_hl(new_offset, seg_h, len_h, lines_h, pp, n, zenith_dist, diag)
            if again and sum(v["significance"] for v in again) >= score:
                offset, hvps = new_offset, again
        extra["horizon_offset_px"] = offset
        extra["hvps"] = [v["vp"].tolist() for v in hvps]
        ranked = vg.rank_by_support([zvp] + [v["vp"] for v in hvps], [zenith_support] + [v["support"] for v in hvps])
        pair = vg.orthogonal_pair(hvps, zvp, pp, diag, self.fov_range.focal_bounds(max(width, height)),
                                  self.finite_limit, self.zenith_tol_deg)
        if pair is None:
            return vg.failure_estimate(self.name, "no orthogonal pair of finite horizontal VPs", extra, ranked)
        focal, vi, vj = pair
        rotation = vg.rotation_from_vps(zvp, vi["vp"], focal, pp, vj["vp"])
        return vg.camera_estimate(self.name, Camera(width, height, focal, pp, rotation),
                                  ranked_vanishing_points=ranked, **extra)

    # ------------------------------------------------------------------ horizon candidates
    def _hl_candidates(self, seg_h, pp, n, zenith_dist, width, height) -> list[float]:
        mids = vg.segment_midpoints(seg_h) - pp
        offsets = mids @ n
        cands: list[float] = []
        # (a) second-order grouping: segments parallel to the HL gather at its offset.
        t_dir = np.array([-n[1], n[0]])
        aligned = np.abs(vg.segment_directions(seg_h) @ t_dir) >= math.cos(math.radians(self.align_deg))
        lo, hi = float(offsets.min()), float(offsets.max())
        if aligned.sum() >= 2 and hi > lo:
            counts, edges = np.histogram(offsets[aligned], bins=self.n_offset_bins, range=(lo, hi))
            for start, w, _ in meaningful_modes(counts, max_width=max(1, self.n_offset_bins // 8), eps=self.nfa_eps):
                inside = aligned & (offsets >= edges[start]) & (offsets <= edges[start + w])
                if inside.any():
                    cands.append(float(np.median(offsets[inside])))
        # (b) prior: offsets implied by the zenith over a focal sweep, or a uniform grid.
        f_lo, f_hi = self.fov_range.focal_bounds(max(width, height))
        if math.isfinite(zenith_dist) and abs(zenith_dist) > vg.EPS:
            for f in np.geomspace(f_lo, f_hi, self.n_prior):
                cands.append(-f * f / zenith_dist)
        else:
            span = 1.5 * max(width, height)
            cands.extend(np.linspace(-span, span, self.n_prior).tolist())
        return cands

    # ------------------------------------------------------------------ hVPs on one horizon
    def _hvps_on_hl(self, offset, seg_h, len_h, lines_h, pp, n, zenith_dist, diag):
        """Meaningful hVP modes on the HL at ``offset``: list of {vp, significance, support}."""
        if math.isfinite(zenith_dist):
            f2 = -offset * zenith_dist
            if f2 <= 0:
                return None  # the horizon must lie across the principal point from the zenith
            scale = math.sqrt(f2 + offset * offset)
        else:
            scale = diag / 2.0
        hl = np.array([n[0], n[1], -(n @ pp) - offset])
        t_dir = np.array([-n[1], n[0]])
        x = np.cross(lines_h, hl)  # intersections with the HL (homogeneous)
        num = (x[:, :2] - np.outer(x[:, 2], pp)) @ t_dir
        theta = np.arctan2(num, scale * x[:, 2])
        theta = np.mod(theta + math.pi / 2, math.pi) - math.pi / 2  # circle of directions, period pi
        bins = self.n_angle_bins
        idx = np.clip(((theta + math.pi / 2) / math.pi * bins).astype(int), 0, bins - 1)
        counts = np.bincount(idx, minlength=bins)
        # A-contrario background: the same segments with independent, uniform orientations.  A line
        # through midpoint m at distance d from the HL (foot at position t0 on it) with uniform
        # orientation meets the HL at a Cauchy(t0, d) position; the bin probabilities are the
        # average of these Cauchy laws over the segments, mapped to the azimuth bins.
        mids = vg.segment_midpoints(seg_h) - pp
        t0 = mids @ t_dir
        dist = np.maximum(np.abs(mids @ n - offset), 1.0)
        edges = scale * np.tan(np.linspace(-math.pi / 2, math.pi / 2, bins + 1))
        edges[0], edges[-1] = -np.inf, np.inf
        cdf = np.arctan((edges[:, None] - t0[None, :]) / dist[None, :]) / math.pi + 0.5
        prior = np.maximum(np.diff(cdf, axis=0).mean(1), 1e-12)
        max_width = max(1, int(round(self.max_mode_deg / 180.0 * bins)))
        modes = meaningful_modes(counts, circular=True, max_width=max_width, eps=self.nfa_eps, prior=prior)
        thr = math.radians(self.inlier_deg)
        out = []
        for start, width_bins, log10_nfa in modes:
            in_mode = np.isin(idx, np.arange(start, start + width_bins) % bins)
            if in_mode.sum() < 2:
                continue
            vp = vg.vp_least_squares(seg_h[in_mode], len_h[in_mode])
            for _ in range(2):
                inl = vg.vp_angle_error(seg_h, vp) < thr
                if inl.sum() < 2:
                    break
                vp = vg.vp_least_squares(seg_h[inl], len_h[inl])
            support = int((vg.vp_angle_error(seg_h, vp) < thr).sum())
            if support < self.min_support:
                continue
            out.append({"vp": vp, "significance": -log10_nfa, "support": support})
        return out or None

