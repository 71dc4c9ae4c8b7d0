"""``python -m fr_eval COMMAND ...``: the ``fr`` command line with the harness commands (installed
copies; ``fr`` itself finds them through the installation's entry points)."""
import sys

from fr_eval.commands import COMMANDS

from fr_torch.cli.main import main

sys.exit(main(extra_commands=COMMANDS))
