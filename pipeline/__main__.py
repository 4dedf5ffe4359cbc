"""``python -m pipeline``: the command-line interface (see ``pipeline.cli``)."""

import sys

from pipeline.cli import main

sys.exit(main())
