"""Argument checks shared by the public APIs: run on the host, before anything is jitted."""

from __future__ import annotations

from typing import Any

import jax
import numpy as np


def check_int(name: str, value: Any, minimum: int = 1) -> int:
    """``value`` as a Python int, or ``ValueError`` naming ``name`` if it is not an int ≥ minimum.

    Booleans are refused (``True`` is an int to Python but never a count here).
    """
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < minimum:
        raise ValueError(f"{name} must be an int >= {minimum}; got {value!r}")
    return int(value)


def is_concrete(*arrays) -> bool:
    """True when none of ``arrays`` is a tracer, i.e. their values can be checked on the host."""
    return not any(isinstance(a, jax.core.Tracer) for a in arrays)
