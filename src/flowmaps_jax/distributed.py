"""Devices and hosts: one 1-D data-parallel mesh (axis ``"data"``), batches split along their
leading axis, state replicated, and multi-host start-up (docs/scaling.md). On one device the
training loop builds no mesh.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from flowmaps_jax.validation import check_int

DATA_AXIS = "data"
"""Name of the mesh's only axis: every batch is split along its leading dimension over it."""

# Environment variables that mean "this process is one of several in a cluster job", each with
# the variable holding the process count.
_CLUSTER_MARKERS = {
    "JAX_COORDINATOR_ADDRESS": "JAX_NUM_PROCESSES",  # any launcher (see initialize)
    "SLURM_JOB_ID": "SLURM_NTASKS",  # Slurm srun
    "OMPI_COMM_WORLD_SIZE": "OMPI_COMM_WORLD_SIZE",  # Open MPI mpirun
}


def cluster_environment(env: Mapping[str, str] | None = None) -> str | None:
    """The variable that marks this process as one of several in a job, or None (one host)."""
    env = os.environ if env is None else env
    for name, count in _CLUSTER_MARKERS.items():
        if name in env and _int_or(env.get(count, "1"), 1) > 1:
            return name
    if len([h for h in env.get("TPU_WORKER_HOSTNAMES", "").split(",") if h.strip()]) > 1:
        return "TPU_WORKER_HOSTNAMES"
    return None


def _int_or(text: str, default: int) -> int:
    try:
        return int(text)
    except ValueError:
        return default


def initialize(env: Mapping[str, str] | None = None) -> bool:
    """Start ``jax.distributed`` when a cluster environment is present, before anything touches
    a device (docs/scaling.md says what to set). Returns whether this call connected the
    processes; ValueError saying what to set when JAX cannot connect.
    """
    env = os.environ if env is None else env
    marker = cluster_environment(env)
    if marker is None or jax.distributed.is_initialized():
        return False
    kwargs: dict[str, Any] = {}
    if marker == "JAX_COORDINATOR_ADDRESS":
        if "JAX_PROCESS_ID" not in env:
            raise ValueError("JAX_COORDINATOR_ADDRESS and JAX_NUM_PROCESSES are set but "
                             "JAX_PROCESS_ID is not: set it to this process's index "
                             f"(0..{env['JAX_NUM_PROCESSES']} - 1)")
        kwargs = {"coordinator_address": env["JAX_COORDINATOR_ADDRESS"],
                  "num_processes": _int_or(env["JAX_NUM_PROCESSES"], 1),
                  "process_id": _int_or(env["JAX_PROCESS_ID"], -1)}
    try:
        jax.distributed.initialize(**kwargs)
    except (ValueError, RuntimeError) as err:
        raise ValueError(
            f"{marker} is set, so this looks like a multi-host job, but jax.distributed could "
            f"not start ({err}). Set JAX_COORDINATOR_ADDRESS=host:port, JAX_NUM_PROCESSES and "
            "JAX_PROCESS_ID on every process, or unset the variable for a one-host run") from err
    return True


# --------------------------------------------------------------------------- the mesh


def data_mesh(num_devices: int | None = None) -> Mesh:
    """A 1-D mesh (axis :data:`DATA_AXIS`) over ``jax.devices()`` — every device of every host —
    or over the first ``num_devices`` of them (one host only). ValueError if there are fewer."""
    if num_devices is not None and num_devices != jax.device_count() \
            and jax.process_count() > 1:
        raise ValueError(f"devices={num_devices} on a {jax.process_count()}-host job: a "
                         "multi-host run uses every device (devices=none)")
    return Mesh(np.asarray(_first(jax.devices(), num_devices)), (DATA_AXIS,))


def training_mesh(num_devices: int | None = None) -> Mesh | None:
    """:func:`data_mesh`, or None when it would hold a single device (then nothing is sharded
    and a run compiles exactly the single-device program)."""
    mesh = data_mesh(num_devices)
    return mesh if mesh.size > 1 else None


def local_mesh(num_devices: int | None = None) -> Mesh | None:
    """A mesh over this host's own devices (all, or the first ``num_devices``), or None if that
    is one device."""
    devices = _first(jax.local_devices(), num_devices)
    return Mesh(np.asarray(devices), (DATA_AXIS,)) if len(devices) > 1 else None


def _first(devices: list, num_devices: int | None) -> list:
    """The first ``num_devices`` of ``devices`` (all for None); ValueError if there are fewer."""
    if num_devices is None:
        return devices
    num_devices = check_int(f"devices (JAX sees {len(devices)} {devices[0].platform} device(s); "
                            "none: all)", num_devices, 1, len(devices))
    return devices[:num_devices]


