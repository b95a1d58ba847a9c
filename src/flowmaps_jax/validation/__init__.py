"""Argument checks shared by the public APIs: run on the host, before anything is jitted.

Each raises ``ValueError`` whose message starts with the argument's name and says what was
expected and what was given, and returns the value in the form the caller goes on with. Array
checks read only ``shape`` and ``dtype`` of tracers (values when concrete), so a traced public
function may run them; the jitted cores do not check again. A shape is a tuple of int sizes,
``None`` (any size) and a leading ``...``. Modules: ``scalars``, ``arrays`` (with
:data:`PROB_ATOL`), ``files``, ``fields`` (config schemas only), ``errors``
(:func:`prefix_errors`); the map is docs/design.md.
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
