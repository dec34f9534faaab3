"""The env's `gst` predictor: history reset, observation slots, r_pred, jit/vmap, weights as a traced leaf."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import hand_state, make_env

from tgrf_jax.config import ConfigError, EnvConfig
from tgrf_jax.env import gst as predictor
from tgrf_jax.env import sensing
from tgrf_jax.env.gst import history as gst_history


def constant_step_params(step_xy):
    """Parameters whose every prediction moves by `step_xy` per step: all weights zero, head bias (dx, dy, ...).

    Zero weights make the spatial block and the LSTM output zero, so the head returns its bias."""
    # (jitted: run eagerly, every initialiser of every layer shape is a program of its own)
    params = jax.tree_util.tree_map(jnp.zeros_like, jax.jit(predictor.init_params)(jax.random.key(0)))
    bias = jnp.array([step_xy[0], step_xy[1], 0.0, 0.0, 0.0])
    return {**params, "head": {**params["head"], "bias": bias}}


@pytest.fixture(scope="module")
def env():
    return make_env(num_humans=3, human_policy="social_force", predictor="gst", time_limit=1.0)


def test_config_accepts_gst_and_checks_horizon():
    assert EnvConfig(predictor="gst").obs_human_dim == 12
    with pytest.raises(ConfigError, match="pred_horizon"):
        EnvConfig(predictor="gst", pred_horizon=3)
    with pytest.raises(ConfigError, match="predictor_params"):
        EnvConfig(predictor="gst", predictor_params="mystery")


def test_default_params_are_the_shipped_weights():
    shipped = predictor.pretrained("orca")
    default = make_env(predictor="gst", predictor_params="orca").default_params.predictor
    for a, b in zip(jax.tree_util.tree_leaves(default), jax.tree_util.tree_leaves(shipped)):
        np.testing.assert_array_equal(np.asarray(a), b)
    assert make_env(predictor="const_vel").default_params.predictor is None


def test_history_is_reset_at_every_episode_start(env):
    params = env.default_params
    step, step_env = jax.jit(env.step), jax.jit(env.step_env)
    obs, state = jax.jit(env.reset)(jax.random.key(0), params)
    assert not np.asarray(state.history.visible[:, :4]).any()
    # reset skips the model: its observation is the one the model's predictions on the fresh history give
    model = gst_history.predictions(params.predictor, state.history)
    assert not np.asarray(model.out_mask).any()
    visible = sensing.visible_mask(state, params)
    for a, b in zip(
        jax.tree_util.tree_leaves(obs), jax.tree_util.tree_leaves(sensing.observe(state, params, model.means, visible))
    ):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    ended = 0
    for i in range(10):  # time_limit 1 s = 4 steps: two episode ends
        obs, new_state, reward, term, trunc, info = step(jax.random.key(i + 1), state, jnp.zeros(2), params)
        h = new_state.history
        if bool(term | trunc):
            ended += 1
            # a fresh episode sees only its current frame: nothing of the episode that just ended
            assert not np.asarray(h.visible[:, :4]).any()
            visible = np.asarray(h.visible[:, 4])
            np.testing.assert_allclose(np.asarray(h.positions[visible, 4]), np.asarray(new_state.humans.pos)[visible])
            # the terminal step's reward (r_pred included) comes from the episode that ended, not the next one
            _, _, reward_no_reset, *_ = step_env(
                jax.random.split(jax.random.key(i + 1))[0], state, jnp.zeros(2), params
            )
            np.testing.assert_allclose(float(reward), float(reward_no_reset))
        else:
            # frames shift by one and the new frame is appended
            np.testing.assert_array_equal(np.asarray(h.visible[:, :4]), np.asarray(state.history.visible[:, 1:]))
        state = new_state
    assert ended == 2


def test_prediction_slots_as_the_reference_places_them(env):
    params = env.default_params
    _, state = jax.jit(env.reset)(jax.random.key(3), params)
    # hand-made history: every human seen in all five frames, walking at constant velocity
    vel = jnp.array([[0.5, 0.0], [0.0, -0.4], [0.3, 0.3]])
    times = jnp.arange(-4, 1, dtype=jnp.float32)[None, :, None] * 0.25
    robot = state.robot.replace(pos=jnp.zeros(2))
    humans = state.humans.replace(pos=jnp.array([[1.0, 0.5], [-2.0, 1.0], [0.5, -6.0]]))
    hist = gst_history.History(
        positions=humans.pos[:, None] + times * vel[:, None],
        visible=jnp.ones((3, 5), bool).at[2].set(jnp.array([0, 0, 0, 1, 1], bool)),
    )
    state = state.replace(robot=robot, humans=humans, history=hist)
    visible = np.array([True, True, False])  # human 2 is out of the 5 m range now
    hist = hist.replace(visible=hist.visible & jnp.asarray(visible)[:, None])
    state = state.replace(history=hist)
    pred = gst_history.predictions(params.predictor, hist)
    predictions, counted = env._predict(state, params, jnp.asarray(visible))
    from tgrf_jax.env import sensing

    obs = sensing.observe(state, params, predictions, jnp.asarray(visible))
    rows = np.asarray(obs.humans)
    mask = np.asarray(obs.human_mask)
    assert mask.tolist() == [True, True, False]
    # rows sorted by distance: human 0 (1.1 m) then human 1 (2.2 m); slots = [x_t, y_t, x_t+1, ..., y_t+5] - robot
    for row, h in zip(rows[:2], (0, 1)):
        np.testing.assert_allclose(row[:2], np.asarray(humans.pos[h]))
        np.testing.assert_allclose(row[2:].reshape(5, 2), np.asarray(pred.means[h]), atol=1e-6)
    assert not rows[2].any()  # unseen human: masked row, no magic coordinate
    np.testing.assert_array_equal(np.asarray(counted), [True, True, False])


def test_unpredicted_human_holds_its_position_and_never_counts_for_r_pred():
    env = make_env(
        num_humans=1, human_policy="social_force", predictor="gst", reward={"scheme": "tgrf", "pred_radius": 1.2}
    )
    params = env.default_params.replace(predictor=constant_step_params((0.25, 0.0)))
    # a (practically) motionless human 1.0 m left of a robot that stays put
    state = hand_state([0.0, 0.0], [0.0, 8.0], [[-1.0, 0.0]], v_pref=1e-6)
    seen = gst_history.History(
        positions=jnp.tile(jnp.array([[[-1.0, 0.0]]]), (1, 5, 1)), visible=jnp.ones((1, 5), bool)
    )
    unseen = seen.replace(visible=jnp.zeros((1, 5), bool))
    step = jax.jit(env.step_env)
    # predicted (seen in the last two frames): -1 + 0.25 k reaches within 1.2 m of the robot at k = 1
    obs, _, _, _, _, info = step(jax.random.key(0), state.replace(history=seen), jnp.zeros(2), params)
    np.testing.assert_allclose(float(info.reward_terms.pred), -10.0 / 2 ** (1 + 1))
    np.testing.assert_allclose(
        np.asarray(obs.humans[0, 2:]).reshape(5, 2)[:, 0], -1.0 + 0.25 * np.arange(1, 6), atol=1e-4
    )
    # seen only now: no prediction; its slots hold its current position (inside 1.2 m), but r_pred stays 0
    obs, _, _, _, _, info = step(jax.random.key(0), state.replace(history=unseen), jnp.zeros(2), params)
    assert float(info.reward_terms.pred) == 0.0
    np.testing.assert_allclose(np.asarray(obs.humans[0]), np.tile([-1.0, 0.0], 6), atol=1e-4)


def test_r_pred_uses_the_post_step_robot_and_the_new_observation():
    env = make_env(num_humans=1, human_policy="social_force", predictor="gst", reward={"scheme": "tgrf"})
    params = env.default_params.replace(predictor=constant_step_params((0.25, 0.0)))
    # a motionless human at (-1.2, 0), predicted to come 0.25 m closer per step; the robot steps to (-0.25, 0)
    state = hand_state([0.0, 0.0], [-8.0, 0.0], [[-1.2, 0.0]], v_pref=1e-6)
    state = state.replace(
        history=gst_history.History(
            positions=jnp.tile(jnp.array([[[-1.2, 0.0]]]), (1, 5, 1)), visible=jnp.ones((1, 5), bool)
        )
    )
    _, _, _, term, _, info = jax.jit(env.step_env)(jax.random.key(0), state, jnp.array([-1.0, 0.0]), params)
    assert not bool(term)
    # post-step robot: first hit at k = 2 (0.45 m) -> -10 / 2^3; the pre-step robot would first be hit at k = 3
    np.testing.assert_allclose(float(info.reward_terms.pred), -1.25)


def test_jit_vmap_and_weights_swap_without_recompiling():
    env = make_env(num_humans=4, human_policy="social_force", predictor="gst")
    params = env.default_params
    keys = jax.random.split(jax.random.key(1), 3)
    obs, state = jax.jit(jax.vmap(env.reset, in_axes=(0, None)))(keys, params)
    step = jax.jit(jax.vmap(env.step, in_axes=(0, 0, 0, None)))
    actions = jnp.zeros((3, 2))
    for _ in range(3):
        obs, state, *_ = step(keys, state, actions, params)
    batched = step(keys, state, actions, params)
    # each env's slots hold the model's predictions from that env's own history
    new_state = batched[1]
    pred = jax.jit(jax.vmap(gst_history.predictions, in_axes=(None, 0)))(params.predictor, new_state.history)
    for e in range(3):
        rows, mask = np.asarray(batched[0].humans[e]), np.asarray(batched[0].human_mask[e])
        expected = np.asarray(pred.means[e] - new_state.robot.pos[e]).reshape(4, 10)
        seen = np.asarray(new_state.history.visible[e, :, -1])
        got = {tuple(np.round(r[2:], 4)) for r in rows[mask]}
        assert got == {tuple(np.round(x, 4)) for x in expected[seen]}
    other = params.replace(predictor=jax.jit(predictor.init_params)(jax.random.key(7)))
    swapped = step(keys, state, actions, other)
    assert step._cache_size() == 1  # new weights are a traced input, not a new program
    visible = np.asarray(batched[0].human_mask)
    assert visible.any()
    assert not np.allclose(np.asarray(swapped[0].humans)[visible], np.asarray(batched[0].humans)[visible])


@pytest.mark.parametrize(
    "fn, positions, visible, message",
    [
        (
            "predict",
            (3, 5, 2, 1),
            (3, 5),
            r"gst.predict: positions has shape \(3, 5, 2, 1\); expected \(humans, 5, 2\)",
        ),
        ("predict", (4, 3, 5, 2), (4, 3, 5), r"positions has shape \(4, 3, 5, 2\); expected \(humans, 5, 2\).*vmap"),
        ("predict", (3, 5), (3, 5), r"positions has shape \(3, 5\); expected \(humans, 5, 2\)"),
        ("predict", (3, 4, 2), (3, 4), r"positions has shape \(3, 4, 2\); expected \(humans, 5, 2\)"),
        ("predict", (3, 5, 2), (3, 4), r"gst.predict: visible has shape \(3, 4\); expected \(3, 5\)"),
        (
            "step_gaussians",
            (3, 5, 2, 1),
            (3, 5),
            (
                r"gst.step_gaussians: positions has shape \(3, 5, 2, 1\); "
                r"expected \(humans, T, 2\)"
            ),
        ),
    ],
)
def test_arrays_of_the_wrong_shape_are_named_with_the_shape_expected(fn, positions, visible, message):
    # what a user passes by hand: a batch of envs without vmap, a missing (x, y) axis, too few frames
    params = predictor.init_params(jax.random.key(0), num_humans=3)
    with pytest.raises(ValueError, match=message):
        getattr(predictor, fn)(params, np.zeros(positions, np.float32), np.ones(visible, bool))
