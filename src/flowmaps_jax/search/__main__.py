"""``python -m flowmaps_jax.search`` (see :mod:`flowmaps_jax.search.cli`)."""

import sys

from flowmaps_jax.search.cli import main

if __name__ == "__main__":
    sys.exit(main())
