"""Array argument checks: arrays, shapes, real and integer arrays, masks and probabilities.
Shapes and dtypes are read from tracers too; values only when concrete (:func:`is_concrete`).
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from flowmaps_jax.validation.scalars import is_real_dtype

PROB_ATOL = 1e-4
"""Tolerance for probabilities computed in float32 (their sum, masked entries, round-off)."""


def is_concrete(*arrays) -> bool:
    """True when none of ``arrays`` is a tracer, i.e. their values can be checked on the host."""
    return not any(isinstance(a, jax.core.Tracer) for a in arrays)


def check_concrete(what: str, *trees) -> None:
    """``ValueError`` (one line) when a leaf of ``trees`` is a tracer: ``what`` takes concrete
    arrays."""
    if not is_concrete(*jax.tree.leaves(trees)):
        raise ValueError(f"{what} takes concrete arrays (it checks their values and compiles "
                         f"its own programs); call it outside jax.jit / jax.vmap")


def _dtype_words(dtype) -> str:
    """What an array of ``dtype`` holds, in words, for error messages."""
    if dtype == np.bool_:
        return "booleans"
    kind = np.dtype(dtype).kind if not jnp.issubdtype(dtype, jax.dtypes.prng_key) else "key"
    return {"c": "complex numbers", "U": "strings", "S": "bytes", "O": "Python objects",
            "key": "PRNG keys"}.get(kind, f"dtype {dtype}")


def _shape_text(shape: tuple) -> str:
    parts = ["..." if s is Ellipsis else "*" if s is None else str(s) for s in shape]
    return "(" + ", ".join(parts) + ("," if len(parts) == 1 else "") + ")"


def check_shape(name: str, actual: tuple[int, ...], expected: tuple | None,
                reason: str = "") -> None:
    """``actual`` (a shape) must match ``expected`` (None: anything); ``reason`` is for the
    message."""
    if expected is None:
        return
    lead = bool(expected) and expected[0] is Ellipsis
    tail = expected[1:] if lead else expected
    fits = len(actual) >= len(tail) if lead else len(actual) == len(tail)
    if not fits or any(e is not None and a != e
                       for a, e in zip(actual[len(actual) - len(tail):], tail, strict=True)):
        why = f" ({reason})" if reason else ""
        raise ValueError(f"{name} must have shape {_shape_text(expected)}{why}; got "
                         f"{tuple(actual)}")


def _as_array(name: str, value: Any):
    """``value`` itself if it has ``shape`` and ``dtype`` (numpy, jax, tracer), else numpy."""
    if hasattr(value, "shape") and hasattr(value, "dtype"):
        return value
    if isinstance(value, (str, bytes)) or value is None:
        raise ValueError(f"{name} must be a numeric array; got {type(value).__name__} {value!r}")
    try:
        return np.asarray(value)
    except (TypeError, ValueError) as err:  # ragged nesting, unconvertible objects
        raise ValueError(f"{name} must be a numeric array; could not convert "
                         f"{type(value).__name__}: {err}") from None


def check_array(name: str, value: Any, shape: tuple | None = None):
    """``value`` if it is an array (numpy, jax or a tracer), not a list or a scalar; the
    optional ``shape`` is matched (``None``: any size; a leading ``...``: any leading dims)."""
    if not (isinstance(value, (np.ndarray, np.generic, jax.Array))
            or isinstance(value, jax.core.Tracer)):
        raise ValueError(f"{name} must be an array (numpy or jax); got {type(value).__name__}")
    check_shape(name, tuple(value.shape), shape)
    return value


def check_real_array(name: str, value: Any, shape: tuple | None = None, *, finite: bool = True,
                     low: float | None = None, high: float | None = None, what: str = ""):
    """A real-valued (integer or float) array, finite when ``finite``, in ``[low, high]`` when
    given (``what`` for that message); numpy for concrete inputs, else the input itself.
    """
    arr = _as_array(name, value)
    if not is_real_dtype(arr.dtype):
        raise ValueError(f"{name} must hold real numbers; got {_dtype_words(arr.dtype)}")
    check_shape(name, tuple(arr.shape), shape)
    if not (finite or low is not None or high is not None) or not is_concrete(arr):
        return arr
    arr = np.asarray(arr)
    if finite and not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} contains NaN or inf")
    if arr.size and ((low is not None and arr.min() < low)
                     or (high is not None and arr.max() > high)):
        span = (f"[{low}, {high}]" if low is not None and high is not None
                else f">= {low}" if low is not None else f"<= {high}")
        why = f" ({what})" if what else ""
        raise ValueError(f"{name} must lie in {span}{why}; got values in "
                         f"{arr.min():.6g}..{arr.max():.6g}")
    return arr


def check_int_array(name: str, value: Any, low: int | None = None, high=None, *,
                    shape: tuple | None = None, high_name: str | None = None):
    """An integer array (not floats or booleans) with every value in ``low..high`` (None:
    unbounded; ``high`` may broadcast, named ``high_name``); numpy for concrete inputs.
    """
    arr = _as_array(name, value)
    if arr.dtype == np.bool_ or not jnp.issubdtype(arr.dtype, jnp.integer):
        raise ValueError(f"{name} must hold integers; got {_dtype_words(arr.dtype)}")
    check_shape(name, tuple(arr.shape), shape)
    if (low is None and high is None) or not is_concrete(arr, high):
        return arr
    arr = np.asarray(arr)
    if arr.size == 0:
        return arr
    bad = np.zeros(arr.shape, bool) if low is None else arr < low
    if high is not None:
        try:
            bad = bad | (arr > np.asarray(high))
        except ValueError:
            raise ValueError(f"{name} {arr.shape} does not broadcast against "
                             f"{high_name or 'its bound'} {np.shape(high)}") from None
    if np.any(bad):
        top = high_name if high_name is not None else ("" if high is None else high)
        range_text = (f">= {low}" if high is None else f"<= {top}" if low is None
                      else f"in {low}..{top}")
        raise ValueError(f"{name} must lie {range_text}; got values in "
                         f"{arr.min()}..{arr.max()}")
    return arr


def check_mask(name: str, value: Any, shape: tuple | None = None):
    """A 0/1 mask as booleans: bool arrays pass; integer or float arrays only if every value is
    0 or 1 (0.5 or 2 is refused). Returns a bool numpy array when concrete."""
    arr = _as_array(name, value)
    if not (arr.dtype == np.bool_ or is_real_dtype(arr.dtype)):
        raise ValueError(f"{name} must be a mask of booleans (or 0/1); got "
                         f"{_dtype_words(arr.dtype)}")
    check_shape(name, tuple(arr.shape), shape)
    if not is_concrete(arr):
        return arr
    arr = np.asarray(arr)
    if arr.dtype != np.bool_:
        odd = arr[(arr != 0) & (arr != 1)]
        if odd.size:
            raise ValueError(f"{name} must hold only 0/1 (or booleans); got {odd.flat[0].item()!r}")
    return arr.astype(bool)


def check_probabilities(name: str, value: Any, shape: tuple | None = None, *,
                        normalised: bool = True, atol: float = 1e-6, min_value: float = 0.0,
                        support: Any = None, support_name: str = "support") -> np.ndarray:
    """Probabilities over the last axis as float64: finite reals at least ``min_value``, summing
    to 1 within ``atol`` if ``normalised``, mass only where ``support`` (..., K') (bool, over the
    first K' entries) allows, named ``support_name``. A tracer is returned as it is."""
    if isinstance(value, (list, tuple)) and any(
            isinstance(v, (str, bytes, bool, np.bool_, complex)) for v in value):
        raise ValueError(f"{name} must be real numbers; got {value!r}")
    arr = check_real_array(name, value, shape, finite=False)
    if not is_concrete(arr, support):
        return arr
    p = np.asarray(arr, np.float64)
    got = f"; got {value!r}" if isinstance(value, (list, tuple)) or p.size <= 16 else ""
    if not np.all(np.isfinite(p)):
        raise ValueError(f"{name} contains NaN or inf{got}")
    if np.any(p < min_value):
        raise ValueError(f"{name} has negative probabilities (min {p.min():.3g}); they must be "
                         f"non-negative{got}")
    if normalised and p.ndim:
        total = p.sum(axis=-1)
        if np.any(np.abs(total - 1.0) > atol):
            worst = total.ravel()[np.argmax(np.abs(total - 1.0).ravel())]
            over = " over its last axis" if p.ndim > 1 else ""
            raise ValueError(f"{name} must sum to 1{over} (within {atol:g}); found a sum of "
                             f"{worst:.12g}{got}")
    if support is not None:
        inside = np.asarray(support, bool)
        if np.any(np.abs(np.where(inside, 0.0, p[..., :inside.shape[-1]])) > atol):
            raise ValueError(f"{name} puts probability where {support_name} is False")
    return p
