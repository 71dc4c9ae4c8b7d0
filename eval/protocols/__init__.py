"""The evaluation protocols: ``fr eval`` (:mod:`.run_eval`), leave one dataset out (:mod:`.lodo`,
:mod:`.lodo_reliability`), training and fitting (:mod:`.reliability_train`, :mod:`.fit_likelihood`) and
the studies built on them (shared focal, focal fusion, resolution)."""
