"""Table-driven checks of a config's fields, and of the dicts configs are read back from.

A config dataclass (or a command line, :func:`check_options`) declares one rule per field (a
``{field: rule}`` table) and checks them all with one call, :func:`check_fields`, instead of
one ``check_*`` call per field. A rule is one of the small classes below (:class:`Int`,
:class:`Real`, :class:`Choice`, ...): data describing what a field may hold. Calling a rule
with ``(name, value)`` runs the matching check of :mod:`flowmaps_jax.validation` and returns
the value in the form to go on with; every message still starts with the field's name.
:func:`check_keys` is the one check of a ``from_dict`` argument: a dict whose keys are the
config's fields.
"""

from __future__ import annotations

import contextlib
import contextvars
import dataclasses
import functools
import inspect
from collections.abc import Callable, Collection, Mapping
from typing import Any

from flowmaps_jax.validation.arrays import (
    PROB_ATOL,
    bind_size,
    check_array,
    check_int_array,
    check_mask,
    check_probabilities,
    check_real_array,
    named_sizes,
)
from flowmaps_jax.validation.files import check_plain_name
from flowmaps_jax.validation.scalars import (
    check_choice,
    check_flag,
    check_instance,
    check_int,
    check_key,
    check_real,
    check_seed,
)

Rule = Callable[[str, Any], Any]
"""A field's rule: ``rule(name, value)`` returns the checked value or raises ``ValueError``
whose message starts with ``name``."""


@dataclasses.dataclass(frozen=True)
class Int:
    """An int in ``minimum..maximum`` (:func:`~flowmaps_jax.validation.check_int`); ``why``,
    if given, says what the maximum protects, in the message of a value above it."""

    minimum: int | None = 1
    maximum: int | None = None
    why: str = ""
    size: str | None = None
    """Binds the named size (``"K"``) of the check's :func:`~.arrays.named_sizes` scope."""

    def __call__(self, name: str, value: Any) -> int:
        if self.why and self.maximum is not None:
            number = check_int(name, value, self.minimum)
            if number > self.maximum:
                raise ValueError(f"{name} must be <= {self.maximum} ({self.why}); got {number}")
        else:
            number = check_int(name, value, self.minimum, self.maximum)
        if self.size is not None:
            bind_size(self.size, number, name)
        return number


@dataclasses.dataclass(frozen=True)
class Real:
    """A finite real number within the bounds (:func:`~flowmaps_jax.validation.check_real`)."""

    low: float | None = None
    high: float | None = None
    low_open: bool = False
    high_open: bool = False

    def __call__(self, name: str, value: Any) -> float:
        return check_real(name, value, self.low, self.high, low_open=self.low_open,
                          high_open=self.high_open)


@dataclasses.dataclass(frozen=True)
class Choice:
    """One of ``choices`` (:func:`~flowmaps_jax.validation.check_choice`)."""

    choices: tuple

    def __call__(self, name: str, value: Any) -> Any:
        return check_choice(name, value, self.choices)


@dataclasses.dataclass(frozen=True)
class Flag:
    """``True`` or ``False`` (:func:`~flowmaps_jax.validation.check_flag`)."""

    def __call__(self, name: str, value: Any) -> bool:
        return check_flag(name, value)


@dataclasses.dataclass(frozen=True)
class Seed:
    """A PRNG seed (:func:`~flowmaps_jax.validation.check_seed`)."""

    def __call__(self, name: str, value: Any) -> int:
        return check_seed(name, value)


@dataclasses.dataclass(frozen=True)
class Array:
    """An array (numpy, jax or a tracer) of ``shape`` (:func:`~flowmaps_jax.validation.check_array`;
    ``None`` for any size, a leading ``...`` for any leading dims)."""

    shape: tuple | None = None

    def __call__(self, name: str, value: Any):
        return check_array(name, value, self.shape)


@dataclasses.dataclass(frozen=True)
class RealArray:
    """A real array of ``shape``, finite if ``finite``, within ``[low, high]`` if given
    (:func:`~flowmaps_jax.validation.check_real_array`; ``what`` names the values)."""

    shape: tuple | None = None
    finite: bool = True
    low: float | None = None
    high: float | None = None
    what: str = ""

    def __call__(self, name: str, value: Any):
        return check_real_array(name, value, self.shape, finite=self.finite, low=self.low,
                                high=self.high, what=self.what)


@dataclasses.dataclass(frozen=True)
class IntArray:
    """An integer array in ``low..high`` (:func:`~flowmaps_jax.validation.check_int_array`;
    a bound may be a named size, ``"K-1"``, or an array, named by ``high_name``)."""

    low: int | str | None = None
    high: Any = None
    shape: tuple | None = None
    high_name: str | None = None

    def __call__(self, name: str, value: Any):
        return check_int_array(name, value, self.low, self.high, shape=self.shape,
                               high_name=self.high_name)


