"""Room 1 of the engine, geometry: the camera model every other room speaks.

* :mod:`~fr_torch.core.geometry.conventions` -- pixel, camera and world frames, angles, rotations,
  vanishing points ``K R[:, i]``, the image centre, Manhattan symmetries;
* :mod:`~fr_torch.core.geometry.horizon` -- the horizon line, its border crossings, the
  :class:`~fr_torch.core.geometry.horizon.Horizon` value;
* :mod:`~fr_torch.core.geometry.camera` -- the :class:`~fr_torch.core.geometry.camera.Camera`
  value type and the records that read K, hfov and angles from it;
* :mod:`~fr_torch.core.geometry.params` -- the search's parameter rows ``[pan, pitch, roll, f(, k)]``;
* :mod:`~fr_torch.core.geometry.lens` -- the division model of a wide-angle lens;
* :mod:`~fr_torch.core.geometry.vanishing` -- ranked vanishing points and Atlanta families.

May import: :mod:`fr_torch.core.exact` and :mod:`fr_torch.errors`; nothing of the rooms above it
(settings, likelihood, search, reliability, the estimator).
"""
