import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import hand_state, make_env, rollout, to_goal

from tgrf_jax.env import COLLISION, RUNNING, SUCCESS, TIMEOUT


@pytest.mark.parametrize("policy", ["orca", "social_force"])
@pytest.mark.parametrize("predictor, dim", [("none", 2), ("const_vel", 12), ("truth", 12)])
def test_shapes_jit_vmap(policy, predictor, dim):
    env = make_env(num_humans=3, human_policy=policy, predictor=predictor)
    params = env.default_params
    keys = jax.random.split(jax.random.key(0), 4)
    obs, state = jax.jit(jax.vmap(env.reset, in_axes=(0, None)))(keys, params)
    assert obs.humans.shape == (4, 3, dim) and obs.human_mask.shape == (4, 3) and obs.robot_node.shape == (4, 7)
    step = jax.jit(jax.vmap(env.step, in_axes=(0, 0, 0, None)))
    obs, state, reward, term, trunc, info = step(keys, state, jnp.ones((4, 2)), params)
    assert reward.shape == (4,) and term.dtype == bool and info.final_obs.humans.shape == (4, 3, dim)
    assert np.all(np.isfinite(np.asarray(state.humans.pos)))


def test_reset_scenario_rules():
    env = make_env()
    params = env.default_params
    obs, state = jax.jit(jax.vmap(env.reset, in_axes=(0, None)))(jax.random.split(jax.random.key(1), 64), params)
    start, goal = np.asarray(state.robot.pos), np.asarray(state.robot.goal)
    assert np.all(np.abs(start) <= 6) and np.all(np.abs(goal) <= 6)
    assert np.all(np.linalg.norm(start - goal, axis=-1) >= 8.0)
    h = state.humans
    np.testing.assert_allclose(h.goal, -h.pos, atol=1e-6)  # antipodal goals
    r = np.linalg.norm(np.asarray(h.pos) - 0.0, axis=-1)
    assert np.all(r > 6 * np.sqrt(2) - 2 * np.sqrt(2)) and np.all(r < 6 * np.sqrt(2) + 2 * np.sqrt(2))
    assert np.all((h.radius >= 0.3) & (h.radius <= 0.5)) and np.all((h.v_pref >= 0.5) & (h.v_pref <= 1.5))
    # Spawn rule: each human clears every other's position by r_i + r_j + 0.5 (almost always satisfiable).
    d = np.linalg.norm(np.asarray(h.pos)[:, :, None] - np.asarray(h.pos)[:, None], axis=-1)
    need = np.asarray(h.radius)[:, :, None] + np.asarray(h.radius)[:, None] + 0.5
    ok = (d >= need - 1e-5) | np.eye(20, dtype=bool)
    assert ok.mean() > 0.999


def test_same_key_same_trajectory_and_different_keys_differ():
    env = make_env(num_humans=5)
    a = rollout(env, jax.random.key(3), env.default_params, 60, to_goal)
    b = rollout(env, jax.random.key(3), env.default_params, 60, to_goal)
    c = rollout(env, jax.random.key(4), env.default_params, 60, to_goal)
    for x, y in zip(jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b)):
        np.testing.assert_array_equal(x, y)
    assert not np.allclose(a[0].robot.pos, c[0].robot.pos)


def test_reach_goal_without_humans():
    env = make_env(num_humans=0, predictor="none")
    params = env.default_params
    states, rewards, term, trunc, info = rollout(env, jax.random.key(0), params, 40, to_goal)
    first_done = int(np.argmax(np.asarray(term)))
    assert term[first_done] and info.outcome[first_done] == SUCCESS
    assert float(rewards[first_done]) == pytest.approx(10.0)
    # Before arriving, every step earns 1.5 x progress = 1.5 x 0.25 m.
    np.testing.assert_allclose(rewards[: first_done - 1], 0.375, atol=1e-5)
    assert not np.any(np.asarray(trunc[:first_done]))


