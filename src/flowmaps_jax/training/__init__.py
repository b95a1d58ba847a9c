"""Training FlowMaps (or the MLP baseline) on FlowSim: config → objective → optimiser → loop.

Modules, in the order data flows through them:

* :mod:`~flowmaps_jax.training.config`: ``TrainConfig``, the ``paper`` / ``cpu`` / ``smoke``
  presets and ``--set key=value`` overrides.
* :mod:`~flowmaps_jax.training.data`: the FlowSim splits and the traceable batch sampler.
* :mod:`~flowmaps_jax.training.objectives`: the CFM loss and one registry entry per model kind
  (init, loss, sample, log_prob).
* :mod:`~flowmaps_jax.training.state`: ``TrainState``, optax optimiser and EMA, the jitted train
  step and validation loss.
* :mod:`~flowmaps_jax.training.checkpoint`: orbax checkpoints (last k + best), each step with
  SHA-256 checksums of its arrays (a ``meta`` item), non-finite state refused both ways.
* :mod:`~flowmaps_jax.training.rundir`: one run per directory (refuse / ``--overwrite``, a lock
  file, atomic writes).
* :mod:`~flowmaps_jax.training.loop`: ``run`` and the ``python -m flowmaps_jax.train`` CLI.
"""
