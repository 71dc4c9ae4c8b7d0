"""``python -m eval COMMAND ...``: the ``fr`` command line with the harness commands, for a source
checkout that is not pip-installed (installed, ``fr`` finds them through entry points)."""
import sys

import baselines  # noqa: F401  (registers the baseline methods; installed: the fr_torch.calibrators entry point)
from eval.commands import COMMANDS
from fr_torch.cli import main

sys.exit(main(extra_commands=COMMANDS))
