"""Evaluation, the one place for it: N distinct episodes in parallel, reduced to the paper's metrics (success,
collision and timeout rates, navigation time, path length, both intrusion ratios; docs/reference.md defines them)
and the field's wider set (SPL, clearance, personal space, speed, acceleration, jerk, path irregularity,
time-to-collision, time stalled; docs/metrics.md defines them), all accumulated inside the compiled program.

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
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from tgrf_jax.config import MAX_EPISODES, TrainConfig
from tgrf_jax.env import COLLISION, OBSTACLE_COLLISION, SUCCESS, TIMEOUT, CrowdNavEnv, EnvParams
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
    # docs/metrics.md
    start_goal_dist: jnp.ndarray  # straight-line distance from the start to the goal (SPL's shortest path)
    min_dist: jnp.ndarray  # smallest edge-to-edge distance to a human (inf without humans)
    personal_steps: jnp.ndarray  # steps with a human inside PERSONAL_SPACE
    speed_sum: jnp.ndarray
    speed_max: jnp.ndarray
    accel_sum: jnp.ndarray  # sum over steps of |a|, a = (v_t - v_{t-1}) / dt
    jerk_sum: jnp.ndarray  # sum over steps of |(a_t - a_{t-1}) / dt|
    turn_sum: jnp.ndarray  # total change of the direction of motion (rad)
    min_ttc: jnp.ndarray  # smallest time-to-collision at constant velocities (inf: never on a collision course)
    stall_steps: jnp.ndarray  # steps slower than STALL_SPEED
    num_humans: jnp.ndarray  # active humans of the episode
    min_dist_obstacle: jnp.ndarray  # smallest edge distance to a static obstacle (inf without obstacles)
    obstacles_dropped: jnp.ndarray  # obstacle slots removed at reset for lying on the robot's start or goal
    human_steps: jnp.ndarray  # active humans summed over the episode's steps
    stuck_steps: jnp.ndarray  # of them stuck (tgrf_jax.env.stuck)
    unreachable_steps: jnp.ndarray  # of them with no path to their goal
    goals_reassigned: jnp.ndarray  # humans given a new goal for staying stuck


# Edge-to-edge distance below which a human is inside the robot's personal space (docs/metrics.md).
PERSONAL_SPACE = 0.45
# The robot counts as stalled below this speed (m/s) (docs/metrics.md).
STALL_SPEED = 0.1
# Below this speed the direction of motion is undefined and not counted in the turning of path irregularity.
_MOVING = 1e-3


def time_to_collision(robot_pos, robot_vel, robot_radius, human_pos, human_vel, human_radius, active):
    """Smallest time until the robot's disc touches an active human's at the current velocities, per
    environment: (B, 2) robot and (B, N, ...) human arrays -> (B,); 0 when touching now, inf when never."""
    p = human_pos - robot_pos[:, None]
    v = human_vel - robot_vel[:, None]
    r = robot_radius + human_radius
    a = jnp.sum(v * v, -1)
    b = 2.0 * jnp.sum(p * v, -1)
    c = jnp.sum(p * p, -1) - r * r
    disc = b * b - 4.0 * a * c
    approaching = (b < 0) & (disc >= 0) & (a > 0)
    t = (-b - jnp.sqrt(jnp.maximum(disc, 0.0))) / jnp.maximum(2.0 * a, 1e-12)
    ttc = jnp.where(c <= 0, 0.0, jnp.where(approaching, t, jnp.inf))
    return jnp.min(jnp.where(active, ttc, jnp.inf), axis=-1, initial=jnp.inf)


def run_episodes(env: CrowdNavEnv, policy: Policy, key, n_episodes: int, params: EnvParams) -> EpisodeStats:
    """Play one episode in each of `n_episodes` parallel environments (pure; jit it)."""
    k_reset, k_loop = jax.random.split(key)
    obs, state = jax.vmap(env.reset, in_axes=(0, None))(jax.random.split(k_reset, n_episodes), params)
    zeros = jnp.zeros(n_episodes, jnp.float32)
    izeros = jnp.zeros(n_episodes, jnp.int32)
    inf = jnp.full(n_episodes, jnp.inf, jnp.float32)
    stats = EpisodeStats(
        zeros,
        zeros,
        izeros,
        zeros,
        zeros,
        izeros,
        zeros,
        izeros,
        zeros,
        start_goal_dist=jnp.linalg.norm(state.robot.goal - state.robot.pos, axis=-1),
        min_dist=inf,
        personal_steps=izeros,
        speed_sum=zeros,
        speed_max=zeros,
        accel_sum=zeros,
        jerk_sum=zeros,
        turn_sum=zeros,
        min_ttc=inf,
        stall_steps=izeros,
        num_humans=jnp.sum(state.humans.active, -1, dtype=jnp.int32),
        min_dist_obstacle=inf,
        obstacles_dropped=state.obstacles_dropped,
        human_steps=izeros,
        stuck_steps=izeros,
        unreachable_steps=izeros,
        goals_reassigned=izeros,
    )
    alive = jnp.ones(n_episodes, bool)
    carry = policy.initialize_carry(n_episodes)
    motion = (state.robot.vel, jnp.zeros_like(state.robot.vel))  # last velocity and acceleration

    def step_one(key, state, action):
        # No auto-reset: an ended episode is masked out, so a fresh one would be computed only to be thrown away.
        # The step key is the one `env.step` would pass on, so the episodes are those of the auto-resetting env.
        return env.step_env(jax.random.split(key)[0], state, action, params)

    step_all = jax.vmap(step_one)

    def body(loop):
        t, key, obs, state, carry, alive, stats, motion = loop
        key, k_act, k_step = jax.random.split(key, 3)
        carry, action = policy.act(carry, obs, jnp.equal(t, 0) & alive, k_act)
        obs, state, reward, terminated, truncated, info = step_all(jax.random.split(k_step, n_episodes), state, action)
        done = terminated | truncated
        fut = info.intrusion_future & alive
        disc = info.intrusion_disc & alive
        vel = state.robot.vel
        prev_vel, prev_acc = motion
        acc = (vel - prev_vel) / params.dt
        speed = jnp.linalg.norm(vel, axis=-1)
        prev_speed = jnp.linalg.norm(prev_vel, axis=-1)
        turning = (speed > _MOVING) & (prev_speed > _MOVING)
        cos = jnp.sum(vel * prev_vel, -1) / jnp.maximum(speed * prev_speed, 1e-12)
        turn = jnp.where(turning, jnp.arccos(jnp.clip(cos, -1.0, 1.0)), 0.0)
        ttc = time_to_collision(
            state.robot.pos,
            vel,
            params.robot_radius,
            state.humans.pos,
            state.humans.vel,
            state.humans.radius,
            state.humans.active,
        )
        add = lambda total, x: total + jnp.where(alive, x, 0)
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
            start_goal_dist=stats.start_goal_dist,
            min_dist=jnp.minimum(stats.min_dist, jnp.where(alive, info.dmin, jnp.inf)),
            personal_steps=add(stats.personal_steps, (info.dmin < PERSONAL_SPACE).astype(jnp.int32)),
            speed_sum=add(stats.speed_sum, speed),
            speed_max=jnp.maximum(stats.speed_max, jnp.where(alive, speed, 0.0)),
            accel_sum=add(stats.accel_sum, jnp.linalg.norm(acc, axis=-1)),
            jerk_sum=add(stats.jerk_sum, jnp.linalg.norm(acc - prev_acc, axis=-1) / params.dt),
            turn_sum=add(stats.turn_sum, turn),
            min_ttc=jnp.minimum(stats.min_ttc, jnp.where(alive, ttc, jnp.inf)),
            stall_steps=add(stats.stall_steps, (speed < STALL_SPEED).astype(jnp.int32)),
            num_humans=stats.num_humans,
            min_dist_obstacle=jnp.minimum(stats.min_dist_obstacle, jnp.where(alive, info.obstacle_dist, jnp.inf)),
            obstacles_dropped=stats.obstacles_dropped,
            human_steps=add(stats.human_steps, info.humans_active),
            stuck_steps=add(stats.stuck_steps, info.humans_stuck),
            unreachable_steps=add(stats.unreachable_steps, info.humans_unreachable),
            goals_reassigned=add(stats.goals_reassigned, info.goals_reassigned),
        )
        return t + 1, key, obs, state, carry, alive & ~done, stats, (vel, acc)

    def cond(loop):
        t, alive = loop[0], loop[5]
        return jnp.any(alive) & (t <= params.max_steps)

    loop = (jnp.zeros((), jnp.int32), k_loop, obs, state, carry, alive, stats, motion)
    return jax.lax.while_loop(cond, body, loop)[-2]


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
    collision_rate: float  # episodes ended by a collision, with a human or a static obstacle
    timeout_rate: float
    nav_time: float  # mean time of successful episodes
    path_length: float  # mean robot path length of successful episodes
    itr_future: float  # % of steps with the robot inside a visible human's true future positions (reference ITR)
    itr_disc: float  # % of steps with nearest edge distance < d_disc
    intrusion_dist_future: float  # mean centre distance during itr_future intrusions
    intrusion_dist_disc: float  # mean nearest edge distance during itr_disc intrusions
    mean_return: float
    # The field's wider set (docs/metrics.md); NaN where undefined (no episode to average) or not recorded.
    spl: float = math.nan  # success weighted by (straight-line distance / path length)
    collision_human_rate: float = math.nan  # episodes ended by hitting a human
    collision_obstacle_rate: float = math.nan  # episodes ended by hitting a static obstacle
    min_dist_obstacle: float = math.nan  # mean over episodes with obstacles of the smallest edge distance to one (m)
    layout_fallback_rate: float = math.nan  # episodes whose drawn layout lost an obstacle on the robot's start/goal
    min_dist_human: float = math.nan  # mean over episodes of the smallest edge distance to a human (m)
    personal_space_compliance: float = math.nan  # % of steps with nobody inside PERSONAL_SPACE
    speed_mean: float = math.nan  # m/s
    speed_max: float = math.nan  # mean over episodes of the episode's top speed (m/s)
    accel_mean: float = math.nan  # m/s^2
    jerk_mean: float = math.nan  # m/s^3
    path_irregularity: float = math.nan  # turning per metre of path (rad/m)
    min_ttc: float = math.nan  # mean over episodes (with a collision course) of the smallest time-to-collision (s)
    time_stalled: float = math.nan  # seconds per episode below STALL_SPEED
    mean_humans: float = math.nan  # active humans per episode
    stuck_rate: float = math.nan  # % of active human-steps in which a human is stuck (tgrf_jax.env.stuck)
    unreachable_rate: float = math.nan  # % of active human-steps in which a human's goal has no path
    goals_reassigned: float = math.nan  # humans per episode given a new goal for staying stuck

    def to_dict(self) -> dict:
        return {k: (None if isinstance(v, float) and math.isnan(v) else v) for k, v in dataclasses.asdict(self).items()}

    # An undefined metric (NaN: no obstacle, no collision course) equals itself: two evaluations of the same
    # episodes are equal results.
    def __eq__(self, other):
        return isinstance(other, EvalResult) and self.to_dict() == other.to_dict()

    __hash__ = None

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

    def finite_mean(x):
        return mean(x, np.isfinite(x))

    shortest = s.start_goal_dist

    return EvalResult(
        n_episodes=n,
        success_rate=mean(success.astype(float)),
        collision_rate=mean(((s.outcome == COLLISION) | (s.outcome == OBSTACLE_COLLISION)).astype(float)),
        timeout_rate=mean((s.outcome == TIMEOUT).astype(float)),
        nav_time=mean(s.time, success),
        path_length=mean(s.path_length, success),
        itr_future=100.0 * mean(s.future_steps / steps),
        itr_disc=100.0 * mean(s.disc_steps / steps),
        intrusion_dist_future=ratio(s.future_dist_sum, s.future_steps),
        intrusion_dist_disc=ratio(s.disc_dist_sum, s.disc_steps),
        mean_return=mean(s.ret),
        spl=mean(np.where(success, shortest / np.maximum(np.maximum(s.path_length, shortest), 1e-9), 0.0)),
        collision_human_rate=mean((s.outcome == COLLISION).astype(float)),
        collision_obstacle_rate=mean((s.outcome == OBSTACLE_COLLISION).astype(float)),
        min_dist_obstacle=finite_mean(s.min_dist_obstacle),
        layout_fallback_rate=mean((s.obstacles_dropped > 0).astype(float)),
        min_dist_human=finite_mean(s.min_dist),
        personal_space_compliance=100.0 * (1.0 - mean(s.personal_steps / steps)),
        speed_mean=mean(s.speed_sum / steps),
        speed_max=mean(s.speed_max),
        accel_mean=mean(s.accel_sum / steps),
        jerk_mean=mean(s.jerk_sum / steps),
        path_irregularity=mean(s.turn_sum / np.maximum(s.path_length, 1e-9)),
        min_ttc=finite_mean(s.min_ttc),
        time_stalled=mean(s.stall_steps * (s.time / steps)),
        mean_humans=mean(s.num_humans.astype(float)),
        stuck_rate=100.0 * ratio(s.stuck_steps, s.human_steps),
        unreachable_rate=100.0 * ratio(s.unreachable_steps, s.human_steps),
        goals_reassigned=mean(s.goals_reassigned.astype(float)),
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
    eval_env = CrowdNavEnv(
        dataclasses.replace(env.config, track_future_intrusion=True, replay_augment=False), env.reward_config
    )
    params = (eval_env.default_params if params is None else params).validate(eval_env.config)
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
# The wider set (docs/metrics.md), printed with tgrf-eval --all-metrics.
EXTRA_METRIC_LABELS = (
    ("spl", "SPL", "{:.3f}"),
    ("collision_human_rate", "hit human", "{:.1%}"),
    ("collision_obstacle_rate", "hit obstacle", "{:.1%}"),
    ("min_dist_obstacle", "min dist obstacle (m)", "{:.3f}"),
    ("layout_fallback_rate", "layout fallbacks", "{:.1%}"),
    ("min_dist_human", "min dist (m)", "{:.3f}"),
    ("personal_space_compliance", "PS compliance (%)", "{:.1f}"),
    ("speed_mean", "speed (m/s)", "{:.2f}"),
    ("speed_max", "max speed (m/s)", "{:.2f}"),
    ("accel_mean", "accel (m/s^2)", "{:.2f}"),
    ("jerk_mean", "jerk (m/s^3)", "{:.2f}"),
    ("path_irregularity", "irregularity (rad/m)", "{:.3f}"),
    ("min_ttc", "min TTC (s)", "{:.2f}"),
    ("time_stalled", "stalled (s)", "{:.2f}"),
    ("mean_humans", "humans", "{:.1f}"),
    ("stuck_rate", "humans stuck (%)", "{:.2f}"),
    ("unreachable_rate", "goal unreachable (%)", "{:.2f}"),
    ("goals_reassigned", "new goals (stuck)", "{:.2f}"),
)


def format_table(results: dict[str, EvalResult], all_metrics: bool = False) -> str:
    """A Markdown table with one row per named result: the paper's metrics, or with `all_metrics` every one."""
    labels = METRIC_LABELS + (EXTRA_METRIC_LABELS if all_metrics else ())
    header = "| policy | episodes | " + " | ".join(label for _, label, _ in labels) + " |"
    rule = "|" + "---|" * (len(labels) + 2)
    rows = [header, rule]
    for name, r in results.items():
        cells = []
        for field, _, fmt in labels:
            v = getattr(r, field)
            cells.append("n/a" if isinstance(v, float) and math.isnan(v) else fmt.format(v))
        rows.append(f"| {name} | {r.n_episodes} | " + " | ".join(cells) + " |")
    return "\n".join(rows)


def evaluate_params(
    config: TrainConfig, params, episodes: int, seed: int, baselines=(), net=None, progress=None
) -> dict:
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
    return {
        "env": repr(env),
        "episodes": episodes,
        "seed": seed,
        "results": {k: v.to_dict() for k, v in results.items()},
    }


def evaluate_state(config: TrainConfig, state, episodes: int, seed: int, baselines=(), net=None, progress=None) -> dict:
    """`evaluate_params` of a training state's parameters."""
    return evaluate_params(config, state.params, episodes, seed, baselines, net, progress)


def format_eval(payload: dict, all_metrics: bool = False) -> str:
    """The Markdown table of an eval.json payload (older payloads lack the wider metrics: shown as n/a)."""
    results = {
        k: EvalResult(**{f: (float("nan") if v is None else v) for f, v in d.items()})
        for k, d in payload["results"].items()
    }
    return format_table(results, all_metrics)
