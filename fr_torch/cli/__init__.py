"""The ``fr`` command line: one module per command, the shared option groups in
:mod:`fr_torch.cli.options`."""
from fr_torch.cli.main import main

__all__ = ["main"]
