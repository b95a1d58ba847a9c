"""A saved state as one array of bytes: the ``state`` item of a step is ``{"packed": (n,) uint8}``,
every leaf's bytes one after the other, and ``meta["layout"]`` lists each leaf's
:func:`leaf_name`, dtype and shape in flattening order. orbax spends about 1 ms per array on a
save or a restore (a smoke model's 205 arrays: about 0.3 s each way; packed: 0.04 s,
docs/results.md), and a read that fails leaves no other array's read behind to report later.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np

from flowmaps_jax.distributed import place
from flowmaps_jax.store.integrity import Damaged, host_leaves, leaf_name, name_list

PACKED = "packed"


def pack(state) -> tuple[dict, list]:
    """(the ``state`` item ``{"packed": (n,) uint8 array}``, placed as ``state``'s first leaf
    is, the layout ``[[name, dtype name, shape], ...]``) of ``state`` (a pytree of arrays; a
    typed PRNG key is stored as its key data, and restores as that raw data)."""
    leaves = host_leaves(state)
    data = np.frombuffer(b"".join(np.ascontiguousarray(arr).tobytes() for _, arr in leaves),
                         np.uint8)
    layout = [[name, arr.dtype.name, list(arr.shape)] for name, arr in leaves]
    return {PACKED: place(data, getattr(jax.tree.leaves(state)[0], "sharding", None))}, layout


def host_arrays(packed, layout) -> list[tuple[str, np.ndarray]]:
    """(name, host array) of every leaf the ``layout`` (untrusted: read from disk) lists, from
    the restored ``packed`` bytes. :class:`Damaged` if the layout is unreadable or does not fit
    them."""
    data, offset, out = np.asarray(packed).tobytes(), 0, []
    try:
        for name, dtype, shape in layout:
            if not all(isinstance(n, int) and n >= 0 for n in shape):
                raise ValueError(f"shape {shape} of {name}")
            dtype, count = jnp.dtype(dtype), math.prod(shape)
            arr = np.frombuffer(data, dtype, count, offset) if count else np.zeros(0, dtype)
            out.append((str(name), arr.reshape(shape)))
            offset += arr.nbytes
    except (TypeError, ValueError) as err:
        raise Damaged(f"has an unreadable layout ({type(err).__name__}: {err})") from None
    if offset != len(data):
        raise Damaged("has a layout that does not match its packed bytes")
    return out


def unpack(arrays: list[tuple[str, np.ndarray]], target=None):
    """The state :func:`pack` stored, from its :func:`host_arrays`: in ``target``'s structure,
    dtypes and shardings (a TrainState or its ``jax.eval_shape``), or as nested dicts on this
    process's first device (``target`` None). :class:`Damaged` if the arrays do not match
    ``target`` or a name comes twice."""
    if target is None:
        device, state = jax.sharding.SingleDeviceSharding(jax.local_devices()[0]), {}
        for name, arr in arrays:
            *parents, last = name.split("/")
            node = state
            for part in parents:
                node = node.setdefault(part, {})
            if not isinstance(node, dict) or last in node:
                raise Damaged(f"has an unreadable layout (the name {name} twice)")
            node[last] = place(arr, device)
        return state
    paths, treedef = jax.tree_util.tree_flatten_with_path(target)
    names = [leaf_name(path) for path, _ in paths]
    if names != [name for name, _ in arrays]:
        differ = sorted(set(names) ^ {name for name, _ in arrays}) or names
        raise Damaged(f"does not match the model: arrays {name_list(differ)} differ in name "
                      f"or order")
    leaves = []
    for (name, arr), (_, want) in zip(arrays, paths, strict=True):
        if tuple(arr.shape) != tuple(want.shape) or arr.dtype != want.dtype:
            raise Damaged(f"does not match the model: {name} is {arr.dtype.name}"
                          f"{tuple(arr.shape)} in the checkpoint, {np.dtype(want.dtype).name}"
                          f"{tuple(want.shape)} in the model")
        leaves.append(place(arr, getattr(want, "sharding", None)))
    return jax.tree_util.tree_unflatten(treedef, leaves)
