"""Recording episodes in JAX: a `lax.scan` over the time limit plays a batch of episodes with the same keys and
step order as `tgrf_jax.evaluate` (so episode i of a render and of an evaluation with the same seed and count are
the same episode) and returns every state, the robot's visibility mask, the predictions it observed, the reward
split into its terms and, in environments with static obstacles or a LiDAR, the episode's layout and every scan, as
numpy `Episode`s. Everything after that is host code."""

from __future__ import annotations

import dataclasses
import functools

import numpy as np


@dataclasses.dataclass
class Episode:
    """One recorded episode as numpy arrays. T = `steps`; index 0 of the (T+1)-long arrays is the reset state.

    `visible` is in human-index order (True: the robot perceives the human: within sensor range and, with
    `env.occlusion`, not hidden behind an obstacle). `pred_pos` / `pred_mask` are the observation's predicted world
    positions in the observation's own row order (visible humans first), so only what the robot observed is drawn.
    Per-step arrays (`reward`, `terms`, `outcomes`) are T long: entry t-1 belongs to step t.

    `obstacles` is the episode's static layout (fixed for the episode, taken from its reset state, so nothing of a
    later episode leaks in): one (V_i, 2) array of world-frame vertices per used obstacle slot, counter-clockwise;
    2 vertices are a wall segment. `lidar` holds the LiDAR scan of every state (ray k at `robot_heading[t] +
    2 pi k / R` counter-clockwise, ranges capped at `sensor_range`), None when the env has no LiDAR
    (`env.lidar_rays: 0`). `obstacle_dist` is the robot's edge-to-edge distance to the nearest obstacle in every
    state (negative: overlapping one), None without obstacles.

    In replayed recordings (`env.scenario: replay`) people enter and leave the scene during the episode: every
    human slot is kept, `active` says where a slot holds someone, and `human_pos` is NaN where it does not (nothing
    is drawn there, and no distance counts it). Elsewhere the slots active at the start are the humans, throughout.
    """

    label: str
    index: int
    robot_pos: np.ndarray  # (T+1, 2)
    robot_vel: np.ndarray  # (T+1, 2)
    goal: np.ndarray  # (2,)
    human_pos: np.ndarray  # (T+1, N, 2)
    human_radius: np.ndarray  # (T+1, N)
    visible: np.ndarray  # (T+1, N) bool, human-index order
    obs_human_pos: np.ndarray  # (T+1, N, 2) world positions of the observed rows (sorted, visible first)
    obs_mask: np.ndarray  # (T+1, N) bool, the observation's human_mask
    pred_pos: np.ndarray | None  # (T+1, N, K, 2) observed predictions (world), None without a predictor
    reward: np.ndarray  # (T,)
    terms: dict  # name -> (T,)
    outcomes: np.ndarray  # (T,) int, the last one is the episode's outcome
    dt: float
    robot_radius: float
    sensor_range: float
    d_disc: float
    goal_tolerance: float
    max_steps: int
    robot_heading: np.ndarray | None = None  # (T+1,) rad, the robot's heading (pi/2 throughout for holonomic robots)
    obstacles: list = dataclasses.field(default_factory=list)  # [(V_i, 2)] the episode's obstacles, world frame
    lidar: np.ndarray | None = None  # (T+1, R) LiDAR ranges (m) of every state, None without a LiDAR
    obstacle_dist: np.ndarray | None = None  # (T+1,) robot edge distance to the nearest obstacle, None without
    occlusion: bool = False  # env.occlusion: humans hidden behind obstacles count as not visible
    active: np.ndarray | None = None  # (T+1, N) bool where slots hold someone (replayed recordings), else None

    @property
    def steps(self) -> int:
        return len(self.reward)

    @property
    def num_humans(self) -> int:
        return self.human_pos.shape[1]

    @property
    def lidar_rays(self) -> int:
        """Rays per scan (0: no LiDAR)."""
        return 0 if self.lidar is None else self.lidar.shape[1]

    def lidar_points(self, t: int) -> np.ndarray:
        """World-frame end points (R, 2) of state t's rays: the hit points, or the range's end where nothing is hit."""
        if self.lidar is None:
            raise ValueError("this episode has no LiDAR scans (its env has env.lidar_rays: 0)")
        ranges = self.lidar[t]
        heading = np.pi / 2 if self.robot_heading is None else self.robot_heading[t]
        angle = heading + 2 * np.pi * np.arange(len(ranges)) / len(ranges)
        return self.robot_pos[t] + ranges[:, None] * np.stack([np.cos(angle), np.sin(angle)], -1)

    @property
    def outcome(self) -> str:
        from tgrf_jax.env import OUTCOME_NAMES

        return OUTCOME_NAMES[int(self.outcomes[-1])] if self.steps else "running"

    @property
    def duration(self) -> float:
        return self.steps * self.dt

    @property
    def ret(self) -> float:
        return float(self.reward.sum())

    def dmin(self) -> np.ndarray:
        """Nearest edge-to-edge robot-human distance of every recorded state (T+1,) (inf without humans)."""
        if self.num_humans == 0:
            return np.full(self.steps + 1, np.inf)
        d = np.linalg.norm(self.human_pos - self.robot_pos[:, None], axis=-1) - self.robot_radius - self.human_radius
        return np.where(np.isnan(d), np.inf, d).min(axis=1)  # NaN: an empty slot of a replayed recording

    def summary(self) -> dict:
        return dict(
            label=self.label,
            episode=self.index,
            outcome=self.outcome,
            steps=self.steps,
            time=round(self.duration, 3),
            ret=round(self.ret, 4),
            path_length=round(float(np.linalg.norm(np.diff(self.robot_pos, axis=0), axis=-1).sum()), 4),
        )


