"""``python -m fr_torch.cli``: the ``fr`` command."""
import sys

from fr_torch.cli.main import main

sys.exit(main())
