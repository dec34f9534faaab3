"""tgrf_jax.gym: Gymnasium's own checker on the single env, the vector env's autoreset modes against the batched
env it wraps, Gymnasium's vector wrappers on it, rendering, and the calls it refuses."""

from __future__ import annotations

import warnings

import jax
import numpy as np
import pytest

gymnasium = pytest.importorskip("gymnasium")  # the [gym] extra; the imports below need it

from gymnasium.utils.env_checker import check_env  # noqa: E402 (after the importorskip above)
from gymnasium.vector import AutoresetMode  # noqa: E402 (after the importorskip above)

from tgrf_jax.env import CrowdNavEnv  # noqa: E402 (after the importorskip above)
from tgrf_jax.gym import ENV_ID, CrowdNavGymEnv, CrowdNavVectorEnv, obs_layout  # noqa: E402 (after the importorskip)

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
    venv = CrowdNavVectorEnv(b, SMALL, autoreset_mode=AutoresetMode.SAME_STEP)
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


# ------------------------------------------------------------------------------------------------ autoreset modes


def rollout(venv, steps: int, seed: int = 0):
    """(obs, reward, terminated, truncated, infos) of `steps` steps of seeded random actions after reset(seed)."""
    obs, _ = venv.reset(seed=seed)
    rng = np.random.default_rng(seed)
    out = [(obs, None, None, None, None)]
    for _ in range(steps):
        out.append(venv.step(rng.uniform(-1, 1, (venv.num_envs, 2)).astype(np.float32)))
    return out


def test_vector_env_next_step_autoreset_is_the_default():
    b = 8
    nxt = CrowdNavVectorEnv(b, SMALL)
    assert nxt.metadata["autoreset_mode"] == AutoresetMode.NEXT_STEP == nxt.autoreset_mode
    same = CrowdNavVectorEnv(b, SMALL, autoreset_mode="same_step")
    # Until the first episode ends both modes play the same steps; the step that ends it returns, in NEXT_STEP,
    # the ended episode's last observation (SAME_STEP's final_obs), and the next step returns the new episode's
    # first (SAME_STEP's obs of the ending step) with reward 0 and no end, while the other environments go on.
    n = rollout(nxt, 14)
    s = rollout(same, 14)
    np.testing.assert_array_equal(n[0][0], s[0][0])
    t = next(i for i in range(1, 15) if (s[i][2] | s[i][3]).any())
    for i in range(1, t):
        for a, c in zip(n[i][:4], s[i][:4]):
            np.testing.assert_array_equal(a, c)
    done = s[t][2] | s[t][3]
    np.testing.assert_array_equal(n[t][2], s[t][2])
    np.testing.assert_array_equal(n[t][3], s[t][3])
    for i in np.flatnonzero(done):
        np.testing.assert_array_equal(n[t][0][i], s[t][4]["final_obs"][i])
        np.testing.assert_array_equal(n[t + 1][0][i], s[t][0][i])
    assert "final_obs" not in n[t][4] and (n[t][4]["_outcome"] == np.ones(b, bool)).all()
    obs, reward, terminated, truncated, infos = n[t + 1]
    assert (reward[done] == 0).all() and not (terminated[done] | truncated[done]).any()
    assert infos["_outcome"].tolist() == (~done).tolist() and (infos["outcome"][done] == 0).all()
    going = ~done & ~(s[t + 1][2] | s[t + 1][3])
    np.testing.assert_array_equal(obs[going], s[t + 1][0][going])
    np.testing.assert_array_equal(reward[~done], s[t + 1][1][~done])


def test_gymnasium_vector_wrappers_work_on_the_default_env():
    from gymnasium.wrappers.vector import DictInfoToList, NormalizeObservation, NormalizeReward, RecordEpisodeStatistics

    b, steps = 4, 30
    venv = DictInfoToList(RecordEpisodeStatistics(NormalizeReward(NormalizeObservation(CrowdNavVectorEnv(b, SMALL)))))
    obs, infos = venv.reset(seed=0)
    assert infos == [{}] * b
    rng = np.random.default_rng(0)
    episodes = []
    for _ in range(steps):
        obs, reward, terminated, truncated, infos = venv.step(rng.uniform(-1, 1, (b, 2)).astype(np.float32))
        assert isinstance(infos, list) and len(infos) == b and np.all(np.isfinite(obs)) and np.all(np.isfinite(reward))
        for i, info in enumerate(infos):
            if terminated[i] or truncated[i]:
                assert info["outcome"] in (1, 2, 3) and info["episode"]["l"] <= 12
                episodes.append(info["episode"])
            elif "outcome" in info:
                assert info["outcome"] == 0
    assert len(episodes) >= b  # every environment ended at least once within 30 steps of 3 s episodes
    assert abs(float(np.mean(obs))) < 3.0  # normalised


