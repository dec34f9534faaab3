"""Evaluation, the one place for it: N distinct episodes in parallel, reduced to the paper's metrics (success,
collision and timeout rates, navigation time, path length, both intrusion ratios; docs/reference.md defines them).

`run_episodes` is the compiled program (one episode in each of N environments, stepped in lock-step without
auto-reset until every episode has ended; finished ones are masked out of the statistics). `evaluate` plays a
policy in bounded batches and summarises; `evaluate_params` / `evaluate_state` evaluate a trained network (and
baseline robots beside it) on its run's env: the final evaluation of `tgrf-train`, the periodic test curves and
`tgrf-eval` all call them, and a sweep runs `run_episodes` vmapped over its runs. Each environment plays its own
reset key (500 distinct scenarios by default, unlike the reference's 250 replayed twice).
"""

from __future__ import annotations

import dataclasses
import json
import math
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from tgrf_jax.config import MAX_EPISODES, TrainConfig
from tgrf_jax.env import COLLISION, SUCCESS, TIMEOUT, CrowdNavEnv, EnvParams
from tgrf_jax.policies import LearnedPolicy, Policy, baseline, make_network_for


@struct.dataclass
class EpisodeStats:
    """Per-episode accumulators, arrays of shape (N,)."""

    outcome: jnp.ndarray
    time: jnp.ndarray
    steps: jnp.ndarray
    path_length: jnp.ndarray
    ret: jnp.ndarray
    future_steps: jnp.ndarray
    future_dist_sum: jnp.ndarray
    disc_steps: jnp.ndarray
    disc_dist_sum: jnp.ndarray


def run_episodes(env: CrowdNavEnv, policy: Policy, key, n_episodes: int, params: EnvParams) -> EpisodeStats:
    """Play one episode in each of `n_episodes` parallel environments (pure; jit it)."""
    k_reset, k_loop = jax.random.split(key)
    obs, state = jax.vmap(env.reset, in_axes=(0, None))(jax.random.split(k_reset, n_episodes), params)
    zeros = jnp.zeros(n_episodes, jnp.float32)
    izeros = jnp.zeros(n_episodes, jnp.int32)
    stats = EpisodeStats(zeros, zeros, izeros, zeros, zeros, izeros, zeros, izeros, zeros)
    alive = jnp.ones(n_episodes, bool)
    carry = policy.initialize_carry(n_episodes)

    def step_one(key, state, action):
        # No auto-reset: an ended episode is masked out, so a fresh one would be computed only to be thrown away.
        # The step key is the one `env.step` would pass on, so the episodes are those of the auto-resetting env.
        return env.step_env(jax.random.split(key)[0], state, action, params)

    step_all = jax.vmap(step_one)

    def body(loop):
        t, key, obs, state, carry, alive, stats = loop
        key, k_act, k_step = jax.random.split(key, 3)
        carry, action = policy.act(carry, obs, jnp.equal(t, 0) & alive, k_act)
        obs, state, reward, terminated, truncated, info = step_all(jax.random.split(k_step, n_episodes), state,
                                                                   action)
        done = terminated | truncated
        fut = info.intrusion_future & alive
        disc = info.intrusion_disc & alive
        stats = EpisodeStats(
            outcome=jnp.where(alive & done, info.outcome, stats.outcome),
            time=jnp.where(alive & done, info.time, stats.time),
            steps=stats.steps + alive,
            # where, not a product with the alive mask: an ended episode keeps stepping and may produce anything
            path_length=stats.path_length + jnp.where(alive, info.path_increment, 0.0),
            ret=stats.ret + jnp.where(alive, reward, 0.0),
            future_steps=stats.future_steps + fut,
            future_dist_sum=stats.future_dist_sum + jnp.where(fut, info.future_dist, 0.0),
            disc_steps=stats.disc_steps + disc,
            disc_dist_sum=stats.disc_dist_sum + jnp.where(disc, info.dmin, 0.0),
        )
        return t + 1, key, obs, state, carry, alive & ~done, stats

    def cond(loop):
        t, alive = loop[0], loop[5]
        return jnp.any(alive) & (t <= params.max_steps)

    loop = (jnp.zeros((), jnp.int32), k_loop, obs, state, carry, alive, stats)
    return jax.lax.while_loop(cond, body, loop)[-1]


