"""``python -m fr_eval.bench``: ``fr bench`` (:mod:`fr_eval.bench.command`)."""
import sys

from fr_eval.bench.command import main

sys.exit(main())
