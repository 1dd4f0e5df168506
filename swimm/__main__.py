"""``python -m swimm``: the `swimm` command line."""

import sys

from swimm.cli import main

sys.exit(main())
