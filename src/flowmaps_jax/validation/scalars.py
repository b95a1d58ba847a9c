"""Scalar argument checks: ints, reals, flags, choices, instances, seeds and PRNG keys, each
returning the Python ``int``/``float``/``bool`` or typed key to go on with."""

from __future__ import annotations

import argparse
import math
import numbers
import operator
import re
from collections.abc import Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

INT32_MAX = 2**31 - 1
"""Largest value an int32 array (every integer the simulator and the model use) can hold."""

FLOAT32_TINY = float(np.finfo(np.float32).tiny)
"""The smallest normal float32 (about 1.18e-38): a real that must be > 0 is refused below it."""

SEED_MAX = 2**32 - 1
"""JAX seeds are 32-bit: ``jax.random.key(2**32)`` is the same key as ``key(0)``."""


def is_real_dtype(dtype) -> bool:
    """Whether ``dtype`` holds real numbers (integers or floats; not booleans, complex, text)."""
    return dtype is not None and dtype != np.bool_ and (
        jnp.issubdtype(dtype, jnp.integer) or jnp.issubdtype(dtype, jnp.floating))


def _interval(low, high, low_open: bool = False, high_open: bool = False) -> str:
    if high is None:
        return f"> {low}" if low_open else f">= {low}"
    if low is None:
        return f"< {high}" if high_open else f"<= {high}"
    return f"in {'(' if low_open else '['}{low}, {high}{')' if high_open else ']'}"


def check_int(name: str, value: Any, minimum: int | None = 1, maximum: int | None = None) -> int:
    """``value`` (an integer, not a bool or float) as a Python int in ``minimum..maximum``
    (None: unbounded), else ``ValueError``."""
    bounds = ("" if minimum is None and maximum is None
              else f" >= {minimum}" if maximum is None
              else f" <= {maximum}" if minimum is None else f" in {minimum}..{maximum}")
    if isinstance(value, (bool, np.bool_)) or getattr(value, "dtype", None) == np.bool_:
        raise ValueError(f"{name} must be an int{bounds}; got {value!r}")
    try:
        number = operator.index(value)
    except TypeError:
        raise ValueError(f"{name} must be an int{bounds}; got {type(value).__name__} "
                         f"{value!r}") from None
    if (minimum is not None and number < minimum) or (maximum is not None and number > maximum):
        raise ValueError(f"{name} must be an int{bounds}; got {number}")
    return number


def check_real(name: str, value: Any, low: float | None = None, high: float | None = None, *,
               low_open: bool = False, high_open: bool = False) -> float:
    """``value`` (a real, not a bool) as a finite Python float within the bounds (``*_open``
    exclude them; > 0 means at least :data:`FLOAT32_TINY`), else ``ValueError``."""
    where = "" if low is None and high is None else " " + _interval(low, high, low_open,
                                                                       high_open)
    if isinstance(value, (bool, np.bool_)) or not (
            isinstance(value, numbers.Real)
            or (getattr(value, "shape", None) == () and is_real_dtype(value.dtype))):
        raise ValueError(f"{name} must be a finite real number{where}; got "
                         f"{type(value).__name__} {value!r}")
    try:
        number = float(value)
    except (OverflowError, TypeError, ValueError):
        number = math.inf
    if not math.isfinite(number):
        raise ValueError(f"{name} must be a finite real number{where}; got {value!r}")
    if low == 0 and low_open and 0 < number < FLOAT32_TINY:  # a positive scale, 0 in float32
        raise ValueError(f"{name} must be{where} and at least {FLOAT32_TINY:.3g} (the smallest "
                         f"normal float32; smaller ones underflow to 0 in computation); got "
                         f"{number!r}")
    too_low = low is not None and (number <= low if low_open else number < low)
    too_high = high is not None and (number >= high if high_open else number > high)
    if too_low or too_high:
        raise ValueError(f"{name} must be{where}; got {number!r}")
    return number


