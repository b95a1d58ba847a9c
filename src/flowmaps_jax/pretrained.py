"""Deprecated alias of flowmaps_jax.shipped and flowmaps_jax.export, removed next release."""

import sys

from flowmaps_jax.predictor import load_pretrained  # noqa: F401
from flowmaps_jax.shipped import (  # noqa: F401
    MAX_BYTES,
    MAX_META_BYTES,
    NAMES,
    PRETRAINED_DIR,
    UNKNOWN,
    WHICH,
    available,
    check_name,
    describe,
)

_EXPORT = ("export_pretrained", "main", "EXIT_USAGE", "EXIT_WRITE_FAILED")


def __getattr__(name: str):
    if name in _EXPORT:  # the exporter imports the training code: only when asked for
        from flowmaps_jax import export

        return getattr(export, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


if __name__ == "__main__":
    from flowmaps_jax.export import main

    sys.exit(main())
