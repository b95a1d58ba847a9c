"""Homes on disk: ``save_homes(path, homes, config)`` writes one ``.npz`` (every ``Homes``
field, ``format_version``, ``config_json``, ``schema_json``) and ``<stem>.schema.json`` beside
it (every field's shape, dtype, unit and meaning, the vocabulary, the regimes, the time
convention), both renamed into place together. ``load_homes(path) -> (homes, config)`` raises
``ValueError`` naming the file for anything ``save_homes`` could not have written.
"""

from __future__ import annotations

import io
import json
import pathlib

import jax.numpy as jnp
import numpy as np

from flowmaps_jax.atomic_files import write_files
from flowmaps_jax.flowsim.homes.config import NUM_CONTEXTS, REGIMES, HomesConfig
from flowmaps_jax.flowsim.homes.world import FIELDS, Homes, field_shape, sizes, validate_homes
from flowmaps_jax.untrusted_files import parse_json, read_npz
from flowmaps_jax.validation import check_file, check_output_file, prefix_errors

FORMAT = "flowmaps-homes"
SCHEMA_VERSION = 1
_META = ("format_version", "config_json", "schema_json")


def schema_path(path) -> pathlib.Path:
    """The schema file beside ``path``: ``homes.npz`` -> ``homes.schema.json``."""
    path = pathlib.Path(path)
    stem = path.name[:-4] if path.name.endswith(".npz") else path.name
    return path.with_name(stem + ".schema.json")


def homes_schema(config: HomesConfig, num_homes: int) -> dict:
    """The JSON schema of a file of ``num_homes`` homes of ``config``."""
    dims = sizes(config, num_homes)
    return {
        "format": FORMAT,
        "schema_version": SCHEMA_VERSION,
        "units": {"length": "metres", "time": "hours"},
        "time": ("hour t = 0 … T − 1 starts on Monday 00:00; hour of day t mod 24; day of week "
                 "floor(t / 24) mod 7 (0 = Monday); preference context = floor(hour of day / 6) "
                 "+ 4 on Saturday and Sunday"),
        "coordinates": "x along the home's width, y along its depth, z up; origin at a corner",
        "sizes": {k: v for k, v in dims.items() if not k.isdigit()},
        "size_meaning": {"E": "homes", "NR": "rooms", "D": "door slots",
                         "R": "receptacle slots", "M": "object slots", "T": "hours",
                         "C": f"preference contexts ({NUM_CONTEXTS})"},
        "fields": {name: {"shape": list(symbols), "sizes": list(field_shape(name, dims)),
                          "dtype": dtype, "unit": unit, "meaning": meaning}
                   for name, (symbols, dtype, unit, meaning) in FIELDS.items()},
        "vocabulary": {
            "room_types": [{"name": r.name, "text": r.text} for r in config.room_types],
            "receptacle_classes": [{"name": r.name, "text": r.text, "size_whd_m": list(r.size)}
                                   for r in config.receptacle_classes],
            "object_classes": [{"name": o.name, "text": o.text, "size_whd_m": list(o.size)}
                               for o in config.object_classes]},
        "regimes": list(REGIMES),
        "members": {"format_version": "int64 scalar, the schema version",
                    "config_json": "the HomesConfig as JSON (HomesConfig.to_dict)",
                    "schema_json": "this schema as JSON"},
    }


def save_homes(path, homes: Homes, config: HomesConfig) -> pathlib.Path:
    """Write ``homes`` (checked against ``config`` first) to ``path`` (.npz) and its schema to
    ``schema_path(path)``. Returns the schema's path."""
    path = check_output_file("path", path)
    side = schema_path(path)
    check_output_file("path's schema file", side)  # no link nor directory there: nothing half
    if isinstance(homes, Homes) and np.shape(homes.home_size)[:1] == (0,):
        raise ValueError("homes holds 0 homes; save_homes writes at least one (load_homes "
                         "refuses a file of none)")
    validate_homes(homes, config)  # the config too
    schema = homes_schema(config, homes.num_homes)
    arrays = {name: np.asarray(value) for name, value in homes.as_dict().items()}
    buffer = io.BytesIO()
    np.savez_compressed(buffer, format_version=np.int64(SCHEMA_VERSION),
                        config_json=np.asarray(json.dumps(config.to_dict())),
                        schema_json=np.asarray(json.dumps(schema)), **arrays)
    write_files({path: buffer.getvalue(), side: json.dumps(schema, indent=1) + "\n"},
                name="path")  # both written aside, then renamed: never one without the other
    return side


def load_homes(path) -> tuple[Homes, HomesConfig]:
    """Read a file written by ``save_homes`` (untrusted, ``untrusted_files.read_npz``);
    ``ValueError`` naming it if it is not one."""
    with prefix_errors("load_homes: "):
        path = check_file("path", path)
        contents = read_npz(repr(path), path, allowed=(*_META, *FIELDS),
                            required=(*_META, *FIELDS))
    with prefix_errors(f"load_homes: {path!r}: "):
        version = contents["format_version"]
        if (version.shape != () or version.dtype.kind not in "iu"
                or int(version) != SCHEMA_VERSION):
            raise ValueError(f"it has format_version {version!r}; this code reads version "
                             f"{SCHEMA_VERSION}")
        with prefix_errors("it has an invalid config_json or schema_json: ", also=(TypeError,)):
            config = HomesConfig.from_dict(parse_json("config_json",
                                                       str(contents["config_json"])))
            schema = parse_json("schema_json", str(contents["schema_json"]))
        if not isinstance(schema, dict) or schema.get("format") != FORMAT or schema.get(
                "schema_version") != SCHEMA_VERSION:
            raise ValueError(f"schema_json is not a {FORMAT} schema of version {SCHEMA_VERSION}")
        shape = contents["home_size"].shape
        if len(shape) != 2 or shape[0] < 1:
            raise ValueError(f"home_size has shape {shape}, expected (E, 2) with E >= 1")
        validate_homes(Homes(**{name: contents[name] for name in FIELDS}), config)
    return Homes(**{name: jnp.asarray(contents[name]) for name in FIELDS}), config
