"""``python -m flowmaps_jax.data``: convert data into recorded worlds and out of them
(docs/data.md). The commands are in :mod:`flowmaps_jax.data.__main__`; the formats in
:mod:`flowmaps_jax.recorded`."""
