"""Entry-point groups through which packages above the core plug into it.

The core (``fr_torch``) never names the evaluation harness or the baselines; they register
themselves in ``pyproject.toml``:

* ``fr_torch.commands``: ``fr`` subcommands; name = command, value = an object ``(module, help)``
  where ``module`` provides ``add_arguments(parser)`` and ``run(args) -> int``
  (see :mod:`fr_torch.cli`);
* ``fr_torch.calibrators``: modules that register calibration methods when imported
  (see :mod:`fr_torch.interface`).

A source checkout that is not installed has no entry points: there only the core's own commands
and methods exist (``python -m eval`` runs the harness commands from a checkout).
"""
from __future__ import annotations

from importlib import metadata

COMMANDS_GROUP = "fr_torch.commands"
CALIBRATORS_GROUP = "fr_torch.calibrators"


def entry_points(group: str) -> dict[str, metadata.EntryPoint]:
    """Entry points of ``group`` by name (the first one wins when a package is seen twice)."""
    found: dict[str, metadata.EntryPoint] = {}
    for entry in metadata.entry_points(group=group):
        found.setdefault(entry.name, entry)
    return found
