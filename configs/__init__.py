"""Shipped configuration (data only): installed as the package ``fr_torch.configs``; read it through
:func:`fr_torch.resources.config_dir`."""
