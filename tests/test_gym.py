"""tgrf_jax.gym: Gymnasium's own checker on the single env, and the vector env's same-step autoreset against
the batched env it wraps."""

from __future__ import annotations

import warnings

import jax
import numpy as np
import pytest

gymnasium = pytest.importorskip("gymnasium")

from gymnasium.utils.env_checker import check_env
from gymnasium.vector import AutoresetMode

from tgrf_jax.env import CrowdNavEnv
from tgrf_jax.gym import ENV_ID, CrowdNavGymEnv, CrowdNavVectorEnv, obs_layout

SMALL = {"num_humans": 5, "time_limit": 3.0}  # 12-step episodes: several end within a short test


@pytest.mark.parametrize("kinematics", ["holonomic", "unicycle"])
def test_single_env_passes_gymnasium_checker(kinematics):
    env = gymnasium.make(ENV_ID, config=dict(SMALL, kinematics=kinematics))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        check_env(env.unwrapped)
    # The unicycle's speed change really is asymmetric ([-0.1, 0.087] m/s per step, as the reference); the
    # checker's advice to normalise the action box is a recommendation for learners, not a fault of the env.
    advice = "we recommend using a symmetric and normalized space"
    assert not [str(w.message) for w in caught if advice not in str(w.message)]


def test_single_env_plays_the_env_episode():
    env = CrowdNavGymEnv(SMALL)
    obs, info = env.reset(seed=3)
    assert obs.shape == env.observation_space.shape and obs.dtype == np.float32 and info == {}
    np.testing.assert_array_equal(env.reset(seed=3)[0], obs)
    layout = obs_layout(env.env)
    assert layout["human_mask"].stop == obs.size == 7 + 2 + 5 * 12 + 5
    steps, done = 0, False
    while not done:
        obs, reward, terminated, truncated, info = env.step(np.array([0.5, 0.0], np.float32))
        assert np.isfinite(reward) and obs in env.observation_space
        done = terminated or truncated
        steps += 1
    assert steps <= 12 and info["outcome_name"] in ("success", "collision", "timeout")
    assert truncated == (info["outcome_name"] == "timeout")


def test_vector_env_same_step_autoreset():
    b = 16
    venv = CrowdNavVectorEnv(b, SMALL)
    assert venv.metadata["autoreset_mode"] == AutoresetMode.SAME_STEP
    assert venv.observation_space.shape == (b, venv.single_observation_space.shape[0])
    obs, _ = venv.reset(seed=0)
    assert obs.shape == venv.observation_space.shape and obs.dtype == np.float32
    # the same batched program, run directly: the vector env adds only the NumPy conversion and the infos
    env = CrowdNavEnv(SMALL)
    params = env.default_params
    key = jax.random.PRNGKey(0)
    key, k = jax.random.split(key)
    _, state = jax.vmap(env.reset_env, in_axes=(0, None))(jax.random.split(k, b), params)
    step = jax.jit(env.step_batch, static_argnums=4)
    rng = np.random.default_rng(0)
    ended = 0
    for _ in range(14):
        actions = rng.uniform(-1, 1, (b, 2)).astype(np.float32)
        obs, reward, terminated, truncated, infos = venv.step(actions)
        key, k = jax.random.split(key)
        ref_obs, state, ref_reward, ref_term, ref_trunc, ref_info = step(k, state, actions, params, b)
        np.testing.assert_array_equal(terminated, np.asarray(ref_term))
        np.testing.assert_array_equal(truncated, np.asarray(ref_trunc))
        np.testing.assert_allclose(reward, np.asarray(ref_reward), rtol=1e-6, atol=1e-6)
        np.testing.assert_allclose(obs[:, :7], np.asarray(ref_obs.robot_node), rtol=1e-6, atol=1e-6)
        assert not (terminated & truncated).any()
        done = terminated | truncated
        if done.any():
            ended += int(done.sum())
            assert infos["_final_obs"].tolist() == done.tolist()
            assert infos["_final_info"].tolist() == done.tolist()
            for i in range(b):
                if done[i]:
                    # the ended episode's last observation; `obs` already holds the new episode's first
                    np.testing.assert_allclose(
                        infos["final_obs"][i][:7], np.asarray(ref_info.final_obs.robot_node[i]), rtol=1e-6, atol=1e-6
                    )
                    assert infos["final_info"]["outcome"][i] in (1, 2, 3)
                    assert not np.array_equal(infos["final_obs"][i], obs[i])
                else:
                    assert infos["final_obs"][i] is None
        else:
            assert "final_obs" not in infos
    assert ended >= b  # every env reached the 3 s limit at least once


def test_vector_env_make_vec_and_bad_input():
    venv = gymnasium.make_vec(ENV_ID, 4, config=SMALL)
    obs, _ = venv.reset(seed=1)
    assert obs.shape[0] == 4
    with pytest.raises(ValueError, match=r"actions must have shape \(4, 2\)"):
        venv.step(np.zeros((3, 2), np.float32))
    with pytest.raises(ValueError, match="num_envs must be an integer >= 1"):
        CrowdNavVectorEnv(0, SMALL)
    with pytest.raises(ValueError, match="seed must be an integer"):
        venv.reset(seed=-1)


LIDAR = {
    "num_humans": 2,
    "time_limit": 3.0,
    "scenario": "corridor",
    "lidar_rays": 12,
    "human_policy": "social_force",
    "predictor": "none",
}


def test_lidar_scan_is_part_of_the_observation():
    env = gymnasium.make(ENV_ID, config=LIDAR).unwrapped
    layout = obs_layout(env.env)
    assert list(layout) == ["robot_node", "robot_vel", "humans", "human_mask", "lidar"]
    assert layout["lidar"] == slice(7 + 2 + 2 * 2 + 2, 7 + 2 + 2 * 2 + 2 + 12)
    space = env.observation_space
    assert space.shape == (layout["lidar"].stop,)
    np.testing.assert_array_equal(space.low[layout["lidar"]], 0.0)
    np.testing.assert_array_equal(space.high[layout["lidar"]], np.float32(5.0))  # the sensor range
    assert space.high[0] == space.high[layout["human_mask"]][0] > 1e5  # the rest keeps the wide bounds
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        check_env(env)
    assert not caught, [str(w.message) for w in caught]
    # without a scan the layout ends with the mask, as before
    assert list(obs_layout(CrowdNavEnv(dict(LIDAR, lidar_rays=0)))) == [
        "robot_node",
        "robot_vel",
        "humans",
        "human_mask",
    ]

    # the vector env's scan is the batched env's Obs.lidar, body frame and all
    b = 3
    venv = CrowdNavVectorEnv(b, LIDAR)
    obs, _ = venv.reset(seed=0)
    raw = CrowdNavEnv(LIDAR)
    _, k = jax.random.split(jax.random.PRNGKey(0))
    ref_obs, _ = jax.jit(jax.vmap(raw.reset_env, in_axes=(0, None)))(jax.random.split(k, b), raw.default_params)
    np.testing.assert_allclose(obs[:, layout["lidar"]], np.asarray(ref_obs.lidar), atol=1e-5)
    assert obs[:, layout["lidar"]].min() < 5.0  # the corridor's walls are in range
    obs, *_ = venv.step(np.zeros((b, 2), np.float32))
    assert obs in venv.observation_space
