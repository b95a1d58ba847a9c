"""Seconds per checkpoint save and restore of a preset's TrainState, as the training loop saves
it (``CheckpointStore.save``: the state packed into one array, checksums in ``meta``) and as a
run restores it (``checkpoints.restore``: into the state's structure for ``--resume``, as raw
dicts for ``load_weights``). ``--leaves`` also times the earlier format, one orbax array per
leaf of the state, written the way the store wrote it before packing (it still restores).

    python experiments/bench_checkpoint.py                        # smoke and cpu, 10 repeats
    python experiments/bench_checkpoint.py --presets paper --repeats 5 --leaves
"""

from __future__ import annotations

import argparse
import json
import pathlib
import statistics
import tempfile
import time


def _timed(fn, repeats: int) -> float:
    seconds = []
    for i in range(repeats):
        start = time.perf_counter()
        fn(i)
        seconds.append(time.perf_counter() - start)
    return statistics.median(seconds)


def measure(preset: str, repeats: int, leaves: bool) -> dict:
    """Median seconds of ``repeats`` saves and restores of ``preset``'s fresh TrainState."""
    import jax
    import orbax.checkpoint as ocp

    from flowmaps_jax.store import checkpoints, integrity
    from flowmaps_jax.store.checkpoint_store import CheckpointStore
    from flowmaps_jax.training import state as train_state
    from flowmaps_jax.training.config import get_preset

    cfg = get_preset(preset)
    state = train_state.init_state(cfg)
    target, config = train_state.abstract_state(cfg), cfg.to_dict()
    row = {"preset": preset, "arrays": len(jax.tree.leaves(state)),
           "MB": round(sum(x.nbytes for x in jax.tree.leaves(state)) / 1e6, 2)}
    with tempfile.TemporaryDirectory() as tmp:
        root = pathlib.Path(tmp)
        with CheckpointStore(root / "packed", keep_last=repeats) as store:
            row["save_s"] = _timed(lambda i: store.save(state.replace(step=state.step + i + 1),
                                                        config), repeats)
        row["restore_s"] = _timed(lambda i: checkpoints.restore(root / "packed", target,
                                                                step=i + 1), repeats)
        row["restore_raw_s"] = _timed(lambda i: checkpoints.restore(root / "packed",
                                                                    step=i + 1), repeats)
        if leaves:
            manager = checkpoints.last_manager(root / "leaves" / "last", repeats)

            def save_leaves(i):
                now = state.replace(step=state.step + i + 1)
                manager.save(i + 1, args=ocp.args.Composite(
                    state=ocp.args.StandardSave(now), config=ocp.args.JsonSave(config),
                    meta=ocp.args.JsonSave({**integrity.describe_state(now, config),
                                            "format": 1})))
                manager.wait_until_finished()

            row["leaves_save_s"] = _timed(save_leaves, repeats)
            manager.close()
            row["leaves_restore_s"] = _timed(lambda i: checkpoints.restore(
                root / "leaves", target, step=i + 1), repeats)
    return row


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--presets", nargs="+", default=["smoke", "cpu"])
    parser.add_argument("--repeats", type=int, default=10)
    parser.add_argument("--leaves", action="store_true",
                        help="also time the earlier format, one array per leaf")
    args = parser.parse_args(argv)
    if args.repeats < 1:
        parser.error(f"--repeats must be at least 1; got {args.repeats}")
    for preset in args.presets:
        print(json.dumps({k: round(v, 4) if isinstance(v, float) else v
                          for k, v in measure(preset, args.repeats, args.leaves).items()}))


if __name__ == "__main__":
    main()
