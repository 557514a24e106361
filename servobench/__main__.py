"""``python -m servobench``: the ``servobench`` command line."""

import sys

from servobench.bench.cli import main

sys.exit(main())
