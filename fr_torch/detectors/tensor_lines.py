"""``torch-lines``: a line-segment detector made of batched tensor operations (CPU or GPU).

Line-support regions grouped by orientation, in the manner of Burns, Hanson & Riseman (1986)
"Extracting straight lines", with LSD-style rectangle fits (von Gioi et al. 2010), written so
that a whole batch of images is processed by the same tensor operations on any device:

1. **Gradients**: the grey image (0..255) is smoothed by a sampled Gaussian of ``sigma`` px
   (separable, replicated borders; on the CPU by OpenCV with the same taps) and differentiated
   by central differences; a pixel is
   *active* when its gradient magnitude exceeds ``grad_threshold`` (grey levels per px) and,
   with ``nms=True``, it is also a local maximum of the magnitude along the gradient
   (4 quantised directions, Canny-style).
2. **Orientation partitions**: the gradient direction (polarity kept, 0..360 deg) is quantised
   into ``n_bins`` bins twice, the second partition shifted by half a bin, so that a line whose
   direction lies on a bin boundary of one partition lies mid-bin in the other.
3. **Connected components**: in each partition, active 8-neighbours in the same bin belong to
   one region.  Computed on the sparse active pixels as a graph (row runs as nodes, links to
   the row below as edges) by min-label propagation with hooking and pointer jumping.
4. **Voting** (Burns): each active pixel votes for the larger of its two regions; a region is
   kept when at least ``min_support`` of its pixels voted for it, and is formed by its voters.
5. **Rectangle fit**: per region, the gradient-magnitude-weighted centroid and second moments
   give the line direction (principal axis) and the RMS distance of the pixels from the line
   (the smaller eigenvalue); the voters' extents along it give the end points.  A region is a
   segment when its length is at least ``min_length`` px, its RMS width at most
   ``max_rms_width`` px, its pixels per px of length at least ``min_density``, and its
   direction within ``max_angle_deg`` of the normal to its mean gradient direction.

Coordinates: ``[x1, y1, x2, y2]`` pixels, x right, y down, origin at the centre of the top-left
pixel (the project's convention, as LSD).  Segments of an image are sorted by decreasing length;
at most ``max_segments`` per image are kept.

``TensorLinesDetector.detect_batch`` takes a ``(B, 1, H, W)`` (or ``(B, H, W)``) tensor of grey
levels 0..255 on any device and returns ``segments (B, N, 4)`` float32 and ``mask (B, N)`` bool
on the same device (``N >= 1``; padding rows are zero with ``mask`` False).  Calling the detector
on one grey ``uint8`` image (the :class:`fr_torch.detectors.registry.Detector` protocol) returns ``(N, 4)``
float64 numpy.  :func:`decode_jpeg_batch` decodes JPEG bytes to such a batch with torchvision
(optional; on the GPU with ``device="cuda"``).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, fields, replace
from typing import Sequence

import numpy as np
import torch
import torch.nn.functional as F

from fr_torch.core.exact import atan2, exact_index_sum
from fr_torch.registry import format_method_spec


@dataclass(frozen=True)
class TensorLinesConfig:
    """Settings (lengths in pixels of the image as given; grey levels 0..255)."""

    sigma: float = 1.0              # Gaussian pre-smoothing (px); 0 = none
    grad_threshold: float = 3.4     # minimum gradient magnitude (grey levels per px)
    nms: bool = True                # keep only maxima of the magnitude along the gradient
    n_bins: int = 8                 # orientation bins over 360 deg (gradient polarity kept)
    min_support: float = 0.5        # share of a region's pixels that must vote for it
    min_length: float = 10.0        # px
    max_rms_width: float = 1.0      # px, largest weighted RMS distance of the pixels from the line
    min_density: float = 0.5        # region pixels per px of length
    max_angle_deg: float = 30.0     # line direction vs the normal of the region's mean gradient
    max_segments: int = 1000        # per image, the longest kept
    cpu_threads: int | None = 1     # torch intra-op threads while detecting on the CPU (None: leave)

    def __post_init__(self):
        if self.n_bins < 2:
            raise ValueError(f"n_bins must be >= 2, got {self.n_bins}")
        for name in ("sigma", "grad_threshold", "min_length", "max_rms_width", "min_density"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value >= 0):
                raise ValueError(f"{name} must be a finite number >= 0, got {value!r}")
        if not 0.0 <= self.min_support <= 1.0:
            raise ValueError(f"min_support must lie in [0, 1], got {self.min_support}")
        if self.max_segments < 1:
            raise ValueError(f"max_segments must be >= 1, got {self.max_segments}")


def _coerce(config: TensorLinesConfig, overrides: dict) -> TensorLinesConfig:
    """``config`` with ``overrides`` (strings from a ``torch-lines[key=value]`` spec converted)."""
    types = {f.name: f.type for f in fields(TensorLinesConfig)}
    clean = {}
    for key, value in overrides.items():
        if key not in types:
            raise ValueError(f"torch-lines: unknown option {key!r} (options: {', '.join(types)})")
        if isinstance(value, str):
            kind = types[key]
            if "bool" in kind:
                value = value.strip().lower() in ("1", "true", "yes", "on")
            elif "int" in kind and "None" in kind and value.strip().lower() == "none":
                value = None
            elif kind.startswith("int"):
                value = int(value)
            elif kind.startswith("float"):
                value = float(value)
        clean[key] = value
    return replace(config, **clean)


#: Settings that do not change the segments (left out of :func:`spec_name`).
_RUN_ONLY_SETTINGS = ("cpu_threads",)


def _spec_value(value) -> str:
    """A setting as a spec writes it (``true`` / ``none`` in lower case)."""
    return str(value).lower() if value is None or isinstance(value, bool) else str(value)


def spec_name(config: TensorLinesConfig) -> str:
    """``torch-lines`` for the default settings, else the spec of the changed ones, e.g.
    ``torch-lines[grad_threshold=3.0]`` (what :func:`fr_torch.detectors.registry.get_detector`
    builds the same detector from).  A reliability model's scope is checked against this name: it
    was measured with the defaults."""
    default = TensorLinesConfig()
    return format_method_spec("torch-lines", {
        f.name: _spec_value(getattr(config, f.name)) for f in fields(config)
        if f.name not in _RUN_ONLY_SETTINGS and getattr(config, f.name) != getattr(default, f.name)})


class TensorLinesDetector:
    """Orientation-region line segments from batched tensor operations (see the module doc).

    ``name``: ``torch-lines``, or with settings that change the segments their spec (:func:`spec_name`)."""

    name = "torch-lines"

    def __init__(self, device: str | torch.device | None = None, config: TensorLinesConfig | None = None,
                 **overrides):
        self.config = _coerce(config or TensorLinesConfig(), overrides)
        self.device = torch.device(device) if device is not None else torch.device("cpu")
        self.name = spec_name(self.config)

    def to(self, device: str | torch.device) -> "TensorLinesDetector":
        """This detector's settings on ``device`` (itself when it is there already)."""
        device = torch.device(device)
        return self if device == self.device else TensorLinesDetector(device=device, config=self.config)

    # ------------------------------------------------------------------ public API

    def __call__(self, gray: np.ndarray) -> np.ndarray:
        """Segments (N, 4) float64 of one grey image (H, W) (uint8 or float grey levels 0..255)."""
        image = np.asarray(gray)
        if image.ndim == 3:
            image = image.mean(axis=2)
        if image.ndim != 2:
            raise ValueError(f"expected a 2-D grey image, got shape {image.shape}")
        tensor = torch.from_numpy(np.ascontiguousarray(image)).to(self.device)
        segments, mask = self.detect_batch(tensor[None])
        return segments[0][mask[0]].double().cpu().numpy()

    def detect_batch(self, images: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Segments of a batch: ``images`` (B, 1, H, W) or (B, H, W) grey levels 0..255.

        Returns ``segments`` (B, N, 4) float32 [x1, y1, x2, y2] px and ``mask`` (B, N) bool, on
        the images' device, N >= 1, each image's segments first, longest first.
        """
        threads = self.config.cpu_threads
        if images.device.type != "cpu" or not threads or threads == torch.get_num_threads():
            return self._detect_batch(images)
        previous = torch.get_num_threads()
        torch.set_num_threads(threads)
        try:
            return self._detect_batch(images)
        finally:
            torch.set_num_threads(previous)

    # ------------------------------------------------------------------ pipeline

    @torch.no_grad()
    def _detect_batch(self, images: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        cfg = self.config
        if images.ndim == 3:
            images = images[:, None]
        if images.ndim != 4 or images.shape[1] != 1:
            raise ValueError(f"expected images of shape (B, 1, H, W) or (B, H, W), got {tuple(images.shape)}")
        dev = images.device
        batch, _, height, width = images.shape
        empty = (torch.zeros(batch, 1, 4, device=dev), torch.zeros(batch, 1, dtype=torch.bool, device=dev))
        if batch == 0 or height < 3 or width < 3:
            return empty
        image = images[:, 0]
        if image.is_floating_point():
            image = torch.nan_to_num(image.float())
        elif image.dtype != torch.uint8 or dev.type != "cpu":                # OpenCV reads uint8
            image = image.float()
        gx, gy = _gradients(image, cfg.sigma)
        squared = gx * gx + gy * gy                                         # squared magnitude
        active = squared > cfg.grad_threshold ** 2
        active[:, :1] = active[:, -1:] = False                              # borders never active:
        active[:, :, :1] = active[:, :, -1:] = False                        # neighbours always exist
        flat = _nonzero(active.reshape(-1))                                 # active pixel ids (P,)
        if flat.numel() == 0:
            return empty
        gx, gy, squared = gx.reshape(-1), gy.reshape(-1), squared.reshape(-1)
        gx, gy = gx.index_select(0, flat), gy.index_select(0, flat)
        if cfg.nms:
            keep = _nonzero(_local_maximum(squared, flat, gx, gy, width))
            flat, gx, gy = flat.index_select(0, keep), gx.index_select(0, keep), gy.index_select(0, keep)
            if flat.numel() == 0:
                return empty
        angle = atan2(gy, gx)                                               # gradient direction
        bins_a, bins_b = _orientation_bins(angle, cfg.n_bins)
        labels_a, labels_b = _components(flat, bins_a, bins_b, width)
        return self._segments(flat, labels_a, labels_b, gx, gy, batch, height, width)

    def _segments(self, flat, labels_a, labels_b, gx, gy, batch, height, width):
        """Segments from the active pixels ``flat`` (P,) with region labels in the two partitions
        and gradients ``gx``, ``gy`` (P,)."""
        cfg = self.config
        dev = flat.device
        n_a = int(labels_a.max()) + 1
        size_a = torch.bincount(labels_a, minlength=n_a)
        size_b = torch.bincount(labels_b)
        # Burns' vote: each pixel joins the larger of its two regions (ties: partition A).
        to_a = size_a[labels_a] >= size_b[labels_b]
        region = torch.where(to_a, labels_a, n_a + labels_b)
        size = torch.cat([size_a, size_b])
        votes = torch.bincount(region, minlength=size.numel())
        # A region of v voters has density v / (length + 1): fewer than
        # min_density * (min_length + 1) voters cannot make a segment.
        min_votes = max(2.0, cfg.min_density * (cfg.min_length + 1.0))
        kept_region = (votes.float() >= cfg.min_support * size.float()) & (votes.float() >= min_votes)
        keep = _nonzero(kept_region.index_select(0, region))
        flat, region, gx, gy = (v.index_select(0, keep) for v in (flat, region, gx, gy))
        if flat.numel() == 0:
            return (torch.zeros(batch, 1, 4, device=dev), torch.zeros(batch, 1, dtype=torch.bool, device=dev))
        renumber = torch.cumsum(kept_region, 0) - 1
        region = renumber.index_select(0, region)
        n = int(kept_region.sum())

        plane = height * width
        owner_pixel = torch.div(flat, plane, rounding_mode="floor")
        within = flat - owner_pixel * plane
        y = torch.div(within, width, rounding_mode="floor")
        x = (within - y * width).float()
        y = y.float()
        w = torch.sqrt(gx * gx + gy * gy)
        # gradient-weighted sums -> centroid and mean gradient direction; then central moments
        columns = torch.stack([w, w * x, w * y, gx, gy, torch.ones_like(w)], 1)
        sums = exact_index_sum(columns, region, n).float()  # the same bits in any batch and on any device
        weight, count = sums[:, 0], sums[:, 5]
        mx, my = sums[:, 1] / weight, sums[:, 2] / weight
        dx, dy = x - mx[region], y - my[region]
        central = torch.stack([w * dx * dx, w * dy * dy, w * dx * dy], 1)
        moments = exact_index_sum(central, region, n).float() / weight[:, None]
        sxx, syy, sxy = moments[:, 0], moments[:, 1], moments[:, 2]
        theta = 0.5 * atan2(2 * sxy, sxx - syy)
        ux, uy = torch.cos(theta), torch.sin(theta)
        # the smaller eigenvalue of the covariance: the weighted mean squared distance from the line
        across_var = (0.5 * (sxx + syy) - torch.sqrt((0.25 * (sxx - syy) ** 2 + sxy * sxy))).clamp_min(0)
        along = dx * ux[region] + dy * uy[region]
        extents = torch.full((n, 2), float("-inf"), device=dev).scatter_reduce_(
            0, region[:, None].expand(-1, 2), torch.stack([along, -along], 1), "amax")
        t1, t0 = extents[:, 0], -extents[:, 1]
        owner = torch.zeros(n, dtype=torch.long, device=dev).scatter_(0, region, owner_pixel)

        length = t1 - t0
        density = count / (length + 1.0)
        gcos, gsin = sums[:, 3], sums[:, 4]
        # |cos| of the angle between the line direction and the mean gradient direction
        normal_cos = (ux * gcos + uy * gsin).abs() / torch.sqrt(gcos * gcos + gsin * gsin).clamp_min(1e-12)
        good = ((length >= cfg.min_length) & (across_var <= cfg.max_rms_width ** 2) & (density >= cfg.min_density)
                & (normal_cos <= math.sin(math.radians(cfg.max_angle_deg))))
        endpoints = torch.stack([mx + t0 * ux, my + t0 * uy, mx + t1 * ux, my + t1 * uy], 1)
        return _pad_by_owner(endpoints[good], length[good], owner[good], batch, cfg.max_segments)


# ---------------------------------------------------------------------- helpers

def _orientation_bins(angle: torch.Tensor, n_bins: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Two quantisations (0..n_bins-1, the second shifted by half a bin) of angles in [-pi, pi]."""
    turns = (angle + math.pi) * (n_bins / (2 * math.pi))                 # in [0, n_bins]
    bins_a = turns.to(torch.int32)                                         # floor (turns >= 0)
    bins_b = (turns + 0.5).to(torch.int32)
    bins_a = torch.where(bins_a >= n_bins, bins_a - n_bins, bins_a)
    bins_b = torch.where(bins_b >= n_bins, bins_b - n_bins, bins_b)
    return bins_a, bins_b


def _gaussian_taps(sigma: float, device) -> torch.Tensor:
    half = max(1, int(math.ceil(3.0 * sigma)))
    x = torch.arange(-half, half + 1, dtype=torch.float32, device=device)
    taps = torch.exp(-0.5 * (x / sigma) ** 2)
    return taps / taps.sum()


def _smooth_1d(image: torch.Tensor, taps: torch.Tensor, dim: int) -> torch.Tensor:
    """Correlate (B, H, W) with odd ``taps`` along ``dim`` (1 or 2), replicated borders."""
    half = (taps.numel() - 1) // 2
    size = image.shape[dim]
    padded = F.pad(image[:, None], (half, half, 0, 0) if dim == 2 else (0, 0, half, half), mode="replicate")[:, 0]
    out = padded.narrow(dim, 0, size) * taps[0]
    for k in range(1, taps.numel()):
        out = out + padded.narrow(dim, k, size) * taps[k]
    return out


def _gradients(image: torch.Tensor, sigma: float) -> tuple[torch.Tensor, torch.Tensor]:
    """(gx, gy), each (B, H, W) float32, grey levels per px, of ``image`` (B, H, W) (uint8 or
    float, finite): central differences of the image smoothed
    by the sampled Gaussian of ``sigma`` px (separable, replicated borders; none for sigma 0).

    On the CPU, OpenCV applies the smoothing and the difference as one separable filter per
    direction (the same taps composed; ~10x faster than torch there).
    """
    taps = _gaussian_taps(sigma, image.device) if sigma > 0 else torch.ones(1, device=image.device)
    if image.device.type == "cpu":
        import cv2

        smooth = taps.numpy()
        derivative = np.convolve(smooth, [-0.5, 0.0, 0.5]).astype(np.float32)  # correlation taps
        gx = np.empty(image.shape, np.float32)
        gy = np.empty(image.shape, np.float32)
        for b, plane in enumerate(image.contiguous().numpy()):
            cv2.sepFilter2D(plane, cv2.CV_32F, derivative, smooth, dst=gx[b], borderType=cv2.BORDER_REPLICATE)
            cv2.sepFilter2D(plane, cv2.CV_32F, smooth, derivative, dst=gy[b], borderType=cv2.BORDER_REPLICATE)
        return torch.from_numpy(gx), torch.from_numpy(gy)
    return _gradients_torch(image.float(), taps)


def _gradients_torch(image: torch.Tensor, taps: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """:func:`_gradients` in torch operations (any device): ``image`` (B, H, W) float, ``taps``
    the odd 1-D smoothing taps."""
    if taps.numel() > 1:
        image = _smooth_1d(_smooth_1d(image, taps, 2), taps, 1)
    padded = F.pad(image[:, None], (1, 1, 1, 1), mode="replicate")[:, 0]
    gx = 0.5 * (padded[:, 1:-1, 2:] - padded[:, 1:-1, :-2])
    gy = 0.5 * (padded[:, 2:, 1:-1] - padded[:, :-2, 1:-1])
    return gx, gy


def _local_maximum(magnitude: torch.Tensor, flat: torch.Tensor, gx: torch.Tensor, gy: torch.Tensor,
                   width: int) -> torch.Tensor:
    """(P,) bool: the pixels ``flat`` (ids into the flattened (B, H, W) ``magnitude``, or any
    increasing function of it; none on a border) that are maxima of the magnitude along their
    gradient ``(gx, gy)`` (P,) quantised to 4 directions, 45 deg apart (Canny-style: >= the
    pixel ahead, > the pixel behind)."""
    ax, ay = gx.abs(), gy.abs()
    tan_half = math.tan(math.pi / 8)
    horizontal = ay <= tan_half * ax
    vertical = ax <= tan_half * ay
    diagonal = ~(horizontal | vertical)
    # steps: 1 (horizontal), width (vertical), width + 1 or width - 1 (diagonal; y grows downwards)
    steps = (horizontal.long() + vertical.long() * width
             + diagonal.long() * (width - 1 + 2 * ((gx * gy) > 0).long()))
    centre = magnitude.index_select(0, flat)
    return ((centre >= magnitude.index_select(0, flat + steps))
            & (centre > magnitude.index_select(0, flat - steps)))


def _nonzero(mask: torch.Tensor) -> torch.Tensor:
    """Ascending indices (long) of the True entries of a 1-D bool tensor, on its device (NumPy
    on the CPU: ~8x faster than torch.nonzero there)."""
    if mask.device.type == "cpu":
        return torch.from_numpy(np.flatnonzero(mask.numpy()))
    return torch.nonzero(mask).squeeze(1)


def _components(flat: torch.Tensor, bins_a: torch.Tensor, bins_b: torch.Tensor,
                width: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Region labels of the active pixels in the two orientation partitions.

    ``flat`` (P,): ascending ids of the active pixels in the flattened (B, H, W) grid, none on
    an image border; ``bins_a``, ``bins_b`` (P,): their bins.
    Active 8-neighbours in the same bin share a region.  Returns two (P,) long tensors of compact
    labels 0, 1, ... (one numbering per partition).

    Runs of same-bin pixels along rows are the graph's nodes (consecutive in ``flat``); the
    three lower neighbours link runs, one edge per run pair of consecutive pixels.
    """
    dev = flat.device
    count = flat.numel()
    bins = torch.stack([bins_a, bins_b])                                # (2, P)
    # runs: a pixel joins the run of the previous active pixel when that is its left neighbour
    joined = torch.zeros(2, count, dtype=torch.bool, device=dev)
    joined[:, 1:] = ((flat[1:] - flat[:-1]) == 1) & (bins[:, 1:] == bins[:, :-1])
    runs = torch.cumsum(~joined.reshape(-1), 0).view(2, count) - 1      # B's ids follow A's
    n_runs = int(runs[1, -1]) + 1
    # the lower neighbours (ids + width - 1, width, width + 1) are among the three active pixels
    # that follow the first id >= id + width - 1
    first = torch.searchsorted(flat, flat + (width - 1))
    position = (first[None] + torch.arange(3, device=dev)[:, None]).clamp_max(count - 1).reshape(-1)
    gap = flat.index_select(0, position) - flat.repeat(3)
    pair = _nonzero((gap >= width - 1) & (gap <= width + 1))
    node = torch.arange(count, device=dev).repeat(3).index_select(0, pair)
    other = position.index_select(0, pair)
    source, target = runs.index_select(1, node), runs.index_select(1, other)  # (2, E) run pairs
    # the pair's runs have one bin each: one test per pair; repeats of the previous pair dropped
    keep = bins.index_select(1, node) == bins.index_select(1, other)
    keep[:, 1:] &= (source[:, 1:] != source[:, :-1]) | (target[:, 1:] != target[:, :-1])
    keep = _nonzero(keep.reshape(-1))
    roots = _connected_roots(n_runs, source.reshape(-1).index_select(0, keep),
                             target.reshape(-1).index_select(0, keep))
    root = roots.index_select(0, runs.reshape(-1)).view(2, count)      # smallest run id
    is_root = torch.zeros(n_runs, dtype=torch.bool, device=dev)
    is_root[root.reshape(-1)] = True
    rank = torch.cumsum(is_root, 0) - 1
    first_b = rank[int(runs[1, 0])]                                    # B's labels start here
    return rank.index_select(0, root[0]), rank.index_select(0, root[1]) - first_b


def _connected_roots(nodes: int, sources: torch.Tensor, targets: torch.Tensor) -> torch.Tensor:
    """(nodes,) long: each node's smallest connected node id, for the undirected graph with
    edges ``sources[i] -- targets[i]``.

    Labels always point at a root (a node labelled with itself).  Each round: every edge hands
    the smaller of its two ends' roots to both roots (hooking), then labels jump to their label's
    label until fixed (pointer jumping); rounds repeat until no label changes, i.e. until the two
    ends of every edge share a root, the smallest node id of their component.
    """
    labels = torch.arange(nodes, device=sources.device)
    if sources.numel() == 0:
        return labels
    while True:
        root_s, root_t = labels.index_select(0, sources), labels.index_select(0, targets)
        smaller = torch.minimum(root_s, root_t)
        updated = labels.clone()
        updated.scatter_reduce_(0, root_s, smaller, "amin")
        updated.scatter_reduce_(0, root_t, smaller, "amin")
        while True:
            jumped = updated.index_select(0, updated)
            if torch.equal(jumped, updated):
                break
            updated = jumped
        if torch.equal(updated, labels):
            return labels
        labels = updated


def _pad_by_owner(endpoints: torch.Tensor, length: torch.Tensor, owner: torch.Tensor, batch: int,
                  max_per_image: int) -> tuple[torch.Tensor, torch.Tensor]:
    """(B, N, 4) segments and (B, N) mask: each image's rows longest first, at most ``max_per_image``."""
    dev = endpoints.device
    order = torch.argsort(length, descending=True, stable=True)
    order = order[torch.argsort(owner[order], stable=True)]
    owner_sorted = owner[order]
    counts = torch.bincount(owner_sorted, minlength=batch)
    first = torch.cumsum(counts, 0) - counts
    rank = torch.arange(order.numel(), device=dev) - first[owner_sorted]
    keep = rank < max_per_image
    n = max(1, min(int(counts.max()) if counts.numel() else 0, max_per_image))
    segments = torch.zeros(batch, n, 4, device=dev)
    mask = torch.zeros(batch, n, dtype=torch.bool, device=dev)
    segments[owner_sorted[keep], rank[keep]] = endpoints[order[keep]].float()
    mask[owner_sorted[keep], rank[keep]] = True
    return segments, mask


def decode_jpeg_batch(data: Sequence[bytes], device: str | torch.device = "cpu") -> list[torch.Tensor]:
    """Decode JPEG files' bytes to grey (1, H, W) uint8 tensors on ``device`` with torchvision
    (``decode_jpeg`` runs on the GPU for a CUDA device).  Needs torchvision (optional)."""
    try:
        from torchvision.io import ImageReadMode, decode_jpeg
    except Exception as exc:  # noqa: BLE001 - missing, or built for another torch (RuntimeError)
        raise RuntimeError(f"decode_jpeg_batch needs a torchvision built for this torch ({torch.__version__}): "
                           f"{type(exc).__name__}: {exc}") from None
    tensors = [torch.frombuffer(bytearray(b), dtype=torch.uint8) for b in data]
    try:
        decoded = decode_jpeg(tensors, mode=ImageReadMode.GRAY, device=device)
    except RuntimeError as exc:
        if "extension" not in str(exc):  # a corrupt JPEG: torchvision's own message
            raise
        raise RuntimeError(f"decode_jpeg_batch needs a torchvision built for this torch ({torch.__version__}): "
                           "its image extension does not load") from None
    return list(decoded)
