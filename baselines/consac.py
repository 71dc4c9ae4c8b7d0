"""``consac`` / ``consac-s``: CONSAC vanishing points (Kluger et al., CVPR 2020) with the authors' weights.

F. Kluger, E. Brachmann, H. Ackermann, C. Rother, M. Y. Yang, B. Rosenhahn, "CONSAC: Robust
Multi-Model Fitting by Conditional Sample Consensus", CVPR 2020 (arXiv 2001.02643).  Our own
implementation of its inference, written from the paper and the authors' published code
(``fkluger/consac``: ``evaluate_vp.py``, ``util/cn_net.py``, ``util/sampling.py``,
``util/em_algorithm.py``), with their default settings; it loads their state dicts unchanged.

Weights (user-supplied, never fetched): ``consac_vp.net`` (CONSAC, supervised on NYU-VP train) and
``consac-s_vp.net`` (CONSAC-S, self-supervised), found in the folder or file named by the option
``consac[weights=PATH]``, else ``$FR_CONSAC_WEIGHTS``, else ``$FR_MODELS/consac`` (default
``../shared/models`` beside the checkout).  Without them every estimate is an "n/a (not
supplied ...)" failure (docs/vp.md).

Inference (one image)
---------------------
1. **Lines**: the segments (``meta.segments`` when given, e.g. NYU-VP's own LSD segments, else
   every LSD segment of the image) in normalised coordinates ``((x - w/2) / s, (y - h/2) / s)``,
   ``s`` = half the long side (CONSAC's ``(x - 320) / 320``, ``(y - 240) / 320`` at 640 x 480).
   Per segment: homogeneous endpoints p1, p2, the line ``l = p1 x p2`` scaled to ``|l_xy| = 1``
   and the midpoint c.  Network input: ``[p1, p2, l_x, l_y, state]`` (9 features).
2. **Network** (:class:`ConsacNetwork`, the authors' ``CNNet``: a 1x1 convolution to 128
   channels, 6 residual blocks of two (1x1 convolution, instance normalisation, batch
   normalisation, ReLU), a 1x1 convolution to one logit; output ``log sigmoid`` normalised over
   the segments).  Batch normalisation uses the statistics of the image's own segments, as in the
   authors' evaluation (their script never switches the network to eval mode).
3. **Conditional sampling** (``P`` = 32 multi-instance hypotheses, each built of ``M`` = 6
   instances from ``S`` = 32 single-instance hypotheses): per instance, sampling weights
   ``softmax(network(state)) / max``; ``S`` pairs of segments drawn without replacement in
   proportion to them; VP = ``l_a x l_b`` (unit); a segment's distance to a VP is
   ``1 - |cos|`` of the angle between its line and the line from its midpoint to the VP; soft
   inlier score ``1 - sigmoid(beta (d - tau))`` with ``tau`` = 0.001, ``beta = 5 / tau``; the
   hypothesis with the largest summed score wins and the state becomes the elementwise maximum of
   the state and its inlier scores.  The multi-instance hypothesis whose instances cover most
   (summed over segments, the maximum over its instances) is kept.
4. **Ranking**: greedily by the coverage each VP adds to those already ranked (the authors'
   ordering, including their tie rule: the first index wins; a VP can appear twice when none
   adds coverage).
5. **EM refinement** (10 iterations, as published): E-step, posterior of each segment for each VP
   from a Gaussian of variance 1e-8 on the distance above (flat priors, marginal floored at 1e-8);
   M-step, each VP = the least-squares intersection of the lines weighted by their posteriors
   (smallest right singular vector of ``(w l)^T (w l)``).  The refined VPs are ranked again (4).

Output: ``ranked_vanishing_points``: the ``M`` refined VPs in pixels, ranked (the VP task scores
the first as many as were labelled); ``extra["vp_variants"]["no EM"]``: the VPs before EM, ranked;
``extra["vp_support"]``: each ranked VP's soft inlier count.  **Focal length and rotation** come
from the VPs by the same geometry as Simon 2018's (:func:`fr_baselines.vp_geometry.orthogonal_pair`):
the zenith is the highest-ranked VP lying within ``vertical_max_deg`` of the image vertical from
the principal point and outside the image's half height; f comes from the highest-scoring pair of
finite remaining VPs compatible with orthogonality and orthogonal to the zenith (``f^2 = -(v_i -
p) . (v_j - p)``); without one the estimate is a flagged failure that keeps its VPs.

Randomness: one ``torch.Generator`` per method object, seeded with ``seed`` (default 1) when it is
built; images are processed in the order they come.  ``threads``: torch's intra-op threads during
an estimate (default 1, as the reproduction check ran).  ``device``: where the network and the
sampling run (``cpu`` default, ``cuda``; a different device draws a different random stream).
"""
from __future__ import annotations

