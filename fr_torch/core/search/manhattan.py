"""The Manhattan fit (fR, Fast-fR): the engine's stages on the mixture likelihood of a pinhole camera.

Stage 1 scores the k^4 grid over pan, pitch, roll and the focal length (:mod:`~fr_torch.core.search.grid`,
each image's ``grid_segments`` longest segments), keeps the best ``top_l`` points, adds each one's
best point along its focal ridge and sharpens them by lattice passes
(:mod:`~fr_torch.core.search.passes`); stage 2 refines them all with Adam inside the box
(:mod:`~fr_torch.core.search.refine`), and the better of each start and its refinement wins.  The lens
fit (:mod:`~fr_torch.core.search.lens`) runs the same stages with k as a fifth parameter.
"""
from __future__ import annotations

import time

import torch

from fr_torch.core.likelihood.measures import SegmentFeatures
from fr_torch.core.likelihood.mixture import MixtureLikelihood
from fr_torch.core.search.grid import grid_hypotheses, parameter_box, score_grid, select_starts
from fr_torch.core.search.passes import SearchResult, subdivide_starts, sweep_focal
from fr_torch.core.search.refine import refine_starts
from fr_torch.core.settings.config import SearchConfig


def search_manhattan(likelihood: MixtureLikelihood, features: SegmentFeatures, config: SearchConfig,
                     long_side: torch.Tensor, known_focal: torch.Tensor | None, iterations: int,
                     fast: bool) -> SearchResult:
    """The whole search (module docstring) for the images of ``features``.

    ``long_side`` (B,) pixels (the FOV range is on the long side); ``known_focal`` (B,) pixels or
    None; ``iterations``, ``fast``: the refinement's steps and mode.  Returns rows
    [pan, pitch, roll, f] (B, 4).
    """
    t0 = time.perf_counter()
    device = features.weight.device
    hypotheses = grid_hypotheses(config, long_side.to(device), None if known_focal is None else known_focal.to(device))
    grid_features = features.longest(config.grid_segments) if config.grid_segments else features
    grid_scores = score_grid(likelihood, grid_features, hypotheses, config.max_chunk_elements,
                             vertical_block=config.grid_points_per_dim)
    grid_counts = grid_features.mask.sum(-1)
    starts, top_scores = select_starts(config, grid_scores, hypotheses)
    lower, upper = parameter_box(config, long_side, known_focal)
    starts, top_scores = sweep_focal(likelihood, features, starts, top_scores, config, lower, upper)
    starts, top_scores = subdivide_starts(likelihood, features, starts, top_scores, config, lower, upper)
    grid_seconds = time.perf_counter() - t0
    params, scores, tied = refine_starts(likelihood, features, starts, top_scores, lower, upper, config, iterations,
                                         fast)
    return SearchResult(params, scores, grid_scores, grid_counts, grid_seconds, tied, lower, upper)
