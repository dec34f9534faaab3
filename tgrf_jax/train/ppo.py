"""Recurrent PPO as one compiled program (PureJaxRL style, Brax-style chunking).

    trainer = make_trainer(config)                     # static choices: shapes, network, env code paths
    hparams = trainer.default_hparams                  # traced numeric settings (vmap over them for sweeps)
    state = trainer.jit_init(key, hparams)             # TrainState: params, optimiser, envs, carries, RNG
    state, metrics = trainer.jit_run_chunk(state, 10)  # 10 PPO updates (count traced); reduced scalars
    state, metrics = trainer.train(key, hparams)       # the whole run (pure; jit / vmap it)

`init`, `run_chunk` and `train` are pure (vmap, shard_map or jit them); `jit_init` and `jit_run_chunk` are their
compiled forms, placed on the trainer's devices (`jit_run_chunk` consumes the state it is given).

One update: roll out `num_steps` steps in `num_envs` environments (the recurrent carry is reset where the
previous step ended an episode), compute GAE (time-limit truncations bootstrap from V(info.final_obs) evaluated
with the carry after the step; terminations cut the bootstrap), then `update_epochs` epochs over
`num_minibatches` minibatches of whole env sequences, each replayed from the carry stored at rollout step 0.

With `ppo.num_shards` > 1 the envs are split into shards that do all of the above on their own and meet in
collectives (gradient, advantage and value-target means; episode counts), on one device each or vmapped on one
(`Trainer.across_shards`, `tgrf_jax.train.shards`).

Everything stochastic draws from the key inside `TrainState`, so a run is a deterministic function of its seed
and hyper-parameters, and a checkpointed `TrainState` resumes bit-for-bit.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import optax
from flax import struct
from jax.sharding import NamedSharding
from jax.sharding import PartitionSpec as P

from tgrf_jax.config import EnvConfig, PPOConfig, TrainConfig
from tgrf_jax.env import (
    COLLISION,
    OBSTACLE_COLLISION,
    SUCCESS,
    TIMEOUT,
    CrowdNavEnv,
    EnvParams,
    EnvState,
    Obs,
)
from tgrf_jax.fields import check_traced, traced_pytree, traced_values
from tgrf_jax.policies import make_network_for
from tgrf_jax.policies.nets import ActorCritic
from tgrf_jax.train import shards
from tgrf_jax.train.shards import SHARD_AXIS

HParams = traced_pytree(
    "HParams",
    PPOConfig,
    first=(("env", EnvParams),),
    module=__name__,
    doc="""Numeric hyper-parameters, traced: `vmap(train, in_axes=(0, 0))` over seeds x grid points works.

    `env` (which holds the reward parameters) plus one float32 leaf per traced field of `PPOConfig`.""",
)


@struct.dataclass
class ReturnStats:
    """Running mean and variance of value targets (exponential moving averages with bias correction).

    With `ppo.norm_value` the critic head predicts (return - mean) / std. Crowd-navigation returns span about
    -20 to +25, so an unnormalised value loss is ~100x larger than the policy loss, dominates the gradient of the
    shared torso and saturates gradient clipping; standardised targets keep the two losses comparable while GAE
    and bootstrapping still work in reward units."""

    mean: jnp.ndarray
    mean_sq: jnp.ndarray
    weight: jnp.ndarray  # bias correction: 1 - decay^n after n updates

    DECAY = 0.99

    @classmethod
    def create(cls):
        z = jnp.zeros((), jnp.float32)
        return cls(mean=z, mean_sq=z, weight=z)

    def update(self, targets, mean=jnp.mean):
        """`mean`: the batch mean (a mean over all shards when the batch is sharded)."""
        d = self.DECAY
        return ReturnStats(
            mean=d * self.mean + (1 - d) * mean(targets),
            mean_sq=d * self.mean_sq + (1 - d) * mean(jnp.square(targets)),
            weight=d * self.weight + (1 - d),
        )

    def moments(self):
        w = jnp.maximum(self.weight, 1e-6)
        mean = jnp.where(self.weight > 0, self.mean / w, 0.0)
        var = jnp.where(self.weight > 0, self.mean_sq / w - jnp.square(mean), 1.0)
        return mean, jnp.sqrt(jnp.maximum(var, 1e-4))

    def denormalize(self, v):
        mean, std = self.moments()
        return v * std + mean

    def normalize(self, x):
        mean, std = self.moments()
        return (x - mean) / std


@struct.dataclass
class TrainState:
    """Complete state of a run between updates (checkpoint this and a resumed run is bit-identical).

    The per-env fields (`ENV_FIELDS`, leading axis num_envs) are split into `ppo.num_shards` contiguous shards
    during an update; the rest is the same on every shard."""

    params: dict
    opt_state: optax.OptState
    env_state: EnvState
    obs: Obs  # current observation of every env (B, ...)
    carry: dict  # recurrent state before processing `obs`
    resets: jnp.ndarray  # (B,) bool: `obs` starts a new episode (the previous step ended one)
    ep_return: jnp.ndarray  # (B,) return of the running episode so far
    return_stats: ReturnStats  # value-target statistics (used when ppo.norm_value)
    key: jnp.ndarray  # raw uint32 PRNG key
    update: jnp.ndarray  # () int32 updates done
    hparams: HParams


class Transition(NamedTuple):
    obs: Obs
    resets: jnp.ndarray
    action: jnp.ndarray  # unclipped Gaussian sample (the env clips it; log-probs use the sample)
    log_prob: jnp.ndarray
    value: jnp.ndarray
    reward: jnp.ndarray
    done: jnp.ndarray  # terminated | truncated
    truncated: jnp.ndarray
    final_value: jnp.ndarray  # V(info.final_obs) where truncated, else 0


ENV_FIELDS = ("env_state", "obs", "carry", "resets", "ep_return")


def map_fields(ts: TrainState, env_fn, shared_fn) -> TrainState:
    """A TrainState-shaped tree: `env_fn` applied to the leaves of the per-env fields, `shared_fn` to the rest."""
    return ts.replace(
        **{
            f.name: jax.tree_util.tree_map(env_fn if f.name in ENV_FIELDS else shared_fn, getattr(ts, f.name))
            for f in dataclasses.fields(ts)
        }
    )


def field_prefix(env_value, shared_value) -> TrainState:
    """A TrainState prefix tree (one value per field), e.g. vmap axes or shardings."""
    return TrainState(
        **{f.name: env_value if f.name in ENV_FIELDS else shared_value for f in dataclasses.fields(TrainState)}
    )


# Reduced per-update scalars. The episode fields are sums (over the episodes that ended in the update), so chunks
# and runs add them up; the others are averaged.
SUMMED_METRICS = ("episodes", "return_sum", "successes", "collisions", "timeouts")
METRIC_NAMES = SUMMED_METRICS + (
    "loss",
    "pg_loss",
    "vf_loss",
    "entropy",
    "approx_kl",
    "clip_frac",
    "grad_norm",
    "lr",
    "reward_mean",
)


def hparams_from_config(config: TrainConfig, env: CrowdNavEnv | None = None) -> HParams:
    env = env or CrowdNavEnv(config.env, config.reward)
    return HParams(env=env.default_params, **traced_values(config.ppo))


# ------------------------------------------------------------------------------------------------ pure pieces


def compute_gae(rewards, values, dones, truncated, final_values, last_value, gamma, gae_lambda):
    """Generalised advantage estimation over a time-major rollout (T, B).

    values[t] = V(obs_t); last_value = V(obs_T). When step t ends an episode (dones[t]) the next observation
    belongs to a new episode, so V(obs_{t+1}) is not used; a truncated step bootstraps from
    final_values[t] = V(final obs of the ended episode) instead, a terminated one from nothing.
    Returns (advantages, returns = advantages + values).
    """
    dones = dones.astype(jnp.float32)
    truncated = truncated.astype(jnp.float32)
    next_values = jnp.concatenate([values[1:], last_value[None]], axis=0)
    deltas = rewards + gamma * ((1.0 - dones) * next_values + truncated * final_values) - values

    def body(gae, xs):
        delta, done = xs
        gae = delta + gamma * gae_lambda * (1.0 - done) * gae
        return gae, gae

    _, adv = jax.lax.scan(body, jnp.zeros_like(last_value), (deltas, dones), reverse=True)
    return adv, adv + values


def ppo_loss(
    net: ActorCritic,
    params,
    carry0,
    batch: Transition,
    advantages,
    returns,
    hp: HParams,
    clip_value: bool,
    value_stats: ReturnStats | None = None,
):
    """Clipped PPO loss of one minibatch of whole sequences (T, b), replayed from carry0 (b,).

    With `value_stats` the critic's output is a standardised value: targets and the rollout's values (stored in
    reward units) are standardised with the same statistics before the (clipped) value loss."""
    _, pi, values = net.apply_sequence(params, carry0, batch.obs, batch.resets)
    old_values = batch.value
    if value_stats is not None:
        returns = value_stats.normalize(returns)
        old_values = value_stats.normalize(old_values)
    log_prob = pi.log_prob(batch.action)
    ratio = jnp.exp(log_prob - batch.log_prob)
    pg1 = ratio * advantages
    pg2 = jnp.clip(ratio, 1.0 - hp.clip_eps, 1.0 + hp.clip_eps) * advantages
    pg_loss = -jnp.mean(jnp.minimum(pg1, pg2))
    sq = jnp.square(values - returns)
    if clip_value:
        v_clipped = old_values + jnp.clip(values - old_values, -hp.clip_eps, hp.clip_eps)
        sq = jnp.maximum(sq, jnp.square(v_clipped - returns))
    vf_loss = 0.5 * jnp.mean(sq)
    entropy = jnp.mean(pi.entropy())
    loss = pg_loss + hp.vf_coef * vf_loss - hp.ent_coef * entropy
    aux = dict(
        pg_loss=pg_loss,
        vf_loss=vf_loss,
        entropy=entropy,
        approx_kl=jnp.mean((ratio - 1.0) - jnp.log(ratio)),
        clip_frac=jnp.mean((jnp.abs(ratio - 1.0) > hp.clip_eps).astype(jnp.float32)),
    )
    return loss, aux


def split_time_major(x, n):
    """(T, B, ...) -> (n, T, B / n, ...): n groups of whole env sequences."""
    return jnp.moveaxis(x.reshape((x.shape[0], n, x.shape[1] // n) + x.shape[2:]), 1, 0)


def split_envs(x, n):
    """(B, ...) -> (n, B / n, ...)."""
    return x.reshape((n, x.shape[0] // n) + x.shape[1:])


def make_optimizer(adam_eps: float):
    """`(learning_rate, max_grad_norm) -> optax optimiser`: the gradient clipped to global norm `max_grad_norm`,
    then an Adam step of size `learning_rate`.

    Both are injected hyper-parameters: they live in the optimiser state (`opt_state.hyperparams`), so the trainer
    writes traced values there (the scheduled rate of the update, `HParams.max_grad_norm`) and sweeps vmap over
    them like any other leaf of `HParams`."""
    return optax.inject_hyperparams(
        lambda learning_rate, max_grad_norm: optax.chain(
            optax.clip_by_global_norm(max_grad_norm), optax.adam(learning_rate, eps=adam_eps)
        )
    )


# Newer optax names the global norm optax.tree.norm and deprecates optax.global_norm; the oldest optax allowed
# (pyproject.toml) has only the latter.
global_norm = getattr(getattr(optax, "tree", None), "norm", None) or optax.global_norm


def with_hyperparams(opt_state, **values):
    """`opt_state` of `make_optimizer` with its injected hyper-parameters set to `values` (float32 scalars, so the
    state keeps its types through the update's scans)."""
    hyperparams = dict(opt_state.hyperparams, **{k: jnp.asarray(v, jnp.float32) for k, v in values.items()})
    return opt_state._replace(hyperparams=hyperparams)


def learning_rate(ppo: PPOConfig, lr, update, num_updates: int):
    """The learning rate of update `update`: `lr` (traced), or with `ppo.anneal_lr` decaying linearly to 0 over
    the run (an optax schedule of the update index, so the rate is constant within an update)."""
    schedule = optax.linear_schedule(lr, 0.0, num_updates) if ppo.anneal_lr else optax.constant_schedule(lr)
    return schedule(update)


# ---------------------------------------------------------------------------------------------------- trainer


@dataclasses.dataclass(frozen=True, eq=False)
class Trainer:
    """The compiled pieces of one training configuration (see the module docstring).

    `update` works on one shard's TrainState (all of it when ppo.num_shards is 1) and meets the other shards in
    collectives over SHARD_AXIS; `run_chunk` takes and returns the whole TrainState and places the shards on
    the devices of `mesh`, or vmaps them on one device when `mesh` is None (see `tgrf_jax.train.shards`).
    Built by `make_trainer`.
    """

    config: TrainConfig
    env: CrowdNavEnv
    net: ActorCritic
    mesh: jax.sharding.Mesh | None = None

    @property
    def num_shards(self) -> int:
        return self.config.ppo.num_shards

    # Collectives over the shards; with one shard they are the identity (the unsharded program, bit for bit).
    def _pmean(self, tree):
        return tree if self.num_shards == 1 else jax.lax.pmean(tree, SHARD_AXIS)

    def _psum(self, tree):
        return tree if self.num_shards == 1 else jax.lax.psum(tree, SHARD_AXIS)

    def _mean(self, x):
        """Mean over the whole (all shards') batch; shards are equal-sized."""
        return self._pmean(jnp.mean(x))

    def shard_key(self, key):
        """A key of this shard's own (the shards' envs and minibatches draw independent numbers)."""
        return key if self.num_shards == 1 else jax.random.fold_in(key, jax.lax.axis_index(SHARD_AXIS))

    @property
    def state_shardings(self):
        """TrainState prefix of NamedShardings (per-env fields split over the mesh), or None without a mesh."""
        if self.mesh is None:
            return None
        return field_prefix(NamedSharding(self.mesh, P(SHARD_AXIS)), NamedSharding(self.mesh, P()))

    def place(self, ts: TrainState) -> TrainState:
        """Put a TrainState (e.g. restored from a checkpoint) where `jit_run_chunk` expects it."""
        return ts if self.mesh is None else jax.device_put(ts, self.state_shardings)

    def across_shards(self, f):
        """Lift `f(shard TrainState) -> (shard TrainState, shared metrics)` to the whole TrainState."""
        s = self.num_shards
        if s == 1:
            return f
        if self.mesh is not None:
            spec = field_prefix(P(SHARD_AXIS), P())
            # check_vma off: the shared fields come out of pmeans and equal updates, identical on every shard
            return jax.shard_map(f, mesh=self.mesh, in_specs=(spec,), out_specs=(spec, P()), check_vma=False)

        def vmapped(ts):
            split = map_fields(ts, lambda x: x.reshape((s, x.shape[0] // s) + x.shape[1:]), lambda x: x)
            ts, metrics = jax.vmap(f, in_axes=(field_prefix(0, None),), axis_name=SHARD_AXIS)(split)
            ts = map_fields(ts, lambda x: x.reshape((s * x.shape[1],) + x.shape[2:]), lambda x: x[0])
            return ts, jax.tree_util.tree_map(lambda x: x[0], metrics)

        return vmapped

    @property
    def num_updates(self) -> int:
        return self.config.ppo.num_updates

    @property
    def default_hparams(self) -> HParams:
        return hparams_from_config(self.config, self.env)

    # ------------------------------------------------------------------------------------------------ init
    def init(self, key, hparams: HParams | None = None) -> TrainState:
        """Fresh TrainState from a key (raw uint32 or typed)."""
        hparams = self.default_hparams if hparams is None else hparams
        if jnp.issubdtype(jnp.asarray(key).dtype, jax.dtypes.prng_key):
            key = jax.random.key_data(key)
        p = self.config.ppo
        key, k_net, k_env = jax.random.split(key, 3)
        params = self.net.init(k_net)
        obs, env_state = jax.vmap(self.env.reset, in_axes=(0, None))(jax.random.split(k_env, p.num_envs), hparams.env)
        return TrainState(
            params=params,
            opt_state=self.optimizer(**self.optimizer_hparams(hparams, 0)).init(params),
            env_state=env_state,
            obs=obs,
            carry=self.net.initialize_carry(p.num_envs),
            resets=jnp.ones((p.num_envs,), bool),
            ep_return=jnp.zeros((p.num_envs,), jnp.float32),
            return_stats=ReturnStats.create(),
            key=key,
            update=jnp.zeros((), jnp.int32),
            hparams=hparams,
        )

    @property
    def optimizer(self):
        """`(learning_rate, max_grad_norm) -> optax optimiser` (`make_optimizer`): clipping, then Adam."""
        return make_optimizer(self.config.ppo.adam_eps)

    def optimizer_hparams(self, hp: HParams, update) -> dict:
        """The optimiser's injected hyper-parameters for update number `update` (traced)."""
        return {
            "learning_rate": learning_rate(self.config.ppo, hp.lr, update, self.num_updates),
            "max_grad_norm": hp.max_grad_norm,
        }

    # --------------------------------------------------------------------------------------------- rollout
    def rollout(self, ts: TrainState, key):
        """num_steps steps in every env. Returns (ts with new env/obs/carry, transitions (T, B), carry0, last_value,
        episode sums)."""
        p = self.config.ppo
        net, env, hp = self.net, self.env, ts.hparams
        to_reward_units = ts.return_stats.denormalize if p.norm_value else (lambda v: v)

        def env_step(runner, k):
            env_state, obs, carry, resets, ep_return = runner
            k_act, k_env = jax.random.split(k)
            carry, pi, value = net.apply(ts.params, carry, obs, resets)
            value = to_reward_units(value)
            action = pi.sample(seed=k_act)
            log_prob = pi.log_prob(action)
            next_obs, env_state, reward, terminated, truncated, info = env.step_batch(
                k_env, env_state, action, hp.env, p.reset_slots
            )
            done = terminated | truncated

            # Bootstrap value of truncated episodes: V(final_obs) with the carry after this step. Only computed
            # when some env truncated (rare: once per 200 steps at most).
            def final_values(_):
                return to_reward_units(net.apply(ts.params, carry, info.final_obs, None)[2])

            final_value = jax.lax.cond(jnp.any(truncated), final_values, lambda _: jnp.zeros_like(value), None)
            final_value = jnp.where(truncated, final_value, 0.0)
            ep_return = ep_return + reward
            outcome = info.outcome
            ep = dict(
                episodes=jnp.sum(done),
                return_sum=jnp.sum(jnp.where(done, ep_return, 0.0)),
                successes=jnp.sum(done & (outcome == SUCCESS)),
                collisions=jnp.sum(done & ((outcome == COLLISION) | (outcome == OBSTACLE_COLLISION))),
                timeouts=jnp.sum(done & (outcome == TIMEOUT)),
            )
            ep_return = jnp.where(done, 0.0, ep_return)
            tr = Transition(obs, resets, action, log_prob, value, reward, done, truncated, final_value)
            return (env_state, next_obs, carry, done, ep_return), (tr, ep)

        runner = (ts.env_state, ts.obs, ts.carry, ts.resets, ts.ep_return)
        runner, (traj, ep) = jax.lax.scan(env_step, runner, jax.random.split(key, p.num_steps))
        env_state, obs, carry, resets, ep_return = runner
        last_value = to_reward_units(net.apply(ts.params, carry, obs, resets)[2])
        carry0 = ts.carry
        ts = ts.replace(env_state=env_state, obs=obs, carry=carry, resets=resets, ep_return=ep_return)
        ep = {k: jnp.sum(v).astype(jnp.float32) for k, v in ep.items()}
        return ts, traj, carry0, last_value, ep

    # ---------------------------------------------------------------------------------------------- update
    def update(self, ts: TrainState) -> tuple[TrainState, dict]:
        """One PPO update: rollout -> GAE -> epochs x minibatches. Returns (ts, reduced scalar metrics)."""
        p = self.config.ppo
        hp = ts.hparams
        key, k_roll, k_perm = jax.random.split(ts.key, 3)
        ts, traj, carry0, last_value, ep = self.rollout(ts, self.shard_key(k_roll))

        # --- advantages
        adv, returns = compute_gae(
            traj.reward, traj.value, traj.done, traj.truncated, traj.final_value, last_value, hp.gamma, hp.gae_lambda
        )
        if p.norm_adv:  # moments of the whole batch: all shards' advantages
            adv_mean = self._mean(adv)
            adv = (adv - adv_mean) / (jnp.sqrt(self._mean(jnp.square(adv - adv_mean))) + 1e-5)
        return_stats = ts.return_stats.update(returns, self._mean) if p.norm_value else ts.return_stats
        value_stats = return_stats if p.norm_value else None

        # the rate (constant within an update) and the clipping norm enter the optimiser state as traced values
        opt_hparams = self.optimizer_hparams(hp, ts.update)
        optimizer = self.optimizer(**opt_hparams)
        opt_state = with_hyperparams(ts.opt_state, **opt_hparams)
        # --- epochs x minibatches over envs (whole sequences)
        n_mb = p.num_minibatches
        loss_grad = jax.value_and_grad(ppo_loss, argnums=1, has_aux=True)

        def minibatch_grad(params, mb):
            """Loss, aux and gradient of one minibatch, accumulated over `p.num_microbatches` equal env slices: the
            loss is a mean over equal-sized slices, so the mean of their gradients is the minibatch's gradient."""
            n_micro = p.num_microbatches
            if n_micro == 1:
                c0, batch, a, r = mb
                return loss_grad(self.net, params, c0, batch, a, r, hp, p.clip_value, value_stats)
            split_t = lambda x: split_time_major(x, n_micro)
            split_c = lambda x: split_envs(x, n_micro)
            c0, batch, a, r = mb
            slices = (
                jax.tree_util.tree_map(split_c, c0),
                jax.tree_util.tree_map(split_t, batch),
                split_t(a),
                split_t(r),
            )

            def accumulate(total, sl):
                out = loss_grad(self.net, params, *sl, hp, p.clip_value, value_stats)
                return jax.tree_util.tree_map(jnp.add, total, out), None

            zeros = jax.tree_util.tree_map(
                lambda s: jnp.zeros(s.shape, s.dtype),
                jax.eval_shape(
                    lambda: loss_grad(
                        self.net, params, *jax.tree_util.tree_map(lambda x: x[0], slices), hp, p.clip_value, value_stats
                    )
                ),
            )
            total, _ = jax.lax.scan(accumulate, zeros, slices)
            return jax.tree_util.tree_map(lambda x: x / n_micro, total)

        def minibatch_step(carry, mb):
            params, opt_state = carry
            (loss, aux), grads = self._pmean(minibatch_grad(params, mb))
            updates, opt_state = optimizer.update(grads, opt_state, params)
            params = optax.apply_updates(params, updates)
            return (params, opt_state), dict(aux, loss=loss, grad_norm=global_norm(grads))  # before clipping

        def epoch(carry, k):
            perm = jax.random.permutation(self.shard_key(k), p.shard_envs)
            take_env = lambda x, axis: jnp.take(x, perm, axis=axis)
            # time-major data (T, B, ...) -> (n_mb, T, b, ...); carries (B, ...) -> (n_mb, b, ...)
            split_t = lambda x: split_time_major(take_env(x, 1), n_mb)
            split_c = lambda x: split_envs(take_env(x, 0), n_mb)
            mbs = (
                jax.tree_util.tree_map(split_c, carry0),
                jax.tree_util.tree_map(split_t, traj),
                split_t(adv),
                split_t(returns),
            )
            return jax.lax.scan(minibatch_step, carry, mbs)

        (params, opt_state), losses = jax.lax.scan(
            epoch, (ts.params, opt_state), jax.random.split(k_perm, p.update_epochs)
        )
        metrics = {k: jnp.mean(v) for k, v in losses.items()}
        metrics.update(self._psum(ep), lr=opt_state.hyperparams["learning_rate"], reward_mean=self._mean(traj.reward))
        ts = ts.replace(params=params, opt_state=opt_state, return_stats=return_stats, key=key, update=ts.update + 1)
        return ts, metrics

    # --------------------------------------------------------------------------------------- chunks / train
    def run_chunk(self, ts: TrainState, n_updates) -> tuple[TrainState, dict]:
        """`n_updates` updates (pure). The count is traced, so one compiled program runs chunks of any length:
        a run's log, checkpoint and evaluation periods never compile the trainer again. Metrics are reduced over
        the chunk: episode fields summed, the rest averaged over updates."""

        def shard_updates(ts):
            n = jnp.asarray(n_updates, jnp.int32)
            metrics = {k: jnp.zeros((), jnp.float32) for k in METRIC_NAMES}

            def body(_, carry):
                ts, sums = carry
                ts, m = self.update(ts)
                return ts, {k: sums[k] + m[k] for k in sums}

            ts, sums = jax.lax.fori_loop(0, n, body, (ts, metrics))
            mean_of = jnp.maximum(n, 1).astype(jnp.float32)
            return ts, {k: v if k in SUMMED_METRICS else v / mean_of for k, v in sums.items()}

        return self.across_shards(shard_updates)(ts)

    # ------------------------------------------------------------------------------------- compiled forms
    # Cached per trainer: every call of one trainer's jitted functions shares their compilations.
    @functools.cached_property
    def jit_init(self) -> Callable[..., TrainState]:
        """`init`, jitted and placed for `jit_run_chunk`; hand-built hyper-parameters are checked as a config's
        would be (concrete values only: use `init` under vmap)."""
        jitted = jax.jit(self.init, out_shardings=self.state_shardings)

        def init(key, hparams: HParams | None = None) -> TrainState:
            if hparams is not None:
                check_hparams(hparams, self.config.env)
            return jitted(key, hparams)

        return init

    @functools.cached_property
    def jit_run_chunk(self) -> Callable[[TrainState, Any], tuple[TrainState, dict]]:
        """`run_chunk`, jitted; the state is donated: a chunk updates it in place rather than holding two
        copies."""
        # Pinned output shardings: zero-element leaves (no obstacle slots, no LiDAR) would otherwise come back
        # replicated, and the compiled chunk refuses them as its next input.
        pinned = {} if self.mesh is None else {"out_shardings": (self.state_shardings, NamedSharding(self.mesh, P()))}
        return jax.jit(self.run_chunk, donate_argnums=0, **pinned)

    def _scan_updates(self, ts: TrainState, n_updates: int) -> tuple[TrainState, dict]:
        """`n_updates` updates of one shard in a lax.scan; metrics per update."""
        return jax.lax.scan(lambda s, _: self.update(s), ts, None, length=n_updates)

    def train(self, key, hparams: HParams | None = None) -> tuple[TrainState, dict]:
        """The whole run as one pure function of (key, hparams); metrics per update (num_updates,)."""
        ts = self.init(key, hparams)
        return self.across_shards(lambda ts: self._scan_updates(ts, self.num_updates))(ts)


def check_hparams(hparams: HParams, env_config: EnvConfig | None = None) -> None:
    """Concrete `HParams` (batched or not) against the declarations of `PPOConfig`, `EnvConfig` and
    `RewardConfig`, and with the env's config against its static capacities; raises ConfigError naming the field
    and the allowed range."""
    check_traced(hparams, PPOConfig, "ppo")
    hparams.env.validate(env_config)


def make_trainer(config: TrainConfig, devices="auto") -> Trainer:
    """The trainer of `config` (validated already: a TrainConfig cannot be invalid).

    `devices` carry the env shards when ppo.num_shards > 1: "auto" (one local device per shard if there are
    enough, else all shards vmapped on the default device), None (always vmapped) or a list of num_shards devices.
    """
    if not isinstance(config, TrainConfig):
        raise TypeError(f"make_trainer needs a TrainConfig, not {type(config).__name__}")
    env = CrowdNavEnv(config.env, config.reward)
    return Trainer(config, env, make_network_for(config), shards.shard_mesh(config.ppo.num_shards, devices))