import math
import os
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from fr_torch.core.geometry.camera import Camera
from fr_torch.core.settings.fov import FovRange
from fr_torch.errors import FRInputError
from fr_torch.plugins.interface import CameraEstimate, ImageMeta, TimedCalibrator
from fr_torch.registry import not_supplied

from . import vp_geometry as vg
from .provenance import sha256

WEIGHTS_ENV = "FR_CONSAC_WEIGHTS"
MODELS_ENV = "FR_MODELS"
WEIGHT_FILES = {"consac": "consac_vp.net", "consac-s": "consac-s_vp.net"}
#: Keys of the authors' checkpoints that their network does not use (a stopping head never trained
#: for vanishing points); dropped before the strict load.
UNUSED_KEYS = ("stop_cond_out.weight", "stop_cond_out.bias")
CHANNELS = 128
INPUT_FEATURES = 9
INSTANCE_NORM_EPS = 1e-5


def default_models_root() -> Path:
    """``$FR_MODELS``, else ``../shared/models`` beside the checkout."""
    return Path(os.environ.get(MODELS_ENV, Path(__file__).resolve().parents[2] / "shared" / "models"))


def weights_path(variant: str, weights: str | os.PathLike | None = None) -> Path:
    """The checkpoint of ``variant`` (``consac`` / ``consac-s``): ``weights`` (a file, or a folder
    holding :data:`WEIGHT_FILES`), else ``$FR_CONSAC_WEIGHTS`` (same), else the models root's
    ``consac/`` folder.  The path may not exist (the caller reports "not supplied")."""
    given = weights or os.environ.get(WEIGHTS_ENV)
    base = Path(given).expanduser() if given else default_models_root() / "consac"
    return base / WEIGHT_FILES[variant] if base.is_dir() or not base.suffix else base


class ConsacNetwork(nn.Module):
    """The authors' ``CNNet`` for vanishing points (module docstring, step 2); its state dict keys
    are theirs (``p_in``, ``<i>s0`` .. ``<i>s3``, ``p_out``).  Input (B, N, 9), output (B, N)
    log sampling weights (normalised over the N segments of each image)."""

    def __init__(self, blocks: int = 6, input_features: int = INPUT_FEATURES):
        super().__init__()
        self.blocks = int(blocks)
        self.p_in = nn.Conv2d(input_features, CHANNELS, 1)
        for i in range(self.blocks):
            self.add_module(f"{i}s0", nn.Conv2d(CHANNELS, CHANNELS, 1))
            self.add_module(f"{i}s1", nn.BatchNorm2d(CHANNELS))
            self.add_module(f"{i}s2", nn.Conv2d(CHANNELS, CHANNELS, 1))
            self.add_module(f"{i}s3", nn.BatchNorm2d(CHANNELS))
        self.p_out = nn.Conv2d(CHANNELS, 1, 1)

    @staticmethod
    def _pointwise(conv: nn.Conv2d, x: torch.Tensor) -> torch.Tensor:
        """A 1x1 convolution on (B, N, C): one matrix product over every segment of the batch."""
        return F.linear(x, conv.weight[:, :, 0, 0], conv.bias)

    @staticmethod
    def _normalise(x: torch.Tensor, norm: nn.BatchNorm2d) -> torch.Tensor:
        """Instance normalisation (per image and channel over the segments, no affine), then batch
        normalisation with the batch statistics of one image (the same normalisation again, with the
        learned scale and shift), x (B, N, C).  Computed as one affine map: the first leaves mean 0
        and variance ``v / (v + eps)``, so the two together scale ``x - mean`` by
        ``1 / sqrt((v + eps) (v / (v + eps) + eps'))`` (the same values up to float rounding)."""
        mean = x.mean(1, keepdim=True)
        centred = x - mean
        variance = (centred * centred).mean(1, keepdim=True)
        scale = torch.rsqrt(variance + INSTANCE_NORM_EPS) * torch.rsqrt(
            variance / (variance + INSTANCE_NORM_EPS) + norm.eps) * norm.weight
        return torch.addcmul(norm.bias, centred, scale)

    def forward(self, inputs: torch.Tensor) -> torch.Tensor:
        x = F.relu(self._pointwise(self.p_in, inputs))
        for i in range(self.blocks):
            residual = x
            x = F.relu(self._normalise(self._pointwise(getattr(self, f"{i}s0"), x), getattr(self, f"{i}s1")))
            x = F.relu(self._normalise(self._pointwise(getattr(self, f"{i}s2"), x), getattr(self, f"{i}s3")))
            x = x + residual
        log_probs = F.logsigmoid(self._pointwise(self.p_out, x))[..., 0]  # (B, N)
        return log_probs - torch.logsumexp(log_probs, dim=1, keepdim=True)


