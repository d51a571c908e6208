import sys

from omnispectral.cli import main

sys.exit(main())
