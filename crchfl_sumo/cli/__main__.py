"""`python -m crchfl_sumo.cli`: the same as the `crchfl-sumo` console script."""

import sys

from crchfl_sumo.cli import main

sys.exit(main())
