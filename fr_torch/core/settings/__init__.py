"""Room 2 of the engine, settings: what a user asks for, checked and parsed once into types.

* :mod:`~fr_torch.core.settings.checks` -- input checks with one-line errors
  (:class:`~fr_torch.errors.FRInputError`);
* :mod:`~fr_torch.core.settings.fov` -- :class:`~fr_torch.core.settings.fov.FovRange`, the search's
  field-of-view range and its focal bounds;
* :mod:`~fr_torch.core.settings.distortion` -- the lens setting
  (:class:`~fr_torch.core.settings.distortion.DistortionSetting`: pinhole, division or auto);
* :mod:`~fr_torch.core.settings.config` -- :class:`~fr_torch.core.settings.config.Mode`,
  :class:`~fr_torch.core.settings.config.SearchConfig` (grid, passes, refinement, lens, extra
  families) and :class:`~fr_torch.core.settings.config.FamiliesConfig`.

May import: geometry, :mod:`fr_torch.core.exact`, :mod:`fr_torch.errors`, :mod:`fr_torch.resources`.
"""
