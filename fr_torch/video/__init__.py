"""Video: online recalibration (fusion of per-frame estimates) and frame sources for ``fr track``."""
