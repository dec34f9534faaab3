"""The crowd-navigation simulator as Gymnasium 1.x environments, for trainers outside tgrf-jax (optional extra:
pip install 'tgrf-jax[gym]').

* `CrowdNavVectorEnv(num_envs, config, reward, autoreset_mode=...)`: a `gymnasium.vector.VectorEnv` of B
  environments stepped by one jitted `CrowdNavEnv.step_batch` call (the trainer's own batched path), NumPy in and
  out. `autoreset_mode` (stated in `metadata`) is Gymnasium's default `AutoresetMode.NEXT_STEP` (an ended
  episode's last observation is returned by the step that ended it; the next step resets that environment,
  ignoring its action, and returns the new episode's first observation with reward 0 and terminated = truncated
  = False), `SAME_STEP` (the step that ends an episode returns the new episode's first observation and carries the
  ended one's last observation and info in `infos["final_obs"]` / `infos["final_info"]`, flagged by
  `infos["_final_obs"]`) or `DISABLED` (ended environments are reset only by `reset(options={"reset_mask":
  mask})`; stepping one before is refused). Every info entry `k` comes with Gymnasium's mask `_k`.
* `CrowdNavGymEnv(config, reward)`: one `gymnasium.Env` (`step` never resets; call `reset` after an end).

Both take `render_mode="rgb_array"`: `render()` returns the current state as an (H, W, 3) uint8 frame drawn by
tgrf-jax's renderer (`tgrf_jax.render`): the single env with the episode's trails, the vector env one frame per
environment. Actions must be finite (a NaN or infinite action is refused with a ValueError), and a closed
environment refuses every further call.

Observations are flat float32 vectors (`Box`), the inputs the networks read, in this order:
robot_node (7: px, py, radius, gx, gy, v_max, heading), robot_vel (2), humans (N x D, rows sorted nearest first,
zeros where nobody is in range), human_mask (N: 1.0 for a human in range), and with a LiDAR (env.lidar_rays = R
> 0) lidar (R: ranges in metres within [0, sensor_range], ray k at heading + 2 pi k / R counter-clockwise, the
robot's body frame, as `Obs.lidar`; absent when R = 0). `obs_layout(env)` gives the slices. The observation
space bounds the scan by [0, sensor_range] and everything else by +-OBS_BOUND. Static obstacles (`Obs.obstacles`,
the map) are not part of the observation. Actions: holonomic (vx, vy) in m/s (the env scales the norm down to
v_max), unicycle (dv, dtheta) within the per-step limits. `terminated` is a collision or the goal, `truncated` the
time limit.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, ClassVar

import gymnasium
import jax
import jax.numpy as jnp
import numpy as np
from gymnasium import spaces
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import batch_space

from tgrf_jax.env import CrowdNavEnv
from tgrf_jax.env import obstacles as obstacles_lib
from tgrf_jax.env.types import OUTCOME_NAMES

__all__ = ["AUTORESET_MODES", "ENV_ID", "RENDER_MODES", "CrowdNavGymEnv", "CrowdNavVectorEnv", "obs_layout"]

ENV_ID = "tgrf_jax/CrowdNav-v0"  # gymnasium.make(ENV_ID, config=..., reward=...) and gymnasium.make_vec(ENV_ID, B)
# Finite observation bounds (Gymnasium's checker flags infinite ones): no position, prediction or heading of the
# simulator comes near them within the longest allowed episode.
OBS_BOUND = 1e6
RENDER_MODES = ("rgb_array",)
AUTORESET_MODES = (AutoresetMode.NEXT_STEP, AutoresetMode.SAME_STEP, AutoresetMode.DISABLED)


def obs_layout(env: CrowdNavEnv) -> dict[str, slice]:
    """Slices of the flat observation: robot_node, robot_vel, humans, human_mask, and lidar when R > 0."""
    n, d, r = env.num_humans, env.obs_human_dim, env.config.lidar_rays
    names, sizes = ["robot_node", "robot_vel", "humans", "human_mask"], [7, 2, n * d, n]
    if r:
        names, sizes = names + ["lidar"], sizes + [r]
    cuts = np.cumsum([0] + sizes)
    return {name: slice(int(a), int(b)) for name, a, b in zip(names, cuts[:-1], cuts[1:])}


def _flat(obs) -> jnp.ndarray:
    """Observation pytree (any leading batch shape) -> flat float32 rows."""
    lead = obs.robot_node.shape[:-1]
    parts = [obs.robot_node, obs.robot_vel, obs.humans.reshape(lead + (-1,)), obs.human_mask.astype(jnp.float32)]
    if obs.lidar.shape[-1]:
        parts.append(obs.lidar)
    return jnp.concatenate(parts, axis=-1).astype(jnp.float32)


def _info(info) -> dict[str, Any]:
    return {
        "outcome": info.outcome,
        "time": info.time,
        "dmin": info.dmin,
        "num_visible": info.num_visible,
        "intrusion_disc": info.intrusion_disc,
        "path_increment": info.path_increment,
    }


def _spaces(env: CrowdNavEnv, params):
    layout = obs_layout(env)
    dim = max(s.stop for s in layout.values())
    if "lidar" not in layout:
        obs_space = spaces.Box(-OBS_BOUND, OBS_BOUND, (dim,), np.float32)
    else:
        low, high = np.full(dim, -OBS_BOUND, np.float32), np.full(dim, OBS_BOUND, np.float32)
        low[layout["lidar"]] = 0.0
        high[layout["lidar"]] = np.float32(params.sensor_range)  # the scan's largest value, exactly
        obs_space = spaces.Box(low, high, (dim,), np.float32)
    if env.config.kinematics == "holonomic":
        v = float(params.robot_v_max)
        act_space = spaces.Box(-v, v, (2,), np.float32)
    else:
        lo = np.array([params.unicycle_dv_min, -params.unicycle_dtheta_max], np.float32)
        hi = np.array([params.unicycle_dv_max, params.unicycle_dtheta_max], np.float32)
        act_space = spaces.Box(lo, hi, (2,), np.float32)
    return obs_space, act_space


def _make_env(config, reward, params):
    env = config if isinstance(config, CrowdNavEnv) else CrowdNavEnv(config, reward)
    params = (env.default_params if params is None else params).validate(env.config)
    return env, params


def _seed_key(seed) -> jax.Array:
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or not 0 <= int(seed) < 2**31:
        raise ValueError(f"seed must be an integer in [0, 2**31), got {seed!r}")
    return jax.random.PRNGKey(int(seed))


def _where(rows, a, b):
    """Per environment (leading axis): `a` where `rows` (B,) is True, else `b`."""
    return jnp.where(rows.reshape(rows.shape + (1,) * (a.ndim - 1)), a, b)


def _render_mode(mode: str | None) -> str | None:
    if mode is not None and mode not in RENDER_MODES:
        raise ValueError(f"render_mode must be None or one of {list(RENDER_MODES)}, got {mode!r}")
    return mode


def _autoreset_mode(mode: AutoresetMode | str) -> AutoresetMode:
    """An AutoresetMode, or its value or name as text ('NextStep', 'next_step', ...)."""
    if isinstance(mode, AutoresetMode):
        return mode
    names = {key: m for m in AutoresetMode for key in (m.value.lower(), m.name.lower())}
    if isinstance(mode, str) and mode.lower() in names:
        return names[mode.lower()]
    allowed = ", ".join(f"AutoresetMode.{m.name}" for m in AUTORESET_MODES)
    raise ValueError(f"autoreset_mode must be one of {allowed} (or its name), got {mode!r}")


def _finite_actions(actions, shape: tuple[int, ...], what: str) -> np.ndarray:
    """`actions` as float32 of `shape`, refusing non-finite values (the env would turn them into a standstill)."""
    try:
        with np.errstate(over="ignore"):  # a value beyond float32 becomes inf, refused below with its value
            arr = np.asarray(actions, np.float32)
    except (TypeError, ValueError):
        raise ValueError(f"{what} must be numbers of shape {shape}, got {actions!r}") from None
    if arr.size == int(np.prod(shape)) and arr.shape != shape and len(shape) == 1:
        arr = arr.reshape(shape)
    if arr.shape != shape:
        raise ValueError(f"{what} must have shape {shape}, got {arr.shape}")
    bad = ~np.isfinite(arr)
    if bad.any():
        where = np.argwhere(bad)[0].tolist()
        raise ValueError(
            f"{what} must be finite (float32): entry {where} is {np.asarray(actions, np.float64)[tuple(where)]}"
        )
    return arr


# ---------------------------------------------------------------------------------------------------- rendering


def _snapshot_fn(env: CrowdNavEnv, params) -> Callable:
    """(flat observation, state) -> what `tgrf_jax.render` draws of that moment, as `record_episodes` keeps it."""
    layout, n, d = obs_layout(env), env.num_humans, env.obs_human_dim
    has_obstacles = env.config.obstacle_slots > 0

    def snapshot(flat, state):
        out = dict(
            robot_pos=state.robot.pos,
            robot_vel=state.robot.vel,
            robot_heading=state.robot.heading,
            goal=state.robot.goal,
            human_pos=state.humans.pos,
            human_radius=state.humans.radius,
            active=state.humans.active,
            visible=env.visible(state, params),
            obs_humans=flat[layout["humans"]].reshape(n, d),
            obs_mask=flat[layout["human_mask"]] > 0.5,
            obstacle_vertices=state.obstacles.vertices,
            obstacle_counts=state.obstacles.num_vertices,
        )
        if "lidar" in layout:
            out["lidar"] = flat[layout["lidar"]]
        if has_obstacles:
            out["obstacle_dist"] = obstacles_lib.clearance(state.robot.pos, state.obstacles) - params.robot_radius
        return out

    return snapshot


def _frame(env: CrowdNavEnv, params, snapshots: list[dict], rewards: list[float], outcomes: list[int]) -> np.ndarray:
    """The last of `snapshots` (an episode's states so far, or one state) drawn as an (H, W, 3) uint8 frame."""
    from tgrf_jax.render import Episode, FramePainter, new_figure

    def seq(name):
        return np.stack([np.asarray(s[name]) for s in snapshots])

    count = int(np.asarray(snapshots[0]["active"]).sum())  # inactive slots are no part of the scene
    robot_pos = seq("robot_pos").astype(np.float64)
    steps = len(snapshots) - 1
    k = env.config.pred_horizon if env.config.uses_predictions else 0
    obs_humans = seq("obs_humans")[:, :count]
    last = snapshots[-1]
    layout = [
        np.asarray(last["obstacle_vertices"][m, :c], np.float64)
        for m, c in enumerate(np.asarray(last["obstacle_counts"]))
        if c >= 2
    ]
    episode = Episode(
        label=ENV_ID,
        index=0,
        robot_pos=robot_pos,
        robot_vel=seq("robot_vel"),
        goal=np.asarray(last["goal"]),
        human_pos=seq("human_pos")[:, :count],
        human_radius=seq("human_radius")[:, :count],
        visible=seq("visible")[:, :count].astype(bool),
        obs_human_pos=obs_humans[..., :2] + robot_pos[:, None],
        obs_mask=seq("obs_mask")[:, :count].astype(bool),
        pred_pos=obs_humans[..., 2:].reshape(steps + 1, count, k, 2) + robot_pos[:, None, None] if k else None,
        reward=np.asarray(rewards, np.float64),
        terms={},
        outcomes=np.asarray(outcomes, np.int32),
        dt=float(params.dt),
        robot_radius=float(params.robot_radius),
        sensor_range=float(params.sensor_range),
        d_disc=float(params.reward.d_disc),
        goal_tolerance=float(params.goal_tolerance),
        max_steps=int(round(float(params.time_limit) / float(params.dt))),
        robot_heading=seq("robot_heading").astype(np.float64),
        obstacles=layout,
        lidar=seq("lidar").astype(np.float64) if "lidar" in last else None,
        obstacle_dist=seq("obstacle_dist").astype(np.float64) if "obstacle_dist" in last else None,
        occlusion=bool(env.config.occlusion and env.config.obstacle_slots > 0),
    )
    _, ax = new_figure()
    painter = FramePainter(ax, episode)
    painter.update(steps)
    return painter.render_rgb()


# ---------------------------------------------------------------------------------------------------- one env


class CrowdNavGymEnv(gymnasium.Env):
    """One crowd-navigation episode at a time (see the module docstring for spaces, layout and rendering)."""

    metadata: ClassVar[dict] = {"render_modes": list(RENDER_MODES), "render_fps": 4}

    def __init__(self, config: Any = None, reward: Any = "tgrf", params: Any = None, render_mode: str | None = None):
        self.env, self.params = _make_env(config, reward, params)
        self.observation_space, self.action_space = _spaces(self.env, self.params)
        self.render_mode = _render_mode(render_mode)
        self.metadata = {**type(self).metadata, "render_fps": 1.0 / float(self.params.dt)}
        env, p = self.env, self.params
        self._reset = jax.jit(lambda key: env.reset_env(key, p))
        self._step = jax.jit(lambda key, state, action: env.step_env(key, state, action, p))
        self._snapshot = jax.jit(_snapshot_fn(env, p))
        self._key = None
        self._state = None
        self._closed = False
        self._history: list[dict] = []  # render_mode only: the episode's states so far, with rewards and outcomes
        self._rewards: list[float] = []
        self._outcomes: list[int] = []

    def _check_open(self, call: str) -> None:
        if self._closed:
            raise RuntimeError(f"{call}() after close(): this environment is closed; make a new one")

    def reset(self, *, seed: int | None = None, options: dict | None = None) -> tuple[np.ndarray, dict]:
        self._check_open("reset")
        super().reset(seed=seed)
        # Keys come from the seeded np_random, so reset(seed=s) repeats and later unseeded resets keep varying.
        self._key = jax.random.PRNGKey(int(self.np_random.integers(2**31)))
        self._key, k = jax.random.split(self._key)
        obs, self._state = self._reset(k)
        flat = _flat(obs)
        if self.render_mode is not None:
            self._history, self._rewards, self._outcomes = [jax.device_get(self._snapshot(flat, self._state))], [], []
        return np.asarray(flat), {}

    def step(self, action: Any) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        self._check_open("step")
        if self._state is None:
            raise RuntimeError("call reset() before step()")
        action = _finite_actions(action, (2,), "action")
        self._key, k = jax.random.split(self._key)
        obs, self._state, reward, terminated, truncated, info = self._step(k, self._state, action)
        info = {k: v.item() for k, v in jax.device_get(_info(info)).items()}
        info["outcome_name"] = OUTCOME_NAMES[info["outcome"]]
        flat = _flat(obs)
        if self.render_mode is not None:
            self._history.append(jax.device_get(self._snapshot(flat, self._state)))
            self._rewards.append(float(reward))
            self._outcomes.append(info["outcome"])
        return np.asarray(flat), float(reward), bool(terminated), bool(truncated), info

    def render(self) -> np.ndarray | None:
        """The current state as an (H, W, 3) uint8 frame (render_mode 'rgb_array'), with the episode's trails."""
        self._check_open("render")
        if self.render_mode is None:
            gymnasium.logger.warn(
                "render() without a render_mode returns nothing: make the env with render_mode='rgb_array'"
            )
            return None
        if not self._history:
            raise RuntimeError("call reset() before render()")
        return _frame(self.env, self.params, self._history, self._rewards, self._outcomes)

    def close(self) -> None:
        self._closed = True
        self._state = None
        self._history, self._rewards, self._outcomes = [], [], []
        super().close()


# ---------------------------------------------------------------------------------------------------- vector env


class CrowdNavVectorEnv(VectorEnv):
    """B environments stepped together (see the module docstring for the autoreset modes and rendering).

    num_resets: fresh episodes drawn per step for the environments that ended (default B: each its own; fewer is
    faster, and environments ending in the same step beyond that number share a start, as in training).
    """

    metadata: ClassVar[dict] = {
        "autoreset_mode": AutoresetMode.NEXT_STEP,
        "render_modes": list(RENDER_MODES),
        "render_fps": 4,
    }

    def __init__(
        self,
        num_envs: int,
        config: Any = None,
        reward: Any = "tgrf",
        params: Any = None,
        num_resets: int | None = None,
        autoreset_mode: AutoresetMode | str = AutoresetMode.NEXT_STEP,
        render_mode: str | None = None,
    ) -> None:
        if isinstance(num_envs, bool) or not isinstance(num_envs, (int, np.integer)) or num_envs < 1:
            raise ValueError(f"num_envs must be an integer >= 1, got {num_envs!r}")
        self.env, self.params = _make_env(config, reward, params)
        self.num_envs = int(num_envs)
        resets = self.num_envs if num_resets is None else int(num_resets)
        if not 1 <= resets <= self.num_envs:
            raise ValueError(f"num_resets = {num_resets} must be within 1 .. num_envs = {self.num_envs}")
        self.autoreset_mode = _autoreset_mode(autoreset_mode)
        self.render_mode = _render_mode(render_mode)
        self.metadata = {
            **type(self).metadata,
            "autoreset_mode": self.autoreset_mode,
            "render_fps": 1.0 / float(self.params.dt),
        }
        self.single_observation_space, self.single_action_space = _spaces(self.env, self.params)
        self.observation_space = batch_space(self.single_observation_space, self.num_envs)
        self.action_space = batch_space(self.single_action_space, self.num_envs)
        env, p, b = self.env, self.params, self.num_envs

        def reset(key):
            obs, state = jax.vmap(env.reset_env, in_axes=(0, None))(jax.random.split(key, b), p)
            return _flat(obs), state

        def reset_some(key, state, obs, mask):
            fresh_obs, fresh = reset(key)
            return _where(mask, fresh_obs, obs), jax.tree_util.tree_map(lambda a, b: _where(mask, a, b), fresh, state)

        def step(key, state, action, hold):
            obs, new_state, reward, terminated, truncated, info = env.step_batch(key, state, action, p, resets)
            # environments held this step keep their state (NEXT_STEP: the fresh episode their last step drew)
            new_state = jax.tree_util.tree_map(lambda new, old: _where(hold, old, new), new_state, state)
            return _flat(obs), new_state, reward, terminated, truncated, _flat(info.final_obs), _info(info)

        self._reset = jax.jit(reset)
        self._reset_some = jax.jit(reset_some)
        self._step = jax.jit(step, donate_argnums=1)
        self._snapshot = jax.jit(jax.vmap(_snapshot_fn(env, p)))
        self._key = None
        self._state = None
        self._obs = None  # the observations last returned
        self._pending = None  # NEXT_STEP: each ended environment's fresh first observation, returned next step
        self._ended = np.zeros(self.num_envs, bool)  # environments whose episode ended on the last step

    def _check_open(self, call: str) -> None:
        if self.closed:
            raise RuntimeError(f"{call}() after close(): this environment is closed; make a new one")

    def reset(self, *, seed: int | None = None, options: dict | None = None) -> tuple[np.ndarray, dict]:
        """Reset every environment, or with options={'reset_mask': (B,) bool} only those flagged."""
        self._check_open("reset")
        unknown = sorted(set(options or {}) - {"reset_mask"})
        if unknown:
            raise ValueError(f"unknown reset options {unknown}; allowed: 'reset_mask'")
        mask = (options or {}).get("reset_mask")
        if seed is not None:
            self._key = _seed_key(seed)
        elif self._key is None:
            self._key = _seed_key(int(np.random.SeedSequence().generate_state(1)[0]) % 2**31)
        self._key, k = jax.random.split(self._key)
        if mask is None:
            obs, self._state = self._reset(k)
            self._ended = np.zeros(self.num_envs, bool)
        else:
            mask = np.asarray(mask)
            if mask.dtype != bool or mask.shape != (self.num_envs,):
                raise ValueError(f"reset_mask must be a bool array of shape ({self.num_envs},), got {mask!r}")
            if self._state is None:
                raise RuntimeError("call reset() without a reset_mask first")
            obs, self._state = self._reset_some(k, self._state, jnp.asarray(self._obs), mask)
            self._ended = self._ended & ~mask
        self._obs = np.asarray(obs)
        return self._obs.copy(), {}

    def step(self, actions: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, dict[str, Any]]:
        self._check_open("step")
        if self._state is None:
            raise RuntimeError("call reset() before step()")
        actions = _finite_actions(actions, (self.num_envs, 2), "actions")
        mode = self.autoreset_mode
        if mode == AutoresetMode.DISABLED and self._ended.any():
            raise RuntimeError(
                f"environments {np.flatnonzero(self._ended).tolist()} ended: with autoreset_mode DISABLED reset them "
                "first, reset(options={'reset_mask': mask})"
            )
        hold = self._ended if mode == AutoresetMode.NEXT_STEP else np.zeros(self.num_envs, bool)
        self._key, k = jax.random.split(self._key)
        obs, self._state, *rest = self._step(k, self._state, actions, jnp.asarray(hold))
        obs, reward, terminated, truncated, final_obs, info = jax.device_get((obs, *rest))
        reward = reward.astype(np.float32)
        stepped = ~hold
        infos: dict[str, Any] = {}
        for key, value in info.items():
            infos[key] = np.where(stepped, value, np.zeros_like(value))
            infos[f"_{key}"] = stepped
        done = (terminated | truncated) & stepped
        if mode == AutoresetMode.SAME_STEP:
            if done.any():
                # Gymnasium's own vector envs hand the last observations over as an object array, None elsewhere.
                last = np.full(self.num_envs, None, dtype=object)
                for i in np.flatnonzero(done):
                    last[i] = final_obs[i]
                infos["final_obs"], infos["_final_obs"] = last, done
                infos["final_info"] = {
                    **{k: np.where(done, v, np.zeros_like(v)) for k, v in info.items()},
                    **{f"_{k}": done for k in info},
                }
                infos["_final_info"] = done
            self._obs = obs
        else:
            out = np.where(done[:, None], final_obs, obs)
            if hold.any():
                out[hold] = self._pending[hold]
                reward = np.where(hold, np.float32(0.0), reward)
                terminated, truncated = terminated & stepped, truncated & stepped
            # rows of the environments that ended now hold their fresh episode's first observation
            self._pending = obs
            self._ended = done
            self._obs = out
        return self._obs.copy(), reward, terminated, truncated, infos

    def render(self) -> tuple[np.ndarray, ...] | None:
        """One (H, W, 3) uint8 frame per environment of its current state (render_mode 'rgb_array')."""
        self._check_open("render")
        if self.render_mode is None:
            gymnasium.logger.warn(
                "render() without a render_mode returns nothing: make the env with render_mode='rgb_array'"
            )
            return None
        if self._state is None:
            raise RuntimeError("call reset() before render()")
        snaps = jax.device_get(self._snapshot(jnp.asarray(self._obs), self._state))
        return tuple(
            _frame(self.env, self.params, [{k: v[i] for k, v in snaps.items()}], [], []) for i in range(self.num_envs)
        )

    def close_extras(self, **kwargs: Any) -> None:
        self._state = None


def _make_vec(
    num_envs: int = 1,
    config: Any = None,
    reward: Any = "tgrf",
    params: Any = None,
    num_resets: int | None = None,
    autoreset_mode: AutoresetMode | str = AutoresetMode.NEXT_STEP,
    render_mode: str | None = None,
    **kwargs: Any,
) -> CrowdNavVectorEnv:
    if kwargs:
        raise ValueError(f"unknown arguments {sorted(kwargs)} for {ENV_ID}'s vector env")
    return CrowdNavVectorEnv(num_envs, config, reward, params, num_resets, autoreset_mode, render_mode)


if ENV_ID not in gymnasium.registry:
    gymnasium.register(ENV_ID, entry_point=CrowdNavGymEnv, vector_entry_point=_make_vec)
