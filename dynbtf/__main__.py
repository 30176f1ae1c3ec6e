"""``python -m dynbtf ...``: the same command line as ``dynbtf ...``."""

import sys

from .cli.main import main

sys.exit(main())
