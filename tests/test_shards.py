"""Env shards (ppo.num_shards): collectives, placement on devices or in a vmap, determinism, config checks."""

import json
import os
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from tgrf_jax.config import ConfigError, TrainConfig
from tgrf_jax.train import make_train, shards
from tgrf_jax.train.shards import SHARD_AXIS


def sharded_config(**ppo) -> TrainConfig:
    return TrainConfig.from_dict({
        "env": {"num_humans": 3, "predictor": "const_vel"},
        "network": {"name": "hh_attn"},
        "ppo": {"num_envs": 8, "num_steps": 8, "total_steps": 8 * 8 * 4, "update_epochs": 2, "num_minibatches": 2,
                "num_shards": 2, **ppo},
    })


def flat_params(state):
    return np.concatenate([np.ravel(x) for x in jax.tree_util.tree_leaves(jax.device_get(state.params))])


def test_shard_sizes_follow_the_config():
    p = sharded_config(num_envs=64, num_minibatches=4, microbatch_envs=4, reset_ratio=8, total_steps=64 * 8).ppo
    assert (p.shard_envs, p.num_microbatches, p.reset_slots) == (32, 2, 4)  # 8-env minibatches in 4-env slices


@pytest.mark.parametrize("ppo, pattern", [
    ({"num_envs": 12, "num_minibatches": 4}, r"ppo.num_envs = 12 must be divisible by ppo.num_shards x "
                                             r"ppo.num_minibatches = 2 x 4"),
    ({"num_shards": 0}, r"ppo.num_shards.*allowed"),
])
def test_bad_shard_settings_are_rejected_with_the_fields_named(ppo, pattern):
    with pytest.raises(ConfigError, match=pattern):
        sharded_config(**ppo)


def test_statistics_are_taken_over_all_shards():
    """Advantage/value-target means inside a shard see the whole batch, and every shard gets the same result."""
    trainer = make_train(sharded_config(), devices=None).trainer
    x = jnp.arange(12.0).reshape(2, 6) ** 2  # two shards of 6 values with different means
    means = jax.vmap(trainer._mean, axis_name=SHARD_AXIS)(x)
    np.testing.assert_allclose(np.asarray(means), [np.mean(np.asarray(x))] * 2, rtol=1e-6)
    keys = jax.vmap(lambda _: trainer.shard_key(jax.random.PRNGKey(0)), axis_name=SHARD_AXIS)(x)
    assert not np.array_equal(keys[0], keys[1])  # shards draw their own envs and minibatches


def test_sharded_training_is_deterministic_and_learns_something():
    t = make_train(sharded_config(), devices=None)
    assert t.trainer.mesh is None
    runs = []
    for _ in range(2):
        state, metrics = t.run_chunk(t.init(jax.random.PRNGKey(3), t.default_hparams), 3)
        runs.append((flat_params(state), {k: float(v) for k, v in metrics.items()}, state))
    (a, ma, sa), (b, mb, _) = runs
    np.testing.assert_array_equal(a, b)
    assert ma == mb
    assert np.all(np.isfinite(a)) and np.abs(a - flat_params(t.init(jax.random.PRNGKey(3)))).max() > 1e-4
    assert sa.obs.humans.shape[0] == 8 and int(sa.update) == 3  # whole-batch layout between chunks


PLACEMENTS = r"""
import json, jax, numpy as np
from tgrf_jax.config import TrainConfig
from tgrf_jax.train import make_train, shards

cfg = TrainConfig.from_dict({
    "env": {"num_humans": 3, "predictor": "const_vel"}, "network": {"name": "hh_attn"},
    "ppo": {"num_envs": 8, "num_steps": 8, "total_steps": 256, "update_epochs": 2, "num_minibatches": 2,
            "num_shards": 2}})
out = {"devices": len(jax.devices())}
for name, devices in (("mesh", "auto"), ("vmap", None)):
    t = make_train(cfg, devices=devices)
    state, metrics = t.run_chunk(t.init(jax.random.PRNGKey(0), t.default_hparams), 3)
    out[name] = {
        "placement": shards.describe(2, t.trainer.mesh),
        "params": np.concatenate([np.ravel(x) for x in jax.tree_util.tree_leaves(jax.device_get(state.params))]).tolist(),
        "episodes": float(metrics["episodes"]), "loss": float(metrics["loss"]),
        "obs": np.asarray(state.obs.humans).ravel().tolist(),
    }
print(json.dumps(out))
"""


def test_shards_on_two_devices_match_shards_vmapped_on_one():
    """The same config on one CPU device per shard (shard_map) and vmapped on one device: the same numbers up to
    float rounding (a fresh process: the device count is fixed when JAX starts)."""
    env = dict(os.environ, JAX_PLATFORMS="cpu", XLA_FLAGS="--xla_force_host_platform_device_count=2")
    # the timeout is a hang guard for a busy machine, not a speed check
    out = subprocess.run([sys.executable, "-c", PLACEMENTS], env=env, capture_output=True, text=True, timeout=900)
    assert out.returncode == 0, out.stderr
    r = json.loads(out.stdout.strip().splitlines()[-1])
    assert r["devices"] == 2
    mesh, vmap = r["mesh"], r["vmap"]
    assert mesh["placement"] == "2 shards on devices 0, 1" and vmap["placement"] == "2 shards vmapped on one device"
    np.testing.assert_allclose(mesh["params"], vmap["params"], rtol=1e-4, atol=1e-6)
    np.testing.assert_allclose(mesh["obs"], vmap["obs"], rtol=1e-4, atol=1e-5)
    assert mesh["episodes"] == vmap["episodes"]
    np.testing.assert_allclose(mesh["loss"], vmap["loss"], rtol=1e-4, atol=1e-6)


def test_a_mesh_needs_one_device_per_shard():
    assert shards.shard_mesh(1) is None and shards.shard_mesh(2, None) is None
    if len(jax.local_devices()) < 2:
        assert shards.shard_mesh(2) is None  # "auto" falls back to vmapping the shards
    with pytest.raises(ValueError, match="needs as many devices"):
        shards.shard_mesh(2, jax.local_devices()[:1])
    with pytest.raises(ValueError, match="allowed 'auto'"):
        shards.shard_mesh(2, "gpu")
