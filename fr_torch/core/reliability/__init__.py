"""Room 5 of the engine, reliability: how far each estimate can be trusted.

* :mod:`~fr_torch.core.reliability.cues` -- the cues of an estimate (the paper's three, the focal
  prior's share, the focal profile, the spreads), computed from the likelihood and the search;
* :mod:`~fr_torch.core.reliability.model` -- the error model (cues -> predicted errors) and its
  shipped models;
* :mod:`~fr_torch.core.reliability.bounds` -- the 90 % bounds behind ``reliable`` (the promise)
  and the horizon's bound;
* :mod:`~fr_torch.core.reliability.sanity` -- the sanity checks (too few segments, not Manhattan,
  at the search box's edge, lines that bend, nothing non-finite).

May import: search, likelihood, settings, geometry, :mod:`fr_torch.core.exact`; not the estimator.
"""
