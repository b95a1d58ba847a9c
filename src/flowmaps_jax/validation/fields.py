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
import pathlib
import re
from collections.abc import Callable, Collection, Mapping
from typing import Any

import numpy as np

from flowmaps_jax.validation.arrays import (
    PROB_ATOL,
    bind_size,
    check_array,
    check_int_array,
    check_mask,
    check_probabilities,
    check_real_array,
    is_concrete,
    named_sizes,
    size,
)
from flowmaps_jax.validation.files import check_output_dir, check_plain_name
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
    a bound may be a named size, ``"K-1"``)."""

    low: int | str | None = None
    high: int | str | None = None
    shape: tuple | None = None

    def __call__(self, name: str, value: Any):
        return check_int_array(name, value, self.low, self.high, shape=self.shape)


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
    tuples) on ``obj``, a frozen dataclass included."""
    labels = labels or {}
    checked: dict[str, Any] = {}
    with named_sizes(), _checked(checked):
        for field, rule in rules.items():
            checked[field] = value = rule(prefix + labels.get(field, field), getattr(obj, field))
            if store:
                object.__setattr__(obj, field, value)
    return checked


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


@dataclasses.dataclass(frozen=True)
class Mixture:
    """A mixture over named components: a non-empty tuple of (name, probability) pairs, each
    name one of ``known`` at most once, the probabilities summing to 1; as (str, float) pairs.
    ``what`` names a component in the messages (e.g. "habit")."""

    known: tuple
    what: str = "component"

    def __call__(self, name: str, value: Any) -> tuple[tuple[str, float], ...]:
        if (not isinstance(value, (tuple, list)) or not value
                or not all(isinstance(p, (tuple, list)) and len(p) == 2 for p in value)):
            raise ValueError(f"{name} must be ({self.what} name, probability) pairs, e.g. "
                             f"(({self.known[0]!r}, 1.0),); got {value!r}")
        names = [check_choice(f"{name}: {self.what} name", p[0], self.known) for p in value]
        if len(set(names)) != len(names):
            raise ValueError(f"{name}: a {self.what} is named twice; got {value!r}")
        probs = check_probabilities(f"{name} probabilities", [p[1] for p in value])
        return tuple((str(n), float(p)) for n, p in zip(names, probs, strict=True))


@dataclasses.dataclass(frozen=True)
class Table:
    """A config's category table: a non-empty tuple of ``cls`` entries (each with a ``name``),
    every entry's fields checked against ``rules`` (messages name ``table: 'entry' field``, or
    the field's ``labels``), the ``unique`` fields distinct across this table and the ``after``
    one (a field checked before it), and each ``refers`` field naming an entry of ``after``.
    Returns the tuple, an entry rebuilt where a rule changed a value (a numpy id -> int)."""

    cls: type
    rules: Mapping[str, Rule]
    unique: tuple[str, ...] = ()
    after: str | None = None
    refers: tuple[str, ...] = ()
    labels: Mapping[str, str] = dataclasses.field(default_factory=dict)

    def __call__(self, name: str, value: Any) -> tuple:
        Entries(self.cls)(name, value)
        earlier = () if self.after is None else (_CHECKED.get() or {})[self.after]
        seen = {field: {getattr(e, field) for e in earlier} for field in self.unique}
        rules = {**self.rules, **{field: Choice(tuple(e.name for e in earlier))
                                  for field in self.refers}}
        entries = []
        for entry in value:
            checked = check_fields(entry, rules, prefix=f"{name}: {entry.name!r} ",
                                   store=False, labels=self.labels)
            for field in self.unique:
                key = checked.get(field, getattr(entry, field))
                if key in seen[field]:
                    raise ValueError(f"{name}: {field} {key!r} is used twice")
                seen[field].add(key)
            changed = {f: v for f, v in checked.items() if v is not getattr(entry, f)}
            entries.append(dataclasses.replace(entry, **changed) if changed else entry)
        return tuple(entries)


def _resolved(rule: Rule) -> Rule:
    """``rule`` with its named-size bounds (``high="D-1"``) read from the current scope; a size
    nothing bound (an optional argument left None) is no bound."""
    bounds = {k: size(v) for k in ("low", "high") if isinstance(v := getattr(rule, k, None), str)}
    return dataclasses.replace(rule, **bounds) if bounds else rule


@dataclasses.dataclass(frozen=True)
class Pattern:
    """A string matching the regular expression ``regex`` in full (``what`` names it in the
    message, e.g. "a SHA-256 hex digest"); a value read from a file is shown clipped."""

    regex: str
    what: str

    def __call__(self, name: str, value: Any) -> str:
        if not (isinstance(value, str) and re.fullmatch(self.regex, value)):
            raise ValueError(f"{name} must be {self.what}; got {str(value)[:40]!r}")
        return value