def test_vector_env_autoreset_disabled():
    b = 4
    venv = CrowdNavVectorEnv(b, SMALL, autoreset_mode=AutoresetMode.DISABLED)
    assert venv.metadata["autoreset_mode"] == AutoresetMode.DISABLED
    obs, _ = venv.reset(seed=0)
    actions = np.zeros((b, 2), np.float32)
    for _ in range(12):
        obs, _, terminated, truncated, _ = venv.step(actions)
        if (terminated | truncated).any():
            break
    done = terminated | truncated
    assert done.any()
    with pytest.raises(RuntimeError, match=r"environments \[.*\] ended: with autoreset_mode DISABLED reset them"):
        venv.step(actions)
    fresh, _ = venv.reset(options={"reset_mask": done})
    np.testing.assert_array_equal(fresh[~done], obs[~done])  # the others keep their observation
    assert not np.array_equal(fresh[done], obs[done])
    venv.step(actions)
    with pytest.raises(ValueError, match=r"reset_mask must be a bool array of shape \(4,\)"):
        venv.reset(options={"reset_mask": [1, 0]})
    with pytest.raises(ValueError, match="unknown reset options"):
        venv.reset(options={"mask": done})
    with pytest.raises(ValueError, match="autoreset_mode must be one of"):
        CrowdNavVectorEnv(b, SMALL, autoreset_mode="sometimes")


# ------------------------------------------------------------------------------------------------ rendering


def test_single_env_renders_rgb_frames():
    env = gymnasium.make(ENV_ID, config=SMALL, render_mode="rgb_array")
    assert "rgb_array" in env.metadata["render_modes"] and env.metadata["render_fps"] == 4.0
    env.reset(seed=0)
    first = env.render()
    assert first.ndim == 3 and first.shape[2] == 3 and first.dtype == np.uint8 and first.shape[0] > 100
    assert len(np.unique(first.reshape(-1, 3), axis=0)) > 10  # a drawing, not a blank
    for _ in range(3):
        env.step(np.array([0.0, 1.0], np.float32))
    later = env.render()
    assert later.shape == first.shape and not np.array_equal(later, first)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        check_env(env.unwrapped)  # its render check included
    advice = "we recommend using a symmetric and normalized space"
    assert not [str(w.message) for w in caught if advice not in str(w.message)]
    with pytest.raises(ValueError, match=r"render_mode must be None or one of \['rgb_array'\]"):
        CrowdNavGymEnv(SMALL, render_mode="human")


def test_vector_env_renders_one_frame_per_env():
    venv = gymnasium.make_vec(ENV_ID, 2, config=SMALL, render_mode="rgb_array")
    assert venv.render_mode == "rgb_array" and "rgb_array" in venv.metadata["render_modes"]
    venv.reset(seed=0)
    frames = venv.render()
    assert len(frames) == 2 and all(f.dtype == np.uint8 and f.ndim == 3 for f in frames)
    assert not np.array_equal(frames[0], frames[1])


# ------------------------------------------------------------------------------------------------ refused calls


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf, 1e39])
def test_non_finite_actions_are_refused(bad):
    env = CrowdNavGymEnv(SMALL)
    env.reset(seed=0)
    with pytest.raises(ValueError, match=r"action must be finite \(float32\): entry \[1\] is"):
        env.step(np.array([0.5, bad]))
    venv = CrowdNavVectorEnv(3, SMALL)
    venv.reset(seed=0)
    actions = np.zeros((3, 2))
    actions[2, 0] = bad
    with pytest.raises(ValueError, match=r"actions must be finite \(float32\): entry \[2, 0\] is"):
        venv.step(actions)


def test_closed_envs_refuse_calls():
    env = CrowdNavGymEnv(SMALL, render_mode="rgb_array")
    env.reset(seed=0)
    env.close()
    for call in (lambda: env.step(np.zeros(2, np.float32)), lambda: env.reset(seed=0), env.render):
        with pytest.raises(RuntimeError, match=r"after close\(\): this environment is closed"):
            call()
    venv = CrowdNavVectorEnv(2, SMALL)
    venv.reset(seed=0)
    venv.close()
    with pytest.raises(RuntimeError, match=r"step\(\) after close\(\)"):
        venv.step(np.zeros((2, 2), np.float32))
    with pytest.raises(RuntimeError, match=r"reset\(\) after close\(\)"):
        venv.reset(seed=0)
