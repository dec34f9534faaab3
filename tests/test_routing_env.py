"""Humans routing around obstacles inside the environment: goals behind walls are reached, nothing changes without
obstacles, stuck humans are measured and given new goals, unreachable goals are counted."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from tgrf_jax import CrowdNavEnv
from tgrf_jax.env import SUCCESS, stuck

WALL = [[-4.0, 0.0], [4.0, 0.0]]
# a U-shaped alcove open downwards: a human inside must walk out of it, down and around
ALCOVE = [[[-1.5, 0.0], [-1.5, 2.0]], [[-1.5, 2.0], [1.5, 2.0]], [[1.5, 2.0], [1.5, 0.0]]]


def _env(obstacles, policy="orca", **env):
    config = dict(
        scenario="circle_crossing",
        num_humans=1,
        obstacles=obstacles,
        human_policy=policy,
        goal_change_prob=0.0,
        predictor="none",
        human_v_pref_min=1.0,
        human_v_pref_max=1.0,
        human_radius_min=0.3,
        human_radius_max=0.3,
    )
    config.update(env)
    return CrowdNavEnv(config, "tgrf")


def _place(env, params, pos, goal):
    """A reset state with the robot out of the way and the one human at `pos` heading for `goal`."""
    _, state = env.reset(jax.random.key(0), params)
    humans = state.humans.replace(
        pos=jnp.asarray([pos], jnp.float32),
        goal=jnp.asarray([goal], jnp.float32),
        vel=jnp.zeros((1, 2)),
        active=jnp.ones((1,), bool),
    )
    robot = state.robot.replace(pos=jnp.array([20.0, 20.0]), goal=jnp.array([25.0, 20.0]))
    return state.replace(
        humans=humans,
        robot=robot,
        progress=stuck.fresh(humans),
        routing=env._plan_routes(state.obstacles, humans, params),
    )


def _walk(env, params, state, steps):
    def body(state, key):
        _, state, _, _, _, info = env.step_env(key, state, jnp.zeros(env.action_size), params)
        return state, (state.humans.pos[0], info)

    _, (path, info) = jax.jit(lambda s: jax.lax.scan(body, s, jax.random.split(jax.random.key(1), steps)))(state)
    return np.asarray(path), info


@pytest.mark.parametrize("policy", ["orca", "social_force"])
@pytest.mark.parametrize(
    "layout, start, goal",
    [([WALL], (0.0, -2.0), (0.0, 2.0)), (ALCOVE, (0.0, 1.2), (0.0, 4.0))],
    ids=["wall", "alcove"],
)
def test_a_human_whose_goal_is_behind_a_wall_reaches_it(policy, layout, start, goal):
    env = _env(layout, policy)
    params = env.default_params
    path, info = _walk(env, params, _place(env, params, start, goal), 120)
    assert np.all(np.isfinite(path))
    dist = np.linalg.norm(path - np.asarray(goal), axis=-1)
    # arrival (within its radius) respawns it elsewhere, so the recorded closest approach is the step before
    assert dist.min() < 0.6, f"closest approach {dist.min():.2f} m"
    # never through the wall: every step stays on its side until it has gone around an end
    assert int(np.asarray(info.humans_unreachable).max()) == 0


def test_without_routing_the_same_human_presses_against_the_wall():
    """The control: straight at the goal (what ORCA alone does), the wall stops it."""
    from tgrf_jax.env import humans as humans_lib

    env = _env([WALL])
    params = env.default_params
    state = _place(env, params, (0.0, -2.0), (0.0, 2.0))
    h = state.humans
    for _ in range(60):
        vel = humans_lib.human_velocities(
            h, None, params, env.config, state.orca_neighbor_dist, state.obstacles, state.obstacle_table
        )
        h = h.replace(pos=h.pos + vel * params.dt, vel=vel)
    assert float(jnp.linalg.norm(h.pos[0] - jnp.array([0.0, 2.0]))) > 2.0


def test_an_enclosed_goal_is_counted_unreachable_and_the_human_gets_a_new_goal():
    box = [[-1.0, 2.0], [1.0, 2.0], [1.0, 4.0], [-1.0, 4.0]]
    env = _env([box], unstuck_after=4.0)
    params = env.default_params
    state = _place(env, params, (0.0, -2.0), (0.0, 3.0))  # the goal is inside the box
    path, info = _walk(env, params, state, 100)
    assert np.all(np.isfinite(path))
    unreachable = np.asarray(info.humans_unreachable)
    assert unreachable[0] == 1
    reassigned = np.asarray(info.goals_reassigned)
    assert reassigned.sum() >= 1, "a human pressed against the box for 4 s gets a new goal"
    assert unreachable[-1] == 0  # its new goal lies outside the box


def test_stuck_counts_a_human_that_stays_put_for_five_seconds():
    box = [[-1.0, 2.0], [1.0, 2.0], [1.0, 4.0], [-1.0, 4.0]]
    env = _env([box], unstuck_after=0.0)  # never reassigned
    params = env.default_params
    _, info = _walk(env, params, _place(env, params, (0.0, -2.0), (0.0, 3.0)), 100)
    stuck_steps = np.asarray(info.humans_stuck)
    assert stuck_steps[:19].sum() == 0  # 5 s = 20 steps of 0.25 s: never before
    assert stuck_steps[-1] == 1
    assert np.asarray(info.goals_reassigned).sum() == 0


def test_open_space_has_no_routing_state_and_no_stuck_reassignments():
    env = CrowdNavEnv({"num_humans": 5}, "tgrf")
    params = env.default_params
    _, state = env.reset(jax.random.key(0), params)
    assert state.routing is None
    assert not env.routes_humans


@pytest.mark.parametrize("route", [True, False])
def test_the_orca_robot_routes_around_a_wall_to_a_goal_behind_it(route):
    """The ORCA robot baseline drives the shortest way round the map's wall (with `route`); straight at its goal,
    ORCA alone keeps it pressed against the wall."""
    from tgrf_jax.policies.baselines import OrcaPolicy

    env = _env([WALL], num_humans=0, time_limit=30.0)
    params = env.default_params
    _, state = env.reset(jax.random.key(0), params)
    state = state.replace(robot=state.robot.replace(pos=jnp.array([0.5, -3.0]), goal=jnp.array([-0.5, 3.0])))
    policy = OrcaPolicy(route=route)
    step = jax.jit(env.step_env)
    obs, state, *_ = step(jax.random.key(0), state, jnp.zeros(2), params)  # standing still: the moved robot's view
    for i in range(1, 120):
        obs, state, _, terminated, truncated, info = step(jax.random.key(i), state, policy.action(obs), params)
        if terminated or truncated:
            break
    reached = bool(terminated) and int(info.outcome) == SUCCESS
    assert reached == route, (route, int(info.outcome), np.asarray(state.robot.pos))