@dataclasses.dataclass(frozen=True)
class Fields:
    """An instance of ``cls`` (a pytree such as ``SceneTokens``) whose fields pass ``rules``
    (``{field: rule}``, named ``name.field``), in the named-size scope of the enclosing
    :func:`check_args`: a pytree argument's fields declared with the function's other arguments,
    their shapes and bounds sharing its sizes (a bound naming a size nothing bound is no bound).
    With ``arrays``, each field that is not None must be an array (numpy or jax, not a list).
    The value bounds of the ``padded`` fields apply only where the mask field ``where`` is True
    (padding may hold anything). A rule may be another :class:`Fields` (a nested pytree).
    Returns the object itself."""

    cls: type
    rules: Mapping[str, Rule]
    arrays: bool = True
    where: str | None = None
    padded: tuple = ()

    def __call__(self, name: str, value: Any) -> Any:
        check_instance(name, value, self.cls)
        checked: dict[str, Any] = {}
        for field, rule in self.rules.items():
            item = getattr(value, field)
            if self.arrays and item is not None and not isinstance(rule, Fields):
                check_array(f"{name}.{field}", item)
            whole = (dataclasses.replace(rule, low=None, high=None) if field in self.padded
                     else _resolved(rule))
            checked[field] = whole(f"{name}.{field}", item)
        real = checked.get(self.where)
        for field in self.padded:
            if is_concrete(checked[field], real):
                inside = np.asarray(checked[field])[np.asarray(real, bool)]
                _resolved(dataclasses.replace(self.rules[field], shape=None))(
                    f"{name}.{field}", inside)
        return value


@dataclasses.dataclass(frozen=True)
class OutputDir:
    """A directory that is or can become a writable one
    (:func:`~flowmaps_jax.validation.check_output_dir`), as a ``pathlib.Path``."""

    def __call__(self, name: str, value: Any) -> pathlib.Path:
        return pathlib.Path(check_output_dir(name, value))


@dataclasses.dataclass(frozen=True)
class IntBelow:
    """An int >= ``minimum`` and below the checked value of ``field``, an argument (or field)
    checked before it (``warmup_steps`` below ``steps``)."""

    field: str
    minimum: int = 0

    def __call__(self, name: str, value: Any) -> int:
        bound = (_CHECKED.get() or {})[self.field]
        number = check_int(name, value, self.minimum)
        if number >= bound:
            raise ValueError(f"{name} must be an int in {self.minimum}..{self.field}-1 "
                             f"({self.field} = {bound}); got {number}")
        return number


@dataclasses.dataclass(frozen=True)
class After:
    """A rule made from the values checked before it in the same :func:`check_args` /
    :func:`check_fields` call: ``make(checked) -> rule``, for a bound that depends on another
    argument (``After(lambda got: Int(0, got["steps"] - 1))``); list it after those it reads."""

    make: Callable[[Mapping[str, Any]], Rule]

    def __call__(self, name: str, value: Any) -> Any:
        return self.make(_CHECKED.get() or {})(name, value)


@dataclasses.dataclass(frozen=True)
class Index:
    """An int index below a named size of the check (``Index("E")``: 0..E−1), the size bound by
    an argument checked before it (``config``, ``scenes``), as a Python int."""

    size: str

    def __call__(self, name: str, value: Any) -> int:
        bound = size(self.size)
        if bound is None:
            raise TypeError(f"Index({self.size!r}) of {name}: the size is not bound yet")
        return check_int(name, value, 0, bound - 1)


@dataclasses.dataclass(frozen=True)
class PositiveArray:
    """A finite real array of ``shape`` whose every value is > 0 (values of concrete arrays
    only); ``what`` follows "must be positive" in the message (e.g. which differences)."""

    shape: tuple | None = None
    what: str = ""

    def __call__(self, name: str, value: Any):
        arr = check_real_array(name, value, self.shape)
        if is_concrete(arr) and np.size(arr) and np.min(arr) <= 0:
            raise ValueError(f"{name} must be positive{self.what}; got a minimum of "
                             f"{np.min(arr)}")
        return arr


def _given(value: Any) -> bool:
    return value is not None and value is not False


@dataclasses.dataclass(frozen=True)
class Needs:
    """A value given (not None or False) only while ``field``, an argument (or field) checked
    before it, is given too (or, with ``needs=False``, is not); the message is the name and
    ``why`` (``--resume needs --run-dir``, ``--overwrite and --resume exclude each other``)."""

    field: str
    why: str
    needs: bool = True

    def __call__(self, name: str, value: Any) -> Any:
        if _given(value) and _given((_CHECKED.get() or {})[self.field]) != self.needs:
            raise ValueError(f"{name} {self.why}")
        return value
