"""Config dataclasses from text: ``key=value`` overrides (:func:`apply_overrides`, ``--set``),
typed values (:func:`replace_fields`, the typed flags), the JSON round trip
(:func:`config_to_dict` / :func:`config_from_dict`; a field's metadata ``"stored_as"`` names the
key it has on disk, and both keys read back) and :func:`flatten`. Nothing here knows
``TrainConfig``: every function works on the dataclass it is given.
"""

from __future__ import annotations

import contextlib
import dataclasses
import decimal
import types
import typing
from typing import Any, Literal

from flowmaps_jax.validation.errors import prefix_errors
from flowmaps_jax.validation.fields import check_keys

SHORTHANDS = {"precision": "model.precision"}
"""Top-level override keys that stand for a nested field (``--set precision=bf16``)."""


def apply_overrides(cfg, overrides: typing.Iterable[str] | dict[str, Any]):
    """Return ``cfg`` with fields replaced, e.g. ``["model.dim=64", "lr=1e-3", "clip_norm=none"]``
    (dotted paths, or :data:`SHORTHANDS`; text converted to the field's type, "none" to None).
    All are applied before the result is checked; ValueError naming the key.
    """
    return replace_fields(cfg, overrides)


def replace_fields(cfg, overrides: typing.Iterable[str] | dict[str, Any] = (),
                   typed: dict[str, Any] | None = None):
    """Return ``cfg`` with the text ``overrides`` (as :func:`apply_overrides`), then the
    ``typed`` ``{key: value}`` set as they are (no text conversion), checked once together.
    """
    items = _override_items(overrides)
    typed_items = list((typed or {}).items())
    if not items and not typed_items:
        return cfg
    cls = type(cfg)
    data = cfg.to_dict()
    for key, value in items:
        _set_path(cls, data, SHORTHANDS.get(key, key).split("."), value, key)
    for key, value in typed_items:
        _set_path(cls, data, SHORTHANDS.get(key, key).split("."), value, key, convert=False)
    keys = ", ".join(dict.fromkeys(k for k, _ in items + typed_items))
    with prefix_errors(f"bad override ({keys}): ", also=(TypeError,)):
        return cls.from_dict(data)


def _override_items(overrides: typing.Iterable[str] | dict[str, Any]) -> list[tuple[str, Any]]:
    """``[(key, value), ...]`` of a dict, or of ``key=value`` strings (ValueError otherwise)."""
    if isinstance(overrides, dict):
        return list(overrides.items())
    items = []
    for text in overrides:
        if "=" not in text:
            raise ValueError(f"override {text!r} must look like key=value")
        key, value = text.split("=", 1)
        items.append((key.strip(), value.strip()))
    return items


def _set_path(cls: type, data: dict, path: list[str], value: Any, full_key: str,
              convert: bool = True) -> None:
    """Set ``data[path]`` (a to_dict() view of dataclass ``cls``) to ``value``, converted from
    text to the field's type when it is a string and ``convert``. A field may be named by its
    stored key too (``model_kind`` for ``family``)."""
    names = _field_names(cls)
    head = _field_of_key(cls).get(path[0], path[0])
    hint = typing.get_type_hints(cls)[head] if head in names else None
    is_section = isinstance(hint, type) and dataclasses.is_dataclass(hint)
    if hint is None or (len(path) > 1 and not is_section):  # the key names no field
        why = (f"{cls.__name__} has no field {path[0]!r}; known: {sorted(names)}" if hint is None
               else f"{head!r} has no sub-fields")
        raise ValueError(f"unknown config key {full_key!r} ({why})")
    stored = _stored_keys(cls)[head]
    if len(path) > 1:
        _set_path(hint, data[stored], path[1:], value, full_key, convert)
    elif is_section:
        raise ValueError(f"config key {full_key!r} is a section; set one of its fields, "
                         f"e.g. {full_key}.{_field_names(hint)[0]}=...")
    else:
        data[stored] = _convert(value, hint, full_key) if convert and isinstance(value, str) \
            else value


def _field_names(cls: type) -> list[str]:
    """Field names of dataclass ``cls`` in declaration order."""
    return [f.name for f in dataclasses.fields(cls)]


def _stored_keys(cls: type) -> dict[str, str]:
    """``{field name: the key it is stored under}`` of dataclass ``cls`` (its name unless its
    metadata says ``stored_as``)."""
    return {f.name: f.metadata.get("stored_as", f.name) for f in dataclasses.fields(cls)}


def _field_of_key(cls: type) -> dict[str, str]:
    """``{stored key: field name}`` for the fields of ``cls`` stored under another key."""
    return {key: name for name, key in _stored_keys(cls).items() if key != name}


_NONE_WORDS = ("none", "null")
_TRUE_WORDS = ("true", "1", "yes", "on")
_FALSE_WORDS = ("false", "0", "no", "off")


