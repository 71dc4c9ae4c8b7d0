"""MCMLSD line-segment detector (Almazan, Tal, Qian & Elder, CVPR 2017), re-implemented in PyTorch.

"MCMLSD: A Dynamic Programming Approach to Line Segment Detection".  Written from the paper; the
authors' trained parameters (HMM likelihood tables and edge-filter taps) are shipped as data in
``fr_torch/data/mcmlsd/mcmlsd_params.npz`` (regenerate with ``tools/make_mcmlsd_params.py``).

Pipeline (every stage is a batched tensor computation; pass ``device="cuda"`` to run on a GPU):

1. **Edges** (simplified Elder-Zucker): Gaussian-derivative gradients at scales 0.5, 1 and 2 px
   (the authors' filter taps for 0.5 and 1 px, sampled Gaussians for 2 px); the image noise level
   is estimated (Immerkaer) and each pixel takes the *minimum reliable scale*, the finest scale
   whose gradient exceeds the noise-only level at false-positive rate ``alpha``.  Edges are the
   local maxima of the gradient magnitude along the gradient direction at that scale, localised
   to sub-pixel precision with a parabola.  (Elder-Zucker use 2nd-derivative zero crossings; we
   use gradient non-maximum suppression.)
2. **Probabilistic Hough voting**: lines ``r = (p - c) . (cos phi, sin phi)`` (``c`` the image
   centre), bins ``th_res`` rad x ``r_res`` px.  Each edge votes with an uncertainty kernel: a
   Gaussian in phi around its gradient direction (``sigma_theta`` = 5.4 deg, truncated at
   ``sig_bound`` sigmas) times a Gaussian in r around its position (``sigma_x`` = 0.4 px), both
   scaled by ``scale_factor = hypot(H, W) / 800`` (kernels calibrated for 640 x 480).
3. **Peaks**: local maxima of the Hough map (phi wraps to r -> -r) above ``frac`` x the highest
   peak (and ``min_votes``), at most ``max_lines``, ranked by strength.
4. **HMM segmentation**: each line is sampled at 1-px steps inside the image.  At each sample the
   observation is whether an edge lies within ``perp_tol`` px of the line (nearest pixel and its
   two neighbours across the line) and, if so, its angular deviation from the line.  A two-state
   (off/on) Markov chain with P(on->off) = 0.0051/scale, P(off->on) = 0.0014/scale, P(on) = 0.247
   and the authors' emission tables (edge-existence probability per line-rank bin of 125 lines;
   angular-deviation histograms in 1-deg bins) is decoded exactly with the Viterbi algorithm; on
   runs are segments.  Segments are scored, as in the paper, by the sum of the forward-backward
   marginal posteriors P(on) over their samples (expected number of correctly labelled points).
   Because our edge maps are denser than the authors', the edge-existence rates are adapted per
   image (``calibrate``): P(edge | off) = the hit rate over all line samples, P(edge | on) keeps
   the trained on/off odds ratio.  Default Hough bins are 0.006 rad (original 0.002) with sub-bin
   parabolic peak fitting, for speed.
5. **Explaining away + refinement** (our addition, replacing the original's sequential vote
   removal): segments are visited by decreasing score and dropped when more than ``max_shared``
   of their supporting edges already support a better segment, or when fewer than
   ``min_density`` of the samples between its first and last supporting edge (edges within
   ``aligned_deg`` of the line) are supported; each kept segment is refitted to its supporting
   sub-pixel edges by total least squares.  The HMM recursions run in numpy on the CPU.

Output: ``(N, 4)`` float64 ``[x1, y1, x2, y2]``, 0-based pixel centres (LSD convention), sorted by
decreasing score (``detect`` also returns the scores).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace
from functools import lru_cache
from pathlib import Path

import cv2
import numpy as np
import torch
import torch.nn.functional as F

PARAMS_PATH = Path(__file__).resolve().parents[1] / "data" / "mcmlsd" / "mcmlsd_params.npz"


@lru_cache(maxsize=4)
def load_params(path: str = str(PARAMS_PATH)) -> dict[str, np.ndarray]:
    """The shipped MCMLSD parameter tables (see ``tools/make_mcmlsd_params.py``)."""
    with np.load(path) as data:
        return {k: data[k].copy() for k in data.files}


@dataclass(frozen=True)
class MCMLSDConfig:
    """Settings; lengths in pixels of a 640 x 480 image (scaled by ``hypot(H, W) / 800``)."""

    # edges
    alpha: float = 1e-4            # per-pixel false-positive rate of the reliable-gradient test
    min_gradient: float = 2.0      # grey levels per pixel, floor on the reliable-gradient threshold
    noise_sigma: float | None = None  # image noise (grey levels); None = estimate from the image
    # Hough voting
    sig_bound: float = 3.0
    r_res: float = 0.2
    th_res: float = 0.006         # the original uses 0.002; sub-bin peak fitting recovers precision
    sigma_x: float = 0.4
    sigma_theta_deg: float = 5.4
    # peaks
    max_lines: int = 5000
    frac: float = 0.05
    min_votes: float = 16.0        # minimum peak height (~ edge pixels on the line)
    nms_theta_deg: float = 0.75    # half-size of the peak suppression window in phi
    nms_r: float = 1.5             # ... and in r (px)
    # HMM
    p_leave_on: float = 0.0051
    p_leave_off: float = 0.0014
    p_on: float = 0.247
    lines_per_bin: int = 125       # line-rank bin width of the edge-existence table
    perp_tol: float = 1.0          # max distance of a supporting edge from the line (px)
    calibrate: bool = True         # adapt the edge-existence rates to this image (see _segment_lines)
    # output
    min_length: float = 8.0
    aligned_deg: float = 10.0      # edges within this angle of the line count as its support
    min_density: float = 0.6       # min fraction of supported samples between a segment's ends
    max_shared: float = 0.5
    refine: bool = True
    cpu_threads: int | None = 1    # torch intra-op threads while detecting on the CPU (None: leave)


class MCMLSDDetector:
    """MCMLSD: probabilistic Hough lines segmented by an on/off hidden Markov chain (see module doc)."""

    name = "mcmlsd"

    def __init__(self, device: str | torch.device | None = None, config: MCMLSDConfig | None = None, **overrides):
        self.config = replace(config or MCMLSDConfig(), **overrides)
        self.device = torch.device(device) if device is not None else torch.device("cpu")
        params = load_params()
        self._params = params
        t = lambda a: torch.as_tensor(np.asarray(a), dtype=torch.float32, device=self.device)  # noqa: E731
        tiny = 1e-6
        self._exist = torch.stack([t(params["exist_edge_off"]), t(params["exist_edge_on"])])
        self._log_ang = torch.stack([t(np.log(params["ang_dev_off"] + tiny)), t(np.log(params["ang_dev_on"] + tiny))])

    # ------------------------------------------------------------------ public API

    def __call__(self, gray: np.ndarray) -> np.ndarray:
        return self.detect(gray)[0]

    def detect(self, gray: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Segments (N, 4) float64 and their scores (N,), sorted by decreasing score."""
        threads = self.config.cpu_threads
        if self.device.type != "cpu" or not threads or threads == torch.get_num_threads():
            return self._detect(gray)
        # Many medium-size tensor ops interleaved with numpy loops: torch's intra-op thread pool
        # costs more than it gains here (5x slower with 2 threads on a busy 2-core machine).
        previous = torch.get_num_threads()
        torch.set_num_threads(threads)
        try:
            return self._detect(gray)
        finally:
            torch.set_num_threads(previous)

    @torch.no_grad()
    def _detect(self, gray: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        gray = np.asarray(gray)
        if gray.ndim == 3:
            gray = gray.mean(axis=2)
        if gray.ndim != 2:
            raise ValueError(f"expected a 2-D grey image, got shape {gray.shape}")
        empty = (np.zeros((0, 4)), np.zeros(0))
        height, width = gray.shape
        if height < 8 or width < 8:
            return empty
        scale = math.hypot(height, width) / 800.0
        image = torch.as_tensor(np.ascontiguousarray(gray), device=self.device).float()
        edges = self._edges(image)
        if edges["x"].numel() < 2:
            return empty
        lines = self._hough_lines(edges, height, width, scale)
        if lines.shape[0] == 0:
            return empty
        return self._segment_lines(edges, lines, height, width, scale)

    # ------------------------------------------------------------------ 1. edges

    def _filters(self, sigma: float):
        """1-D Gaussian / first-derivative taps (correlation form, derivative along +x)."""
        p = self._params
        if sigma in (0.5, 1.0):
            key = "05" if sigma == 0.5 else "1"
            # the shipped taps are convolution kernels (derivative taps positive on the left):
            # reversed, they are correlation taps (what F.conv2d applies) giving +dI/dx
            g, g1 = p["gx" + key], np.asarray(p["g1x" + key])[::-1]
        else:
            half = int(math.ceil(3.5 * sigma))
            x = np.arange(-half, half + 1, dtype=np.float64)
            g = np.exp(-0.5 * (x / sigma) ** 2) / (math.sqrt(2 * math.pi) * sigma)
            g1 = x / sigma**2 * g  # correlation taps of the Gaussian derivative (+d/dx)
        g = np.asarray(g, np.float64) / np.sum(g)
        g1 = np.asarray(g1, np.float64)
        size = max(len(g), len(g1))  # zero-pad both (odd, centred) to the same length
        g, g1 = (np.pad(v, ((size - len(v)) // 2,)) for v in (g, g1))
        return g, g1

    def _edges(self, image: torch.Tensor) -> dict[str, torch.Tensor]:
        cfg = self.config
        height, width = image.shape
        img = image[None, None]
        # Immerkaer's noise estimate (grey levels)
        if cfg.noise_sigma is None:
            lap = torch.tensor([[1, -2, 1], [-2, 4, -2], [1, -2, 1]], dtype=torch.float32, device=image.device)
            resp = F.conv2d(img, lap[None, None]).abs()
            sigma_n = float(resp.sum()) * math.sqrt(math.pi / 2) / (6.0 * resp.numel())
            sigma_n = max(sigma_n, 0.5)
        else:
            sigma_n = float(cfg.noise_sigma)
        z = math.sqrt(-2.0 * math.log(cfg.alpha))

        dev = image.device
        best_gx = torch.zeros(height, width, device=dev)
        best_gy = torch.zeros_like(best_gx)
        off_x = torch.zeros_like(best_gx)
        off_y = torch.zeros_like(best_gx)
        is_max = torch.zeros(height, width, dtype=torch.bool, device=dev)
        assigned = torch.zeros(height, width, dtype=torch.bool, device=dev)
        for sigma in (0.5, 1.0, 2.0):
            g, g1 = self._filters(sigma)
            gx, gy = _gradients(image, g, g1)
            mag = torch.hypot(gx, gy)
            noise = sigma_n * float(np.linalg.norm(g) * np.linalg.norm(g1))
            threshold = max(z * noise, cfg.min_gradient)
            reliable = (mag > threshold) & ~assigned        # minimum reliable scale
            local_max, vx, vy = _nms(mag, gx, gy)
            best_gx = torch.where(reliable, gx, best_gx)
            best_gy = torch.where(reliable, gy, best_gy)
            off_x = torch.where(reliable, vx, off_x)
            off_y = torch.where(reliable, vy, off_y)
            is_max = torch.where(reliable, local_max, is_max)
            assigned |= reliable
        edge = is_max & assigned
        edge[:1, :] = False
        edge[-1:, :] = False
        edge[:, :1] = False
        edge[:, -1:] = False
        ys, xs = torch.nonzero(edge, as_tuple=True)
        gx, gy = best_gx[ys, xs], best_gy[ys, xs]
        phi = torch.remainder(torch.atan2(gy, gx), math.pi)  # normal direction, mod pi
        sub_x, sub_y = xs.float() + off_x[ys, xs], ys.float() + off_y[ys, xs]
        index = torch.full((height * width,), -1, dtype=torch.long, device=image.device)
        index[ys * width + xs] = torch.arange(ys.numel(), device=image.device)
        return {"x": sub_x, "y": sub_y, "phi": phi,
                "index": index, "height": height, "width": width}

    # ------------------------------------------------------------------ 2-3. Hough

    def _hough_lines(self, edges, height: int, width: int, scale: float) -> torch.Tensor:
        """(L, 3) [phi, r, strength] of Hough peaks, strongest first (r relative to the centre)."""
        cfg = self.config
        dev = self.device
        cx, cy = (width - 1) / 2.0, (height - 1) / 2.0
        sig_th = math.radians(cfg.sigma_theta_deg)
        sig_r = cfg.sigma_x * scale
        n_th = int(round(math.pi / cfg.th_res))
        th_res = math.pi / n_th
        r_max = math.hypot(cx, cy) + 2.0
        n_r_half = int(math.ceil(r_max / cfg.r_res))
        n_r = 2 * n_r_half + 1

        dx, dy, phi = edges["x"] - cx, edges["y"] - cy, edges["phi"]
        half = int(math.ceil(cfg.sig_bound * sig_th / th_res))
        offs = torch.arange(-half, half + 1, device=dev)
        base = torch.round(phi / th_res).long()
        theta0 = base.float() * th_res
        # r at theta0 + k th_res by angle addition (no gathers): r0 cos(k d) + t0 sin(k d)
        r0 = dx * torch.cos(theta0) + dy * torch.sin(theta0)
        t0 = -dx * torch.sin(theta0) + dy * torch.cos(theta0)
        ck, sk = torch.cos(offs.float() * th_res), torch.sin(offs.float() * th_res)
        acc = torch.zeros(n_th * n_r, device=dev)
        chunk = max(1, 4_000_000 // len(offs))
        for s in range(0, dx.numel(), chunk):
            sl = slice(s, s + chunk)
            b = base[sl, None] + offs[None]                                 # (E, K) phi bins
            w = torch.exp(-0.5 * ((offs[None].float() * th_res + (theta0[sl] - phi[sl])[:, None]) / sig_th) ** 2)
            r = r0[sl, None] * ck[None] + t0[sl, None] * sk[None]
            outside = (b < 0) | (b >= n_th)                                 # phi wraps: r -> -r
            r = torch.where(outside, -r, r)
            bw = torch.remainder(b, n_th)
            ri = r / cfg.r_res + n_r_half
            i0 = torch.floor(ri)
            frac = ri - i0
            flat = bw * n_r + i0.long()
            acc.index_add_(0, flat.reshape(-1), (w * (1 - frac)).reshape(-1))
            acc.index_add_(0, (flat + 1).reshape(-1), (w * frac).reshape(-1))
        acc = acc.view(1, 1, n_th, n_r)
        # Gaussian uncertainty of r (peak-normalised so that a peak ~ number of supporting edges)
        kr = int(math.ceil(cfg.sig_bound * sig_r / cfg.r_res))
        xr = torch.arange(-kr, kr + 1, device=dev, dtype=torch.float32) * cfg.r_res
        kernel = torch.exp(-0.5 * (xr / sig_r) ** 2)
        # peak 1: with the linear split over two r bins, one edge adds ~1 to its line
        if dev.type == "cpu":  # OpenCV's row filter is much faster than conv2d on the CPU
            acc = torch.from_numpy(cv2.filter2D(acc[0, 0].numpy(), -1, kernel.numpy()[None],
                                                borderType=cv2.BORDER_CONSTANT))[None, None]
        else:
            acc = F.conv2d(F.pad(acc, (kr, kr, 0, 0)), kernel.view(1, 1, 1, -1))
        # peaks: local maxima with phi wrapping onto r -> -r
        wt = max(1, int(round(math.radians(cfg.nms_theta_deg) / th_res)))
        wr = max(1, int(round(cfg.nms_r / cfg.r_res)))
        wrapped = torch.cat([acc[:, :, -wt:].flip(-1), acc, acc[:, :, :wt].flip(-1)], dim=2)
        pooled = _running_max(wrapped[0, 0], wt, 0)[wt:-wt]              # separable max filter
        pooled = _running_max(F.pad(pooled, (wr, wr), value=-1.0), wr, 1)[:, wr:-wr]
        acc = acc[0, 0]
        top = float(acc.max())
        threshold = max(cfg.frac * top, cfg.min_votes)
        peak = (acc >= pooled) & (acc >= threshold)
        ti, ri = torch.nonzero(peak, as_tuple=True)
        strength = acc[ti, ri]
        order = torch.argsort(strength, descending=True)[: cfg.max_lines]
        ti, ri, strength = ti[order], ri[order], strength[order]
        # sub-bin peak position: parabola through the neighbours in phi (wrapping) and in r
        up = torch.cat([acc[-1:].flip(-1), acc[:-1]], 0)[ti, ri]
        down = torch.cat([acc[1:], acc[:1].flip(-1)], 0)[ti, ri]
        left = acc[ti, (ri - 1).clamp(min=0)]
        right = acc[ti, (ri + 1).clamp(max=n_r - 1)]
        dt = _parabola_peak(up, strength, down)
        dr = _parabola_peak(left, strength, right)
        phi = (ti.float() + dt) * th_res
        r = (ri - n_r_half).float() * cfg.r_res + dr * cfg.r_res
        return torch.stack([phi, r, strength], 1)

    # ------------------------------------------------------------------ 4-5. HMM segmentation

    def _segment_lines(self, edges, lines: torch.Tensor, height: int, width: int, scale: float):
        cfg = self.config
        dev = self.device
        cx, cy = (width - 1) / 2.0, (height - 1) / 2.0
        phi, r = lines[:, 0], lines[:, 1]
        nx, ny = torch.cos(phi), torch.sin(phi)
        dxl, dyl = -ny, nx
        fx, fy = cx + r * nx, cy + r * ny
        # clip the line to the image box [0, W-1] x [0, H-1]
        big = 1e9
        t_lo = torch.full_like(phi, -big)
        t_hi = torch.full_like(phi, big)
        for f, d, hi in ((fx, dxl, width - 1.0), (fy, dyl, height - 1.0)):
            safe = d.abs() > 1e-9
            a = torch.where(safe, (0.0 - f) / torch.where(safe, d, torch.ones_like(d)), torch.full_like(d, -big))
            b = torch.where(safe, (hi - f) / torch.where(safe, d, torch.ones_like(d)), torch.full_like(d, big))
            inside = (f >= 0) & (f <= hi)
            lo_, hi_ = torch.minimum(a, b), torch.maximum(a, b)
            lo_ = torch.where(safe, lo_, torch.where(inside, lo_, torch.full_like(lo_, big)))
            t_lo, t_hi = torch.maximum(t_lo, lo_), torch.minimum(t_hi, hi_)
        span = t_hi - t_lo
        keep = span >= cfg.min_length
        rank = torch.arange(lines.shape[0], device=dev)[keep]
        if rank.numel() == 0:
            return np.zeros((0, 4)), np.zeros(0)
        phi, nx, ny, dxl, dyl, fx, fy, t_lo, span = (v[keep] for v in (phi, nx, ny, dxl, dyl, fx, fy, t_lo, span))
        length = torch.floor(span).long() + 1
        by_length = torch.argsort(length, descending=True)  # the HMM recursions run on prefixes
        rank, phi, nx, ny, dxl, dyl, fx, fy, t_lo, length = (
            v[by_length] for v in (rank, phi, nx, ny, dxl, dyl, fx, fy, t_lo, length))
        n_steps = int(length.max())
        steps = torch.arange(n_steps, device=dev, dtype=torch.float32)
        valid = steps[None] < length[:, None]                               # (N, T)
        t = t_lo[:, None] + steps[None]
        px, py = fx[:, None] + t * dxl[:, None], fy[:, None] + t * dyl[:, None]

        # observation at each sample: best edge among the 3 pixels across the line
        ex, ey, ephi, index = edges["x"], edges["y"], edges["phi"], edges["index"]
        best_dev = torch.full(px.shape, 1e3, device=dev)
        best_id = torch.full(px.shape, -1, dtype=torch.long, device=dev)
        for j in (-1.0, 0.0, 1.0):
            qx = torch.floor(px + j * nx[:, None] + 0.5).long().clamp(0, width - 1)
            qy = torch.floor(py + j * ny[:, None] + 0.5).long().clamp(0, height - 1)
            eid = index[qy * width + qx]
            has = (eid >= 0) & valid
            e = eid.clamp(min=0)
            dist = ((ex[e] - px) * nx[:, None] + (ey[e] - py) * ny[:, None]).abs()
            dev_ang = torch.remainder(ephi[e] - phi[:, None] + math.pi / 2, math.pi) - math.pi / 2
            ok = has & (dist <= cfg.perp_tol) & (dev_ang.abs() < best_dev.abs())
            best_dev = torch.where(ok, dev_ang, best_dev)
            best_id = torch.where(ok, eid, best_id)
        has_edge = best_id >= 0
        dev_bin = torch.round(torch.rad2deg(best_dev)).long().clamp(-90, 90) + 90
        rank_bin = (rank // cfg.lines_per_bin).clamp(max=self._exist.shape[1] - 1)
        exist = self._exist
        if cfg.calibrate:
            # Our edge maps are denser than the authors' detector's: the background (off-state)
            # edge rate is re-estimated on this image as the hit rate over all line samples (mostly
            # off), and the on-state rates keep the trained on/off odds ratio of each rank bin.
            rate = float((has_edge & valid).sum()) / max(1.0, float(valid.sum()))
            off = torch.clamp(torch.full_like(exist[0], min(rate, 0.95)), min=exist[0])
            odds = exist[1] / (1 - exist[1]) / (exist[0] / (1 - exist[0])) * off / (1 - off)
            exist = torch.stack([off, odds / (1 + odds)])
        log_exist, log_nexist = torch.log(exist + 1e-6), torch.log(1 - exist + 1e-6)
        # log-emissions (N, T, 2) for states off=0 / on=1
        log_e = []
        for s in (0, 1):
            on_edge = log_exist[s][rank_bin][:, None] + self._log_ang[s][dev_bin]
            no_edge = log_nexist[s][rank_bin][:, None].expand_as(on_edge)
            log_e.append(torch.where(has_edge, on_edge, no_edge))
        log_e = torch.stack(log_e, -1) * valid[..., None]

        p_off_on = min(cfg.p_leave_off / scale, 0.5)
        p_on_off = min(cfg.p_leave_on / scale, 0.5)
        a = np.array([[1 - p_off_on, p_off_on], [p_on_off, 1 - p_on_off]])
        pi = np.array([1 - cfg.p_on, cfg.p_on])
        # The recursions run over T steps on (N, 2) arrays: numpy on the CPU (microseconds a
        # step) whatever the device; emissions are laid out time-major.
        log_e_np = log_e.permute(1, 0, 2).contiguous().cpu().numpy().astype(np.float64)
        lengths_np = length.cpu().numpy()
        on_path = _viterbi(log_e_np, lengths_np, np.log(a), np.log(pi))
        post_on = _posterior_on(log_e_np, lengths_np, a, pi)
        on_path = torch.as_tensor(on_path.T.copy(), device=dev)
        if getattr(self, "keep_debug", False):  # intermediate results, for inspection
            self.debug = {"has_edge": has_edge, "valid": valid, "on": on_path, "rank": rank, "dev": best_dev}
        post_on = torch.as_tensor(post_on.T.copy(), device=dev, dtype=torch.float32)

        # on runs -> candidate segments
        on = on_path & valid
        padded = F.pad(on.to(torch.int8), (1, 1))
        change = padded[:, 1:] - padded[:, :-1]
        li, start = torch.nonzero(change == 1, as_tuple=True)
        _, stop = torch.nonzero(change == -1, as_tuple=True)                 # exclusive; same order
        cum_post = F.pad(torch.cumsum(post_on * valid, 1), (1, 0))
        score = cum_post[li, stop] - cum_post[li, start]
        cum_edge = F.pad(torch.cumsum(has_edge.long(), 1), (1, 0))
        support = cum_edge[li, stop] - cum_edge[li, start]
        ok = (stop - start >= cfg.min_length) & (support >= 2)
        li, start, stop, score = li[ok], start[ok], stop[ok], score[ok]
        order = torch.argsort(score, descending=True)
        li, start, stop, score = li[order], start[order], stop[order], score[order]
        aligned = has_edge & (best_dev.abs() <= math.radians(cfg.aligned_deg))
        return self._explain_away(li, start, stop, score, aligned, best_id, px, py, edges)

    def _explain_away(self, li, start, stop, score, has_edge, best_id, px, py, edges):
        """Greedy: keep segments by decreasing score unless most of their edges are taken."""
        cfg = self.config
        li, start, stop, score = (v.cpu().numpy() for v in (li, start, stop, score))
        steps = best_id.shape[1]
        ids_flat = torch.where(has_edge, best_id, torch.full_like(best_id, -1)).reshape(-1).cpu().numpy()
        px, py = px.reshape(-1).cpu().numpy(), py.reshape(-1).cpu().numpy()
        ex, ey = edges["x"].cpu().numpy().astype(np.float64), edges["y"].cpu().numpy().astype(np.float64)
        claimed = np.zeros(ex.shape[0] + 1, bool)  # last slot: never claimed (padding id -1)
        out, out_score = [], []
        for i, a, b, sc in zip(li, start, stop, score):
            base = i * steps
            ids = ids_flat[base + a: base + b]
            k = np.flatnonzero(ids >= 0)
            if k.size < 3:
                continue
            if k.size < cfg.min_density * (k[-1] - k[0] + 1):
                continue
            ids = ids[k]
            if np.count_nonzero(claimed[ids]) > cfg.max_shared * k.size:
                continue
            claimed[ids] = True
            k0, k1 = base + a + k[0], base + a + k[-1]  # first / last supported samples
            p0 = np.array([px[k0], py[k0]])
            p1 = np.array([px[k1], py[k1]])
            if cfg.refine:  # total least squares line through the supporting sub-pixel edges
                x, y = ex[ids], ey[ids]
                mx, my = x.mean(), y.mean()
                sxx, syy, sxy = np.dot(x - mx, x - mx), np.dot(y - my, y - my), np.dot(x - mx, y - my)
                ang = 0.5 * math.atan2(2 * sxy, sxx - syy)
                d = np.array([math.cos(ang), math.sin(ang)])
                c = np.array([mx, my])
                p0 = c + np.dot(p0 - c, d) * d
                p1 = c + np.dot(p1 - c, d) * d
            if math.hypot(*(p1 - p0)) < cfg.min_length:
                continue
            out.append(np.concatenate([p0, p1]))
            out_score.append(float(sc))
        if not out:
            return np.zeros((0, 4)), np.zeros(0)
        return np.asarray(out, np.float64), np.asarray(out_score, np.float64)


# ---------------------------------------------------------------------- helpers

def _running_max(values: torch.Tensor, half: int, dim: int) -> torch.Tensor:
    """Max over a window of +-half along dim (valid at least half away from the ends)."""
    out = values.clone()
    for k in range(1, half + 1):
        out[(slice(None),) * dim + (slice(k, None),)] = torch.maximum(
            out[(slice(None),) * dim + (slice(k, None),)], values[(slice(None),) * dim + (slice(None, -k),)])
    result = out.clone()
    for k in range(1, half + 1):
        result[(slice(None),) * dim + (slice(None, -k),)] = torch.maximum(
            result[(slice(None),) * dim + (slice(None, -k),)], out[(slice(None),) * dim + (slice(k, None),)])
    return result


def _gradients(image: torch.Tensor, g: np.ndarray, g1: np.ndarray) -> tuple[torch.Tensor, torch.Tensor]:
    """Separable Gaussian-derivative gradients (d/dx, d/dy) with replicated borders."""
    if image.device.type == "cpu":  # OpenCV's separable filter is ~10x faster than conv2d here
        arr = image.numpy()
        kg, k1 = g.astype(np.float32), g1.astype(np.float32)
        gx = cv2.sepFilter2D(arr, cv2.CV_32F, k1, kg, borderType=cv2.BORDER_REPLICATE)
        gy = cv2.sepFilter2D(arr, cv2.CV_32F, kg, k1, borderType=cv2.BORDER_REPLICATE)
        return torch.from_numpy(gx), torch.from_numpy(gy)
    pad = len(g) // 2
    gt = torch.as_tensor(g.copy(), dtype=torch.float32, device=image.device)
    g1t = torch.as_tensor(g1.copy(), dtype=torch.float32, device=image.device)
    padded = F.pad(image[None, None], (pad, pad, pad, pad), mode="replicate")
    gx = F.conv2d(F.conv2d(padded, gt.view(1, 1, -1, 1)), g1t.view(1, 1, 1, -1))[0, 0]
    gy = F.conv2d(F.conv2d(padded, gt.view(1, 1, 1, -1)), g1t.view(1, 1, -1, 1))[0, 0]
    return gx, gy


def _nms(mag: torch.Tensor, gx: torch.Tensor, gy: torch.Tensor):
    """Non-maximum suppression along the gradient quantised to 4 directions (Canny-style).

    Returns (is local max, sub-pixel offset x, offset y) from a parabola through the magnitude
    at the pixel and its two neighbours along the quantised gradient direction.
    """
    height, width = mag.shape
    padded = F.pad(mag[None, None], (1, 1, 1, 1), mode="replicate")[0, 0]
    sector = torch.remainder(torch.round(torch.atan2(gy, gx) / (math.pi / 4)), 4).long()
    ahead = torch.zeros_like(mag)
    behind = torch.zeros_like(mag)
    step_x = torch.zeros_like(mag)
    step_y = torch.zeros_like(mag)
    for k, (dx, dy) in enumerate(((1, 0), (1, 1), (0, 1), (-1, 1))):
        sel = sector == k
        fwd = padded[1 + dy:1 + dy + height, 1 + dx:1 + dx + width]
        bwd = padded[1 - dy:1 - dy + height, 1 - dx:1 - dx + width]
        ahead = torch.where(sel, fwd, ahead)
        behind = torch.where(sel, bwd, behind)
        step_x = torch.where(sel, torch.full_like(mag, float(dx)), step_x)
        step_y = torch.where(sel, torch.full_like(mag, float(dy)), step_y)
    local_max = (mag >= ahead) & (mag > behind)
    v = _parabola_peak(behind, mag, ahead)
    return local_max, v * step_x, v * step_y


def _parabola_peak(before: torch.Tensor, centre: torch.Tensor, after: torch.Tensor) -> torch.Tensor:
    """Offset (in bins, within +-0.5) of the vertex of the parabola through three samples."""
    denom = before - 2 * centre + after
    safe = torch.where(denom < -1e-12, denom, -torch.ones_like(denom))
    return torch.where(denom < -1e-12, 0.5 * (before - after) / safe, torch.zeros_like(denom)).clamp(-0.5, 0.5)


def _active_counts(lengths: np.ndarray, steps: int) -> np.ndarray:
    """For lines sorted by decreasing length: how many are still running at each step."""
    return (lengths[None, :] > np.arange(steps)[:, None]).sum(1)


def _viterbi(log_e: np.ndarray, lengths: np.ndarray, log_a: np.ndarray, log_pi: np.ndarray) -> np.ndarray:
    """MAP state sequences of 2-state HMMs by dynamic programming (exact), time-major.

    ``log_e`` (T, N, 2) log-emissions (off, on) of N chains sorted by decreasing ``lengths``;
    step k only touches the chains still running (a prefix).  Returns (T, N) bool, True = on
    (False past a chain's end).  numpy keeps the per-step overhead to microseconds.
    """
    steps, n, _ = log_e.shape
    active = _active_counts(lengths, steps)
    delta = log_pi[None] + log_e[0]
    back = np.zeros((steps, n, 2), dtype=bool)  # True: best predecessor is "on"
    for k in range(1, steps):
        m = active[k]
        d = delta[:m]
        from_off = d[:, :1] + log_a[0]
        from_on = d[:, 1:] + log_a[1]
        came_on = from_on > from_off
        back[k, :m] = came_on
        delta[:m] = np.maximum(from_on, from_off) + log_e[k, :m]
    state = delta[:, 1] > delta[:, 0]
    path = np.zeros((steps, n), dtype=bool)
    rows = np.arange(n)
    for k in range(steps - 1, -1, -1):
        m = active[k]
        path[k, :m] = state[:m]
        if k:
            state[:m] = back[k, rows[:m], state[:m].astype(np.intp)]
    return path


def _posterior_on(log_e: np.ndarray, lengths: np.ndarray, a: np.ndarray, pi: np.ndarray) -> np.ndarray:
    """Marginal posteriors P(on) (T, N) by the scaled forward-backward algorithm (time-major)."""
    steps, n, _ = log_e.shape
    active = _active_counts(lengths, steps)
    e = np.exp(log_e - log_e.max(axis=2, keepdims=True))  # per-step scalings cancel out
    alpha = np.zeros_like(e)
    f = pi[None] * e[0]
    alpha[0] = f
    for k in range(1, steps):
        m = active[k]
        f = f[:m]
        f = (f @ a) * e[k, :m]
        if k % 16 == 0:  # rescale now and then (a step shrinks the sum by at most ~e^-14)
            f /= f.sum(1, keepdims=True)
        alpha[k, :m] = f
    beta = np.ones_like(e)
    b = np.ones((n, 2), dtype=e.dtype)
    for k in range(steps - 2, -1, -1):
        m = active[k + 1]
        nb = (e[k + 1, :m] * b[:m]) @ a.T
        if k % 16 == 0:
            nb /= nb.sum(1, keepdims=True)
        b[:m] = nb
        beta[k, :m] = nb
    post = alpha * beta
    total = post.sum(2)
    return np.where(total > 0, post[..., 1] / np.where(total > 0, total, 1.0), 0.0)
