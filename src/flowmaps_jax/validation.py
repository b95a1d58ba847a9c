"""Argument checks shared by the public APIs: run on the host, before anything is jitted.

One function per concept. Each raises ``ValueError`` whose message starts with the argument's
name and says what was expected and what was given; each returns the value in the form the
caller should go on with (a Python ``int``/``float``/``bool``, a numpy array, a typed key, a path
string). Array checks read only ``shape`` and ``dtype`` of tracers (values are checked when the
array is concrete), so a public function may run them and still be traced by ``jax.jit``; the
jitted cores behind the public functions do not check again.

Scalars: :func:`check_int`, :func:`check_real`, :func:`check_flag`, :func:`check_choice`,
:func:`check_instance`, :func:`check_seed`, :func:`check_key`.
Arrays: :func:`check_array`, :func:`check_real_array`, :func:`check_int_array`,
:func:`check_mask`, :func:`check_probabilities`.
Files: :func:`check_path`, :func:`check_file`, :func:`check_dir`, :func:`check_output_file`,
:func:`check_output_dir`.
Names: :func:`check_plain_name` (a preset or file name, a metadata field: no path, no markup).
Untrusted files: :func:`read_npz` (member names whitelisted, declared sizes checked before
anything is decompressed, no pickles).
Resources: :func:`array_bytes`, :func:`memory_limit`, :func:`flops_limit`,
:func:`check_request_size`, :func:`check_resources`, :func:`network_flops`,
:func:`solver_evaluations`. Every size that scales memory or time goes through
:func:`check_resources` before anything runs: a request above the budget is a ``ValueError``
naming it, the estimate and the limit. The budgets: memory, :data:`MAX_BYTES_ENV` (default the
accelerator's memory, else the host's); work, :data:`MAX_FLOPS_ENV` (default
:data:`DEFAULT_MAX_FLOPS` floating-point operations per uninterruptible call).
"""

from __future__ import annotations

import functools
import math
import numbers
import operator
import os
import re
import zipfile
from collections.abc import Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

INT32_MAX = 2**31 - 1
"""Largest value an int32 array (every integer the simulator and the model use) can hold."""

SEED_MAX = 2**32 - 1
"""JAX seeds are 32-bit: ``jax.random.key(2**32)`` is the same key as ``key(0)``."""


def is_concrete(*arrays) -> bool:
    """True when none of ``arrays`` is a tracer, i.e. their values can be checked on the host."""
    return not any(isinstance(a, jax.core.Tracer) for a in arrays)


# ------------------------------------------------------------------------------ scalars


def _interval(low, high, low_open: bool = False, high_open: bool = False) -> str:
    if high is None:
        return f"> {low}" if low_open else f">= {low}"
    if low is None:
        return f"< {high}" if high_open else f"<= {high}"
    return f"in {'(' if low_open else '['}{low}, {high}{')' if high_open else ']'}"


def check_int(name: str, value: Any, minimum: int | None = 1, maximum: int | None = None) -> int:
    """``value`` as a Python int in ``minimum..maximum`` (None: unbounded), else ``ValueError``.

    Python and numpy integers and 0-d integer arrays pass; booleans (an int to Python but never
    a count here), floats (even 3.0) and strings do not.
    """
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
    """``value`` as a finite Python float within the bounds, else ``ValueError``.

    Python and numpy real numbers (and 0-d real arrays) pass; booleans, complex numbers,
    strings, NaN and ±inf do not. ``low_open``/``high_open`` exclude the bound itself.
    """
    where = "" if low is None and high is None else " " + _interval(low, high, low_open,
                                                                       high_open)
    if isinstance(value, (bool, np.bool_)) or not (
            isinstance(value, numbers.Real)
            or (getattr(value, "shape", None) == () and _is_real_dtype(value.dtype))):
        raise ValueError(f"{name} must be a finite real number{where}; got "
                         f"{type(value).__name__} {value!r}")
    try:
        number = float(value)
    except (OverflowError, TypeError, ValueError):
        number = math.inf
    if not math.isfinite(number):
        raise ValueError(f"{name} must be a finite real number{where}; got {value!r}")
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
    """A PRNG key (or key array) as a typed key of one of the allowed key-array ``shapes``.

    Typed keys (``jax.random.key``) pass unchanged; raw uint32 keys (``jax.random.PRNGKey``,
    trailing dim 2) are wrapped, so both kinds share compiled code. Works on tracers.
    """
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


# ------------------------------------------------------------------------------ arrays


