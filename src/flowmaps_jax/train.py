"""``python -m flowmaps_jax.train``: the training command (:mod:`flowmaps_jax.training.loop`)."""

import sys

from flowmaps_jax.training.loop import main

if __name__ == "__main__":
    sys.exit(main())
