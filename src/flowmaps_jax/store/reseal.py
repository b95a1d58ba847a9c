"""``python -m flowmaps_jax.store.reseal DIRECTORY``: add the ``seal`` to every unsealed model
whose ``.npz`` still matches its recorded SHA-256 (only the ``.json`` is rewritten, atomically).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import pathlib
import sys
from collections.abc import Sequence

from flowmaps_jax.atomic_files import write_file
from flowmaps_jax.store import pretrained
from flowmaps_jax.validation import check_dir


def reseal(directory: str | pathlib.Path) -> dict[str, str]:
    """Seal the unsealed models in ``directory``; returns {name: "sealed" or "already sealed"}.
    ValueError naming a damaged model (nothing written for it or after it)."""
    root = pathlib.Path(check_dir("directory", directory))
    done = {}
    for name in pretrained.available(root):
        meta = pretrained._read_meta(name, root)
        data = (root / f"{name}.npz").read_bytes()
        if "seal" in meta:
            pretrained.check_seal(name, meta, data)
            done[name] = "already sealed"
            continue
        if hashlib.sha256(data).hexdigest() != meta["sha256"]:
            raise ValueError(f"pretrained {name!r} in {root}: {name}.npz does not match the "
                             f"SHA-256 its .json recorded; not sealing damaged weights")
        meta["seal"] = pretrained.seal(meta, data)
        write_file(root / f"{name}.json", json.dumps(meta, indent=2) + "\n",
                   name="weights file")
        done[name] = "sealed"
    return done


def main(argv: Sequence[str] | None = None) -> int:
    """CLI: seal the pretrained weights in a directory (exit 2 on a refusal)."""
    parser = argparse.ArgumentParser(prog="python -m flowmaps_jax.store.reseal",
                                     description="Seal pretrained weights written before "
                                                 "seals existed (the .npz is not changed).")
    parser.add_argument("directory", help="the folder holding <name>.npz and <name>.json "
                                          "(named explicitly, also for the package's own)")
    args = parser.parse_args(argv)
    try:
        done = reseal(args.directory)
    except ValueError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    for name, what in done.items():
        print(f"{name}: {what}")
    if not done:
        print(f"no pretrained weights in {args.directory}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
