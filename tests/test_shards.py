"""Env shards (ppo.num_shards): collectives, placement on devices or in a vmap, determinism, config checks."""

import json
import os
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import cpu_devices_env

from tgrf_jax.config import ConfigError, TrainConfig
from tgrf_jax.train import make_trainer, shards
from tgrf_jax.train.shards import SHARD_AXIS


def sharded_config(**ppo) -> TrainConfig:
    return TrainConfig.from_dict(
        {
            "env": {"num_humans": 3, "predictor": "const_vel"},
            "network": {"name": "mlp"},  # shards split the envs; the network does not matter and MLP compiles fastest
            "ppo": {
                "num_envs": 8,
                "num_steps": 8,
                "total_steps": 8 * 8 * 4,
                "update_epochs": 2,
                "num_minibatches": 2,
                "num_shards": 2,
                **ppo,
            },
        }
    )


def test_shard_sizes_follow_the_config():
    p = sharded_config(num_envs=64, num_minibatches=4, microbatch_envs=4, reset_ratio=8, total_steps=64 * 8).ppo
    assert (p.shard_envs, p.num_microbatches, p.reset_slots) == (32, 2, 4)  # 8-env minibatches in 4-env slices


@pytest.mark.parametrize(
    "ppo, pattern",
    [
        (
            {"num_envs": 12, "num_minibatches": 4},
            r"ppo.num_envs = 12 must be divisible by ppo.num_shards x "
            r"ppo.num_minibatches = 2 x 4",
        ),
        ({"num_shards": 0}, r"ppo.num_shards.*allowed"),
    ],
)
def test_bad_shard_settings_are_rejected_with_the_fields_named(ppo, pattern):
    with pytest.raises(ConfigError, match=pattern):
        sharded_config(**ppo)


def test_statistics_are_taken_over_all_shards():
    """Advantage/value-target means inside a shard see the whole batch, and every shard gets the same result."""
    trainer = make_trainer(sharded_config(), devices=None)
    x = jnp.arange(12.0).reshape(2, 6) ** 2  # two shards of 6 values with different means
    means = jax.vmap(trainer._mean, axis_name=SHARD_AXIS)(x)
    np.testing.assert_allclose(np.asarray(means), [np.mean(np.asarray(x))] * 2, rtol=1e-6)
    keys = jax.vmap(lambda _: trainer.shard_key(jax.random.PRNGKey(0)), axis_name=SHARD_AXIS)(x)
    assert not np.array_equal(keys[0], keys[1])  # shards draw their own envs and minibatches


# One fresh process (the device count is fixed when JAX starts) with two CPU devices trains the same config as the
# shards on one device each (shard_map) and vmapped on one device, the latter twice: compiling these programs is
# most of this file's time, so the tests below share that one process.
PLACEMENTS = r"""
import json, sys, jax, numpy as np
from tgrf_jax.config import TrainConfig
from tgrf_jax.train import make_trainer, shards

def flat(tree):
    return np.concatenate([np.ravel(x) for x in jax.tree_util.tree_leaves(jax.device_get(tree))]).tolist()

def train(t):
    initial = t.jit_init(jax.random.PRNGKey(3), t.default_hparams)
    initial_params = flat(initial.params)  # before jit_run_chunk, which consumes (donates) the state
    # compiled once, as a run compiles it; each chunk's output is the next chunk's input
    compiled = t.jit_run_chunk.lower(initial, np.int32(1)).compile()
    state, _ = compiled(initial, np.int32(2))
    donated = all(x.is_deleted() for x in jax.tree_util.tree_leaves(initial.params))  # updated in place
    state, metrics = compiled(state, np.int32(1))
    return {
        "placement": shards.describe(2, t.mesh), "mesh_is_none": t.mesh is None,
        "params": flat(state.params), "initial_params": initial_params,
        "metrics": {k: float(v) for k, v in metrics.items()},
        "obs": np.asarray(state.obs.humans).ravel().tolist(), "obs_envs": int(state.obs.humans.shape[0]),
        "update": int(state.update), "donated": donated,
    }

cfg = TrainConfig.from_dict(json.loads(sys.argv[1]))
mesh, vmap = make_trainer(cfg, devices="auto"), make_trainer(cfg, devices=None)
print(json.dumps({"devices": len(jax.devices()), "mesh": train(mesh), "vmap": train(vmap), "vmap_again": train(vmap)}))
"""


@pytest.fixture(scope="module")
def placements():
    env = dict(os.environ, JAX_PLATFORMS="cpu", **cpu_devices_env(2))
    # the timeout is a hang guard for a busy machine, not a speed check
    out = subprocess.run(
        [sys.executable, "-c", PLACEMENTS, json.dumps(sharded_config().to_dict())],
        env=env,
        capture_output=True,
        text=True,
        timeout=900,
    )
    assert out.returncode == 0, out.stderr
    return json.loads(out.stdout.strip().splitlines()[-1])


def test_sharded_training_is_deterministic_and_learns_something(placements):
    a, b = placements["vmap"], placements["vmap_again"]
    assert a["mesh_is_none"] and b["mesh_is_none"]
    assert a["params"] == b["params"] and a["metrics"] == b["metrics"] and a["obs"] == b["obs"]
    params, initial = np.asarray(a["params"]), np.asarray(a["initial_params"])
    assert np.all(np.isfinite(params)) and np.abs(params - initial).max() > 1e-4
    assert a["obs_envs"] == 8 and a["update"] == 3  # whole-batch layout between chunks
    assert a["donated"] and placements["mesh"]["donated"]  # a chunk consumes the state it is given


def test_shards_on_two_devices_match_shards_vmapped_on_one(placements):
    """The same config on one CPU device per shard (shard_map) and vmapped on one device: the same numbers up to
    float rounding."""
    r = placements
    assert r["devices"] == 2
    mesh, vmap = r["mesh"], r["vmap"]
    assert mesh["placement"] == "2 shards on devices 0, 1" and vmap["placement"] == "2 shards vmapped on one device"
    assert not mesh["mesh_is_none"]
    np.testing.assert_allclose(mesh["params"], vmap["params"], rtol=1e-4, atol=1e-6)
    np.testing.assert_allclose(mesh["obs"], vmap["obs"], rtol=1e-4, atol=1e-5)
    assert mesh["metrics"]["episodes"] == vmap["metrics"]["episodes"]
    np.testing.assert_allclose(mesh["metrics"]["loss"], vmap["metrics"]["loss"], rtol=1e-4, atol=1e-6)


def test_a_mesh_needs_one_device_per_shard():
    assert shards.shard_mesh(1) is None and shards.shard_mesh(2, None) is None
    if len(jax.local_devices()) < 2:
        assert shards.shard_mesh(2) is None  # "auto" falls back to vmapping the shards
    with pytest.raises(ValueError, match="needs as many devices"):
        shards.shard_mesh(2, jax.local_devices()[:1])
    with pytest.raises(ValueError, match="allowed 'auto'"):
        shards.shard_mesh(2, "gpu")
