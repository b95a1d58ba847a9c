"""Compound field rules: rules built from the simple ones of :mod:`.fields`.

:class:`Table` (a config's category table), :class:`Fields` (a pytree argument's fields),
:class:`After`, :class:`IntBelow`, :class:`Index` and :class:`Needs` (bounds that read another
argument checked before), :class:`Mixture`, :class:`Pattern`, :class:`OutputDir`,
:class:`PositiveArray` and :class:`NonEmpty`. They run inside :func:`~.fields.check_args` /
:func:`~.fields.check_fields` and read the values checked so far from its scope.
"""

from __future__ import annotations

import dataclasses
import pathlib
import re
from collections.abc import Callable, Mapping
from typing import Any

import numpy as np

from flowmaps_jax.validation.arrays import (
    check_array,
    check_probabilities,
    check_real_array,
    is_concrete,
    size,
)
from flowmaps_jax.validation.fields import _CHECKED, Choice, Entries, Rule, check_fields
from flowmaps_jax.validation.files import check_output_dir
from flowmaps_jax.validation.scalars import check_choice, check_instance, check_int


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
class NonEmpty:
    """``rule``'s value, which must hold something: an array with no axis of size 0 (a batch of
    at least one scene, query, box), or a non-empty sequence; ``what`` follows the name in the
    message (e.g. "at least one scene and one query")."""

    rule: Rule
    what: str = ""

    def __call__(self, name: str, value: Any) -> Any:
        value = self.rule(name, value)
        shape = np.shape(value) if hasattr(value, "shape") else (len(value),)
        if 0 in shape:
            why = f" ({self.what})" if self.what else ""
            raise ValueError(f"{name} must not be empty{why}; got shape {tuple(shape)}")
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
