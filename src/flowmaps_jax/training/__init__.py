"""Training a model on its world: config → objective → optimiser → loop (the module map:
docs/design.md). "val" is the EMA loss on the fixed validation batches; what is on disk is
:mod:`flowmaps_jax.store`.
"""
