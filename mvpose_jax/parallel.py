"""Data parallelism over a device mesh, with JAX's own distribution (no other library).

One mesh axis, ``"data"``: batches are split along their leading axis, one block per device;
parameters and optimiser state are replicated on every device. Under `jax.jit` the compiler
partitions each step from those input shardings (per-device forward and backward on the local
block, then one all-reduce of the gradients), so the training code itself stays unchanged.

Several hosts: every process runs the same program and calls `initialize_distributed` first; the
mesh then spans every process's devices. Each process computes the same global batch (the data
stream is deterministic from the seed) and hands over only the blocks of its own devices.

This module imports only jax and numpy; `train` and `inference` use it.
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

DATA_AXIS = "data"


def initialize_distributed(
    coordinator_address: str | None = None,
    num_processes: int | None = None,
    process_id: int | None = None,
) -> bool:
    """Joins a multi-host run (`jax.distributed.initialize`) when one is asked for.

    Args:
      coordinator_address: ``host:port`` of process 0 (None: read by jax from the environment,
        ``JAX_COORDINATOR_ADDRESS``, or found by its cluster detection on Slurm, TPU pods, ...).
      num_processes: processes in the run (None: ``JAX_NUM_PROCESSES`` or cluster detection).
      process_id: this process's index, 0 .. num_processes - 1 (None: ``JAX_PROCESS_ID`` or
        cluster detection).
    Returns:
      True when `jax.distributed.initialize` was called; False when nothing asks for several
      processes (no argument given and none of the three environment variables set), so a
      single-host run never waits for a coordinator.
    """
    env = ("JAX_COORDINATOR_ADDRESS", "JAX_NUM_PROCESSES", "JAX_PROCESS_ID")
    asked = (coordinator_address, num_processes, process_id)
    if all(a is None for a in asked) and not any(os.environ.get(v) for v in env):
        return False
    jax.distributed.initialize(
        coordinator_address=coordinator_address, num_processes=num_processes, process_id=process_id
    )
    return True


def resolve_num_devices(spec: str | int | None) -> int | None:
    """``--devices`` as a device count: None stays None (one device, no mesh), "all" is every
    device of every process (call after `initialize_distributed`), a number is itself."""
    if spec is None:
        return None
    return jax.device_count() if spec == "all" else int(spec)


def make_data_mesh(
    num_devices: int | None = None, devices: Sequence[jax.Device] | None = None
) -> Mesh:
    """A one-axis ``("data",)`` mesh over the first ``num_devices`` devices (of every process).

    Args:
      num_devices: devices to use (None: all of them).
      devices: the devices to pick from (default `jax.devices()`, global across processes).
    Raises:
      ValueError when more devices are asked for than exist.
    """
    devices = list(jax.devices() if devices is None else devices)
    n = len(devices) if num_devices is None else int(num_devices)
    if not 1 <= n <= len(devices):
        raise ValueError(f"asked for {n} devices, {len(devices)} available ({devices[0].platform})")
    # Auto axes: the compiler propagates shardings through the step (the model code needs no
    # sharding annotations; jax's default Explicit axes would ask every op to type its sharding).
    return jax.make_mesh(
        (n,), (DATA_AXIS,), axis_types=(jax.sharding.AxisType.Auto,), devices=devices[:n]
    )


def mesh_size(mesh: Mesh) -> int:
    """Devices along the data axis."""
    return int(mesh.shape[DATA_AXIS])


def data_sharding(mesh: Mesh) -> NamedSharding:
    """Leading axis split along ``"data"``, the rest whole on each device."""
    return NamedSharding(mesh, PartitionSpec(DATA_AXIS))


def replicated(mesh: Mesh) -> NamedSharding:
    """Every device holds the whole array."""
    return NamedSharding(mesh, PartitionSpec())


def shard_batch(mesh: Mesh, batch: Any) -> Any:
    """Splits every leaf of a batch pytree along its leading axis over the mesh's devices.

    Args:
      batch: pytree of (B, ...) arrays (numpy or jax), the GLOBAL batch; B a multiple of the
        device count (pad first: `pad_leading`).
    Returns:
      The same pytree of global jax arrays, block i of B / devices rows on device i.
    Raises:
      ValueError when a leading axis does not divide evenly.
    """
    n = mesh_size(mesh)
    for leaf in jax.tree.leaves(batch):
        if np.ndim(leaf) == 0 or np.shape(leaf)[0] % n:
            raise ValueError(
                f"leading axis of shape {np.shape(leaf)} does not split over {n} devices"
            )
    return _put(batch, data_sharding(mesh))


def replicate(mesh: Mesh, tree: Any) -> Any:
    """Copies every leaf of a pytree (parameters, optimiser state, ...) to every mesh device."""
    return _put(tree, replicated(mesh))


def pad_leading(x: np.ndarray | jax.Array, multiple: int) -> np.ndarray | jax.Array:
    """Zero-pads the leading axis of ``x`` (N, ...) to the next multiple of ``multiple``."""
    extra = -np.shape(x)[0] % multiple
    if not extra:
        return x
    pad = [(0, extra)] + [(0, 0)] * (np.ndim(x) - 1)
    return np.pad(x, pad) if isinstance(x, np.ndarray) else jnp.pad(x, pad)


def padded_size(n: int, multiple: int) -> int:
    """The smallest multiple of ``multiple`` that is >= n."""
    return math.ceil(n / multiple) * multiple


def to_host(x: jax.Array) -> np.ndarray:
    """A global array as one numpy array on this host (gathers other processes' blocks)."""
    if isinstance(x, jax.Array) and not x.is_fully_addressable:
        from jax.experimental import multihost_utils

        return np.asarray(multihost_utils.process_allgather(x, tiled=True))
    return np.asarray(x)


def _put(tree: Any, sharding: NamedSharding) -> Any:
    if jax.process_count() == 1:
        return jax.device_put(tree, sharding)

    # Several processes: every process holds the same global values; each builds the blocks of
    # its own devices from them (device_put cannot address other processes' devices).
    def one(x):
        host = np.asarray(x)
        return jax.make_array_from_callback(host.shape, sharding, lambda index: host[index])

    return jax.tree.map(one, tree)
