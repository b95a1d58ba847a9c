"""Argument checks shared by the public APIs: run on the host, before anything is jitted.

One function per concept. Each raises ``ValueError`` whose message starts with the argument's
name and says what was expected and what was given; each returns the value in the form the
caller should go on with (a Python ``int``/``float``/``bool``, a numpy array, a typed key, a path
string). Array checks read only ``shape`` and ``dtype`` of tracers (values are checked when the
array is concrete), so a public function may run them and still be traced by ``jax.jit``; the
jitted cores behind the public functions do not check again.

Modules (everything is importable from ``flowmaps_jax.validation``; the names are listed below):

* :mod:`.scalars`: ints, reals, flags, choices, instances, seeds, PRNG keys.
* :mod:`.arrays`: arrays, shapes, real and integer arrays, masks, probabilities (with
  :data:`PROB_ATOL` for computed float32 distributions). A shape is a tuple of int sizes,
  ``None`` (any size) and a leading ``...`` (any leading dims); a caller computes the sizes
  from its arguments (``(num_envs, k + 1)``) and passes them in.
* :mod:`.files`: paths, readable files and folders, writable outputs, plain names (a preset or
  file name, a metadata field: no path, no markup).
* :mod:`.fields`: the config dataclasses' schemas only: :func:`check_fields` (a config's fields,
  from a ``{field: rule}`` table), :func:`check_table`, :func:`check_mixture`, :func:`check_keys`
  (the dict a ``from_dict`` reads). A public function checks its arguments in its own body,
  with the plain checks above.
* :mod:`.errors`: :func:`prefix_errors`, a block whose ``ValueError`` messages get one prefix
  (the file or command they concern).

Not checks, and so not here: the atomic writer of output files is
:mod:`flowmaps_jax.atomic_files`, the reader of untrusted files
:mod:`flowmaps_jax.untrusted_files`, the memory and work budgets :mod:`flowmaps_jax.resources`.
"""

from flowmaps_jax.validation.arrays import (
    PROB_ATOL,
    check_array,
    check_concrete,
    check_int_array,
    check_mask,
    check_probabilities,
    check_real_array,
    check_shape,
    is_concrete,
)
from flowmaps_jax.validation.errors import prefix_errors
from flowmaps_jax.validation.fields import check_fields, check_keys, check_mixture, check_table
from flowmaps_jax.validation.files import (
    check_dir,
    check_file,
    check_output_dir,
    check_output_file,
    check_path,
    check_plain_name,
)
from flowmaps_jax.validation.scalars import (
    INT32_MAX,
    SEED_MAX,
    check_choice,
    check_flag,
    check_instance,
    check_int,
    check_key,
    check_real,
    check_seed,
    is_real_dtype,
)

__all__ = [
    "INT32_MAX",
    "PROB_ATOL",
    "SEED_MAX",
    "check_array",
    "check_choice",
    "check_concrete",
    "check_dir",
    "check_fields",
    "check_file",
    "check_flag",
    "check_instance",
    "check_int",
    "check_int_array",
    "check_key",
    "check_keys",
    "check_mask",
    "check_mixture",
    "check_output_dir",
    "check_output_file",
    "check_path",
    "check_plain_name",
    "check_probabilities",
    "check_real",
    "check_real_array",
    "check_seed",
    "check_shape",
    "check_table",
    "is_concrete",
    "is_real_dtype",
    "prefix_errors",
]