def test_time_limit_truncates_and_keeps_final_obs():
    env = make_env(num_humans=0, predictor="none")
    params = env.default_params
    states, rewards, term, trunc, info = rollout(env, jax.random.key(0), params, 201, lambda o: jnp.zeros(2))
    assert int(params.max_steps) == 200
    assert not np.any(np.asarray(term))
    assert np.flatnonzero(np.asarray(trunc)).tolist() == [199]
    assert info.outcome[199] == TIMEOUT and float(info.time[199]) == pytest.approx(50.0)
    assert np.all(np.asarray(info.outcome[:199]) == RUNNING)
    # After auto-reset the new episode starts elsewhere, but final_obs still shows the truncated state.
    np.testing.assert_allclose(info.final_obs.robot_node[199, :2], states.robot.pos[198], atol=1e-6)
    assert int(states.step_count[199]) == 0


def test_collision_is_judged_after_the_step():
    env = make_env(num_humans=1, predictor="none", human_policy="social_force")
    params = env.default_params.replace(sf_a=jnp.float32(0.0))
    # Human 0.8 m ahead (edges 0.2 m apart), standing still; the robot drives 0.25 m into it.
    state = hand_state([0.0, 0.0], [5.0, 0.0], [[0.8, 0.0]])
    obs, nxt, reward, term, trunc, info = env.step_env(jax.random.key(0), state, jnp.array([1.0, 0.0]), params)
    assert bool(term) and int(info.outcome) == COLLISION and float(reward) == pytest.approx(-10.0)
    # Driving away from the same human is no collision.
    obs, nxt, reward, term, trunc, info = env.step_env(jax.random.key(0), state, jnp.array([-1.0, 0.0]), params)
    assert not bool(term)


def test_swept_collision_catches_tunnelling():
    env = make_env(num_humans=1, predictor="none", human_policy="social_force", robot_v_max=10.0)
    params = env.default_params.replace(sf_a=jnp.float32(0.0), sf_ki=jnp.float32(0.0))
    # The robot jumps 2.5 m in one step straight through a small human: the endpoints are clear.
    state = hand_state([0.0, 0.0], [9.0, 0.0], [[1.25, 0.0]])
    obs, nxt, reward, term, trunc, info = env.step_env(jax.random.key(0), state, jnp.array([10.0, 0.0]), params)
    assert float(info.dmin) > 0 and bool(term) and int(info.outcome) == COLLISION


def test_danger_reward_and_telescoping_potential():
    env = make_env(num_humans=1, predictor="none", human_policy="social_force")
    params = env.default_params.replace(sf_a=jnp.float32(0.0), sf_ki=jnp.float32(0.0))
    # Human beside the path: at 0.4 m edge distance after the step the robot is in the danger zone.
    state = hand_state([0.0, 0.0], [9.0, 0.0], [[0.25, 1.0]])
    obs, s1, reward, term, trunc, info = env.step_env(jax.random.key(0), state, jnp.array([1.0, 0.0]), params)
    dmin = float(info.dmin)
    assert dmin == pytest.approx(0.4, abs=1e-5) and bool(info.intrusion_disc)
    assert float(reward) == pytest.approx(-2.5 * np.exp(-(dmin**2) / 0.08), abs=1e-5)
    assert float(s1.goal_dist_ref) == pytest.approx(9.0)  # reference distance frozen inside the zone
    # Two more steps take it out of the zone: the first r_pot pays for all progress since the reference.
    _, s2, r2, *_ = env.step_env(jax.random.key(1), s1, jnp.array([1.0, 0.0]), params)
    _, s3, r3, *_ = env.step_env(jax.random.key(2), s2, jnp.array([1.0, 0.0]), params)
    assert float(r3) == pytest.approx(1.5 * (9.0 - float(s3.goal_dist_ref)), abs=1e-5)
    assert float(s3.goal_dist_ref) == pytest.approx(8.25, abs=1e-5)