def load_network(path: Path) -> ConsacNetwork:
    """:class:`ConsacNetwork` with the authors' state dict at ``path`` (strict, after dropping
    :data:`UNUSED_KEYS`); FRInputError (one line) when it does not load."""
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
        state = {k: v for k, v in state.items() if k not in UNUSED_KEYS}
        network = ConsacNetwork()
        network.load_state_dict(state, strict=True)
    except (OSError, RuntimeError, ValueError, AttributeError, KeyError) as exc:
        raise FRInputError(f"CONSAC weights {path}: cannot load ({type(exc).__name__}: {str(exc)[:200]})") from None
    return network.eval()


def line_features(segments: np.ndarray, width: int, height: int) -> torch.Tensor:
    """(N, 12) float32 per segment in normalised coordinates: p1, p2, line (|l_xy| = 1), midpoint."""
    scale = max(width, height) / 2.0
    seg = np.asarray(segments, np.float64).reshape(-1, 4)
    p1 = np.c_[(seg[:, 0] - width / 2.0) / scale, (seg[:, 1] - height / 2.0) / scale, np.ones(len(seg))]
    p2 = np.c_[(seg[:, 2] - width / 2.0) / scale, (seg[:, 3] - height / 2.0) / scale, np.ones(len(seg))]
    line = np.cross(p1, p2)
    line /= np.linalg.norm(line[:, :2], axis=1, keepdims=True)
    return torch.from_numpy(np.c_[p1, p2, line, (p1 + p2) / 2.0]).to(torch.float32)


def to_pixels(points: torch.Tensor, width: int, height: int) -> np.ndarray:
    """Homogeneous normalised points (M, 3) -> homogeneous pixel points (M, 3), float64."""
    scale = max(width, height) / 2.0
    p = points.detach().to(torch.float64).numpy()
    return np.c_[scale * p[:, 0] + width / 2.0 * p[:, 2], scale * p[:, 1] + height / 2.0 * p[:, 2], p[:, 2]]


def angular_distances(vps: torch.Tensor, features: torch.Tensor) -> torch.Tensor:
    """CONSAC's distance ``1 - |cos|`` between each segment's line and the line from its midpoint to
    each VP: vps (..., 3), features (N, 12) -> (..., N)."""
    lines, centroids = features[:, 6:9], features[:, 9:12]
    constrained = torch.linalg.cross(centroids.expand(vps.shape[:-1] + centroids.shape),
                                     vps[..., None, :].expand(vps.shape[:-1] + centroids.shape), dim=-1)
    constrained = constrained[..., :2] / (torch.linalg.vector_norm(constrained[..., :2], dim=-1, keepdim=True) + 1e-8)
    unit = lines[:, :2] / (torch.linalg.vector_norm(lines[:, :2], dim=-1, keepdim=True) + 1e-8)
    return 1.0 - (constrained * unit).sum(-1).abs()


def greedy_order(inliers: torch.Tensor) -> list[int]:
    """The authors' ranking of instances by added coverage: inlier scores (M, N) -> order (M,)."""
    scores = inliers.clone()
    order = []
    for _ in range(scores.shape[0]):
        best = int(torch.argmax(scores.sum(-1)))
        scores = torch.maximum(scores[best], scores)
        scores[best] = 0
        order.append(best)
    return order


