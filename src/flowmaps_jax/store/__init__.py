"""Everything on disk: checkpoints, their integrity, the pretrained weights and the run
directory. Below the predictor and the training loop, above :mod:`flowmaps_jax.model`; the only
package that imports orbax, and it needs no training code (no optax). The module map:
docs/design.md.
"""
