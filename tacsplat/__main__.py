"""``python -m tacsplat``: the same as the ``tacsplat`` command."""

import sys

from tacsplat.cli import main

sys.exit(main())