def replicated(mesh: Mesh) -> NamedSharding:
    """Every device holds the whole array (params, EMA, optimiser state, metrics)."""
    return NamedSharding(mesh, PartitionSpec())


def batch_sharding(mesh: Mesh) -> NamedSharding:
    """The leading axis split evenly over the mesh, the rest whole (a batch of scenes)."""
    return NamedSharding(mesh, PartitionSpec(DATA_AXIS))


def check_divides(name: str, size: int, mesh: Mesh | None, what: str = "rows") -> None:
    """ValueError unless ``size`` splits evenly over the mesh's devices (None: one device)."""
    if mesh is None or size % mesh.size == 0:
        return
    n = mesh.size
    low, high = (size // n) * n, (size // n + 1) * n
    options = f"{low} or {high}" if low > 0 else f"{high}"
    raise ValueError(
        f"{name}={size} does not divide evenly over the {n} devices of the mesh ({what} are "
        f"split over devices): use a multiple of {n} (e.g. {options}), or fewer devices "
        f"(--set devices=K with K dividing {size})")


def num_padded(size: int, mesh: Mesh | None) -> int:
    """``size`` rounded up to a multiple of the mesh size (unchanged without a mesh)."""
    if mesh is None:
        return size
    return -(-size // mesh.size) * mesh.size


def shard_rows(tree: Any, mesh: Mesh | None) -> Any:
    """A pytree of arrays with a common leading axis split by rows over the mesh, padded to a
    multiple of its size with the last row (callers drop it with ``[:size]``)."""
    if mesh is None:
        return tree
    leaves = jax.tree.leaves(tree)
    size = leaves[0].shape[0]
    extra = num_padded(size, mesh) - size

    def pad(x):
        if extra:
            x = jnp.concatenate([x, jnp.repeat(x[-1:], extra, axis=0)])
        return x

    return jax.device_put(jax.tree.map(pad, tree), batch_sharding(mesh))


def place(x: Any, sharding: jax.sharding.Sharding | None) -> jax.Array:
    """``x`` on ``sharding``'s devices (None: the default device), also when they span several
    hosts: every host must pass the same value (each fills its own devices from its copy)."""
    if sharding is None or sharding.is_fully_addressable:
        return jax.device_put(x, sharding)
    x = np.asarray(x)
    return jax.make_array_from_callback(x.shape, sharding, lambda index: x[index])


def replicate(tree: Any, mesh: Mesh | None) -> Any:
    """Place a pytree on every device of the mesh (unchanged without a mesh; :func:`place`)."""
    if mesh is None:
        return tree
    sharding = replicated(mesh)
    if sharding.is_fully_addressable:
        return jax.device_put(tree, sharding)
    return jax.tree.map(lambda x: place(x, sharding), tree)


def from_hosts(tree: Any, mesh: Mesh) -> Any:
    """One global batch from each host's rows: host p's ``tree`` (rows (B/P, ...)) becomes rows
    p·B/P .. (p+1)·B/P of a global (B, ...) array split over the mesh. No data crosses hosts."""
    sharding = batch_sharding(mesh)
    return jax.tree.map(
        lambda x: jax.make_array_from_process_local_data(sharding, np.asarray(x)), tree)


# --------------------------------------------------------------------------- hosts


def agree(ok: bool) -> bool:
    """Process 0's ``ok``, on every process (all must call it). One process: ``ok``."""
    if jax.process_count() == 1:
        return bool(ok)
    from jax.experimental import multihost_utils

    return bool(multihost_utils.broadcast_one_to_all(np.int32(bool(ok))))


def barrier(name: str) -> None:
    """Wait until every process of the job reaches this point (no-op on one host)."""
    if jax.process_count() > 1:
        from jax.experimental import multihost_utils

        multihost_utils.sync_global_devices(name)


def host_part(size: int, index: int | None = None, count: int | None = None) -> slice:
    """The slice of ``size`` items (environments, batch rows) this host owns: host p of P owns
    ``[p·size/P, (p+1)·size/P)``. ``size`` must divide by P (ValueError otherwise)."""
    index = jax.process_index() if index is None else index
    count = jax.process_count() if count is None else count
    if size % count:
        raise ValueError(f"{size} does not divide over {count} hosts; use a multiple of {count}")
    per_host = size // count
    return slice(index * per_host, (index + 1) * per_host)


def describe(mesh: Mesh | None) -> str:
    """One line for logs: devices, their kind and hosts."""
    if mesh is None:
        device = jax.devices()[0]
        return f"1 device ({device.platform}: {device.device_kind})"
    device = mesh.devices.flat[0]
    hosts = jax.process_count()
    return (f"{mesh.size} devices ({device.platform}: {device.device_kind}), data-parallel over "
            f"mesh axis '{DATA_AXIS}'" + (f", {hosts} hosts" if hosts > 1 else ""))
