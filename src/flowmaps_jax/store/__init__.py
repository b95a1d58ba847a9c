"""Everything on disk: checkpoints, their integrity, the pretrained weights and the run
directory; the only package that imports orbax (docs/design.md)."""
