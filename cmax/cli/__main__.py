"""``python -m cmax.cli``: the ``cmax`` console script."""
import sys

from cmax.cli import main

sys.exit(main())
