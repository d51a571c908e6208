"""``python -m omnispectral``: the command-line interface (same as the ``omnispectral`` command)."""

import sys

from omnispectral.cli import main

sys.exit(main())