@dataclasses.dataclass(frozen=True)
class Distribution:
    """Probabilities over the last axis (:func:`~flowmaps_jax.validation.check_probabilities`)
    of ``shape``, a computed float32 one by default (sums within ``atol``, round-off negatives
    down to ``-atol``); ``support`` names an argument (or field) checked before it, a mask
    marking where mass may lie."""

    shape: tuple | None = None
    atol: float = PROB_ATOL
    support: str | None = None
    normalised: bool = True

    def __call__(self, name: str, value: Any):
        support = None if self.support is None else (_CHECKED.get() or {})[self.support]
        return check_probabilities(name, value, self.shape, atol=self.atol,
                                   min_value=-self.atol, normalised=self.normalised,
                                   support=support, support_name=self.support or "support")


@dataclasses.dataclass(frozen=True)
class Mask:
    """A 0/1 mask as booleans (:func:`~flowmaps_jax.validation.check_mask`)."""

    shape: tuple | None = None

    def __call__(self, name: str, value: Any):
        return check_mask(name, value, self.shape)


@dataclasses.dataclass(frozen=True)
class Key:
    """A PRNG key of one of the key-array ``shapes``, as a typed key
    (:func:`~flowmaps_jax.validation.check_key`)."""

    shapes: tuple = ((),)

    def __call__(self, name: str, value: Any):
        return check_key(value, name, self.shapes)


@dataclasses.dataclass(frozen=True)
class PlainName:
    """A plain name (:func:`~flowmaps_jax.validation.check_plain_name`)."""

    def __call__(self, name: str, value: Any) -> str:
        return check_plain_name(name, value)


@dataclasses.dataclass(frozen=True)
class Instance:
    """An instance of ``cls`` (:func:`~flowmaps_jax.validation.check_instance`)."""

    cls: type | tuple[type, ...]

    def __call__(self, name: str, value: Any) -> Any:
        return check_instance(name, value, self.cls)


@dataclasses.dataclass(frozen=True)
class Text:
    """A non-empty string (with ``strip``, one with something in it other than white space);
    ``what`` names it in the message, e.g. "a checkpoint directory or pretrained:NAME"."""

    what: str = "a non-empty string"
    strip: bool = True

    def __call__(self, name: str, value: Any) -> str:
        if not isinstance(value, str) or not (value.strip() if self.strip else value):
            raise ValueError(f"{name} must be {self.what}; got {value!r}")
        return value


@dataclasses.dataclass(frozen=True)
class Entries:
    """A non-empty tuple (not a list) of ``cls`` instances: a config's table of categories."""

    cls: type

    def __call__(self, name: str, value: Any) -> tuple:
        if not isinstance(value, tuple) or not value:
            raise ValueError(f"{name} must be a non-empty tuple of {self.cls.__name__}")
        for entry in value:
            check_instance(f"{name} entries", entry, self.cls)
        return value


@dataclasses.dataclass(frozen=True)
class Optional:
    """``None`` (or a value of ``off``, such as 0 for "off", of the same type), or a value
    passing ``rule``."""

    rule: Rule
    off: tuple = ()

    def __call__(self, name: str, value: Any) -> Any:
        if value is None or any(type(value) is type(v) and value == v for v in self.off):
            return value
        return self.rule(name, value)


@dataclasses.dataclass(frozen=True)
class Each:
    """A tuple or list of ``length`` values (any length >= 1 if None), each passing ``rule``
    (named ``name[i]`` when ``index``, else ``name``); returned as a tuple. ``what`` describes
    the whole in the message of a wrong length."""

    rule: Rule
    length: int | None = None
    what: str = "values"
    index: bool = False

    def __call__(self, name: str, value: Any) -> tuple:
        if (not isinstance(value, (tuple, list)) or not value
                or (self.length is not None and len(value) != self.length)):
            count = "" if self.length is None else f"{self.length} "
            raise ValueError(f"{name} must be a tuple of {count}{self.what}; got {value!r}")
        return tuple(self.rule(f"{name}[{i}]" if self.index else name, v)
                     for i, v in enumerate(value))


@dataclasses.dataclass(frozen=True)
class Members:
    """A non-empty tuple of names, each one of ``known`` (``what`` says what they name, e.g.
    "room type"), each at most once if ``distinct``."""

    known: frozenset
    what: str
    distinct: bool = True

    def __call__(self, name: str, value: Any) -> tuple:
        if not isinstance(value, tuple) or not value:
            raise ValueError(f"{name} must be a non-empty tuple of {self.what} names; got "
                             f"{value!r}")
        for entry in value:
            if entry not in self.known:
                raise ValueError(f"{name}: unknown {self.what} {entry!r} (known: "
                                 f"{sorted(self.known)})")
        if self.distinct and len(set(value)) != len(value):
            raise ValueError(f"{name} names a {self.what} twice: {value!r}")
        return value


