"""The crowd-navigation simulator as Gymnasium 1.x environments, for trainers outside tgrf-jax (optional extra:
pip install 'tgrf-jax[gym]').

* `CrowdNavVectorEnv(num_envs, config, reward)`: a `gymnasium.vector.VectorEnv` of B environments stepped by
  one jitted `CrowdNavEnv.step_batch` call (the trainer's own batched path), NumPy in and out. It resets an
  ended episode within the step that ended it (`AutoresetMode.SAME_STEP`, stated in `metadata`): that step
  returns the new episode's first observation, and `infos["final_obs"]` / `infos["final_info"]` carry the ended
  episode's last observation and info for the environments flagged in `infos["_final_obs"]`.
* `CrowdNavGymEnv(config, reward)`: one `gymnasium.Env` (`step` never resets; call `reset` after an end).

Observations are flat float32 vectors (`Box`), the inputs the networks read, in this order:
robot_node (7: px, py, radius, gx, gy, v_max, heading), robot_vel (2), humans (N x D, rows sorted nearest first,
zeros where nobody is in range), human_mask (N: 1.0 for a human in range), and with a LiDAR (env.lidar_rays = R
> 0) lidar (R: ranges in metres within [0, sensor_range], ray k at heading + 2 pi k / R counter-clockwise, the
robot's body frame, as `Obs.lidar`; absent when R = 0). `obs_layout(env)` gives the slices. The observation
space bounds the scan by [0, sensor_range] and everything else by +-OBS_BOUND. Static obstacles (`Obs.obstacles`,
the map) are not part of the observation. Actions: holonomic (vx, vy) in m/s (the env scales the norm down to v_max), unicycle (dv, dtheta) within
the per-step limits. `terminated` is a collision or the goal, `truncated` the time limit.
"""

from __future__ import annotations

from typing import Any, ClassVar

import gymnasium
import jax
import jax.numpy as jnp
import numpy as np
from gymnasium import spaces
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import batch_space

from tgrf_jax.env import CrowdNavEnv
from tgrf_jax.env.types import OUTCOME_NAMES

__all__ = ["ENV_ID", "CrowdNavGymEnv", "CrowdNavVectorEnv", "obs_layout"]

ENV_ID = "tgrf_jax/CrowdNav-v0"  # gymnasium.make(ENV_ID, config=..., reward=...) and gymnasium.make_vec(ENV_ID, B)
# Finite observation bounds (Gymnasium's checker flags infinite ones): no position, prediction or heading of the
# simulator comes near them within the longest allowed episode.
OBS_BOUND = 1e6


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
    params = (env.default_params if params is None else params).validate()
    return env, params


def _seed_key(seed) -> jax.Array:
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or not 0 <= int(seed) < 2**31:
        raise ValueError(f"seed must be an integer in [0, 2**31), got {seed!r}")
    return jax.random.PRNGKey(int(seed))


class CrowdNavGymEnv(gymnasium.Env):
    """One crowd-navigation episode at a time (see the module docstring for spaces and layout)."""

    metadata: ClassVar[dict] = {"render_modes": []}

    def __init__(self, config=None, reward="tgrf", params=None):
        self.env, self.params = _make_env(config, reward, params)
        self.observation_space, self.action_space = _spaces(self.env, self.params)
        env, p = self.env, self.params
        self._reset = jax.jit(lambda key: env.reset_env(key, p))
        self._step = jax.jit(lambda key, state, action: env.step_env(key, state, action, p))
        self._key = None
        self._state = None

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        # Keys come from the seeded np_random, so reset(seed=s) repeats and later unseeded resets keep varying.
        self._key = jax.random.PRNGKey(int(self.np_random.integers(2**31)))
        self._key, k = jax.random.split(self._key)
        obs, self._state = self._reset(k)
        return np.asarray(_flat(obs)), {}

    def step(self, action):
        if self._state is None:
            raise RuntimeError("call reset() before step()")
        action = np.asarray(action, np.float32).reshape(2)
        self._key, k = jax.random.split(self._key)
        obs, self._state, reward, terminated, truncated, info = self._step(k, self._state, action)
        info = {k: v.item() for k, v in jax.device_get(_info(info)).items()}
        info["outcome_name"] = OUTCOME_NAMES[info["outcome"]]
        return np.asarray(_flat(obs)), float(reward), bool(terminated), bool(truncated), info


class CrowdNavVectorEnv(VectorEnv):
    """B environments stepped together with same-step autoreset (see the module docstring).

    num_resets: fresh episodes drawn per step for the environments that ended (default B: each its own; fewer is
    faster, and environments ending in the same step beyond that number share a start, as in training).
    """

    metadata: ClassVar[dict] = {"autoreset_mode": AutoresetMode.SAME_STEP, "render_modes": []}

    def __init__(self, num_envs: int, config=None, reward="tgrf", params=None, num_resets: int | None = None):
        if isinstance(num_envs, bool) or not isinstance(num_envs, (int, np.integer)) or num_envs < 1:
            raise ValueError(f"num_envs must be an integer >= 1, got {num_envs!r}")
        self.env, self.params = _make_env(config, reward, params)
        self.num_envs = int(num_envs)
        resets = self.num_envs if num_resets is None else int(num_resets)
        if not 1 <= resets <= self.num_envs:
            raise ValueError(f"num_resets = {num_resets} must be within 1 .. num_envs = {self.num_envs}")
        self.single_observation_space, self.single_action_space = _spaces(self.env, self.params)
        self.observation_space = batch_space(self.single_observation_space, self.num_envs)
        self.action_space = batch_space(self.single_action_space, self.num_envs)
        env, p, b = self.env, self.params, self.num_envs

        def reset(key):
            obs, state = jax.vmap(env.reset_env, in_axes=(0, None))(jax.random.split(key, b), p)
            return _flat(obs), state

        def step(key, state, action):
            obs, state, reward, terminated, truncated, info = env.step_batch(key, state, action, p, resets)
            return _flat(obs), state, reward, terminated, truncated, _flat(info.final_obs), _info(info)

        self._reset = jax.jit(reset)
        self._step = jax.jit(step, donate_argnums=1)
        self._key = None
        self._state = None

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        if seed is not None:
            self._key = _seed_key(seed)
        elif self._key is None:
            self._key = _seed_key(int(np.random.SeedSequence().generate_state(1)[0]) % 2**31)
        self._key, k = jax.random.split(self._key)
        obs, self._state = self._reset(k)
        return np.asarray(obs), {}

    def step(self, actions):
        if self._state is None:
            raise RuntimeError("call reset() before step()")
        actions = np.asarray(actions, np.float32)
        if actions.shape != (self.num_envs, 2):
            raise ValueError(f"actions must have shape ({self.num_envs}, 2), got {actions.shape}")
        self._key, k = jax.random.split(self._key)
        obs, self._state, reward, terminated, truncated, final_obs, info = jax.device_get(
            self._step(k, self._state, actions)
        )
        infos: dict[str, Any] = dict(info)
        done = terminated | truncated
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
        return obs, reward.astype(np.float32), terminated, truncated, infos


def _make_vec(num_envs: int = 1, config=None, reward="tgrf", params=None, num_resets=None, **kwargs):
    if kwargs:
        raise ValueError(f"unknown arguments {sorted(kwargs)} for {ENV_ID}'s vector env")
    return CrowdNavVectorEnv(num_envs, config, reward, params, num_resets)


if ENV_ID not in gymnasium.registry:
    gymnasium.register(ENV_ID, entry_point=CrowdNavGymEnv, vector_entry_point=_make_vec)
