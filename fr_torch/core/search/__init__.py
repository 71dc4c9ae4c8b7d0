"""Room 4 of the engine, search: one engine -- grid, lattice passes, refinement -- and the fits that use it.

The engine:

* :mod:`~fr_torch.core.search.grid` -- the search box, the k^4 grid of hypotheses and its scores,
  the best starts;
* :mod:`~fr_torch.core.search.passes` -- the focal sweep, the coarse-to-fine lattice passes, the tie
  rules and :class:`~fr_torch.core.search.passes.SearchResult`;
* :mod:`~fr_torch.core.search.refine` -- Adam in the unit box
  (:func:`~fr_torch.core.search.refine.adam_in_box`, the one refinement loop) and the chain rule
  from vanishing points to parameters.

The fits, each a choice of parameters, box and objective handed to the engine:

* :mod:`~fr_torch.core.search.manhattan` -- fR / Fast-fR's mixture fit;
* :mod:`~fr_torch.core.search.lens` -- the same with the division model's k as a fifth parameter.

May import: likelihood, settings, geometry, :mod:`fr_torch.core.exact`; not reliability or the estimator.
"""