def test_prediction_reward_and_features():
    env = make_env(num_humans=1, predictor="const_vel", human_policy="social_force")
    params = env.default_params.replace(sf_a=jnp.float32(0.0), sf_ki=jnp.float32(0.0))
    # A human walking towards the robot's spot: its prediction at t+2 lands on the robot.
    state = hand_state([0.0, 0.0], [0.0, -9.0], [[2.0, 0.0]], human_vel=[[-1.0, 0.0]], human_goal=[[-9.0, 0.0]])
    obs, nxt, reward, term, trunc, info = env.step_env(jax.random.key(0), state, jnp.zeros(2), params)
    rel = np.asarray(obs.humans[0]).reshape(6, 2)
    np.testing.assert_allclose(rel[:, 0], 1.75 - 0.25 * np.arange(6), atol=1e-5)
    # Robot at the origin; predictions at 1.5, 1.25, ..., 0.5 m: within 0.6 m only at k = 5.
    assert float(info.reward_terms.pred) == pytest.approx(-10 / 2 ** (5 + 1))


def test_respawn_and_goal_change():
    env = make_env(num_humans=3, predictor="none", human_policy="social_force")
    params = env.default_params
    state = hand_state(
        [0.0, 0.0],
        [0.0, 8.0],
        [[3.0, 3.0], [-3.0, 3.0], [5.0, -5.0]],
        human_goal=[[3.0, 3.05], [-3.0, 8.0], [5.0, -8.0]],
    )
    obs, nxt, *_ = env.step_env(jax.random.key(0), state, jnp.zeros(2), params)
    h = nxt.humans
    r = float(np.linalg.norm(h.pos[0]))
    assert 6 * np.sqrt(2) - 2.9 < r < 6 * np.sqrt(2) + 2.9  # respawned on the crossing circle
    np.testing.assert_allclose(h.goal[0], -h.pos[0], atol=1e-6)
    np.testing.assert_array_equal(h.vel[0], [0.0, 0.0])
    np.testing.assert_allclose(h.goal[1], [-3.0, 8.0])  # others keep their goals between goal changes
    # At a goal-change step (every 20 steps), with probability 1 everyone gets a new goal.
    params = params.replace(goal_change_prob=jnp.float32(1.0))
    state19 = state.replace(step_count=jnp.int32(19))
    _, nxt, *_ = env.step_env(jax.random.key(0), state19, jnp.zeros(2), params)
    assert not np.allclose(nxt.humans.goal[1], [-3.0, 8.0])
    assert abs(np.linalg.norm(nxt.humans.goal[1]) - 6 * np.sqrt(2)) < 1.1


def test_observation_sorting_and_masks():
    env = make_env(num_humans=4, predictor="none", human_policy="social_force")
    state = hand_state([0.0, 0.0], [9.0, 9.0], [[4.0, 0.0], [30.0, 0.0], [1.0, 1.0], [0.0, -2.0]])
    obs = env.reset_env(jax.random.key(0), env.default_params)[0]  # warm the code path
    from tgrf_jax.env import sensing

    visible = sensing.visible_mask(state, env.default_params)
    obs = sensing.observe(state, env.default_params, None, visible)
    np.testing.assert_array_equal(obs.human_mask, [True, True, True, False])
    np.testing.assert_allclose(obs.humans[:3], [[1.0, 1.0], [0.0, -2.0], [4.0, 0.0]])
    np.testing.assert_array_equal(obs.humans[3], [0.0, 0.0])


def test_robot_visible_makes_humans_react():
    cfg = dict(num_humans=1, predictor="none", human_policy="orca")
    state = hand_state([0.0, 0.0], [0.0, 9.0], [[2.0, 0.2]], human_goal=[[-6.0, 0.2]])
    blind = make_env(**cfg)
    seeing = make_env(robot_visible=True, **cfg)
    _, a, *_ = blind.step_env(jax.random.key(0), state, jnp.zeros(2), blind.default_params)
    _, b, *_ = seeing.step_env(jax.random.key(0), state, jnp.zeros(2), seeing.default_params)
    np.testing.assert_allclose(a.humans.vel[0], [-1.0, 0.0], atol=1e-5)  # walks straight through
    assert float(np.linalg.norm(b.humans.vel[0] - a.humans.vel[0])) > 0.05  # avoids the robot


