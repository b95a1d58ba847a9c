"""``python -m flowmaps_jax.train``: the training command (:mod:`flowmaps_jax.training.cli`)."""

import sys

from flowmaps_jax.training.cli import main

if __name__ == "__main__":
    sys.exit(main())
