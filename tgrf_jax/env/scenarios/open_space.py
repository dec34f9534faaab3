"""The open-space (crowd) scenarios: no obstacles, only a crowd drawn by each scenario's rules.

`circle_crossing` is the paper's (the reference's `crowd_sim_pred_real_gst.py` and its parents;
docs/reference.md); the others follow the scenario names of Francis et al., "Principles and Guidelines for
Evaluating Social Robot Navigation Algorithms" (ACM THRI 2025), and CrowdNav's layouts (docs/scenarios.md). Each is
a `Scenario` record (module constants below), registered by `tgrf_jax.env.scenarios`.

Geometry follows the arena's traced parameters: a = arena_size (the robot's start and goal region), R =
circle_radius (where humans enter and leave), lanes of half-width a / 2 (traffic) or a / 4 (head-on and
overtaking lanes). The robot of the lane scenarios walks up the y axis from (x0, -a) to (x1, a).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from tgrf_jax.env.geometry import norm
from tgrf_jax.env.scenarios.sampling import box, choose, uniform
from tgrf_jax.env.types import EnvParams, Robot
from tgrf_jax.scenario_registry import Scenario


def open_space(fn):
    """A human sampler that has no use for the layout, as the `Scenario` record calls it (with the layout)."""
    return lambda key, params, layout, *rest: fn(key, params, *rest)


def timeless(respawn):
    """A respawn sampler that has no use for the episode time, as the `Scenario` record calls it (with `t`)."""
    return lambda key, params, layout, pos, goal, t, tries: respawn(key, params, layout, pos, goal, tries)


def crowd(robot, spawn, new_goal, respawn, speed=1.0) -> Scenario:
    """An open-space scenario from human samplers without the layout argument (nor, for `respawn`, the time)."""
    return Scenario(robot, open_space(spawn), open_space(new_goal), timeless(open_space(respawn)), speed=speed)


def arena_robot(key, params: EnvParams, tries: int) -> Robot:
    """Start and goal ~ U(-a, a)^2 each, at least `min_start_goal_dist` apart."""
    pts = uniform(key, (tries, 2, 2), minval=-params.arena_size, maxval=params.arena_size)
    dist = norm(pts[:, 0] - pts[:, 1])
    start_goal = choose(pts.reshape(tries, 4), dist - params.min_start_goal_dist).reshape(2, 2)
    zero = jnp.zeros((), jnp.float32)
    return Robot(pos=start_goal[0], vel=jnp.zeros(2), goal=start_goal[1], heading=zero + jnp.pi / 2, speed=zero)


def lane_robot(key, params: EnvParams, tries: int) -> Robot:
    """Start near (0, -a), goal near (0, a), each shifted sideways by up to 0.5 m."""
    x = uniform(key, (2,), -0.5, 0.5)
    a = params.arena_size
    zero = jnp.zeros((), jnp.float32)
    return Robot(
        pos=jnp.stack([x[0], -a]), vel=jnp.zeros(2), goal=jnp.stack([x[1], a]), heading=zero + jnp.pi / 2, speed=zero
    )


def circle_candidates(key, params: EnvParams, shape):
    """Spawn points on the crossing circle with one-sided noise in [0, noise) per axis, as the reference."""
    k_a, k_n = jax.random.split(key)
    angle = uniform(k_a, shape, maxval=2 * jnp.pi)
    noise = uniform(k_n, shape + (2,)) * params.spawn_noise
    return params.circle_radius * jnp.stack([jnp.cos(angle), jnp.sin(angle)], -1) + noise


def goal_candidates(key, params: EnvParams, v_pref, shape):
    """New goals on the circle with symmetric noise (U - 0.5) * v_pref per axis (goal changes)."""
    k_a, k_n = jax.random.split(key)
    angle = uniform(k_a, shape, maxval=2 * jnp.pi)
    noise = (uniform(k_n, shape + (2,)) - 0.5) * v_pref[..., None, None]
    return params.circle_radius * jnp.stack([jnp.cos(angle), jnp.sin(angle)], -1) + noise


# circle_crossing (Francis et al.: circular crossing): spawn on a circle, walk to the antipode; goal changes
# pick a new point of the circle.
def _circle_spawn(key, params, n, tries):
    pos = circle_candidates(key, params, (n, tries))
    return pos, -pos


def _circle_new_goal(key, params, humans, tries):
    return goal_candidates(key, params, humans.v_pref, (humans.pos.shape[0], tries))


def _circle_respawn(key, params, pos, goal, tries):
    new = circle_candidates(key, params, (tries,))
    return new, -new


CIRCLE_CROSSING = crowd(arena_robot, _circle_spawn, _circle_new_goal, _circle_respawn)


# square_crossing (CrowdNav): start on one side of a square of half-width R, goal anywhere on the other side.
def _square_pair(key, params, shape):
    k_side, k_start, k_goal = jax.random.split(key, 3)
    side = jnp.where(uniform(k_side, shape) < 0.5, -1.0, 1.0)[..., None]
    r = params.circle_radius
    start = box(k_start, shape, 0.0, r, -r, r) * jnp.stack([side[..., 0], jnp.ones(shape)], -1)
    goal = box(k_goal, shape, 0.0, r, -r, r) * jnp.stack([-side[..., 0], jnp.ones(shape)], -1)
    return start, goal


def _square_spawn(key, params, n, tries):
    return _square_pair(key, params, (n, tries))


def _square_new_goal(key, params, humans, tries):
    side = jnp.where(humans.pos[:, 0] < 0, -1.0, 1.0)[:, None]  # the far side of where the human is
    r = params.circle_radius
    goal = box(key, (humans.pos.shape[0], tries), 0.0, r, -r, r)
    return goal * jnp.stack([-side * jnp.ones_like(goal[..., 0]), jnp.ones_like(goal[..., 0])], -1)


def _square_respawn(key, params, pos, goal, tries):
    return _square_pair(key, params, (tries,))


SQUARE_CROSSING = crowd(arena_robot, _square_spawn, _square_new_goal, _square_respawn)


# parallel_traffic (Francis et al.: parallel traffic): two opposing streams in a lane of half-width a/2 along the
# robot's way; even slots walk with the robot, odd slots against it. Arrived humans re-enter at their stream's start.
def stream_goal(key, params, direction, shape, half_width):
    return box(key, shape, -half_width, half_width, 0.0, 0.0) + jnp.stack(
        [jnp.zeros(shape), direction * params.circle_radius * jnp.ones(shape)], -1
    )


def _parallel_spawn(key, params, n, tries):
    k_pos, k_goal = jax.random.split(key)
    c, r = 0.5 * params.arena_size, params.circle_radius
    direction = jnp.where(jnp.arange(n) % 2 == 0, 1.0, -1.0)[:, None]
    pos = box(k_pos, (n, tries), -c, c, -r, r)
    return pos, stream_goal(k_goal, params, direction, (n, tries), c)


def _lane_new_goal(half_width_factor):
    def new_goal(key, params, humans, tries):
        direction = jnp.sign(humans.goal[:, 1:2])  # keep walking the stream's way
        return stream_goal(key, params, direction, (humans.pos.shape[0], tries), half_width_factor * params.arena_size)

    return new_goal


def _lane_respawn(half_width_factor):
    def respawn(key, params, pos, goal, tries):
        k_pos, k_goal = jax.random.split(key)
        direction = jnp.sign(goal[1])
        c = half_width_factor * params.arena_size
        return (
            stream_goal(k_pos, params, -direction, (tries,), c),
            stream_goal(k_goal, params, direction, (tries,), c),
        )

    return respawn


PARALLEL_TRAFFIC = crowd(lane_robot, _parallel_spawn, _lane_new_goal(0.5), _lane_respawn(0.5))


# perpendicular_traffic (Francis et al.: perpendicular traffic): one stream crossing the robot's way from left
# to right, in a band of half-width a/2 about the middle of its path.
def _cross_goal(key, params, shape, x):
    c = 0.5 * params.arena_size
    return box(key, shape, x, x, -c, c)


def _perpendicular_spawn(key, params, n, tries):
    k_pos, k_goal = jax.random.split(key)
    c, r = 0.5 * params.arena_size, params.circle_radius
    return box(k_pos, (n, tries), -r, r, -c, c), _cross_goal(k_goal, params, (n, tries), r)


def _perpendicular_new_goal(key, params, humans, tries):
    return _cross_goal(key, params, (humans.pos.shape[0], tries), params.circle_radius)


def _perpendicular_respawn(key, params, pos, goal, tries):
    k_pos, k_goal = jax.random.split(key)
    r = params.circle_radius
    return _cross_goal(k_pos, params, (tries,), -r), _cross_goal(k_goal, params, (tries,), r)


PERPENDICULAR_TRAFFIC = crowd(lane_robot, _perpendicular_spawn, _perpendicular_new_goal, _perpendicular_respawn)


# frontal_approach (Francis et al.: frontal approach): humans come head-on down the robot's lane (half-width
# a/4), from ahead of the robot's start to behind it.
def _frontal_spawn(key, params, n, tries):
    k_pos, k_goal = jax.random.split(key)
    c, a, r = 0.25 * params.arena_size, params.arena_size, params.circle_radius
    return box(k_pos, (n, tries), -c, c, -0.5 * a, r), stream_goal(k_goal, params, -1.0, (n, tries), c)


FRONTAL_APPROACH = crowd(lane_robot, _frontal_spawn, _lane_new_goal(0.25), _lane_respawn(0.25))


# robot_overtaking (Francis et al.: robot overtaking): humans at half their usual speed walk the robot's way in its
# lane, so the robot has to pass them.
def _overtaking_spawn(key, params, n, tries):
    k_pos, k_goal = jax.random.split(key)
    c, a, r = 0.25 * params.arena_size, params.arena_size, params.circle_radius
    return box(k_pos, (n, tries), -c, c, -0.5 * a, r), stream_goal(k_goal, params, 1.0, (n, tries), c)


ROBOT_OVERTAKING = crowd(lane_robot, _overtaking_spawn, _lane_new_goal(0.25), _lane_respawn(0.25), speed=0.5)


# robot_crowding (Francis et al.: robot crowding): humans enter on the circle and head for points on the robot's
# path, converging on it; goal changes pick other points of the path.
def _path_points(key, params, shape):
    a = params.arena_size
    return box(key, shape, -0.5, 0.5, -a, a)


def _crowding_spawn(key, params, n, tries):
    k_pos, k_goal = jax.random.split(key)
    return circle_candidates(k_pos, params, (n, tries)), _path_points(k_goal, params, (n, tries))


def _crowding_new_goal(key, params, humans, tries):
    return _path_points(key, params, (humans.pos.shape[0], tries))


def _crowding_respawn(key, params, pos, goal, tries):
    k_pos, k_goal = jax.random.split(key)
    return circle_candidates(k_pos, params, (tries,)), _path_points(k_goal, params, (tries,))


ROBOT_CROWDING = crowd(lane_robot, _crowding_spawn, _crowding_new_goal, _crowding_respawn)


# random (CrowdNav's random goals): start and goal uniform in the square of half-width R; an arrived human stays
# where it is and walks on to a new random goal.
def _square_points(key, params, shape):
    r = params.circle_radius
    return box(key, shape, -r, r, -r, r)


def _random_spawn(key, params, n, tries):
    k_pos, k_goal = jax.random.split(key)
    return _square_points(k_pos, params, (n, tries)), _square_points(k_goal, params, (n, tries))


def _random_new_goal(key, params, humans, tries):
    return _square_points(key, params, (humans.pos.shape[0], tries))


def _random_respawn(key, params, pos, goal, tries):
    return jnp.broadcast_to(pos, (tries, 2)), _square_points(key, params, (tries,))


RANDOM = crowd(arena_robot, _random_spawn, _random_new_goal, _random_respawn)

# replay's record in the registry: its episodes come from recordings (tgrf_jax.env.replay); in a mix's table its
# row needs samplers of the common shapes, and circle crossing's serve, their draws replaced by the recording's.
REPLAY_STAND_IN = crowd(arena_robot, _circle_spawn, _circle_new_goal, _circle_respawn)
