"""Goal frame: the policy input is invariant to rotating and translating the world, and the action rotates with it.
The LiDAR scan (body frame) is turned into the goal or world frame by a circular shift with interpolation."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from tests.test_nets import random_obs
from tgrf_jax.env import obstacles as obstacles_lib
from tgrf_jax.env.types import Obs
from tgrf_jax.policies.nets import make_network
from tgrf_jax.policies.nets.frames import action_to_world, rotate_scan, to_goal_frame, to_world_frame


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
    return obs.replace(
        robot_node=node, robot_vel=rotate(obs.robot_vel, angle), humans=pairs, human_vel=rotate(obs.human_vel, angle)
    )


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
    net = make_network(
        name, "small", obs_human_dim=12, num_humans=5, frame="goal", rotate_action=True, init_log_std=-0.7
    )
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


# ---------------------------------------------------------------------------------------------------- LiDAR scan


def test_rotate_scan_by_whole_rays_is_a_circular_shift():
    rng = np.random.default_rng(0)
    for rays in (1, 7, 36, 360, 1440):
        scan = rng.uniform(0.0, 5.0, (3, rays)).astype(np.float32)
        for k in (-rays - 3, -1, 0, 1, 5, rays // 3, rays + 2):
            angles = np.array([k, k + rays, -k], np.float64) * 2 * math.pi / rays
            out = np.asarray(rotate_scan(jnp.asarray(scan), jnp.asarray(angles, jnp.float32)))
            for row, shift in enumerate((k, k + rays, -k)):  # ray j of the result is ray j + shift of the scan
                np.testing.assert_array_equal(out[row], np.roll(scan[row], -shift), err_msg=f"{rays} rays, {shift}")
    empty = jnp.zeros((2, 0))
    assert rotate_scan(empty, jnp.ones(2)).shape == (2, 0)


def test_rotate_scan_interpolates_between_rays():
    rays = 72
    theta = 2 * np.pi * np.arange(rays) / rays
    smooth = lambda t: 3.0 + np.cos(t) + 0.5 * np.sin(2 * t)
    scan = jnp.asarray(smooth(theta), jnp.float32)
    step = 2 * np.pi / rays
    # half a ray: the mean of the two neighbours
    np.testing.assert_allclose(rotate_scan(scan, step / 2), (scan + jnp.roll(scan, -1)) / 2, rtol=1e-6)
    for angle in (0.3, -2.0, 3.1, 7.0):
        out = np.asarray(rotate_scan(scan, angle))
        # linear interpolation of a smooth ring: error below step^2 max|f''| / 8 (max|f''| <= 3)
        np.testing.assert_allclose(out, smooth(theta + angle), atol=3 * step**2 / 8 + 1e-5)
        assert np.max(np.abs(out - np.asarray(scan))) > 0.2  # it did turn
    # differentiable in the ranges and in the angle
    g_scan, g_angle = jax.grad(lambda sc, a: jnp.sum(rotate_scan(sc, a) * jnp.arange(rays)), (0, 1))(scan, 0.3)
    assert np.all(np.isfinite(g_scan)) and np.isfinite(g_angle) and abs(float(g_angle)) > 0


WALL_X = 2.0


def test_scan_frames_put_ray_0_on_world_x_and_on_the_goal():
    """A wall at x = 2 in front of a holonomic robot (heading pi/2: body ray 0 along +y) with its goal along +y."""
    rays = 8
    obstacles = obstacles_lib.from_polygons([[[WALL_X, -3.0], [WALL_X, 3.0]]])
    no_one = jnp.zeros((0,))
    scan = obstacles_lib.lidar_scan(
        jnp.zeros(2),
        jnp.float32(np.pi / 2),
        obstacles,
        jnp.zeros((0, 2)),
        no_one,
        no_one.astype(bool),
        num_rays=rays,
        max_range=5.0,
    )
    np.testing.assert_allclose(scan[6], WALL_X, rtol=1e-6)  # body ray 6 (3/4 of a turn from +y) along +x
    assert scan[0] == 5.0
    obs = random_obs(jax.random.PRNGKey(0), (1,), 2, 2).replace(
        robot_node=jnp.array([[0.0, 0.0, 0.3, 0.0, 4.0, 1.0, np.pi / 2]], jnp.float32), lidar=scan[None]
    )
    world = to_world_frame(obs).lidar[0]
    np.testing.assert_allclose(world, np.roll(np.asarray(scan), 2), rtol=1e-6)
    np.testing.assert_allclose(world[0], WALL_X, rtol=1e-6)
    goal_up, _ = to_goal_frame(obs)  # the goal along +y, as the heading: the body scan unchanged
    np.testing.assert_array_equal(goal_up.lidar, obs.lidar)
    goal_right, _ = to_goal_frame(obs.replace(robot_node=obs.robot_node.at[0, 3:5].set(jnp.array([4.0, 0.0]))))
    np.testing.assert_allclose(goal_right.lidar[0, 0], WALL_X, rtol=1e-6)  # ray 0 at the goal, through the wall
    # without a scan nothing changes
    bare = random_obs(jax.random.PRNGKey(1), (2,), 3, 2)
    assert to_world_frame(bare) is bare


def scene_obs(angle, shift, rays, turn_heading):
    """One hand-made situation (robot, goal, two humans, a box and a wall), rotated by `angle` about the origin and
    shifted, its scan recomputed by the env's LiDAR. turn_heading: the robot's heading turns with the scene (a
    unicycle); otherwise it stays pi/2 (the env's holonomic robot), so the body-frame scan itself turns."""
    c, s = math.cos(angle), math.sin(angle)
    move = lambda p: np.asarray(p, np.float64) @ np.array([[c, s], [-s, c]]) + shift
    turn = lambda v: np.asarray(v, np.float64) @ np.array([[c, s], [-s, c]])
    robot, goal = move([0.5, -1.0]), move([3.0, 2.5])
    humans = move([[1.5, 0.4], [-1.0, 1.2]])
    radii = np.array([0.3, 0.4])
    polygons = [
        move([[2.0, -2.5], [3.0, -2.5], [3.0, -1.5], [2.0, -1.5]]).tolist(),
        move([[-2.0, 2.0], [-2.0, -3.0]]).tolist(),
    ]
    obstacles = obstacles_lib.from_polygons(polygons)
    heading = np.pi / 2 + (angle if turn_heading else 0.0)
    f32 = lambda x: jnp.asarray(x, jnp.float32)
    scan = obstacles_lib.lidar_scan(
        f32(robot), f32(heading), obstacles, f32(humans), f32(radii), jnp.ones(2, bool), num_rays=rays, max_range=5.0
    )
    obs = Obs(
        robot_node=f32([*robot, 0.3, *goal, 1.0, heading]),
        robot_vel=f32(turn([0.3, 0.1])),
        humans=f32(humans - robot),
        human_mask=jnp.ones(2, bool),
        human_vel=f32(turn([[0.5, 0.0], [0.0, -0.5]])),
        human_radius=f32(radii),
        lidar=scan,
        obstacles=obstacles,
    )
    return jax.tree_util.tree_map(lambda x: x[None], obs)


@pytest.mark.parametrize("turn_heading", [False, True])
def test_goal_frame_scan_is_invariant_to_rotating_the_scene(turn_heading):
    rays = 90
    base, _ = to_goal_frame(scene_obs(0.0, np.zeros(2), rays, turn_heading))
    assert float(jnp.min(base.lidar)) < 1.5 and float(jnp.max(base.lidar)) == 5.0  # hits near and far, and misses
    step = 2 * math.pi / rays
    for k in (7, -31, 45):  # whole rays: exact up to float rounding of the ray casting
        moved, _ = to_goal_frame(scene_obs(k * step, np.array([4.0, -1.5]), rays, turn_heading))
        # a heading that stays pi/2 has turned relative to the goal; everything else is the same
        heading = slice(None) if turn_heading else slice(0, 6)
        np.testing.assert_allclose(moved.robot_node[:, heading], base.robot_node[:, heading], atol=2e-5)
        for x, y in zip(
            jax.tree_util.tree_leaves(base.replace(robot_node=0, obstacles=0)),
            jax.tree_util.tree_leaves(moved.replace(robot_node=0, obstacles=0)),
        ):
            np.testing.assert_allclose(np.asarray(x), np.asarray(y), atol=2e-4)
    for angle in (0.3, -2.0, 3.1):  # between rays: up to the interpolation error (none when the heading turns too)
        moved, _ = to_goal_frame(scene_obs(angle, np.array([-2.0, 3.0]), rays, turn_heading))
        err = np.abs(np.asarray(moved.lidar - base.lidar))[0]
        if turn_heading:
            assert err.max() < 2e-4
        else:
            # most rays see a smooth surface; the rays next to an edge of a silhouette may jump
            assert np.median(err) < 0.02 and np.mean(err < 0.1) > 0.85 and err.max() < 5.0, np.sort(err)[-10:]
        np.testing.assert_allclose(moved.humans, base.humans, atol=2e-5)


def test_goal_frame_lidar_policy_is_rotation_equivariant():
    """HH Attn with a scan in the goal frame: a robot turned with the scene (its body-frame scan unchanged, its
    heading and goal direction turned) takes the turned action and has the same value; the world-frame policy,
    whose scan turns by the heading, does not. (A holonomic robot keeps heading pi/2, an input the policy reads
    in the goal frame as its angle to the goal, so there the scan's invariance is tested above, not the policy's.)"""
    rays = 36
    goal_net = make_network(
        "hh_attn", "small", obs_human_dim=2, num_humans=2, frame="goal", rotate_action=True, lidar_rays=rays
    )
    world_net = make_network("hh_attn", "small", obs_human_dim=2, num_humans=2, lidar_rays=rays)
    params = jax.jit(goal_net.init)(jax.random.PRNGKey(0))  # the same parameters fit both frames

    def run(net):
        @jax.jit
        def f(obs):
            _, pi, value = net.apply(params, net.initialize_carry(1), obs, None)
            return pi.mean()[0], value[0]

        return f

    angle = 11 * 2 * math.pi / rays
    a = scene_obs(0.0, np.zeros(2), rays, True)
    b = scene_obs(angle, np.array([1.0, 2.0]), rays, True)
    goal_frame, world_frame = run(goal_net), run(world_net)
    (mean_a, v_a), (mean_b, v_b) = goal_frame(a), goal_frame(b)
    np.testing.assert_allclose(v_a, v_b, rtol=1e-4, atol=1e-4)
    np.testing.assert_allclose(rotate(mean_a, angle), mean_b, rtol=1e-4, atol=1e-4)
    (w_a, _), (w_b, _) = world_frame(a), world_frame(b)
    assert not np.allclose(rotate(w_a, angle), w_b, atol=1e-3)