def check_flag(name: str, value: Any) -> bool:
    """``value`` as a bool: only ``True``/``False`` (or numpy bools) pass, not "yes" or 1."""
    if not isinstance(value, (bool, np.bool_)):
        raise ValueError(f"{name} must be True or False; got {type(value).__name__} {value!r}")
    return bool(value)


def check_choice(name: str, value: Any, choices: Sequence[Any]) -> Any:
    """``value`` if it is one of ``choices`` (of the same type: 1 is not "1", True is not 1)."""
    for choice in choices:
        if (isinstance(value, type(choice)) and isinstance(value, bool) == isinstance(choice, bool)
                and value == choice):
            return value
    raise ValueError(f"{name} must be one of {tuple(choices)}; got {value!r}")


def check_instance(name: str, value: Any, cls: type | tuple[type, ...]) -> Any:
    """``value`` if it is an instance of ``cls``, else ``ValueError`` naming both types."""
    if not isinstance(value, cls):
        names = " or ".join(c.__name__ for c in (cls if isinstance(cls, tuple) else (cls,)))
        raise ValueError(f"{name} must be a {names}; got {type(value).__name__}")
    return value


def check_seed(name: str, value: Any) -> int:
    """A PRNG seed: an int in 0..2**32 − 1 (larger ones would alias smaller seeds in JAX)."""
    return check_int(name, value, 0, SEED_MAX)


def check_key(key: Any, name: str = "key", shapes: Sequence[tuple[int, ...]] = ((),)
              ) -> jax.Array:
    """A PRNG key (typed, or raw uint32 wrapped) as a typed key of one of ``shapes``."""
    allowed = " or ".join(str(tuple(s)) for s in shapes)
    if isinstance(key, jax.Array) and jnp.issubdtype(key.dtype, jax.dtypes.prng_key):
        typed = key
    else:
        shape, dtype = getattr(key, "shape", None), getattr(key, "dtype", None)
        if dtype != np.uint32 or shape is None or len(shape) < 1 or shape[-1] != 2:
            raise ValueError(f"{name} must be a JAX PRNG key (jax.random.key(seed) or "
                             f"jax.random.PRNGKey(seed)); got {type(key).__name__} "
                             f"with shape {shape} and dtype {dtype}")
        typed = jax.random.wrap_key_data(jnp.asarray(key))  # legacy raw key -> typed key
    if tuple(typed.shape) not in {tuple(s) for s in shapes}:
        raise ValueError(f"{name} must be a key array of shape {allowed}; got shape "
                         f"{tuple(typed.shape)}")
    return typed


_ASCII_INT = re.compile(r"[+-]?[0-9]+")


def ascii_int(text: str) -> int:
    """An ``argparse`` type: an integer written with ASCII digits (``int`` also reads "٢" and
    "1_0"); ``argparse.ArgumentTypeError`` otherwise, which argparse reports with the flag."""
    if not _ASCII_INT.fullmatch(text.strip()):
        raise argparse.ArgumentTypeError(f"expected an integer (ASCII digits); got {text!r}")
    return int(text)


def ascii_float(text: str) -> float:
    """An ``argparse`` type: a number written in ASCII, as :func:`ascii_int`."""
    try:
        if text.isascii() and "_" not in text:
            return float(text)
    except ValueError:
        pass
    raise argparse.ArgumentTypeError(f"expected a number (ASCII digits); got {text!r}")


def int_list(text: str) -> list[int]:
    """An ``argparse`` type: comma-separated ASCII integers (``"1,4,16"`` -> [1, 4, 16]), no
    empty item; ``argparse.ArgumentTypeError`` otherwise."""
    items = [item.strip() for item in text.split(",")]
    if not text.strip():
        raise argparse.ArgumentTypeError(f"expected at least one integer; got {text!r}")
    if not all(_ASCII_INT.fullmatch(item) for item in items):
        raise argparse.ArgumentTypeError(f"expected comma-separated integers (ASCII digits, no "
                                         f"empty item); got {text!r}")
    return [int(item) for item in items]