def _is_real_dtype(dtype) -> bool:
    return dtype is not None and dtype != np.bool_ and (
        jnp.issubdtype(dtype, jnp.integer) or jnp.issubdtype(dtype, jnp.floating))


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


def _check_shape(name: str, actual: tuple[int, ...], expected: tuple | None) -> None:
    """``expected``: sizes, ``None`` for any size, a leading ``...`` for any leading dims."""
    if expected is None:
        return
    lead = bool(expected) and expected[0] is Ellipsis
    tail = expected[1:] if lead else expected
    fits = len(actual) >= len(tail) if lead else len(actual) == len(tail)
    if fits:
        fits = all(e is None or a == e for a, e in zip(actual[len(actual) - len(tail):], tail,
                                                       strict=True))
    if not fits:
        raise ValueError(f"{name} must have shape {_shape_text(expected)}; got {tuple(actual)}")


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
    _check_shape(name, tuple(value.shape), shape)
    return value


def check_real_array(name: str, value: Any, shape: tuple | None = None, *, finite: bool = True):
    """A real-valued (integer or float) array: booleans, complex numbers, strings and objects
    are refused, as are NaN and ±inf when ``finite`` (values of concrete arrays only).

    Returns a numpy array for concrete inputs with values checked, else the input itself.
    """
    arr = _as_array(name, value)
    if not _is_real_dtype(arr.dtype):
        raise ValueError(f"{name} must hold real numbers; got {_dtype_words(arr.dtype)}")
    _check_shape(name, tuple(arr.shape), shape)
    if not finite or not is_concrete(arr):
        return arr
    arr = np.asarray(arr)
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} contains NaN or inf")
    return arr


def check_int_array(name: str, value: Any, low: int | None = None, high=None, *,
                    shape: tuple | None = None, high_name: str | None = None):
    """An integer array with every value in ``low..high`` (inclusive; None: unbounded).

    ``high`` may be an array broadcasting against ``value`` (each value below its own bound);
    name it with ``high_name`` for the message. Floats (even 3.0) and booleans are refused.
    Values are checked on concrete arrays only; returns numpy for those, else the input.
    """
    arr = _as_array(name, value)
    if arr.dtype == np.bool_ or not jnp.issubdtype(arr.dtype, jnp.integer):
        raise ValueError(f"{name} must hold integers; got {_dtype_words(arr.dtype)}")
    _check_shape(name, tuple(arr.shape), shape)
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
    if not (arr.dtype == np.bool_ or _is_real_dtype(arr.dtype)):
        raise ValueError(f"{name} must be a mask of booleans (or 0/1); got "
                         f"{_dtype_words(arr.dtype)}")
    _check_shape(name, tuple(arr.shape), shape)
    if not is_concrete(arr):
        return arr
    arr = np.asarray(arr)
    if arr.dtype != np.bool_:
        odd = arr[(arr != 0) & (arr != 1)]
        if odd.size:
            raise ValueError(f"{name} must hold only 0/1 (or booleans); got {odd.flat[0].item()!r}")
    return arr.astype(bool)


def check_probabilities(name: str, value: Any, shape: tuple | None = None, *,
                        normalised: bool = True, atol: float = 1e-6) -> np.ndarray:
    """Probabilities over the last axis as float64: real numbers (a float32 array passes; strings
    and booleans are refused as such), finite, non-negative and, if ``normalised``, summing to 1
    within ``atol``. ``value`` may be a sequence of numbers or an array; it must be concrete."""
    if isinstance(value, (list, tuple)) and any(
            isinstance(v, (str, bytes, bool, np.bool_, complex)) for v in value):
        raise ValueError(f"{name} must be real numbers; got {value!r}")
    arr = check_real_array(name, value, shape, finite=False)
    p = np.asarray(arr, np.float64)
    if not np.all(np.isfinite(p)):
        raise ValueError(f"{name} contains NaN or inf; got {value!r}")
    if np.any(p < 0):
        raise ValueError(f"{name} must be non-negative; got {value!r}")
    if normalised and p.ndim:
        total = p.sum(axis=-1)
        if np.any(np.abs(total - 1.0) > atol):
            worst = total.ravel()[np.argmax(np.abs(total - 1.0).ravel())]
            raise ValueError(f"{name} must sum to 1; got {value!r} (sum {worst:.6g})")
    return p


# ------------------------------------------------------------------------------ files