def _record(env, policy, key, n_episodes: int, params, n_steps: int):
    """Pure: play `n_episodes` episodes for `n_steps` steps, freezing each after it ends; returns stacked outputs.

    `env.step_env` never resets, and an ended episode's state is frozen, so no later episode enters a recording;
    the obstacles are taken once, from the reset states (`first`)."""
    import jax
    import jax.numpy as jnp

    from tgrf_jax.env import obstacles as obstacles_lib

    has_obstacles = env.config.obstacle_slots > 0
    has_lidar = env.config.lidar_rays > 0

    def snapshot(obs, state):
        visible = jax.vmap(env.visible, in_axes=(0, None))(state, params)
        out = dict(
            robot_pos=state.robot.pos,
            robot_vel=state.robot.vel,
            goal=state.robot.goal,
            robot_heading=state.robot.heading,
            human_pos=state.humans.pos,
            human_radius=state.humans.radius,
            visible=visible,
            obs_humans=obs.humans,
            obs_mask=obs.human_mask,
            active=state.humans.active,
        )
        if has_lidar:
            out["lidar"] = obs.lidar
        if has_obstacles:
            out["obstacle_dist"] = (
                jax.vmap(obstacles_lib.clearance)(state.robot.pos, state.obstacles) - params.robot_radius
            )
        return out

    def step_one(key, state, action):
        k_step, _ = jax.random.split(key)  # as env.step splits it, so trajectories match evaluate()
        return env.step_env(k_step, state, action, params)

    def body(loop, t):
        key, obs, state, carry, alive = loop
        key, k_act, k_step = jax.random.split(key, 3)
        carry, action = policy.act(carry, obs, jnp.equal(t, 0) & alive, k_act)
        new_obs, new_state, reward, terminated, truncated, info = jax.vmap(step_one)(
            jax.random.split(k_step, n_episodes), state, action
        )

        def keep(new, old):
            return jnp.where(alive.reshape((-1,) + (1,) * (new.ndim - 1)), new, old)

        state = jax.tree_util.tree_map(keep, new_state, state)
        obs = jax.tree_util.tree_map(keep, new_obs, obs)
        out = dict(snapshot(obs, state), alive=alive, reward=reward, outcome=info.outcome, terms=info.reward_terms)
        return (key, obs, state, carry, alive & ~(terminated | truncated)), out

    k_reset, k_loop = jax.random.split(key)
    obs, state = jax.vmap(env.reset, in_axes=(0, None))(jax.random.split(k_reset, n_episodes), params)
    first = snapshot(obs, state)
    first["obstacle_vertices"] = state.obstacles.vertices
    first["obstacle_counts"] = state.obstacles.num_vertices
    loop = (k_loop, obs, state, policy.initialize_carry(n_episodes), jnp.ones(n_episodes, bool))
    _, outs = jax.lax.scan(body, loop, jnp.arange(n_steps))
    return first, outs


@functools.cache
def _record_jit():
    import jax

    return jax.jit(_record, static_argnums=(0, 1, 3, 5))


# Episode steps recorded at once (every state of every episode of a batch stays in memory until it is drawn: about
# 1.5 kB per step with 20 humans and predictions, so some 300 MB). A LiDAR scan adds 4 bytes per ray and step, so
# envs with one record proportionally fewer steps at once.
RECORD_STEPS = 200_000
_STEP_BYTES = 1500


def eval_key(seed: int, batch: int = 0):
    """The key with which `tgrf_jax.evaluate.evaluate(env, policy, jax.random.key(seed), n)` (and so `tgrf-eval
    --seed`) plays its batch `batch` of episodes: `record_episodes(env, policy, eval_key(seed), n)` replays them."""
    import jax

    return jax.random.fold_in(jax.random.key(seed), batch)


