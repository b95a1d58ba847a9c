"""Table-driven checks of a config dataclass's fields: one ``rule(name, value)`` per field (a
``{field: rule}`` schema) checked by :func:`check_fields`; a rule returns the value to go on with
or raises ``ValueError`` starting with ``name``. Cross-field checks live in the config's
``__post_init__`` (with :func:`check_table` and :func:`check_mixture`); :func:`check_keys`
checks a ``from_dict`` argument.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Collection, Mapping, Sequence
from typing import Any

from flowmaps_jax.validation.arrays import check_probabilities
from flowmaps_jax.validation.scalars import check_choice, check_instance, check_int, check_real

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

    def __call__(self, name: str, value: Any) -> int:
        if self.why and self.maximum is not None:
            number = check_int(name, value, self.minimum)
            if number > self.maximum:
                raise ValueError(f"{name} must be <= {self.maximum} ({self.why}); got {number}")
            return number
        return check_int(name, value, self.minimum, self.maximum)


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


def check_fields(obj: Any, rules: Mapping[str, Rule], *, prefix: str = "",
                 store: bool = True, labels: Mapping[str, str] | None = None) -> dict[str, Any]:
    """Check every field of ``obj`` named in ``rules``, in order (messages name ``prefix + field``
    or ``labels``); returns ``{field: value}``. With ``store`` the checked form is kept on
    ``obj``; without, numpy or JAX scalars are still replaced by Python numbers."""
    labels = labels or {}
    checked: dict[str, Any] = {}
    for field, rule in rules.items():
        given = getattr(obj, field)
        checked[field] = value = rule(prefix + labels.get(field, field), given)
        if store or (type(value) in _PYTHON_NUMBERS and type(given) not in _PYTHON_NUMBERS):
            object.__setattr__(obj, field, value)
    return checked


_PYTHON_NUMBERS = (int, float, bool)


def check_table(name: str, value: Any, cls: type, rules: Mapping[str, Rule], *,
                unique: Sequence[str] = (), earlier: Sequence[Any] = (),
                refers: Sequence[str] = (), labels: Mapping[str, str] | None = None) -> tuple:
    """A config's non-empty table of ``cls`` entries, each checked against ``rules``, the
    ``unique`` fields distinct across it and ``earlier``, each ``refers`` field naming an entry
    of ``earlier``. Returns the tuple, entries rebuilt where a rule changed a value."""
    if not isinstance(value, tuple) or not value:
        raise ValueError(f"{name} must be a non-empty tuple of {cls.__name__}")
    for entry in value:
        check_instance(f"{name} entries", entry, cls)
    seen = {field: {getattr(e, field) for e in earlier} for field in unique}
    rules = {**rules, **{field: Choice(tuple(e.name for e in earlier)) for field in refers}}
    entries = []
    for entry in value:
        checked = check_fields(entry, rules, prefix=f"{name}: {entry.name!r} ", store=False,
                               labels=labels)
        for field in unique:
            key = checked.get(field, getattr(entry, field))
            if key in seen[field]:
                raise ValueError(f"{name}: {field} {key!r} is used twice")
            seen[field].add(key)
        changed = {f: v for f, v in checked.items() if v is not getattr(entry, f)}
        entries.append(dataclasses.replace(entry, **changed) if changed else entry)
    return tuple(entries)


def check_mixture(name: str, value: Any, known: Sequence[str], what: str = "component"
                  ) -> tuple[tuple[str, float], ...]:
    """A mixture over named components: a non-empty tuple of (name, probability) pairs, each
    name one of ``known`` at most once, the probabilities summing to 1; as (str, float) pairs.
    ``what`` names a component in the messages (e.g. "habit")."""
    if (not isinstance(value, (tuple, list)) or not value
            or not all(isinstance(p, (tuple, list)) and len(p) == 2 for p in value)):
        raise ValueError(f"{name} must be ({what} name, probability) pairs, e.g. "
                         f"(({known[0]!r}, 1.0),); got {value!r}")
    names = [check_choice(f"{name}: {what} name", p[0], known) for p in value]
    if len(set(names)) != len(names):
        raise ValueError(f"{name}: a {what} is named twice; got {value!r}")
    probs = check_probabilities(f"{name} probabilities", [p[1] for p in value])
    return tuple((str(n), float(p)) for n, p in zip(names, probs, strict=True))


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