def check_path(name: str, value: Any) -> str:
    """``value`` (a str or os.PathLike, not None, a number or bytes) as a non-empty path string."""
    if not isinstance(value, (str, os.PathLike)):
        raise ValueError(f"{name} must be a path (str or os.PathLike); got "
                         f"{type(value).__name__} {value!r}")
    path = os.fspath(value)
    if not isinstance(path, str) or not path:
        raise ValueError(f"{name} must be a non-empty path; got {value!r}")
    return path


def check_file(name: str, value: Any) -> str:
    """An existing, readable regular file; a directory is named as such."""
    path = check_path(name, value)
    if os.path.isdir(path):
        raise ValueError(f"{name} {path!r} is a directory, not a file")
    if not os.path.exists(path):
        raise ValueError(f"{name} {path!r} does not exist")
    if not os.path.isfile(path):
        raise ValueError(f"{name} {path!r} is not a regular file")
    if not os.access(path, os.R_OK):
        raise ValueError(f"{name} {path!r} is not readable")
    return path


def check_dir(name: str, value: Any) -> str:
    """An existing, readable directory; a file where a directory is expected is named as such."""
    path = check_path(name, value)
    if not os.path.exists(path):
        raise ValueError(f"{name} {path!r} does not exist")
    if not os.path.isdir(path):
        raise ValueError(f"{name} {path!r} is a file, not a directory")
    if not os.access(path, os.R_OK | os.X_OK):
        raise ValueError(f"{name} {path!r} is not readable")
    return path


def _existing_parent(path: str) -> str:
    parent = os.path.dirname(os.path.abspath(path))
    while not os.path.exists(parent):
        parent = os.path.dirname(parent)
    return parent


def check_output_file(name: str, value: Any, *, overwrite: bool = True) -> str:
    """A file path that can be written now: its folder exists and is writable, the path is not a
    directory, and (unless ``overwrite``) no file is there yet."""
    path = check_path(name, value)
    if os.path.isdir(path):
        raise ValueError(f"{name} {path!r} is a directory; give a file path")
    folder = os.path.dirname(os.path.abspath(path))
    if not os.path.isdir(folder):
        what = "is not a directory" if os.path.exists(folder) else "does not exist"
        raise ValueError(f"{name} {path!r}: its folder {folder!r} {what}")
    if not os.access(folder, os.W_OK | os.X_OK):
        raise ValueError(f"{name} {path!r}: its folder {folder!r} is not writable")
    if os.path.exists(path):
        if not overwrite:
            raise ValueError(f"{name} {path!r} already exists")
        if not os.access(path, os.W_OK):
            raise ValueError(f"{name} {path!r} exists and is not writable")
    return path


def check_output_dir(name: str, value: Any, *, empty: bool = False) -> str:
    """A directory that exists (or can be created) and is writable; with ``empty``, one that
    holds nothing yet. A path that is a file, or lies under a file, is refused."""
    path = check_path(name, value)
    if os.path.exists(path):
        if not os.path.isdir(path):
            raise ValueError(f"{name} {path!r} is a file, not a directory")
        if not os.access(path, os.W_OK | os.X_OK):
            raise ValueError(f"{name} {path!r} is not writable")
        if empty and os.listdir(path):
            raise ValueError(f"{name} {path!r} is not empty (it holds "
                             f"{', '.join(sorted(os.listdir(path))[:5])}...)")
        return path
    parent = _existing_parent(path)
    if not os.path.isdir(parent):
        raise ValueError(f"{name} {path!r} lies under {parent!r}, which is a file")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise ValueError(f"{name} {path!r} cannot be created: {parent!r} is not writable")
    return path


# ------------------------------------------------------------------------------ names

_PLAIN_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.+-]{0,63}")


def check_plain_name(name: str, value: Any) -> str:
    """``value`` if it is a plain name: 1 to 64 letters, digits, ``_ . + -``, starting with a
    letter or digit (so no path separator, no ``..`` escape, no markup or control character)."""
    if not isinstance(value, str) or not _PLAIN_NAME.fullmatch(value) or ".." in value:
        raise ValueError(f"{name} must be a plain name (letters, digits, '_', '.', '+', '-'; "
                         f"at most 64, no path); got {_short_repr(value)}")
    return value


def _short_repr(value: Any, limit: int = 60) -> str:
    text = repr(value)
    return text if len(text) <= limit else text[:limit] + "..."


# ------------------------------------------------------------------------------ untrusted files


