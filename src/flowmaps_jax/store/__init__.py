"""Everything on disk: checkpoints, their integrity, the pretrained weights and the run directory.

The one layer that reads and writes files of models and runs, below the predictor and the
training loop and above :mod:`flowmaps_jax.model`; the only package that imports orbax. It
needs no training code (no optax), so inference loads models through it.

* :mod:`.checkpoints`: the orbax checkpoint directory (``last/`` and ``best/``): find, restore
  and verify a step, a step's weights and model (:func:`~.checkpoints.load_weights`), set later
  steps aside.
* :mod:`.checkpoint_store`: :class:`~.checkpoint_store.CheckpointStore`, writing a run's
  checkpoints (the last k and the best by validation loss), atomically.
* :mod:`.integrity`: SHA-256 checksums, finiteness and the ``meta`` format of a saved step.
* :mod:`.model_spec`: the model family, sizes and simulator a stored config describes.
* :mod:`.pretrained`: the pretrained weights packaged in ``flowmaps_jax/pretrained/``: read
  them safely, write them from a checkpoint (``python -m flowmaps_jax.export``).
* :mod:`.rundir`: a run directory for one run (:func:`~.rundir.claim`, the lock, atomic writes,
  the metrics file).
"""
