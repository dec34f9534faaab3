"""Invariants of the environment checked on hypothesis-generated actions and scenes."""

import jax
import jax.numpy as jnp
import numpy as np
from helpers import make_env
from hypothesis import given, settings
from hypothesis import strategies as st

from tgrf_jax.env import sensing

ENV = make_env(num_humans=5, predictor="const_vel")
PARAMS = ENV.default_params
RESET = jax.jit(ENV.reset)
STEP = jax.jit(ENV.step)
STEP_NO_RESET = jax.jit(ENV.step_env)
UNICYCLE = make_env(num_humans=5, predictor="none", kinematics="unicycle")
U_RESET = jax.jit(UNICYCLE.reset)
U_STEP = jax.jit(UNICYCLE.step)

any_float = st.floats(allow_nan=True, allow_infinity=True, width=32)
actions = st.lists(st.tuples(any_float, any_float), min_size=1, max_size=12)
seeds = st.integers(0, 2**31 - 1)
FAST = settings(max_examples=30, deadline=None)


def _run(reset, step, seed, action_list, params):
    key = jax.random.key(seed)
    obs, state = reset(key, params)
    out = []
    for i, a in enumerate(action_list):
        prev = state
        action = jnp.array(a, jnp.float32)
        obs, state, reward, term, trunc, info = step(jax.random.fold_in(key, i), state, action, params)
        out.append((prev, obs, state, reward, info))
    return out


def _finite(tree):
    return all(
        np.all(np.isfinite(np.asarray(x, dtype=np.float64)))
        for x in jax.tree_util.tree_leaves(tree)
        if np.issubdtype(np.asarray(x).dtype, np.floating)
    )


@FAST
@given(seed=seeds, action_list=actions)
def test_any_action_gives_finite_state_and_bounded_speed(seed, action_list):
    for _prev, obs, state, reward, info in _run(RESET, STEP, seed, action_list, PARAMS):
        assert _finite(state.robot) and _finite(state.humans) and _finite(obs)
        assert np.isfinite(float(reward))
        assert float(jnp.linalg.norm(state.robot.vel)) <= float(PARAMS.robot_v_max) + 1e-5
        assert float(info.path_increment) <= float(PARAMS.robot_v_max * PARAMS.dt) + 1e-5


@FAST
@given(seed=seeds, action_list=actions)
def test_unicycle_any_action_stays_within_limits(seed, action_list):
    params = UNICYCLE.default_params
    for prev, _obs, state, reward, _info in _run(U_RESET, U_STEP, seed, action_list, params):
        assert _finite(state.robot) and np.isfinite(float(reward))
        assert abs(float(state.robot.speed)) <= float(params.robot_v_max) + 1e-6
        if int(state.step_count) > 0:  # not a fresh episode
            assert abs(float(state.robot.heading - prev.robot.heading)) <= float(params.unicycle_dtheta_max) + 1e-6


@FAST
@given(seed=seeds, sensor_range=st.floats(0.0, 12.0))
def test_masks_agree_with_distances(seed, sensor_range):
    params = PARAMS.replace(sensor_range=jnp.float32(sensor_range))
    obs, state = RESET(jax.random.key(seed), params)
    edge = np.asarray(
        sensing.edge_distances(state.robot.pos, state.humans.pos, params.robot_radius, state.humans.radius)
    )
    visible = edge <= sensor_range
    assert int(obs.human_mask.sum()) == int(visible.sum())
    # Visible rows come first, sorted by distance, and match the visible humans' relative positions.
    k = int(visible.sum())
    assert np.all(np.asarray(obs.human_mask[:k])) and not np.any(np.asarray(obs.human_mask[k:]))
    rel = np.asarray(state.humans.pos - state.robot.pos)[visible]
    expected = rel[np.argsort(np.linalg.norm(rel, axis=-1))]
    np.testing.assert_allclose(np.asarray(obs.humans[:k, :2]), expected, atol=1e-5)
    assert np.all(np.asarray(obs.humans[k:]) == 0.0)


@FAST
@given(seed=seeds)
def test_respawned_humans_are_valid(seed):
    key = jax.random.key(seed)
    obs, state = RESET(key, PARAMS)
    # Put every human on its goal: one arrival is served per step, lowest index first.
    state = state.replace(humans=state.humans.replace(goal=state.humans.pos))
    n = state.humans.pos.shape[0]
    goals_before = state.humans.goal
    circle, spread = float(PARAMS.circle_radius), float(PARAMS.spawn_noise) * np.sqrt(2)
    for i in range(n):
        obs, state, *_ = STEP_NO_RESET(jax.random.fold_in(key, i), state, jnp.zeros(2), PARAMS)
        h = jax.tree_util.tree_map(lambda x, i=i: np.asarray(x)[i], state.humans)
        # Human i is fresh (heading for its antipode); the ones still waiting keep their old goals.
        assert np.all(h.goal == -h.pos)
        waiting = np.all(np.asarray(state.humans.goal) == np.asarray(goals_before), axis=-1)
        assert waiting.tolist() == [j > i for j in range(n)]
        assert circle - spread - 1e-4 <= np.linalg.norm(h.pos) <= circle + spread + 1e-4
        np.testing.assert_array_equal(h.goal, -h.pos)
        np.testing.assert_array_equal(h.vel, [0.0, 0.0])
        assert 0.3 <= h.radius <= 0.5 and 0.5 <= h.v_pref <= 1.5
        for q in (np.asarray(state.robot.pos), np.asarray(state.robot.goal)):
            assert np.linalg.norm(h.pos - q) > 0.3 + 0.3
