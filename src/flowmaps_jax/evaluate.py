"""``python -m flowmaps_jax.evaluate``: the evaluation CLI (:mod:`flowmaps_jax.evaluation.cli`)."""

from __future__ import annotations

import sys

from flowmaps_jax.evaluation.cli import main

if __name__ == "__main__":
    sys.exit(main())
