"""``python -m pipelines.cli``: the ``radarseg`` command."""

import sys

from pipelines.cli import main

sys.exit(main())
