"""Goal frame: the policy input is invariant to rotating and translating the world, and the action rotates with it."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from tests.test_nets import random_obs
from tgrf_jax.policies.nets import make_network
from tgrf_jax.policies.nets.frames import action_to_world, to_goal_frame


def rotate(v, angle):
    c, s = jnp.cos(angle), jnp.sin(angle)
    return jnp.stack([c * v[..., 0] - s * v[..., 1], s * v[..., 0] + c * v[..., 1]], axis=-1)


def transform_world(obs, angle, shift):
    """The same situation after rotating the world by `angle` and translating it by `shift`."""
    node = obs.robot_node
    pos = rotate(node[..., 0:2], angle) + shift
    goal = rotate(node[..., 3:5], angle) + shift
    node = node.at[..., 0:2].set(pos).at[..., 3:5].set(goal).at[..., 6].add(angle)
    humans = obs.humans
    pairs = rotate(humans.reshape(humans.shape[:-1] + (-1, 2)), angle).reshape(humans.shape)
    return obs.replace(robot_node=node, robot_vel=rotate(obs.robot_vel, angle), humans=pairs,
                       human_vel=rotate(obs.human_vel, angle))


@pytest.mark.parametrize("angle", [0.3, -2.0, 3.1])
def test_local_observation_is_invariant_to_world_rotation_and_translation(angle):
    obs = random_obs(jax.random.PRNGKey(0), (5,), 6, 12)
    obs = obs.replace(human_vel=jax.random.normal(jax.random.PRNGKey(1), (5, 6, 2)))
    moved = transform_world(obs, angle, jnp.array([4.0, -1.5]))
    a, _ = to_goal_frame(obs)
    b, _ = to_goal_frame(moved)
    for x, y in zip(jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b)):
        np.testing.assert_allclose(np.asarray(x), np.asarray(y), atol=2e-5)


def test_goal_lies_on_the_positive_x_axis_and_actions_round_trip():
    obs = random_obs(jax.random.PRNGKey(2), (4,), 3, 2)
    local, axes = to_goal_frame(obs)
    dist = jnp.linalg.norm(obs.robot_node[:, 3:5] - obs.robot_node[:, 0:2], axis=-1)
    np.testing.assert_allclose(local.robot_node[:, 3], dist, rtol=1e-5)
    np.testing.assert_allclose(local.robot_node[:, [0, 1, 4]], 0.0)
    # a unit velocity along local x points at the goal in the world frame
    toward = action_to_world(jnp.tile(jnp.array([[1.0, 0.0]]), (4, 1)), axes)
    np.testing.assert_allclose(toward * dist[:, None], obs.robot_node[:, 3:5] - obs.robot_node[:, 0:2], atol=1e-4)


def test_robot_at_its_goal_gives_finite_inputs():
    obs = random_obs(jax.random.PRNGKey(3), (2,), 3, 2)
    obs = obs.replace(robot_node=obs.robot_node.at[:, 3:5].set(obs.robot_node[:, 0:2]))
    local, axes = to_goal_frame(obs)
    assert all(bool(jnp.all(jnp.isfinite(x))) for x in jax.tree_util.tree_leaves((local, axes)))


@pytest.mark.parametrize("name", ["hh_attn", "mlp"])
def test_goal_frame_policy_is_rotation_equivariant(name):
    net = make_network(name, "small", obs_human_dim=12, num_humans=5, frame="goal", rotate_action=True,
                       init_log_std=-0.7)
    # initialisation and forward passes jitted: run eagerly, every operation is a program of its own
    params = jax.jit(net.init)(jax.random.PRNGKey(0))
    np.testing.assert_allclose(params["params"]["heads"]["log_std"], -0.7)
    obs = random_obs(jax.random.PRNGKey(4), (3,), 5, 12)
    angle = 1.1
    moved = transform_world(obs, angle, jnp.array([-3.0, 2.0]))
    carry = net.initialize_carry(3)

    def mean_and_value(net):
        @jax.jit
        def run(params, obs):
            _, pi, value = net.apply(params, carry, obs, None)
            return pi.mean(), value

        return run

    goal_frame = mean_and_value(net)
    mean_a, v_a = goal_frame(params, obs)
    mean_b, v_b = goal_frame(params, moved)
    np.testing.assert_allclose(v_a, v_b, rtol=1e-4, atol=1e-4)
    np.testing.assert_allclose(rotate(mean_a, angle), mean_b, rtol=1e-4, atol=1e-4)
    # the world-frame policy has no such symmetry (sanity check that the test can fail)
    world = make_network(name, "small", obs_human_dim=12, num_humans=5)
    wp = jax.jit(world.init)(jax.random.PRNGKey(0))
    world_frame = mean_and_value(world)
    w_a, _ = world_frame(wp, obs)
    w_b, _ = world_frame(wp, moved)
    assert not np.allclose(rotate(w_a, angle), w_b, atol=1e-3)