class Consac(TimedCalibrator):
    """CONSAC (module docstring); ``variant`` ``consac`` or ``consac-s`` picks the checkpoint."""

    name = "consac"
    #: The VP task runs it once for both intrinsics settings: it never reads focal length or principal point
    #: for its vanishing points.
    uses_intrinsics = False

    def __init__(self, variant: str = "consac", weights: str | None = None, seed: int = 1, threads: int = 1,
                 threshold: float = 0.001, hypotheses: int = 32, outer_hypotheses: int = 32, instances: int = 6,
                 em_iterations: int = 10, em_variance: float = 1e-8, range=None, vertical_max_deg: float = 30.0,
                 finite_limit: float = 20.0, zenith_tol_deg: float = 5.0, name: str | None = None,
                 device: str = "cpu"):
        if variant not in WEIGHT_FILES:
            raise ValueError(f"CONSAC variant must be one of {', '.join(WEIGHT_FILES)}, got {variant!r}")
        self.variant = variant
        self.name = name or variant
        self.path = weights_path(variant, weights)
        self.seed = int(seed)
        self.threads = int(threads)
        self.threshold = float(threshold)
        self.hypotheses, self.outer_hypotheses = int(hypotheses), int(outer_hypotheses)
        self.instances, self.em_iterations, self.em_variance = int(instances), int(em_iterations), float(em_variance)
        self.fov_range = FovRange.parse(range)
        self.vertical_max_deg, self.finite_limit = float(vertical_max_deg), float(finite_limit)
        self.zenith_tol_deg = float(zenith_tol_deg)
        self.device = torch.device(device)
        self.generator = torch.Generator(device=self.device).manual_seed(self.seed)
        self._network: ConsacNetwork | None = None

    @property
    def available(self) -> bool:
        return self.path.is_file()

    @property
    def weights(self) -> str | None:
        """Caption text: the checkpoint's file name and sha256 (None when absent)."""
        if not self.available:
            return None
        return f"{self.path.name} (sha256 {sha256(self.path)})"

    def network(self) -> ConsacNetwork:
        if self._network is None:
            self._network = load_network(self.path).to(self.device)
        return self._network

    # ------------------------------------------------------------------ estimate
    def _estimate(self, image, meta: ImageMeta) -> CameraEstimate:
        if not self.available:
            return CameraEstimate.failure(self.name, not_supplied(
                f"CONSAC weights {self.path}; give consac[weights=PATH], --consac-weights or ${WEIGHTS_ENV}"))
        try:
            segments = vg.input_segments(image, meta)
            network = self.network()
        except FRInputError as exc:
            return CameraEstimate.failure(self.name, f"bad input: {exc}")
        width, height = vg.image_size(image, meta)
        if width <= 0 or height <= 0:
            return CameraEstimate.failure(self.name, "unknown image size")
        lengths = vg.segment_lengths(segments)
        segments = segments[lengths > 0]
        if len(segments) < 2:
            return CameraEstimate.failure(self.name, f"too few line segments ({len(segments)})")
        previous = torch.get_num_threads()
        torch.set_num_threads(max(1, self.threads))
        try:
            with torch.no_grad():
                features = line_features(segments, width, height).to(self.device)
                raw, raw_scores, refined, refined_scores = (
                    t.cpu() for t in self.vanishing_points(network, features))
        finally:
            torch.set_num_threads(previous)
        ranked = vg.positive_w(to_pixels(refined, width, height))
        before_em = vg.positive_w(to_pixels(raw, width, height))
        extra = {"vp_variants": {"no EM": before_em}, "vp_support": refined_scores.tolist(),
                 "vp_support_no_em": raw_scores.tolist(), "num_segments": int(len(segments))}
        return self._camera(ranked, refined_scores.numpy(), vg.principal_point(meta, width, height), width, height,
                            extra)

    def vanishing_points(self, network: ConsacNetwork, features: torch.Tensor):
        """(VPs before EM (M, 3), their coverage scores (M,), VPs after EM (M, 3), scores (M,)), each
        ranked, in normalised coordinates (module docstring, steps 3-5)."""
        count = features.shape[0]
        beta = 5.0 / self.threshold
        outer, inner, instances = self.outer_hypotheses, self.hypotheses, self.instances
        device = features.device
        state = torch.zeros(outer, count, device=device)
        inputs = torch.cat([features[:, :8].expand(outer, count, 8), state[..., None]], -1)
        models = torch.zeros(outer, instances, 3, device=device)
        best_inliers = torch.zeros(outer, instances, count, device=device)
        lines = features[:, 6:9]
        for m in range(instances):
            inputs[..., 8] = state
            probs = torch.softmax(network(inputs), dim=1)
            probs = probs / probs.max(1, keepdim=True).values
            choice = torch.multinomial(probs.repeat_interleave(inner, 0), 2, replacement=False,
                                       generator=self.generator)  # (P*S, 2)
            vps = torch.linalg.cross(lines[choice[:, 0]], lines[choice[:, 1]], dim=-1)
            vps = (vps / (torch.linalg.vector_norm(vps, dim=-1, keepdim=True) + 1e-8)).view(outer, inner, 3)
            inliers = torch.sigmoid(-beta * (angular_distances(vps, features) - self.threshold))  # (P, S, N)
            best = inliers.sum(-1).argmax(1)  # (P,)
            rows = torch.arange(outer, device=device)
            models[:, m] = vps[rows, best]
            best_inliers[:, m] = inliers[rows, best]
            state = torch.maximum(state, best_inliers[:, m])
        chosen = int(best_inliers.max(1).values.sum(-1).argmax())
        raw_order = greedy_order(best_inliers[chosen])
        raw = models[chosen, raw_order]
        refined = self.em(models[chosen], features)
        refined_inliers = torch.sigmoid(-beta * (angular_distances(refined, features) - self.threshold))
        refined_order = greedy_order(refined_inliers)
        return (raw, best_inliers[chosen, raw_order].sum(-1), refined[refined_order],
                refined_inliers[refined_order].sum(-1))

    def em(self, vps: torch.Tensor, features: torch.Tensor) -> torch.Tensor:
        """EM refinement of VPs (M, 3) on the segments (module docstring, step 5)."""
        lines = features[:, 6:9]
        norm = 1.0 / math.sqrt(2.0 * math.pi * self.em_variance)
        for _ in range(self.em_iterations):
            distance = angular_distances(vps, features).T  # (N, M)
            likelihood = norm * torch.exp(-distance * distance / (2.0 * self.em_variance))
            posterior = likelihood / torch.clamp(likelihood.sum(-1, keepdim=True), min=1e-8)
            weighted = lines[None] * posterior.T[..., None]  # (M, N, 3)
            _, _, vh = torch.linalg.svd(weighted.transpose(1, 2) @ weighted)
            vps = vh[:, 2, :]
        return vps

    def _camera(self, ranked: np.ndarray, scores: np.ndarray, pp: np.ndarray, width: int, height: int,
                extra: dict) -> CameraEstimate:
        """f and R from the ranked VPs (module docstring); a flagged failure that keeps the VPs without."""
        zenith = vg.pick_zenith(ranked, pp, self.vertical_max_deg, height / 2.0)
        if zenith is None:
            return vg.failure_estimate(self.name, "no vertical vanishing point among the VPs", extra, ranked)
        others = [{"vp": ranked[i], "significance": float(scores[i])} for i in range(len(ranked)) if i != zenith]
        pair = vg.orthogonal_pair(others, ranked[zenith], pp, math.hypot(width, height),
                                  self.fov_range.focal_bounds(max(width, height)), self.finite_limit,
                                  self.zenith_tol_deg)
        if pair is None:
            return vg.failure_estimate(self.name, "no orthogonal pair of finite horizontal VPs", extra, ranked)
        focal, vi, vj = pair
        rotation = vg.rotation_from_vps(ranked[zenith], vi["vp"], focal, pp, vj["vp"])
        return vg.camera_estimate(self.name, Camera(width, height, focal, pp, rotation),
                                  ranked_vanishing_points=ranked, **extra)


def make_consac_s(**kwargs) -> Consac:
    """CONSAC-S: the self-supervised checkpoint (``consac-s_vp.net``)."""
    return Consac(variant="consac-s", **kwargs)
