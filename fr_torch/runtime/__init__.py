"""The application layer: the public :class:`~fr_torch.runtime.estimator.FREstimator` on images,
the decode + detect + search pipeline over worker processes, device policy and result output."""