def read_npz(name: str, source: Any, *, allowed: Sequence[str] | None = None,
             required: Sequence[str] = (), max_bytes: int | None = None,
             expected: dict[str, tuple[tuple[int, ...], Any]] | None = None
             ) -> dict[str, np.ndarray]:
    """The arrays of an untrusted ``.npz`` (a path, or its bytes as a file object), read safely.

    Before anything is decompressed: the file must be a zip whose members are ``<key>.npy`` for
    keys in ``allowed`` (None: any key) with ``required`` present, no member twice, and whose
    declared sizes (the zip directory's, then each ``.npy`` header's shape and dtype) add up to at
    most ``max_bytes`` (default :func:`memory_limit`); ``expected`` ({key: (shape, dtype)}) pins
    members exactly. Objects (pickles) are refused. A member that inflates past its declared
    size is refused while reading. Any failure is a ``ValueError`` naming ``name``.
    """
    limit = memory_limit() if max_bytes is None else int(max_bytes)
    try:
        archive = zipfile.ZipFile(source)
    except (OSError, zipfile.BadZipFile, ValueError) as err:
        raise ValueError(f"{name} is not a readable .npz file ({err})") from None
    with archive:
        infos = archive.infolist()
        keys = []
        for info in infos:
            key = info.filename[:-4] if info.filename.endswith(".npy") else None
            if key is None or (allowed is not None and key not in allowed) \
                    or (expected is not None and key not in expected):
                raise ValueError(f"{name} holds an unexpected member {info.filename!r}")
            keys.append(key)
        if len(set(keys)) != len(keys):
            raise ValueError(f"{name} holds a member twice")
        missing = [k for k in (*required, *(expected or {})) if k not in keys]
        if missing:
            raise ValueError(f"{name} is missing arrays {sorted(set(missing))}")
        declared = sum(info.file_size for info in infos)
        if declared > limit:
            raise ValueError(f"{name} declares {declared / 1e9:.3g} GB of arrays, more than the "
                             f"{limit / 1e9:.3g} GB allowed; not reading it")
        arrays = {}
        for info, key in zip(infos, keys, strict=True):
            try:
                with archive.open(info) as member:
                    arrays[key] = _read_npy(member, info.file_size,
                                            None if expected is None else expected[key])
            except (OSError, ValueError, EOFError, zipfile.BadZipFile) as err:
                raise ValueError(f"{name}: member {info.filename!r} is not a valid array "
                                 f"({err})") from None
    return arrays


def _read_npy(member, declared: int, expected) -> np.ndarray:
    """One ``.npy`` member, its header checked against its declared size before the data."""
    version = np.lib.format.read_magic(member)
    readers = {(1, 0): np.lib.format.read_array_header_1_0,
               (2, 0): np.lib.format.read_array_header_2_0}
    if version not in readers:
        raise ValueError(f"unsupported .npy format version {version}")
    shape, fortran, dtype = readers[version](member)
    if dtype.hasobject:
        raise ValueError("it holds Python objects")
    if expected is not None and (tuple(shape) != tuple(expected[0])
                                 or dtype != np.dtype(expected[1])):
        raise ValueError(f"expected shape {tuple(expected[0])} and dtype "
                         f"{np.dtype(expected[1])}; got {tuple(shape)} and {dtype}")
    size = array_bytes(shape, dtype)
    if size > declared:
        raise ValueError(f"its header claims {size} bytes, more than the {declared} declared")
    data = member.read(size + 1)
    if len(data) != size:
        raise ValueError(f"it holds {len(data)} bytes of data where its header says {size}")
    array = np.frombuffer(data, dtype=dtype, count=math.prod(shape) if shape else 1)
    return array.reshape(shape, order="F" if fortran else "C").copy()


# ------------------------------------------------------------------------------ resources

MAX_BYTES_ENV = "FLOWMAPS_MAX_BYTES"
"""Environment variable overriding the memory budget of one request (bytes; ``64G`` etc.)."""
MAX_FLOPS_ENV = "FLOWMAPS_MAX_FLOPS"
"""Environment variable overriding the work budget of one uninterruptible call (FLOPs)."""
DEFAULT_MAX_FLOPS = 10**17
"""Default work budget, by the generous estimates here: about 200 default evaluations of the cpu
preset's models (2 minutes each on a 2-core CPU) or 30 of a paper-size model; it refuses sizes
that would run for days (``--num-steps 10**9``). Raise it with :data:`MAX_FLOPS_ENV`."""
_SUFFIXES = {"": 1, "K": 10**3, "M": 10**6, "G": 10**9, "T": 10**12, "P": 10**15,
             "KI": 2**10, "MI": 2**20, "GI": 2**30, "TI": 2**40, "PI": 2**50}


