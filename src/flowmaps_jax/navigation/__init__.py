"""Search policies (:mod:`.policies`) and the homes navigation (:mod:`.navigation`), below both
evaluation and search."""