_run_episodes_static = jax.jit(run_episodes, static_argnums=(0, 1, 3))  # a hashable policy object
_run_episodes_traced = jax.jit(run_episodes, static_argnums=(0, 3))  # a policy pytree (traced parameters)


def _run_episodes_jit(env, policy, key, n_episodes, params):
    run = _run_episodes_traced if hasattr(policy, "tree_flatten") else _run_episodes_static
    return run(env, policy, key, n_episodes, params)

# Episodes evaluated at once by default: enough to fill any CPU or GPU, small enough (a few hundred MB of
# state for 20 humans) that a million-episode evaluation runs in bounded memory.
MAX_BATCH = 1000


@dataclasses.dataclass(frozen=True)
class EvalResult:
    """Metrics of one evaluation (docs/reference.md). Times in seconds, lengths in metres, ratios in percent."""

    n_episodes: int
    success_rate: float
    collision_rate: float
    timeout_rate: float
    nav_time: float  # mean time of successful episodes
    path_length: float  # mean robot path length of successful episodes
    itr_future: float  # % of steps with the robot inside a visible human's true future positions (reference ITR)
    itr_disc: float  # % of steps with nearest edge distance < d_disc
    intrusion_dist_future: float  # mean centre distance during itr_future intrusions
    intrusion_dist_disc: float  # mean nearest edge distance during itr_disc intrusions
    mean_return: float

    def to_dict(self) -> dict:
        return {k: (None if isinstance(v, float) and math.isnan(v) else v) for k, v in dataclasses.asdict(self).items()}

    def to_json(self) -> str:
        return json.dumps(self.to_dict(), indent=2)


def summarize(stats: EpisodeStats) -> EvalResult:
    s = jax.tree_util.tree_map(np.asarray, stats)
    n = len(s.outcome)
    success = s.outcome == SUCCESS
    steps = np.maximum(s.steps, 1)

    def mean(x, where=None):
        x = x if where is None else x[where]
        return float(np.mean(x)) if x.size else float("nan")

    def ratio(total, count):
        return float(total.sum() / count.sum()) if count.sum() else float("nan")

    return EvalResult(
        n_episodes=n,
        success_rate=mean(success.astype(float)),
        collision_rate=mean((s.outcome == COLLISION).astype(float)),
        timeout_rate=mean((s.outcome == TIMEOUT).astype(float)),
        nav_time=mean(s.time, success),
        path_length=mean(s.path_length, success),
        itr_future=100.0 * mean(s.future_steps / steps),
        itr_disc=100.0 * mean(s.disc_steps / steps),
        intrusion_dist_future=ratio(s.future_dist_sum, s.future_steps),
        intrusion_dist_disc=ratio(s.disc_dist_sum, s.disc_steps),
        mean_return=mean(s.ret),
    )