def _env_budget(variable: str) -> int | None:
    """The positive number in environment ``variable`` (e.g. ``64G``, ``1e12``), None if unset."""
    text = os.environ.get(variable, "").strip()
    if not text:
        return None
    match = re.fullmatch(r"([0-9.eE+]+)\s*([KMGTPkmgtp][Ii]?)?[Bb]?", text)
    try:
        value = float(match.group(1)) * _SUFFIXES[(match.group(2) or "").upper()]
    except (AttributeError, ValueError, KeyError):
        value = math.nan
    if not (math.isfinite(value) and value >= 1):
        raise ValueError(f"{variable} must be a positive number like 64G or 1e12; got {text!r}")
    return int(value)


def array_bytes(shape: Sequence[int], dtype: Any = np.float32) -> int:
    """Bytes of an array of ``shape`` and ``dtype`` (exact Python int, no overflow)."""
    return math.prod(int(s) for s in shape) * np.dtype(dtype).itemsize


@functools.lru_cache(maxsize=1)
def _device_memory() -> int:
    try:
        stats = jax.devices()[0].memory_stats() or {}
    except Exception:  # backends without memory stats
        stats = {}
    if stats.get("bytes_limit"):
        return int(stats["bytes_limit"])
    try:
        return int(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES"))
    except (AttributeError, OSError, ValueError):
        return 16 * 2**30


def memory_limit() -> int:
    """Bytes one request may use: ``$FLOWMAPS_MAX_BYTES`` when set, else the default device's
    memory limit when JAX reports one (accelerators), else the host's physical memory."""
    override = _env_budget(MAX_BYTES_ENV)
    return _device_memory() if override is None else override


def flops_limit() -> int:
    """Floating-point operations one uninterruptible call may take: ``$FLOWMAPS_MAX_FLOPS``
    when set, else :data:`DEFAULT_MAX_FLOPS`."""
    override = _env_budget(MAX_FLOPS_ENV)
    return DEFAULT_MAX_FLOPS if override is None else override


def check_request_size(name: str, num_bytes: int, limit: int | None = None) -> int:
    """``num_bytes`` if it is at most ``limit`` (default :func:`memory_limit`), else a
    ``ValueError`` saying how many GB the request ``name`` would need."""
    limit = memory_limit() if limit is None else int(limit)
    if num_bytes > limit:
        raise ValueError(f"{name} would need about {num_bytes / 1e9:.3g} GB, more than the "
                         f"{limit / 1e9:.3g} GB available ({MAX_BYTES_ENV} overrides it); ask "
                         f"for less or split the request")
    return int(num_bytes)


def check_resources(name: str, *, num_bytes: int = 0, flops: int = 0) -> None:
    """The shared budget check: ``ValueError`` naming ``name`` (the argument and its value)
    when the estimated memory (bytes) or work (FLOPs) is over :func:`memory_limit` /
    :func:`flops_limit`."""
    check_request_size(name, int(num_bytes))
    limit = flops_limit()
    if flops > limit:
        raise ValueError(f"{name} would take about {float(flops):.3g} floating-point operations, "
                         f"more than the budget of {float(limit):.3g} ({MAX_FLOPS_ENV} overrides "
                         f"it); ask for less")


def network_flops(model: Any, kind: str, num_tokens: int) -> tuple[int, int]:
    """(FLOPs of one network evaluation of one query-sample, FLOPs of encoding one map of
    ``num_tokens`` tokens) for a model config (``ModelConfig``; ``kind`` "flowmaps" or "mlp").
    A rough, generous estimate (2 FLOPs per weight use, attention included)."""
    dim, ratio = int(model.dim), int(model.mlp_ratio)
    per_layer = dim * dim * (4 + 2 * ratio)
    encoder = 2 * int(model.encoder_layers) * num_tokens * (per_layer + 2 * num_tokens * dim)
    if kind == "mlp":
        hidden = int(model.baseline_hidden)
        return 2 * (dim * hidden + hidden * hidden + 8 * hidden + 4 * dim * dim), encoder
    blocks = int(model.cdit_blocks)
    return 2 * blocks * (per_layer + 6 * dim * dim + 2 * num_tokens * dim), encoder


def solver_evaluations(num_steps: int, method: str = "midpoint") -> int:
    """Network evaluations of one ODE solve with ``num_steps`` grid points."""
    return (int(num_steps) - 1) * (2 if method == "midpoint" else 1)