def test_unicycle_kinematics_limits():
    env = make_env(num_humans=0, predictor="none", kinematics="unicycle")
    params = env.default_params
    state = hand_state([0.0, 0.0], [0.0, 9.0], np.zeros((0, 2)))
    _, s1, reward, *_ = env.step_env(jax.random.key(0), state, jnp.array([5.0, 1.0]), params)
    assert float(s1.robot.speed) == pytest.approx(0.087)
    assert float(s1.robot.heading) == pytest.approx(np.pi / 2 + 0.06)
    _, s2, reward, *_ = env.step_env(jax.random.key(0), s1, jnp.array([-5.0, 0.0]), params)
    assert float(s2.robot.speed) == pytest.approx(-0.013, abs=1e-6)
    assert float(reward) < 0  # backwards motion is penalised


@pytest.mark.parametrize("num_resets", [1, 64])  # fewer resets than finished envs, and as many as there are envs
def test_step_batch_shares_fresh_episodes_among_finished_envs(num_resets):
    env = make_env(num_humans=10, predictor="none")
    params = env.default_params
    n_envs, n_steps = 32, 40
    act = jax.vmap(to_goal)

    @jax.jit
    def run(key):
        obs, state = jax.vmap(env.reset, in_axes=(0, None))(jax.random.split(key, n_envs), params)

        def body(carry, k):
            obs, state = carry
            obs2, state2, reward, term, trunc, info = env.step_batch(k, state, act(obs), params, num_resets)
            return (obs2, state2), (state, state2, obs2, term | trunc)

        return jax.lax.scan(body, (obs, state), jax.random.split(jax.random.fold_in(key, 1), n_steps))[1]

    before, after, obs, done = run(jax.random.key(7))
    done = np.asarray(done)
    assert done.sum() > 10  # straight to goal through 10 humans: plenty of collisions
    steps_before, steps_after = np.asarray(before.step_count), np.asarray(after.step_count)
    np.testing.assert_array_equal(steps_after, np.where(done, 0, steps_before + 1))
    start = np.asarray(after.robot.pos)
    goal = np.asarray(after.robot.goal)
    assert np.all(np.linalg.norm(start - goal, axis=-1)[done] >= 8.0)  # finished envs hold fresh episodes
    np.testing.assert_allclose(np.asarray(obs.robot_node)[..., :2], start, atol=1e-6)
    shared_seen = False
    for t in np.nonzero(done.sum(axis=1) >= 2)[0]:
        fresh = start[t][done[t]]
        distinct = len({tuple(p) for p in fresh.round(5)})
        if done[t].sum() <= num_resets:
            assert distinct == len(fresh)  # each finished env got its own fresh episode
        else:
            assert distinct == num_resets  # beyond num_resets the fresh episodes are shared round-robin
            shared_seen = True
    if num_resets == 1:
        assert shared_seen


def test_orca_neighbor_distance_is_drawn_per_episode_and_fixed_within_it():
    env = make_env(num_humans=4)
    params = env.default_params
    reset = jax.jit(jax.vmap(env.reset, in_axes=(0, None)))
    _, state = reset(jax.random.split(jax.random.key(5), 256), params)
    nd = np.asarray(state.orca_neighbor_dist)
    assert np.all((nd >= 5.0) & (nd < 10.0)) and nd.std() > 1.0  # U(5, 10): std 1.44
    states = rollout(env, jax.random.key(6), params, 30, to_goal)[0]
    fresh = np.asarray(states.step_count) == 0
    drawn = np.asarray(states.orca_neighbor_dist)
    same_episode = ~fresh[1:]
    np.testing.assert_array_equal(drawn[1:][same_episode], drawn[:-1][same_episode])
    fixed = env.default_params.replace(orca_neighbor_dist_min=jnp.float32(7.0), orca_neighbor_dist_max=jnp.float32(7.0))
    _, state = reset(jax.random.split(jax.random.key(5), 256), fixed)
    np.testing.assert_array_equal(state.orca_neighbor_dist, 7.0)


