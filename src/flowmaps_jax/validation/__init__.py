"""Argument checks shared by the public APIs, run on the host before anything is jitted: each
raises ``ValueError`` starting with the argument's name and returns the value in the form to go
on with. Array checks read only shape and dtype of tracers. A shape is a tuple of int sizes,
``None`` (any size) and a leading ``...``.
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
