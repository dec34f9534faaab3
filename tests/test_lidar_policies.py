"""Policies in scenes with static obstacles: learned networks reading the env's LiDAR scan, and the ORCA robot
baseline avoiding the obstacles of the map."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from tgrf_jax.config import TrainConfig
from tgrf_jax.env import CrowdNavEnv
from tgrf_jax.env import obstacles as obstacles_lib
from tgrf_jax.env.types import Obs
from tgrf_jax.policies import LearnedPolicy, OrcaPolicy, make_network_for

RAYS = 16


def test_learned_policy_reads_the_env_scan():
    """make_network_for builds the scan branch from env.lidar_rays (scaled by env.sensor_range) and the policy acts
    on the env's own observations; its actions depend on the scan."""
    config = TrainConfig.from_dict(
        {
            "env": {
                "scenario": "corridor",
                "lidar_rays": RAYS,
                "sensor_range": 4.0,
                "num_humans": 3,
                "human_policy": "social_force",
                "predictor": "none",
            }
        }
    )
    net = make_network_for(config)
    assert net.lidar_rays == RAYS and net.lidar_range == 4.0
    assert make_network_for(TrainConfig.from_dict({"env": {"scenario": "corridor"}})).lidar_rays == 0
    env = CrowdNavEnv(config.env, config.reward)
    params = env.default_params
    policy = LearnedPolicy(net, jax.jit(net.init)(jax.random.PRNGKey(0)))
    b, steps = 4, 6

    @jax.jit
    def play(key):
        obs, state = jax.vmap(env.reset_env, in_axes=(0, None))(jax.random.split(key, b), params)

        def body(c, key):
            obs, state, carry = c
            carry, action = policy.act(carry, obs, jnp.zeros(b, bool), key)
            blind = obs.replace(lidar=jnp.full_like(obs.lidar, 4.0))  # nothing in range
            _, blind_action = policy.act(carry, blind, jnp.zeros(b, bool), key)
            obs, state, *_ = env.step_batch(key, state, action, params, b)
            return (obs, state, carry), (action, blind_action, obs.lidar)

        return jax.lax.scan(body, (obs, state, policy.initialize_carry(b)), jax.random.split(key, steps))[1]

    actions, blind_actions, scans = play(jax.random.PRNGKey(1))
    assert scans.shape == (steps, b, RAYS) and float(scans.min()) < 4.0  # the corridor walls are in range
    assert np.all(np.isfinite(actions))
    assert np.max(np.abs(actions - blind_actions)) > 1e-4


# ------------------------------------------------------------------------------------------------ ORCA baseline


def scene(robot, goal, polygons, num_humans=2, humans=None):
    """One observation (batch of 1): the robot (radius 0.3, v_max 1) at `robot` heading for `goal`, humans hidden
    unless `humans` (positions, world frame) are given, and the obstacles of the map."""
    robot, goal = np.asarray(robot, np.float32), np.asarray(goal, np.float32)
    rel = np.zeros((num_humans, 2), np.float32)
    mask = np.zeros(num_humans, bool)
    if humans is not None:
        rel[: len(humans)] = np.asarray(humans, np.float32) - robot
        mask[: len(humans)] = True
    # obstacles padded to 3 slots (one program for every scene with a map), or none at all (M = 0)
    obstacles = obstacles_lib.from_polygons(polygons, num_slots=3 if polygons else 0, max_vertices=4)
    obs = Obs(
        robot_node=jnp.array([*robot, 0.3, *goal, 1.0, np.pi / 2], jnp.float32),
        robot_vel=jnp.zeros(2),
        humans=jnp.asarray(rel),
        human_mask=jnp.asarray(mask),
        human_vel=jnp.zeros((num_humans, 2)),
        human_radius=jnp.where(jnp.asarray(mask), 0.3, 0.0),
        lidar=jnp.zeros((0,)),
        obstacles=obstacles,
    )
    return jax.tree_util.tree_map(lambda x: x[None], obs)


WALL = [[3.0, 1.5], [-3.0, 1.5]]  # across the robot's way from (0, 0) to (0, 4)


@jax.jit
def orca_act(obs):
    policy = OrcaPolicy()
    return policy.act(policy.initialize_carry(1), obs, None, None)[1][0]


@pytest.mark.parametrize("num_humans", [2, 0])
def test_orca_robot_stops_short_of_a_wall(num_humans):
    """Driving at a wall between it and its goal, the ORCA robot with the map slows down and never touches it; the
    same robot without obstacles in its observation drives through."""
    wall = obstacles_lib.from_polygons([WALL])

    def drive(polygons):
        pos, vel, closest = np.zeros(2, np.float32), np.zeros(2, np.float32), np.inf
        for _ in range(24):  # 6 s at dt = 0.25
            obs = scene(pos, (0.0, 4.0), polygons, num_humans)
            vel = np.asarray(orca_act(obs.replace(robot_vel=jnp.asarray(vel)[None])))
            assert np.linalg.norm(vel) <= 1.0 + 1e-5
            new_pos = pos + vel * np.float32(0.25)
            closest = min(closest, float(obstacles_lib.swept_distance(jnp.asarray(pos), jnp.asarray(new_pos), wall)))
            pos = new_pos
        return pos, closest

    pos, closest = drive([WALL])
    assert closest >= 0.3 - 1e-3, closest  # the robot's radius: no contact
    assert pos[1] > 0.5  # it did move towards the wall first
    if num_humans:
        blind_pos, blind_closest = drive([])
        assert blind_pos[1] > 1.5 + 0.3 and blind_closest < 0.3  # through the wall


def test_orca_robot_without_obstacles_is_unchanged():
    """No obstacle slot (M = 0), only unused slots, or a wall far out of reach: the same action as before."""
    act = orca_act
    humans = [(0.4, 1.0), (-1.0, 2.0)]
    base = np.asarray(act(scene((0.0, 0.0), (0.0, 4.0), [], humans=humans)))
    assert np.linalg.norm(base - [0.0, 1.0]) > 0.05  # the humans matter
    far = [[[40.0, 40.0], [41.0, 40.0]]]  # beyond time_horizon_obst * v_max + radius
    np.testing.assert_allclose(np.asarray(act(scene((0.0, 0.0), (0.0, 4.0), far, humans=humans))), base, atol=1e-6)
    unused = scene((0.0, 0.0), (0.0, 4.0), [], humans=humans)
    unused = unused.replace(obstacles=jax.tree_util.tree_map(lambda x: x[None], obstacles_lib.empty(3, 4)))
    assert unused.obstacles.vertices.shape == scene((0.0, 0.0), (0.0, 4.0), far).obstacles.vertices.shape
    np.testing.assert_allclose(np.asarray(act(unused)), base, atol=1e-6)