def evaluate(
    env: CrowdNavEnv,
    policy: Policy,
    key,
    n_episodes: int = 500,
    *,
    params: EnvParams | None = None,
    batch_size: int | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> EvalResult:
    """Evaluate `policy` on `n_episodes` distinct episodes (jitted, batched) and summarise them.

    The environment is evaluated with ground-truth future tracking switched on, so both ITR definitions are
    reported. Episodes run in batches of at most `batch_size` (default `MAX_BATCH`), so memory stays bounded
    however many are asked for; batch i uses `fold_in(key, i)`, so results depend on the batch size (not on
    anything else). `progress(done, total)` is called after each batch. `params` are checked first
    (`EnvParams.validate`): a zero or negative dt, say, is an error, not an evaluation that never ends.
    """
    if not 1 <= n_episodes <= MAX_EPISODES:
        raise ValueError(f"n_episodes = {n_episodes} is out of range; allowed: 1 .. {MAX_EPISODES:,}")
    if batch_size is not None and batch_size < 1:
        raise ValueError(f"batch_size = {batch_size} must be >= 1")
    eval_env = CrowdNavEnv(dataclasses.replace(env.config, track_future_intrusion=True), env.reward_config)
    params = (eval_env.default_params if params is None else params).validate()
    batch_size = min(MAX_BATCH if batch_size is None else batch_size, n_episodes)
    chunks = []
    for i, start in enumerate(range(0, n_episodes, batch_size)):
        size = min(batch_size, n_episodes - start)
        # Host copies: only the small per-episode statistics of finished batches stay in memory.
        chunks.append(jax.device_get(_run_episodes_jit(eval_env, policy, jax.random.fold_in(key, i), size, params)))
        if progress is not None:
            progress(start + size, n_episodes)
    stats = jax.tree_util.tree_map(lambda *xs: np.concatenate(xs), *chunks)
    return summarize(stats)


METRIC_LABELS = (
    ("success_rate", "SR", "{:.1%}"),
    ("collision_rate", "collision", "{:.1%}"),
    ("timeout_rate", "timeout", "{:.1%}"),
    ("nav_time", "NT (s)", "{:.2f}"),
    ("path_length", "PL (m)", "{:.2f}"),
    ("itr_future", "ITR future (%)", "{:.2f}"),
    ("itr_disc", "ITR disc (%)", "{:.2f}"),
    ("intrusion_dist_future", "dist in ITR future (m)", "{:.3f}"),
    ("intrusion_dist_disc", "dist in ITR disc (m)", "{:.3f}"),
    ("mean_return", "return", "{:.2f}"),
)


def format_table(results: dict[str, EvalResult]) -> str:
    """A Markdown table with one row per named result."""
    header = "| policy | episodes | " + " | ".join(label for _, label, _ in METRIC_LABELS) + " |"
    rule = "|" + "---|" * (len(METRIC_LABELS) + 2)
    rows = [header, rule]
    for name, r in results.items():
        cells = []
        for field, _, fmt in METRIC_LABELS:
            v = getattr(r, field)
            cells.append("n/a" if isinstance(v, float) and math.isnan(v) else fmt.format(v))
        rows.append(f"| {name} | {r.n_episodes} | " + " | ".join(cells) + " |")
    return "\n".join(rows)


def evaluate_params(config: TrainConfig, params, episodes: int, seed: int, baselines=(), net=None,
                    progress=None) -> dict:
    """The deterministic policy of network `params` and optional baseline robots on `config`'s env and reward, as
    an eval.json payload. `net` (default: built from the config) keys the compiled evaluation: pass the same one
    to reuse it. `progress(name)` (optional) gives each policy's `evaluate` progress callback."""
    env = CrowdNavEnv(config.env, config.reward)
    key = jax.random.key(seed)
    params = jax.device_get(params)  # off the shards' devices: evaluation runs on the default device
    net = make_network_for(config) if net is None else net
    track = (lambda name: None) if progress is None else progress
    results = {"learned": evaluate(env, LearnedPolicy(net, params), key, episodes, progress=track("learned"))}
    for name in baselines:
        results[name] = evaluate(env, baseline(name), key, episodes, progress=track(name))
    return {"env": repr(env), "episodes": episodes, "seed": seed,
            "results": {k: v.to_dict() for k, v in results.items()}}


def evaluate_state(config: TrainConfig, state, episodes: int, seed: int, baselines=(), net=None,
                   progress=None) -> dict:
    """`evaluate_params` of a training state's parameters."""
    return evaluate_params(config, state.params, episodes, seed, baselines, net, progress)


def format_eval(payload: dict) -> str:
    """The Markdown table of an eval.json payload."""
    results = {k: EvalResult(**{f: (float("nan") if v is None else v) for f, v in d.items()})
               for k, d in payload["results"].items()}
    return format_table(results)