def _convert(text: str, hint: Any, key: str) -> Any:
    """A command-line string as the annotated type ``hint`` (a tuple from comma-separated
    items); text that does not convert is returned as it is, for the field's rule to refuse."""
    origin = typing.get_origin(hint)
    if origin in (typing.Union, types.UnionType):
        args = typing.get_args(hint)
        if type(None) in args and text.lower() in _NONE_WORDS:
            return None
        for arg in args:
            value = text if arg is type(None) else _convert(text, arg, key)
            if value is not text:
                return value
        return text
    args = typing.get_args(hint)
    if origin is tuple and args and set(args) <= {int, float, str, Ellipsis}:  # "7,9,17,18"
        items = [item.strip() for item in text.split(",")]
        kinds = [args[0]] * len(items) if args[1:] == (Ellipsis,) else list(args)
        if len(kinds) != len(items):  # the field's rule refuses the text, naming the key
            return text
        return tuple(_convert(item, kind, key) for item, kind in zip(items, kinds, strict=True))
    if origin is Literal:
        return next((choice for choice in typing.get_args(hint) if str(choice) == text), text)
    if hint is bool:
        lower = text.lower()
        return True if lower in _TRUE_WORDS else False if lower in _FALSE_WORDS else text
    if hint in (int, float) and not text.isascii():  # int("１") is 1 to Python: left as text
        return text
    if hint is int:
        with contextlib.suppress(ValueError):
            return int(text)
        with contextlib.suppress(ArithmeticError, ValueError):  # "1e4", "8.0": exact integers
            exact = decimal.Decimal(text.strip())
            if exact.is_finite() and abs(exact.adjusted()) <= 30 \
                    and exact == exact.to_integral_value():
                return int(exact)
        return text  # "1.0000000000000001" is no integer: the field's rule refuses it
    if hint is float:
        with contextlib.suppress(ValueError):
            return float(text)
        return text
    if hint is str:
        return text
    raise ValueError(f"config key {key!r} (type {hint}) cannot be set from the command line")


# --------------------------------------------------------------------------------------------
# JSON round trip


def config_to_dict(cfg) -> dict:
    """The fields of dataclass ``cfg`` as a JSON-able dict, each under its stored key (its name,
    or its metadata's ``stored_as``): nested configs become nested dicts (through their own
    ``to_dict`` when they have one), tuples become lists."""
    return {f.metadata.get("stored_as", f.name): _to_jsonable(getattr(cfg, f.name))
            for f in dataclasses.fields(cfg)}


def _to_jsonable(obj: Any) -> Any:
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        to_dict = getattr(obj, "to_dict", None)
        return _to_jsonable(to_dict()) if to_dict is not None else config_to_dict(obj)
    if isinstance(obj, dict):
        return {str(k): _to_jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_to_jsonable(v) for v in obj]
    return obj


# Fields that older versions wrote and that no longer exist (they configured nothing): configs
# saved with them still load. (A nested config with its own ``from_dict`` drops its own, as
# ``ModelConfig.from_dict`` does ``model.config.REMOVED_FIELDS``.)
_REMOVED_KEYS = {"TrainConfig": ("run_dir",)}


def config_from_dict(cls: type, data: Any, where: str = "config") -> Any:
    """Inverse of :func:`config_to_dict`: dataclass ``cls`` from a dict (a field under its stored
    key or its name); unknown keys raise ``ValueError`` naming ``where``."""
    removed = _REMOVED_KEYS.get(cls.__name__, ())
    check_keys(where, data, [*_field_names(cls), *_field_of_key(cls), *removed],
               what=f"has keys that are no field of {cls.__name__}:")
    data = {k: v for k, v in data.items() if k not in removed}
    for key, name in _field_of_key(cls).items():
        if key in data and name in data:
            raise ValueError(f"{where} sets {name!r} twice (as {name!r} and as {key!r})")
        if key in data:
            data[name] = data.pop(key)
    hints = typing.get_type_hints(cls)
    kwargs = {}
    for name, value in data.items():
        hint = hints[name]
        if isinstance(hint, type) and dataclasses.is_dataclass(hint):
            if hasattr(hint, "from_dict"):  # which checks its dict itself
                value = hint.from_dict(value)
            else:
                value = config_from_dict(hint, value, f"{where}.{name}")
        elif isinstance(value, list):
            value = tuple(value)
        kwargs[name] = value
    return cls(**kwargs)


def flatten(data: dict, prefix: str = "") -> dict[str, Any]:
    """A nested dict as one level with dotted keys: ``{"model": {"dim": 64}}`` →
    ``{"model.dim": 64}``."""
    out: dict[str, Any] = {}
    for key, value in data.items():
        name = f"{prefix}{key}"
        if isinstance(value, dict):
            out.update(flatten(value, name + "."))
        else:
            out[name] = value
    return out