def episodes_per_batch(params, lidar_rays: int = 0) -> int:
    """Episodes recorded at once: `evaluate`'s batch (so a render replays the evaluation's episodes), fewer where
    episodes are so long that a batch would exceed `RECORD_STEPS` steps (fewer still with a LiDAR of `lidar_rays`
    rays: its scans are stored too)."""
    from tgrf_jax.evaluate import MAX_BATCH

    steps = RECORD_STEPS * _STEP_BYTES // (_STEP_BYTES + 4 * int(lidar_rays))
    return max(1, min(MAX_BATCH, steps // episode_steps(params)))


def episode_steps(params) -> int:
    return int(round(float(params.time_limit) / float(params.dt)))


def record_episodes(env, policy, key, n_episodes: int = 1, params=None, *, label: str | None = None) -> list[Episode]:
    """Play `n_episodes` episodes of `policy` in `env` (one jitted scan, batched) and return them as `Episode`s.

    `policy` follows the `tgrf_jax.policies` interface (baselines or `LearnedPolicy`). Each episode runs until it
    ends (success, a collision with a human or an obstacle, or the time limit). Keys and step order are those of
    `tgrf_jax.evaluate.run_episodes`, so the same key gives the same episodes; use `eval_key(seed)` to replay what
    `evaluate` / `tgrf-eval` played (recordings, `env.scenario: replay`, are played unaugmented, as there).
    """
    import jax

    if int(n_episodes) < 1:
        raise ValueError(f"n_episodes = {n_episodes} must be >= 1")
    if getattr(env, "replay", None) is not None and env.config.replay_augment:
        # evaluate() plays recordings unaugmented: the same key then gives the episodes it played
        from tgrf_jax.env import CrowdNavEnv

        env = CrowdNavEnv(dataclasses.replace(env.config, replay_augment=False), env.reward_config)
    params = (env.default_params if params is None else params).validate(env.config)
    n_steps = episode_steps(params)
    first, outs = jax.device_get(_record_jit()(env, policy, key, int(n_episodes), params, n_steps))
    label = label or getattr(policy, "name", None) or type(policy).__name__
    k = env.config.pred_horizon if env.config.uses_predictions else 0
    occlusion = bool(env.config.occlusion and env.config.obstacle_slots > 0)
    replayed = getattr(env, "replay", None) is not None
    episodes = []
    for b in range(int(n_episodes)):
        steps = int(outs["alive"][:, b].sum())
        # Inactive slots (the last ones, parked far away) are no part of the scene: cut from every human array.
        # The observation's rows beyond the active count are masked, as nobody inactive is ever visible.
        # (Replayed recordings fill and empty their slots as people come and go: all are kept, with their mask.)
        seq = lambda name, b=b, steps=steps: np.concatenate([first[name][b][None], outs[name][:steps, b]])
        count = env.config.num_humans if replayed else int(first["active"][b].sum())
        humans_seq = lambda name, seq=seq, count=count: seq(name)[:, :count]
        active = humans_seq("active").astype(bool) if replayed else None
        human_pos = humans_seq("human_pos")
        if replayed:
            human_pos = np.where(active[..., None], human_pos, np.nan)
        robot_pos = seq("robot_pos")
        obs_humans = humans_seq("obs_humans")
        n = obs_humans.shape[1]
        obs_pos = obs_humans[:, :, :2] + robot_pos[:, None]
        pred = obs_humans[:, :, 2:].reshape(steps + 1, n, k, 2) + robot_pos[:, None, None] if k else None
        counts = first["obstacle_counts"][b]
        layout = [np.array(first["obstacle_vertices"][b, m, :c], np.float64) for m, c in enumerate(counts) if c >= 2]
        episodes.append(
            Episode(
                label=label,
                index=b,
                robot_pos=robot_pos,
                robot_vel=seq("robot_vel"),
                goal=np.asarray(first["goal"][b]),
                human_pos=human_pos,
                human_radius=humans_seq("human_radius"),
                visible=humans_seq("visible").astype(bool),
                obs_human_pos=obs_pos,
                obs_mask=humans_seq("obs_mask").astype(bool),
                pred_pos=pred,
                reward=np.asarray(outs["reward"][:steps, b], np.float64),
                terms={
                    f.name: np.asarray(getattr(outs["terms"], f.name)[:steps, b], np.float64)
                    for f in dataclasses.fields(outs["terms"])
                },
                outcomes=np.asarray(outs["outcome"][:steps, b]),
                dt=float(params.dt),
                robot_radius=float(params.robot_radius),
                sensor_range=float(params.sensor_range),
                d_disc=float(params.reward.d_disc),
                goal_tolerance=float(params.goal_tolerance),
                max_steps=n_steps,
                robot_heading=np.asarray(seq("robot_heading"), np.float64),
                obstacles=layout,
                lidar=np.asarray(seq("lidar"), np.float64) if "lidar" in first else None,
                obstacle_dist=np.asarray(seq("obstacle_dist"), np.float64) if "obstacle_dist" in first else None,
                occlusion=occlusion,
                active=active,
            )
        )
    return episodes


# ------------------------------------------------------------------------------------------------ drawing
