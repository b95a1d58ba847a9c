"""Training FlowMaps (or the MLP baseline) on FlowSim: config → objective → optimiser → loop.

Modules, in the order data flows through them:

* :mod:`~flowmaps_jax.training.config`: ``TrainConfig`` (each field declaring its role: compiled
  in, resumable), the ``paper`` / ``cpu`` / ``smoke`` presets.
* :mod:`~flowmaps_jax.training.overrides`: ``--set key=value`` overrides, the typed flags
  (``replace_fields``) and the config's JSON round trip.
* :mod:`~flowmaps_jax.training.data`: the FlowSim splits and the traceable batch sampler.
* :mod:`~flowmaps_jax.training.objectives`: the model family's init and loss bound to the run
  (the families and their losses are :mod:`flowmaps_jax.model.families`).
* :mod:`~flowmaps_jax.training.state`: ``TrainState``, optax optimiser and EMA, the jitted train
  step and the val loss.
* :mod:`~flowmaps_jax.training.runlog`: a run's records: ``metrics.jsonl``, its checkpoints
  (last k + best), the best val step, the summary.
* :mod:`~flowmaps_jax.training.resume`: the resume policy (which checkpoint ``--resume``
  continues, with which config).
* :mod:`~flowmaps_jax.training.loop`: ``run``, the training loop (prelude, step loop, summary).
* :mod:`~flowmaps_jax.training.cli`: the ``python -m flowmaps_jax.train`` command.

"val" in training is the EMA loss on the fixed validation batches (``val_every``,
``metrics.jsonl``'s ``"kind": "val"``); checking arguments is :mod:`flowmaps_jax.validation`.
What is on disk (checkpoints, their checksums, the run directory and its lock) is
:mod:`flowmaps_jax.store`.
"""
