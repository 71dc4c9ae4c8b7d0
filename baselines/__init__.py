"""Baseline calibration methods behind the common :class:`fr_torch.plugins.interface.Calibrator` interface.

They are found by name through the entry points of group ``fr_torch.calibrators`` declared in
pyproject.toml, exactly like a third-party plug-in: ``lee2009`` (orthogonal VP triplet over a focal
sweep), ``simon2018`` (a-contrario horizon-first VPs), ``ctrlc`` and ``ctrlc-retrained`` (CTRL-C
through onnxruntime, two trainings, weights supplied by the user; ``fr export-ctrlc`` makes them),
``external`` and ``hold-geoffroy2018`` (per-image predictions from a CSV) and ``prior`` (60 deg HFOV,
upright camera).  Shared VP geometry lives in :mod:`fr_baselines.vp_geometry`.
"""