@dataclasses.dataclass(frozen=True)
class Probabilities:
    """A tuple of ``length`` probabilities summing to 1, as Python floats."""

    length: int

    def __call__(self, name: str, value: Any) -> tuple[float, ...]:
        if not isinstance(value, (tuple, list)) or len(value) != self.length:
            raise ValueError(f"{name} must be a tuple of {self.length} probabilities; got "
                             f"{value!r}")
        return tuple(float(p) for p in check_probabilities(name, value))


@dataclasses.dataclass(frozen=True)
class Pair:
    """A (lo, hi) pair with ``low`` <= lo <= hi (<= ``high``, if given): ints >= ``low`` if
    ``integer``, else reals > ``low``; as a tuple of Python numbers."""

    low: float = 0.0
    integer: bool = False
    high: float | None = None

    def __call__(self, name: str, value: Any) -> tuple:
        if not isinstance(value, (tuple, list)) or len(value) != 2:
            raise ValueError(f"{name} must be a (lo, hi) pair; got {value!r}")
        entry = (Int(int(self.low), self.high) if self.integer
                 else Real(self.low, self.high, low_open=True))
        lo, hi = Each(entry, 2, index=True)(name, value)
        if lo > hi:
            raise ValueError(f"{name} must have lo <= hi; got {value!r}")
        return (lo, hi)


_CHECKED: contextvars.ContextVar[Mapping[str, Any] | None] = contextvars.ContextVar(
    "flowmaps_checked", default=None)


@contextlib.contextmanager
def _checked(values: Mapping[str, Any]):
    """The arguments (or fields) of the running check, for a rule that reads another one's
    checked value (:class:`Distribution`'s ``support``)."""
    token = _CHECKED.set(values)
    try:
        yield
    finally:
        _CHECKED.reset(token)


def check_fields(obj: Any, rules: Mapping[str, Rule], *, prefix: str = "",
                 store: bool = True, labels: Mapping[str, str] | None = None) -> dict[str, Any]:
    """Check every field of ``obj`` named in ``rules`` against its rule, in the table's order;
    the message names ``prefix + field`` (or ``prefix + labels[field]``). Returns the checked
    values ``{field: value}``; with ``store``, also keeps the checked form (Python numbers,
    tuples) on ``obj``, a frozen dataclass included. Without ``store``, a number given as a
    numpy or JAX scalar (``np.int64(8)``, ``np.float32(1e-3)``, a 0-d array) is still replaced
    by the Python number its rule returned, so a config never holds one (``to_dict`` and JSON
    would fail on it later); Python values are kept as given."""
    labels = labels or {}
    checked: dict[str, Any] = {}
    with named_sizes(), _checked(checked):
        for field, rule in rules.items():
            given = getattr(obj, field)
            checked[field] = value = rule(prefix + labels.get(field, field), given)
            if store or (type(value) in _PYTHON_NUMBERS
                         and type(given) not in _PYTHON_NUMBERS):
                object.__setattr__(obj, field, value)
    return checked


_PYTHON_NUMBERS = (int, float, bool)


def check_args(**rules: Rule) -> Callable[[Callable], Callable]:
    """A function's argument checks, declared with its signature: ``@check_args(num_envs=Int(),
    key=Key())`` checks each named argument against its rule (defaults included) before the
    function runs, and passes it on in its checked form (a Python int, a typed key); every
    message names the argument. Arguments whose bounds depend on other arguments are checked in
    the body."""
    def decorate(function: Callable) -> Callable:
        signature = inspect.signature(function)
        unknown = sorted(set(rules) - set(signature.parameters))
        if unknown:
            raise TypeError(f"check_args: {function.__qualname__} has no arguments {unknown}")

        @functools.wraps(function)
        def checked(*args, **kwargs):
            bound = signature.bind(*args, **kwargs)
            bound.apply_defaults()
            with named_sizes(), _checked(bound.arguments):
                for name, rule in rules.items():
                    bound.arguments[name] = rule(name, bound.arguments[name])
            return function(*bound.args, **bound.kwargs)

        return checked

    return decorate


def check_options(args: Any, rules: Mapping[str, Rule]) -> None:
    """A command line's parsed options (an ``argparse.Namespace``) against ``{dest: rule}``,
    before anything runs; each message names the option as typed (``num_envs``: ``--num-envs``).
    The values are checked, not converted."""
    check_fields(args, rules, prefix="--", store=False,
                 labels={dest: dest.replace("_", "-") for dest in rules})


def check_keys(name: str, data: Any, known: Collection[str] | None = None, *,
               what: str = "unknown fields") -> dict:
    """``data`` if it is a dict whose keys all lie in ``known`` (None: any keys), else
    ``ValueError`` starting with ``name`` (e.g. ``"FlowSimConfig.from_dict"``) and listing the
    others as ``what``."""
    if not isinstance(data, dict):
        raise ValueError(f"{name} needs a dict; got {type(data).__name__}")
    unknown = [] if known is None else sorted(set(data) - set(known), key=str)
    if unknown:
        raise ValueError(f"{name}: {what} {unknown}")
    return data

