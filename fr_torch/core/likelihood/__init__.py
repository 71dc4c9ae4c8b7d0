"""Room 3 of the engine, likelihood: how well a camera explains a photo's segments.

* :mod:`~fr_torch.core.likelihood.segments` -- segment batches as the engine takes them (checks,
  the longest-N filter, padding);
* :mod:`~fr_torch.core.likelihood.measures` -- the segments' features and the deviation measures
  (a)-(e) of a segment from a vanishing point;
* :mod:`~fr_torch.core.likelihood.mixture` -- the parameters and the mixture of three Manhattan
  families and a uniform background, the objective ``sum_i len_i log p_i`` with the focal prior,
  posteriors;
* :mod:`~fr_torch.core.likelihood.objective` -- the fused measure-b objective and its analytic
  gradient with respect to the vanishing points;
* :mod:`~fr_torch.core.likelihood.native` and ``kernels_measure_b.c`` -- the same two as C kernels
  on a CPU, loaded and checked bit for bit against the torch path (the check lives in ``mixture``).

May import: geometry, settings, :mod:`fr_torch.core.exact`; not the search, reliability or the estimator.
"""
