"""Where the env shards of a run (`ppo.num_shards`) execute: one device each, or vmapped on one device.

A shard is a slice of the parallel envs with its own rollout and its own minibatches; the shards meet only in
collectives over the axis `SHARD_AXIS` (the mean of every minibatch gradient, advantage and value-target
statistics, episode counts). The numbers depend on `ppo.num_shards`, not on where the shards run, up to float
rounding: separate devices and a vmap on one device reduce in different orders.

On a CPU, XLA spreads one program's small ops over the cores poorly, while programs pinned to one device each run
side by side, so tgrf-train asks for one CPU device per shard (`tgrf_jax.configure_cpu`, docs/design.md).
"""

from __future__ import annotations

import jax
import numpy as np

SHARD_AXIS = "shards"


def shard_mesh(num_shards: int, devices="auto") -> jax.sharding.Mesh | None:
    """The mesh that carries `num_shards` shards, or None to vmap them on one device.

    `devices`: "auto" takes the first `num_shards` local devices of the default backend if there are that many;
    None always vmaps; a sequence of devices must hold exactly `num_shards` of them.
    """
    if num_shards <= 1 or devices is None:
        return None
    if isinstance(devices, str):
        if devices != "auto":
            raise ValueError(f"devices = {devices!r}: allowed 'auto', None or a sequence of devices")
        local = jax.local_devices()
        if len(local) < num_shards:
            return None
        devices = local[:num_shards]
    devices = list(devices)
    if len(devices) != num_shards:
        raise ValueError(f"ppo.num_shards = {num_shards} needs as many devices, got {len(devices)}")
    return jax.sharding.Mesh(np.array(devices), (SHARD_AXIS,))


def describe(num_shards: int, mesh) -> str:
    if num_shards <= 1:
        return "1 shard"
    if mesh is None:
        return f"{num_shards} shards vmapped on one device"
    return f"{num_shards} shards on devices {', '.join(str(d.id) for d in mesh.devices.flat)}"
