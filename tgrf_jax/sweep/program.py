"""A sweep's compiled program and its placement: G runs with a leading run axis split over D devices.

    state = stack([jit(trainer.init)(key_i, hparams_i) for each run])   # tgrf-train's init, run by run
    chunk = jit(shard_map(vmap(trainer.run_chunk)))     # n updates of all G runs, one compiled program
                                                        # (a device holding one run: run_chunk unbatched)

`BatchedTrainer` holds those compiled pieces for one static configuration and one device mesh (shared by the
sweeps of a process); the outer loop's `Program`s of a sweep are `BatchedProgram` (the runs of one sweep on a
`BatchedTrainer`) and `SequentialProgram` (the runs in turn, each through tgrf-train's `SoloProgram`).

The run axis is split over all devices (a `jax.sharding.Mesh` with one axis, "runs"; G is padded to a multiple
of the device count with copies of the last run, and the padding is dropped from every result), across hosts too
(multi-controller JAX). Inside `shard_map` each device vmaps over its own runs, so the runs never communicate.

The batched program is compiled differently from the single-run one, so a run in a sweep agrees with its
tgrf-train run up to float32 rounding, not bit for bit; so do different device counts. Bit-identical: a one-run
sweep and the tgrf-train run, a resumed sweep and an uninterrupted one, and equal numbers of runs per device.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np
import yaml

from tgrf_jax.config import ConfigError, TrainConfig, griddable_fields

AXIS = "runs"  # mesh axis name of the run dimension


def _host(tree):
    """Device arrays -> host numpy (all processes get the full arrays, also when sharded over several hosts)."""
    import jax
    from jax.experimental import multihost_utils

    def one(x):
        if isinstance(x, jax.Array) and not x.is_fully_addressable:
            return np.asarray(multihost_utils.process_allgather(x, tiled=True))
        return np.asarray(jax.device_get(x))

    return jax.tree_util.tree_map(one, tree)


def _place(tree, sharding):
    """Host arrays with a leading run axis -> global jax.Arrays split over the mesh (works across hosts)."""
    import jax

    def one(x):
        x = np.asarray(x)
        return jax.make_array_from_callback(x.shape, sharding, lambda idx: x[idx])

    return jax.tree_util.tree_map(one, tree)


def _pad(tree, g_pad: int):
    """Pad the leading run axis to g_pad with copies of the last run."""

    def one(x):
        x = np.asarray(x)
        if x.shape[0] == g_pad:
            return x
        return np.concatenate([x, np.repeat(x[-1:], g_pad - x.shape[0], axis=0)], axis=0)

    import jax

    return jax.tree_util.tree_map(one, tree)


def _stack(trees):
    import jax

    return jax.tree_util.tree_map(lambda *xs: np.stack([np.asarray(x) for x in xs]), *trees)


def _take(tree, i):
    import jax

    return jax.tree_util.tree_map(lambda x: x[i], tree)


def _per_run(f, n_batched: int | None = None):
    """f over the leading (run) axis of the first `n_batched` arguments (default: all): vmapped, except where a
    device holds a single run, which runs f itself (tgrf-train's unbatched program, without vmap's overheads,
    e.g. a `lax.cond` turned into a select that evaluates both branches)."""
    import jax

    def g(*args):
        k = len(args) if n_batched is None else n_batched
        batched, rest = args[:k], args[k:]
        if jax.tree_util.tree_leaves(batched)[0].shape[0] == 1:
            out = f(*jax.tree_util.tree_map(lambda x: x[0], batched), *rest)
            return jax.tree_util.tree_map(lambda x: x[None], out)
        return jax.vmap(f, in_axes=(0,) * k + (None,) * len(rest))(*batched, *rest)

    return g


class BatchedTrainer:
    """A `Trainer`'s compiled pieces for runs along a leading run axis split over one device mesh.

    `run_chunk(state, n)` (once `compile`d for the state's run count) and `eval_stats(params, env_params, key,
    n_episodes)` take and return pytrees with a leading run axis split over the mesh; inside `shard_map` each
    device vmaps over its own runs (or, holding one run, runs the unbatched function), so the runs never
    communicate. `init_one(key, hparams)` is tgrf-train's single-run init.
    """

    def __init__(self, config: TrainConfig, devices):
        import jax
        from jax.sharding import Mesh, NamedSharding
        from jax.sharding import PartitionSpec as P

        from tgrf_jax.env import CrowdNavEnv
        from tgrf_jax.evaluate import run_episodes
        from tgrf_jax.policies.learned import LearnedPolicy
        from tgrf_jax.train.ppo import make_trainer

        self.config = config
        self.devices = tuple(devices)
        self.mesh = Mesh(np.array(self.devices), (AXIS,))
        self.sharding = NamedSharding(self.mesh, P(AXIS))
        # the run axis takes the devices; a run's env shards (ppo.num_shards) are vmapped on its device
        trainer = make_trainer(config, devices=None)
        self.trainer = trainer
        spec = P(AXIS)

        def smap(f, n_in, replicated_last=False):
            in_specs = tuple([spec] * n_in + ([P()] if replicated_last else []))
            # check_vma off: the runs never communicate, and loops that start from replicated values (the shared
            # evaluation key) would otherwise need explicit casts
            return jax.shard_map(f, mesh=self.mesh, in_specs=in_specs, out_specs=spec, check_vma=False)

        # Runs are initialised one at a time with tgrf-train's own jit(trainer.init) (bit-identical initial states),
        # not with vmap(trainer.init): on XLA:CPU the vmapped init (batched LAPACK QR of the orthogonal
        # initialisers) can deadlock at execution, every worker thread idle.
        self.init_one = jax.jit(trainer.init)

        def run_chunk(ts, n_updates):
            return smap(_per_run(trainer.run_chunk, n_batched=1), 1, replicated_last=True)(ts, n_updates)

        # out_shardings pins every output leaf to the run axis: zero-element leaves (no obstacle slots, no LiDAR)
        # would otherwise come back replicated, and the compiled chunk refuses them as its next input
        self.jit_run_chunk = jax.jit(run_chunk, donate_argnums=0, out_shardings=self.sharding)
        net = trainer.net
        self.eval_env = CrowdNavEnv(
            dataclasses.replace(config.env, track_future_intrusion=True, replay_augment=False), config.reward
        )

        def eval_stats(params, env_params, key, n_episodes):
            def one(p, ep, k):
                return run_episodes(self.eval_env, LearnedPolicy(net, p), k, n_episodes, ep)

            return smap(_per_run(one, n_batched=2), 2, replicated_last=True)(params, env_params, key)

        self.eval_stats = jax.jit(eval_stats, static_argnums=3)
        self.compiled: dict[int, Any] = {}  # G_pad -> jit_run_chunk compiled ahead of time (count traced)

    def is_compiled(self, state) -> bool:
        return _padded_runs(state) in self.compiled

    def compile(self, state) -> None:
        self.compiled[_padded_runs(state)] = self.jit_run_chunk.lower(state, np.int32(1)).compile()

    def run_chunk(self, state, n_updates: int):
        return self.compiled[_padded_runs(state)](state, np.int32(n_updates))


def _padded_runs(state) -> int:
    """The length of a stacked state's run axis: the batch size a chunk is compiled for."""
    return int(np.shape(state.update)[0])


_TRAINERS: dict[tuple, BatchedTrainer] = {}


def _static_signature(config: TrainConfig) -> str:
    """Everything of a config except the griddable fields and the run section (which the trainer never reads)."""
    data = config.to_dict()
    for name in griddable_fields():
        section, field = name.split(".", 1)
        data[section].pop(field, None)
    data.pop("run", None)
    return yaml.safe_dump(data, sort_keys=True)


def batched_trainer(config: TrainConfig, devices) -> BatchedTrainer:
    """One BatchedTrainer per (static config, devices) per process (repeated sweeps reuse compilations)."""
    key = (_static_signature(config), tuple(d.id for d in devices))
    if key not in _TRAINERS:
        _TRAINERS[key] = BatchedTrainer(config, devices)
    return _TRAINERS[key]


def barrier(name: str) -> None:
    """Wait for every process (multi-host sweeps)."""
    import jax

    if jax.process_count() > 1:
        from jax.experimental import multihost_utils

        multihost_utils.sync_global_devices(name)


def evaluate_runs(batched: BatchedTrainer, runs, params, g_pad: int, episodes: int, seed: int) -> list[dict]:
    """The final evaluation of every run in one batched program: per run the same episodes (keys) and env
    parameters as `tgrf_jax.evaluate.evaluate_state` use for that run alone."""
    import jax

    from tgrf_jax.env import CrowdNavEnv
    from tgrf_jax.evaluate import summarize

    envs = [
        CrowdNavEnv(
            dataclasses.replace(r.config.env, track_future_intrusion=True, replay_augment=False), r.config.reward
        )
        for r in runs
    ]
    env_params = _place(_pad(_stack([e.default_params for e in envs]), g_pad), batched.sharding)
    key = jax.random.fold_in(jax.random.key(seed), 0)  # `evaluate` with one batch of all episodes
    stats = _host(batched.eval_stats(params, env_params, key, episodes))
    out = []
    for i, r in enumerate(runs):
        res = summarize(_take(stats, i))
        out.append(
            {
                "env": repr(CrowdNavEnv(r.config.env, r.config.reward)),
                "episodes": episodes,
                "seed": seed,
                "results": {"learned": res.to_dict()},
            }
        )
    return out


def _run_inputs(runs):
    """(hparams, keys) of every run, stacked: what tgrf-train derives from each run's config."""
    import jax

    from tgrf_jax.train.ppo import check_hparams, hparams_from_config

    hps = [hparams_from_config(r.config) for r in runs]
    shapes = [jax.tree_util.tree_map(lambda x: (np.shape(x), np.asarray(x).dtype), h) for h in hps]
    struct0 = jax.tree_util.tree_structure(hps[0])
    for r, h, s in zip(runs, hps, shapes):
        if jax.tree_util.tree_structure(h) != struct0 or s != shapes[0]:
            raise ConfigError(
                f"run {r.name}: its hyper-parameters have another structure than run "
                f"{runs[0].name}'s; it cannot share the compiled program"
            )
    hparams = _stack(hps)
    check_hparams(hparams, runs[0].config.env)  # each run's concrete values, as tgrf-train's init checks them
    return hparams, _stack([jax.random.PRNGKey(r.config.run.seed) for r in runs])


def _restore_stacked(checkpointer, trainer, keys, hparams, step: int):
    """A sweep checkpoint (every run's state along a leading run axis) on the host, and the update it holds."""
    import jax

    from tgrf_jax.storage.checkpoint import CheckpointError

    template = jax.eval_shape(jax.vmap(trainer.init), keys, hparams)
    host_state = _host(checkpointer.restore(template, step))
    updates = sorted(set(np.asarray(host_state.update).tolist()))
    if len(updates) != 1:
        raise CheckpointError(
            f"checkpoint {str(checkpointer.directory / str(step))!r} holds runs at different updates {updates}"
        )
    return host_state, updates[0]


class BatchedProgram:
    """The outer loop's `Program` for the runs of one sweep on a `BatchedTrainer`: per run the traced
    hyper-parameters and key that tgrf-train derives from that run's config, stacked, padded and placed on the
    trainer's mesh."""

    def __init__(self, runs, devices):
        self.runs = runs
        configs = [r.config for r in runs]
        self.num_runs = G = len(runs)
        self.num_devices = D = len(devices)
        self.g_pad = -(-G // D) * D
        self.hparams, self.keys = _run_inputs(runs)
        self.batched = batched_trainer(configs[0], devices)
        self.config = configs[0]
        self.num_updates = self.batched.trainer.num_updates
        self.batch_size = self.config.ppo.batch_size

    def _placed(self, host_state):
        return _place(_pad(host_state, self.g_pad), self.batched.sharding)

    def init(self):
        init = self.batched.init_one
        return self._placed(_stack([_host(init(self.keys[i], _take(self.hparams, i))) for i in range(self.num_runs)]))

    def restore(self, checkpointer, step: int):
        host_state, update = _restore_stacked(checkpointer, self.batched.trainer, self.keys, self.hparams, step)
        return self._placed(host_state), update

    def is_compiled(self, state) -> bool:
        return self.batched.is_compiled(state)

    def compile(self, state) -> None:
        self.batched.compile(state)

    def run_chunk(self, state, n_updates: int):
        return self.batched.run_chunk(state, n_updates)

    def run_metrics(self, metrics) -> list[dict]:
        metrics = _host(metrics)
        return [{k: float(v[i]) for k, v in metrics.items()} for i in range(self.num_runs)]

    def host_state(self, state):
        return _take(_host(state), slice(0, self.num_runs))

    def evaluate(self, state, episodes: int, seed: int) -> list[dict]:
        return evaluate_runs(self.batched, self.runs, state.params, self.g_pad, episodes, seed)

    def describe(self, state) -> str:
        import jax

        c, p = self.config, self.config.ppo
        n_params = self.batched.trainer.net.num_params(_take(_host(state.params), 0))
        pad = f", padded to {self.g_pad}" if self.g_pad != self.num_runs else ""
        return (
            f"{self.num_runs} runs{pad} on {self.num_devices} {jax.devices()[0].platform} device(s), "
            f"{self.g_pad // self.num_devices} run(s) per device | {self.batched.trainer.env} | "
            f"{c.network.name}/{c.network.size} ({n_params:,} params) | {p.num_envs} envs x {p.num_steps} "
            f"steps, {self.num_updates} updates = {self.num_updates * p.batch_size:,} env steps per run"
        )


class SequentialProgram:
    """The outer loop's `Program` for a sweep whose runs take turns: each chunk trains every run in turn through
    tgrf-train's own compiled chunk, with that run's env shards on the devices as tgrf-train places them. One
    program for all runs (their hyper-parameters are traced), and every run is bit-identical to its tgrf-train
    run. On CPUs it trains large configs faster than the batched layout (docs/benchmarks.md); its checkpoints
    hold the batched layout's stacked state. Single-host only."""

    def __init__(self, runs, devices):
        import jax

        from tgrf_jax.train.run_dir import SoloProgram

        if jax.process_count() > 1:
            raise ConfigError("the sequential layout runs on one host; use the batched layout for multi-host sweeps")
        self.runs = runs
        self.num_runs = len(runs)
        self.hparams, self.keys = _run_inputs(runs)
        self.config = runs[0].config
        shards = self.config.ppo.num_shards
        # tgrf-train's placement: one device per env shard where the sweep has enough, else the shards vmapped
        on_devices = len(devices) >= shards > 1
        self.solo = SoloProgram(self.config, list(devices)[:shards] if on_devices else None)
        self.num_devices = shards if on_devices else 1
        self.trainer = self.solo.trainer
        self.num_updates = self.solo.num_updates
        self.batch_size = self.solo.batch_size

    def init(self):
        return [self.trainer.jit_init(self.keys[i], _take(self.hparams, i)) for i in range(self.num_runs)]

    def restore(self, checkpointer, step: int):
        host_state, update = _restore_stacked(checkpointer, self.trainer, self.keys, self.hparams, step)
        return [self.trainer.place(_take(host_state, i)) for i in range(self.num_runs)], update

    def is_compiled(self, states) -> bool:
        return self.solo.is_compiled(states[0])

    def compile(self, states) -> None:
        self.solo.compile(states[0])

    def run_chunk(self, states, n_updates: int):
        out = [self.solo.run_chunk(s, n_updates) for s in states]
        return [o[0] for o in out], [o[1] for o in out]

    def run_metrics(self, metrics) -> list[dict]:
        return [self.solo.run_metrics(m)[0] for m in metrics]

    def host_state(self, states):
        return _stack([_host(s) for s in states])

    def evaluate(self, states, episodes: int, seed: int) -> list[dict]:
        from tgrf_jax.evaluate import evaluate_state

        net = self.trainer.net  # one compiled evaluation for every run
        return [evaluate_state(r.config, s, episodes, seed, net=net) for r, s in zip(self.runs, states)]

    def describe(self, states) -> str:
        return f"{self.num_runs} runs in turn, each as tgrf-train trains it | {self.solo.describe(states[0])}"