def test_neighbor_distance_changes_the_crowd():
    # Two humans 6 m apart walking towards each other: within a 7 m neighbourhood they avoid each other at
    # once, with a 5 m one they walk straight on for the first step.
    env = make_env(num_humans=2, predictor="none")
    params = env.default_params
    pos, goal = [[-3.0, 0.0], [3.0, 0.1]], [[10.0, 0.0], [-10.0, 0.1]]
    near = hand_state([0.0, -20.0], [0.0, -30.0], pos, human_goal=goal, neighbor_dist=5.0)
    far = hand_state([0.0, -20.0], [0.0, -30.0], pos, human_goal=goal, neighbor_dist=7.0)
    _, s_near, *_ = env.step_env(jax.random.key(0), near, jnp.zeros(2), params)
    _, s_far, *_ = env.step_env(jax.random.key(0), far, jnp.zeros(2), params)
    assert abs(float(s_near.humans.vel[0, 1])) < 1e-6 < abs(float(s_far.humans.vel[0, 1]))


def test_terminal_step_is_never_a_future_intrusion():
    # The robot steps onto its goal in the path of a human walking at it: the step ends the episode, so it
    # is no intrusion; the same step short of the goal is one.
    env = make_env(num_humans=1, predictor="none", track_future_intrusion=True)
    params = env.default_params
    human, human_goal = [[0.0, 1.5]], [[0.0, -50.0]]
    reach = hand_state([0.0, -0.25], [0.0, 0.0], human, human_goal=human_goal)
    near = hand_state([0.0, -0.25], [0.0, 5.0], human, human_goal=human_goal)
    *_, term, _, info_reach = env.step_env(jax.random.key(0), reach, jnp.array([0.0, 1.0]), params)
    *_, term_near, _, info_near = env.step_env(jax.random.key(0), near, jnp.array([0.0, 1.0]), params)
    assert bool(term) and int(info_reach.outcome) == SUCCESS and not bool(info_reach.intrusion_future)
    assert np.isinf(float(info_reach.future_dist))
    assert not bool(term_near) and bool(info_near.intrusion_future) and float(info_near.future_dist) < 0.6


@pytest.mark.parametrize(
    "action, direction",
    [
        ([1e30, -1e30], [1.0, -1.0]),
        ([3e38, 0.0], [1.0, 0.0]),
        ([np.inf, -np.inf], [1.0, -1.0]),
        ([-np.inf, 5.0], [-1.0, 0.0]),
        ([np.nan, 2.0], [0.0, 1.0]),
        ([0.3, 0.4], [0.6, 0.8]),
    ],
)
def test_huge_and_non_finite_actions_keep_their_direction(action, direction):
    env = make_env(num_humans=1, predictor="none")
    params = env.default_params
    state = hand_state([0.0, 0.0], [0.0, 9.0], [[5.0, 5.0]])
    _, nxt, *_ = env.step_env(jax.random.key(0), state, jnp.asarray(action, jnp.float32), params)
    vel = np.asarray(nxt.robot.vel)
    direction = np.asarray(direction) / np.linalg.norm(direction)
    expected_speed = min(1.0, float(np.linalg.norm(np.nan_to_num(np.asarray(action, np.float64), nan=0.0))))
    np.testing.assert_allclose(vel, direction * expected_speed, atol=1e-6)


def test_quoted_number_in_a_python_dict_is_refused():
    """A dict given in Python, not read from YAML: "5" is text, not the integer 5, as a quoted YAML value is."""
    from tgrf_jax.config import ConfigError
    from tgrf_jax.env import CrowdNavEnv

    with pytest.raises(ConfigError, match=r"^env\.num_humans = '5' must be an integer \(it is quoted text"):
        CrowdNavEnv({"num_humans": "5"})
