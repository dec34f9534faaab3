"""Scenarios: how the robot's start and goal and the humans' spawns, goals, goal changes and respawns are drawn.

`circle_crossing` is the paper's (the reference's `crowd_sim_pred_real_gst.py` and its parents;
docs/reference.md); the others follow the scenario names of Francis et al., "Principles and Guidelines for
Evaluating Social Robot Navigation Algorithms" (ACM THRI 2025), and CrowdNav's layouts (docs/scenarios.md).
Each scenario is a `Scenario` of pure candidate samplers; the shared machinery here picks among the candidates
(rejection sampling), so every scenario obeys the same spacing rules. With `env.scenario: mix` an episode's
scenario is drawn at reset, stored in the state, and its samplers are selected with `lax.switch`.

Rejection sampling is bounded: each draw proposes `tries` candidates at once and takes the first valid one;
when none is valid (a very crowded scene), it takes the candidate with the most clearance, so shapes and run
time never depend on luck.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import jax
import jax.numpy as jnp

from tgrf_jax.config import SCENARIO_OBSTACLE_SLOTS, SCENARIO_OBSTACLE_VERTICES, SCENARIOS
from tgrf_jax.env import obstacles as obstacles_lib
from tgrf_jax.env.batching import cond_gathered
from tgrf_jax.env.geometry import norm
from tgrf_jax.env.obstacles import Obstacles
from tgrf_jax.env.types import EnvParams, Humans, Robot


def _mix32(x):
    """murmur3's 32-bit finaliser: a cheap bijective integer hash with full avalanche."""
    x = x ^ (x >> 16)
    x = x * jnp.uint32(0x85EBCA6B)
    x = x ^ (x >> 13)
    x = x * jnp.uint32(0xC2B2AE35)
    return x ^ (x >> 16)


def uniform(key, shape, minval=0.0, maxval=1.0):
    """Uniform floats in [minval, maxval) from one key, drawn by hashing a counter.

    Scene sampling needs thousands of numbers per step and XLA:CPU's threefry costs ~13 ns per number, more
    than the whole crowd simulation; here threefry draws only a 64-bit seed per call and a counter hash
    expands it. Still a pure function of the key, so runs stay reproducible.
    """
    seed = jax.random.bits(key, (2,), jnp.uint32)
    size = 1
    for d in shape:
        size *= d
    counter = jnp.arange(size, dtype=jnp.uint32).reshape(shape)
    bits = _mix32(_mix32(counter * jnp.uint32(0x9E3779B9) + seed[0]) ^ seed[1])
    unit = (bits >> 8).astype(jnp.float32) * jnp.float32(2.0**-24)
    return minval + unit * (maxval - minval)


def sample_robot(key, params: EnvParams, tries: int) -> Robot:
    """Start and goal ~ U(-a, a)^2 each, at least `min_start_goal_dist` apart."""
    pts = uniform(key, (tries, 2, 2), minval=-params.arena_size, maxval=params.arena_size)
    dist = norm(pts[:, 0] - pts[:, 1])
    start_goal = choose(pts.reshape(tries, 4), dist - params.min_start_goal_dist).reshape(2, 2)
    zero = jnp.zeros((), jnp.float32)
    return Robot(pos=start_goal[0], vel=jnp.zeros(2), goal=start_goal[1], heading=zero + jnp.pi / 2, speed=zero)


def sample_attributes(key, params: EnvParams, shape=()):
    """Radius and preferred speed of newly spawned humans."""
    k_r, k_v = jax.random.split(key)
    radius = uniform(k_r, shape, minval=params.human_radius_min, maxval=params.human_radius_max)
    v_pref = uniform(k_v, shape, minval=params.human_v_pref_min, maxval=params.human_v_pref_max)
    return radius, v_pref


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


def _pair_sq_dist(a, b):
    """Squared distances between points a (..., T, 2) and b (..., M, 2) -> (..., T, M).

    x and y are handled as separate arrays: a reduction over a trailing axis of size 2 vectorises badly on CPU.
    """
    dx = a[..., :, None, 0] - b[..., None, :, 0]
    dy = a[..., :, None, 1] - b[..., None, :, 1]
    return dx * dx + dy * dy


def clearance(candidates, own_radius, others_pos, others_goal, others_radius, others_valid, gap):
    """Smallest squared-distance margin between candidates (..., T, 2) and other agents' positions and goals.

    A candidate is acceptable where the margin is >= 0, i.e. it keeps r_self + r_other + gap from every other
    agent's position and goal (the reference's spawn rule); larger margins mean more room. `others_*` have
    shape (..., M, ...). Squares avoid a square root per pair in this hot loop.
    """
    need = own_radius[..., None, None] + others_radius[..., None, :] + gap  # (..., 1, M)
    sq = jnp.minimum(_pair_sq_dist(candidates, others_pos), _pair_sq_dist(candidates, others_goal))
    margin = jnp.where(others_valid[..., None, :], sq - need * need, jnp.inf)
    return jnp.min(margin, axis=-1, initial=jnp.inf)


# Inactive slots wait here, 10 m apart: far beyond any sensor range or arena, and at finite coordinates.
PARKING = 1.0e4


def active_slots(key, params: EnvParams, num_humans: int):
    """The episode's active mask (N,): the first k slots, k ~ U{active_humans_min..active_humans_max}.

    Bounds are rounded and clipped to the capacity, so gridded or hand-built params cannot ask for more humans
    than there are slots. With min = max = N (the default) every slot is active whatever the key.
    """
    lo = jnp.clip(jnp.round(params.active_humans_min), 0, num_humans)
    hi = jnp.clip(jnp.round(params.active_humans_max), lo, num_humans)
    count = jnp.minimum(lo + jnp.floor(uniform(key, ()) * (hi - lo + 1.0)), hi)
    return jnp.arange(num_humans) < count


def park(humans: Humans) -> Humans:
    """Move the inactive slots to their parking spots, at rest, with their goals where they stand."""
    n = humans.pos.shape[0]
    spot = jnp.stack([PARKING + 10.0 * jnp.arange(n, dtype=jnp.float32), jnp.full((n,), PARKING)], -1)
    on = humans.active[:, None]
    return humans.replace(
        pos=jnp.where(on, humans.pos, spot), goal=jnp.where(on, humans.goal, spot), vel=jnp.where(on, humans.vel, 0.0)
    )


# ------------------------------------------------------------------------------------------------ the scenarios
#
# Geometry follows the arena's traced parameters: a = arena_size (the robot's start and goal region), R =
# circle_radius (where humans enter and leave), lanes of half-width a / 2 (traffic) or a / 4 (head-on and
# overtaking lanes). The robot of the lane scenarios walks up the y axis from (x0, -a) to (x1, a).


class Scenario(NamedTuple):
    """One scenario's samplers (pure functions of a key and the traced params).

    robot(key, params, tries) -> Robot
    spawn(key, params, layout, n, tries) -> (pos, goal) candidates, each (n, tries, 2): human i of an episode
    new_goal(key, params, layout, humans, tries) -> goal candidates (N, tries, 2) for a goal change
    respawn(key, params, layout, pos, goal, tries) -> (pos, goal) candidates (tries, 2) replacing an arrived human
    layout(key, params, robot, tries) -> (vertices (S, V, 2), num_vertices (S,)): the episode's obstacles in the
        scenario's S = SCENARIO_OBSTACLE_SLOTS slots (None: an open space)
    speed: factor on the humans' preferred speeds

    `layout` in the human samplers is the episode's `Obstacles` (the scenario's slots first): the obstacle
    scenarios read their drawn geometry (a corridor's width, a door's place) from it.
    """

    robot: Callable
    spawn: Callable
    new_goal: Callable
    respawn: Callable
    speed: float = 1.0
    layout: Callable | None = None


def _open_space(fn):
    """A crowd scenario's human sampler, which has no use for the layout."""
    return lambda key, params, layout, *rest: fn(key, params, *rest)


def _crowd(robot, spawn, new_goal, respawn, speed=1.0) -> Scenario:
    return Scenario(robot, _open_space(spawn), _open_space(new_goal), _open_space(respawn), speed)


def _box(key, shape, lo_x, hi_x, lo_y, hi_y):
    """Points uniform in a box; bounds broadcast against `shape`."""
    u = uniform(key, shape + (2,))
    return jnp.stack([lo_x + u[..., 0] * (hi_x - lo_x), lo_y + u[..., 1] * (hi_y - lo_y)], -1)


def _lane_robot(key, params: EnvParams, tries: int) -> Robot:
    """Start near (0, -a), goal near (0, a), each shifted sideways by up to 0.5 m."""
    x = uniform(key, (2,), -0.5, 0.5)
    a = params.arena_size
    zero = jnp.zeros((), jnp.float32)
    return Robot(
        pos=jnp.stack([x[0], -a]), vel=jnp.zeros(2), goal=jnp.stack([x[1], a]), heading=zero + jnp.pi / 2, speed=zero
    )


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


# square_crossing (CrowdNav): start on one side of a square of half-width R, goal anywhere on the other side.
def _square_pair(key, params, shape):
    k_side, k_start, k_goal = jax.random.split(key, 3)
    side = jnp.where(uniform(k_side, shape) < 0.5, -1.0, 1.0)[..., None]
    r = params.circle_radius
    start = _box(k_start, shape, 0.0, r, -r, r) * jnp.stack([side[..., 0], jnp.ones(shape)], -1)
    goal = _box(k_goal, shape, 0.0, r, -r, r) * jnp.stack([-side[..., 0], jnp.ones(shape)], -1)
    return start, goal


def _square_spawn(key, params, n, tries):
    return _square_pair(key, params, (n, tries))


def _square_new_goal(key, params, humans, tries):
    side = jnp.where(humans.pos[:, 0] < 0, -1.0, 1.0)[:, None]  # the far side of where the human is
    r = params.circle_radius
    goal = _box(key, (humans.pos.shape[0], tries), 0.0, r, -r, r)
    return goal * jnp.stack([-side * jnp.ones_like(goal[..., 0]), jnp.ones_like(goal[..., 0])], -1)


def _square_respawn(key, params, pos, goal, tries):
    return _square_pair(key, params, (tries,))


# parallel_traffic (Francis et al.: parallel traffic): two opposing streams in a lane of half-width a/2 along the
# robot's way; even slots walk with the robot, odd slots against it. Arrived humans re-enter at their stream's start.
def _stream_goal(key, params, direction, shape, half_width):
    return _box(key, shape, -half_width, half_width, 0.0, 0.0) + jnp.stack(
        [jnp.zeros(shape), direction * params.circle_radius * jnp.ones(shape)], -1
    )


def _parallel_spawn(key, params, n, tries):
    k_pos, k_goal = jax.random.split(key)
    c, r = 0.5 * params.arena_size, params.circle_radius
    direction = jnp.where(jnp.arange(n) % 2 == 0, 1.0, -1.0)[:, None]
    pos = _box(k_pos, (n, tries), -c, c, -r, r)
    return pos, _stream_goal(k_goal, params, direction, (n, tries), c)


def _lane_new_goal(half_width_factor):
    def new_goal(key, params, humans, tries):
        direction = jnp.sign(humans.goal[:, 1:2])  # keep walking the stream's way
        return _stream_goal(key, params, direction, (humans.pos.shape[0], tries), half_width_factor * params.arena_size)

    return new_goal


def _lane_respawn(half_width_factor):
    def respawn(key, params, pos, goal, tries):
        k_pos, k_goal = jax.random.split(key)
        direction = jnp.sign(goal[1])
        c = half_width_factor * params.arena_size
        return (
            _stream_goal(k_pos, params, -direction, (tries,), c),
            _stream_goal(k_goal, params, direction, (tries,), c),
        )

    return respawn


# perpendicular_traffic (Francis et al.: perpendicular traffic): one stream crossing the robot's way from left
# to right, in a band of half-width a/2 about the middle of its path.
def _cross_goal(key, params, shape, x):
    c = 0.5 * params.arena_size
    return _box(key, shape, x, x, -c, c)


def _perpendicular_spawn(key, params, n, tries):
    k_pos, k_goal = jax.random.split(key)
    c, r = 0.5 * params.arena_size, params.circle_radius
    return _box(k_pos, (n, tries), -r, r, -c, c), _cross_goal(k_goal, params, (n, tries), r)


def _perpendicular_new_goal(key, params, humans, tries):
    return _cross_goal(key, params, (humans.pos.shape[0], tries), params.circle_radius)


def _perpendicular_respawn(key, params, pos, goal, tries):
    k_pos, k_goal = jax.random.split(key)
    r = params.circle_radius
    return _cross_goal(k_pos, params, (tries,), -r), _cross_goal(k_goal, params, (tries,), r)


# frontal_approach (Francis et al.: frontal approach): humans come head-on down the robot's lane (half-width
# a/4), from ahead of the robot's start to behind it.
def _frontal_spawn(key, params, n, tries):
    k_pos, k_goal = jax.random.split(key)
    c, a, r = 0.25 * params.arena_size, params.arena_size, params.circle_radius
    return _box(k_pos, (n, tries), -c, c, -0.5 * a, r), _stream_goal(k_goal, params, -1.0, (n, tries), c)


# robot_overtaking (Francis et al.: robot overtaking): humans at half their usual speed walk the robot's way in its
# lane, so the robot has to pass them.
def _overtaking_spawn(key, params, n, tries):
    k_pos, k_goal = jax.random.split(key)
    c, a, r = 0.25 * params.arena_size, params.arena_size, params.circle_radius
    return _box(k_pos, (n, tries), -c, c, -0.5 * a, r), _stream_goal(k_goal, params, 1.0, (n, tries), c)


# robot_crowding (Francis et al.: robot crowding): humans enter on the circle and head for points on the robot's
# path, converging on it; goal changes pick other points of the path.
def _path_points(key, params, shape):
    a = params.arena_size
    return _box(key, shape, -0.5, 0.5, -a, a)


def _crowding_spawn(key, params, n, tries):
    k_pos, k_goal = jax.random.split(key)
    return circle_candidates(k_pos, params, (n, tries)), _path_points(k_goal, params, (n, tries))


def _crowding_new_goal(key, params, humans, tries):
    return _path_points(key, params, (humans.pos.shape[0], tries))


def _crowding_respawn(key, params, pos, goal, tries):
    k_pos, k_goal = jax.random.split(key)
    return circle_candidates(k_pos, params, (tries,)), _path_points(k_goal, params, (tries,))


# random (CrowdNav's random goals): start and goal uniform in the square of half-width R; an arrived human stays
# where it is and walks on to a new random goal.
def _square_points(key, params, shape):
    r = params.circle_radius
    return _box(key, shape, -r, r, -r, r)


def _random_spawn(key, params, n, tries):
    k_pos, k_goal = jax.random.split(key)
    return _square_points(k_pos, params, (n, tries)), _square_points(k_goal, params, (n, tries))


def _random_new_goal(key, params, humans, tries):
    return _square_points(key, params, (humans.pos.shape[0], tries))


def _random_respawn(key, params, pos, goal, tries):
    return jnp.broadcast_to(pos, (tries, 2)), _square_points(key, params, (tries,))


# ------------------------------------------------------------------------------ scenarios with static obstacles
#
# Humans have no planner beyond ORCA's local avoidance (as in RVO2), so each obstacle scenario draws human starts
# and goals whose straight path stays clear of the walls: along a corridor, through a door's gap, down one arm of
# an intersection. The robot gets no such help: its goal may lie behind a wall's end or a door.
_WALL_CLEARANCE = 0.6  # how far from a wall the humans' lanes stay (the largest human radius plus a margin)


def _slots(*polygons):
    """(vertices (S, V, 2), num_vertices (S,)) of the scenario slots from polygons (V_i, 2) of up to V vertices."""
    vertices = jnp.zeros((SCENARIO_OBSTACLE_SLOTS, SCENARIO_OBSTACLE_VERTICES, 2), jnp.float32)
    counts = jnp.zeros((SCENARIO_OBSTACLE_SLOTS,), jnp.int32)
    for m, polygon in enumerate(polygons):
        vertices = vertices.at[m, : polygon.shape[0]].set(polygon)
        counts = counts.at[m].set(polygon.shape[0])
    return vertices, counts


def _box_polygon(cx, cy, hx, hy, angle=0.0):
    """A rectangle's 4 vertices, counter-clockwise, centred at (cx, cy) with half-sizes (hx, hy), rotated."""
    corners = jnp.array([[-1.0, -1.0], [1.0, -1.0], [1.0, 1.0], [-1.0, 1.0]]) * jnp.stack([hx, hy])
    c, s = jnp.cos(angle), jnp.sin(angle)
    return jnp.stack([cx + c * corners[:, 0] - s * corners[:, 1], cy + s * corners[:, 0] + c * corners[:, 1]], -1)


def _segment(x0, y0, x1, y1):
    return jnp.stack([jnp.stack([x0, y0]), jnp.stack([x1, y1])]).astype(jnp.float32)


# corridor: two walls at x = -w and x = +w along the robot's way (a corridor 2.5 to 4 m wide, w drawn per
# episode); humans walk it both ways in lanes clear of the walls.
def _corridor_layout(key, params, robot, tries):
    w = uniform(key, (), 1.25, 2.0)
    r = params.circle_radius
    return _slots(_segment(-w, r, -w, -r), _segment(w, -r, w, r))


def _corridor_lane(layout):
    """Half-width of the humans' lanes: inside the corridor, clear of its walls."""
    return jnp.maximum(layout.vertices[1, 0, 0] - _WALL_CLEARANCE, 0.1)


def _corridor_spawn(key, params, layout, n, tries):
    k_pos, k_goal = jax.random.split(key)
    c, r = _corridor_lane(layout), params.circle_radius
    direction = jnp.where(jnp.arange(n) % 2 == 0, 1.0, -1.0)[:, None]
    return _box(k_pos, (n, tries), -c, c, -r, r), _stream_goal(k_goal, params, direction, (n, tries), c)


def _corridor_new_goal(key, params, layout, humans, tries):
    direction = jnp.sign(humans.goal[:, 1:2])
    return _stream_goal(key, params, direction, (humans.pos.shape[0], tries), _corridor_lane(layout))


def _corridor_respawn(key, params, layout, pos, goal, tries):
    k_pos, k_goal = jax.random.split(key)
    direction, c = jnp.sign(goal[1]), _corridor_lane(layout)
    return (_stream_goal(k_pos, params, -direction, (tries,), c), _stream_goal(k_goal, params, direction, (tries,), c))


# doorway: a wall across the robot's way at y = y_d in [-1, 1] with one gap 1.2 to 2 m wide centred at x_d in
# [-1, 1]; humans cross it both ways through the gap, on straight lines through a point of the gap.
def _doorway_layout(key, params, robot, tries):
    u = uniform(key, (3,))
    y, x, half = 2.0 * u[0] - 1.0, 2.0 * u[1] - 1.0, 0.6 + 0.4 * u[2]
    r = params.circle_radius + 2.0
    return _slots(_segment(-r, y, x - half, y), _segment(x + half, y, r, y))


def _door(layout):
    """The gap's centre (2,) and half-width."""
    left_end, right_start = layout.vertices[0, 1], layout.vertices[1, 0]
    return 0.5 * (left_end + right_start), 0.5 * (right_start[0] - left_end[0])


def _through_door(key, layout, shape, side):
    """Start and goal on opposite sides of the door (`side` +1: the start below it), their straight line crossing
    the wall inside the gap, each 2 to 6 m from it."""
    k_x, k_a, k_d = jax.random.split(key, 3)
    centre, half = _door(layout)
    cross = centre[0] + (2.0 * uniform(k_x, shape) - 1.0) * jnp.maximum(half - _WALL_CLEARANCE, 0.0)
    angle = (2.0 * uniform(k_a, shape) - 1.0) * 0.6
    dist = uniform(k_d, shape + (2,), 2.0, 6.0)
    ux, uy = jnp.sin(angle), jnp.cos(angle) * side
    point = jnp.stack([cross, jnp.broadcast_to(centre[1], shape)], -1)
    direction = jnp.stack([ux, uy], -1)
    return point - dist[..., :1] * direction, point + dist[..., 1:] * direction


def _doorway_spawn(key, params, layout, n, tries):
    side = jnp.where(jnp.arange(n) % 2 == 0, 1.0, -1.0)[:, None]
    return _through_door(key, layout, (n, tries), side)


def _doorway_new_goal(key, params, layout, humans, tries):
    # back through the door from the side the human is on now
    side = jnp.where(humans.pos[:, 1:2] < _door(layout)[0][1], 1.0, -1.0)
    return _through_door(key, layout, (humans.pos.shape[0], tries), side)[1]


def _doorway_respawn(key, params, layout, pos, goal, tries):
    k_side, k_pair = jax.random.split(key)
    side = jnp.where(uniform(k_side, ()) < 0.5, 1.0, -1.0)
    return _through_door(k_pair, layout, (tries,), side)


# intersection: two corridors of half-width w (1.25 to 2 m) crossing at the origin, walled by four corner blocks,
# so people coming along the cross corridor are hidden until they reach the crossing (a blind corner). The robot
# goes straight up its corridor; two humans in three walk the cross corridor, the others the robot's.
def _intersection_layout(key, params, robot, tries):
    w = uniform(key, (), 1.25, 2.0)
    r = params.circle_radius
    half, mid = 0.5 * (r - w), 0.5 * (r + w)
    return _slots(*(_box_polygon(sx * mid, sy * mid, half, half) for sx, sy in ((1, 1), (-1, 1), (-1, -1), (1, -1))))


def _intersection_lane(layout):
    return jnp.maximum(layout.vertices[0, 0, 0] - _WALL_CLEARANCE, 0.1)  # the NE block's inner corner is (w, w)


def _arm_pair(key, params, layout, shape, across, direction):
    """Start and goal at the two ends of a corridor (`across`: the cross corridor along x), in its lane."""
    k_s, k_g = jax.random.split(key)
    c = _intersection_lane(layout)
    start = _stream_goal(k_s, params, -direction, shape, c)
    goal = _stream_goal(k_g, params, direction, shape, c)
    swap = lambda p: jnp.where(across[..., None], p[..., ::-1], p)  # noqa: E731  (x, y) -> (y, x)
    return swap(start), swap(goal)


def _intersection_spawn(key, params, layout, n, tries):
    k_pair, k_dir = jax.random.split(key)
    across = jnp.broadcast_to((jnp.arange(n) % 3 != 2)[:, None], (n, tries))
    direction = jnp.where(uniform(k_dir, (n, 1)) < 0.5, -1.0, 1.0) * jnp.ones((n, tries))
    start, goal = _arm_pair(k_pair, params, layout, (n, tries), across, direction)
    # spread the starts along the corridor so the crossing is busy from the first step
    t = uniform(jax.random.fold_in(key, 1), (n, tries, 1))
    return start + t * (goal - start) * 0.9, goal


def _intersection_new_goal(key, params, layout, humans, tries):
    across = jnp.abs(humans.goal[:, 0]) > jnp.abs(humans.goal[:, 1])
    n = humans.pos.shape[0]
    along = jnp.where(across, humans.goal[:, 0], humans.goal[:, 1])
    direction = jnp.sign(along)[:, None] * jnp.ones((n, tries))
    return _arm_pair(key, params, layout, (n, tries), jnp.broadcast_to(across[:, None], (n, tries)), direction)[1]


def _intersection_respawn(key, params, layout, pos, goal, tries):
    k_pair, k_kind = jax.random.split(key)
    u = uniform(k_kind, (2,))
    across = jnp.broadcast_to(u[0] < 2.0 / 3.0, (tries,))
    direction = jnp.where(u[1] < 0.5, -1.0, 1.0) * jnp.ones((tries,))
    return _arm_pair(k_pair, params, layout, (tries,), across, direction)


# random_obstacles: 1 to 8 boxes (sides 0.5 to 1.5 m, any orientation) scattered in the robot's arena, each clear
# of the robot's start and goal and 0.6 m from the others (so there is always a way between them); humans cross
# the circle as in circle_crossing, around the boxes.
def _random_obstacles_layout(key, params, robot, tries):
    k_count, k_box = jax.random.split(key)
    count = 1 + jnp.floor(uniform(k_count, ()) * SCENARIO_OBSTACLE_SLOTS)
    a = params.arena_size
    u = uniform(k_box, (SCENARIO_OBSTACLE_SLOTS, tries, 5))
    centre = (2.0 * u[..., :2] - 1.0) * a
    half = 0.25 + 0.5 * u[..., 2:4]
    angle = u[..., 4] * (0.5 * jnp.pi)
    reach = jnp.sqrt(jnp.sum(half * half, -1))  # the box's circumradius
    keep_off = reach + params.robot_radius + 0.5
    margin = jnp.minimum(norm(centre - robot.pos) - keep_off, norm(centre - robot.goal) - keep_off)

    def place(carry, m):
        placed_centre, placed_reach, placed = carry
        apart = norm(centre[m][:, None] - placed_centre[None]) - reach[m][:, None] - placed_reach[None] - 0.6
        ok = margin[m] >= 0.0
        ok = ok & jnp.all((apart >= 0.0) | ~placed[None], axis=-1)
        pick = jnp.argmax(ok)
        use = jnp.any(ok) & (m < count)
        carry = (
            placed_centre.at[m].set(centre[m, pick]),
            placed_reach.at[m].set(reach[m, pick]),
            placed.at[m].set(use),
        )
        box = _box_polygon(centre[m, pick, 0], centre[m, pick, 1], half[m, pick, 0], half[m, pick, 1], angle[m, pick])
        return carry, (box, jnp.where(use, 4, 0).astype(jnp.int32))

    init = (
        jnp.zeros((SCENARIO_OBSTACLE_SLOTS, 2)),
        jnp.zeros((SCENARIO_OBSTACLE_SLOTS,)),
        jnp.zeros((SCENARIO_OBSTACLE_SLOTS,), bool),
    )
    _, (boxes, counts) = jax.lax.scan(place, init, jnp.arange(SCENARIO_OBSTACLE_SLOTS))
    return boxes.astype(jnp.float32), counts


SCENARIO_TABLE = {
    "circle_crossing": _crowd(sample_robot, _circle_spawn, _circle_new_goal, _circle_respawn),
    "square_crossing": _crowd(sample_robot, _square_spawn, _square_new_goal, _square_respawn),
    "parallel_traffic": _crowd(_lane_robot, _parallel_spawn, _lane_new_goal(0.5), _lane_respawn(0.5)),
    "perpendicular_traffic": _crowd(_lane_robot, _perpendicular_spawn, _perpendicular_new_goal, _perpendicular_respawn),
    "frontal_approach": _crowd(_lane_robot, _frontal_spawn, _lane_new_goal(0.25), _lane_respawn(0.25)),
    "robot_overtaking": _crowd(_lane_robot, _overtaking_spawn, _lane_new_goal(0.25), _lane_respawn(0.25), 0.5),
    "robot_crowding": _crowd(_lane_robot, _crowding_spawn, _crowding_new_goal, _crowding_respawn),
    "random": _crowd(sample_robot, _random_spawn, _random_new_goal, _random_respawn),
    "corridor": Scenario(_lane_robot, _corridor_spawn, _corridor_new_goal, _corridor_respawn, layout=_corridor_layout),
    "doorway": Scenario(_lane_robot, _doorway_spawn, _doorway_new_goal, _doorway_respawn, layout=_doorway_layout),
    "intersection": Scenario(
        _lane_robot, _intersection_spawn, _intersection_new_goal, _intersection_respawn, layout=_intersection_layout
    ),
    "random_obstacles": _crowd(sample_robot, _circle_spawn, _circle_new_goal, _circle_respawn)._replace(
        layout=_random_obstacles_layout
    ),
}
assert tuple(SCENARIO_TABLE) == SCENARIOS, "config.SCENARIOS lists the scenarios in this order"


class Sampler(NamedTuple):
    """The samplers of one configured env: `scenarios` holds one `Scenario` (a fixed scenario: called directly)
    or the mix's (each call selects the episode's by `lax.switch` on its index into `scenarios`)."""

    scenarios: tuple
    names: tuple

    def local(self, index):
        """A `SCENARIOS` index (what `EnvState.scenario` holds) as an index into `scenarios`."""
        lookup = [self.names.index(name) if name in self.names else 0 for name in SCENARIOS]
        return jnp.asarray(lookup, jnp.int32)[index]

    def global_index(self, local):
        """An index into `scenarios` as a `SCENARIOS` index."""
        return jnp.asarray([SCENARIOS.index(name) for name in self.names], jnp.int32)[local]

    def _call(self, field, index, *args, static=()):
        """Scenario `field`'s sampler on `args` plus the trailing `static` Python values (shapes: bound, not
        passed through the switch, which would trace them); `index` is a `SCENARIOS` index."""
        fns = [getattr(s, field) for s in self.scenarios]
        if len(fns) == 1:
            return fns[0](*args, *static)
        return jax.lax.switch(self.local(index), [lambda *a, f=f: f(*a, *static) for f in fns], *args)

    @property
    def draws_obstacles(self) -> bool:
        return any(s.layout is not None for s in self.scenarios)

    def layout(self, key, params, robot, index, tries: int):
        """The scenario's obstacle slots (vertices (S, V, 2), num_vertices (S,)); open spaces leave them empty."""
        empty = lambda key, params, robot, tries: _slots()  # noqa: E731
        fns = [s.layout or empty for s in self.scenarios]
        if len(fns) == 1:
            return fns[0](key, params, robot, tries)
        return jax.lax.switch(self.local(index), [lambda *a, f=f: f(*a, tries) for f in fns], key, params, robot)

    def scale_speed(self, v_pref, index):
        """Preferred speeds times the scenario's speed factor."""
        speeds = [s.speed for s in self.scenarios]
        if speeds == [1.0]:
            return v_pref
        if len(speeds) == 1:
            return v_pref * speeds[0]
        return v_pref * jnp.asarray(speeds, jnp.float32)[index]


def sampler(config) -> Sampler:
    """The samplers of an `EnvConfig`'s scenario, or of its mix's scenarios in the order of its weights."""
    names = config.drawn_scenarios
    return Sampler(tuple(SCENARIO_TABLE[name] for name in names), names)


def scenario_index(name: str) -> int:
    """The index of a scenario in `SCENARIOS` (what `EnvState.scenario` holds)."""
    return SCENARIOS.index(name)


def draw_scenario(key, weights):
    """An index ~ Categorical(weights / sum(weights)); zero-weight scenarios are never drawn."""
    edges = jnp.cumsum(weights)
    u = uniform(key, ()) * edges[-1]
    return jnp.minimum(jnp.sum(edges <= u), weights.shape[0] - 1).astype(jnp.int32)


def robot_start(key, params: EnvParams, sampler: Sampler, index, tries: int) -> Robot:
    return sampler._call("robot", index, key, params, static=(tries,))


_CIRCLE_CROSSING = Sampler((SCENARIO_TABLE["circle_crossing"],), ("circle_crossing",))


def obstacle_margin(candidates, own_radius, layout: Obstacles | None, gap):
    """How far candidates (..., T, 2) of radius `own_radius` (...,) keep `gap` from every obstacle (negative:
    too close or inside one), or None without obstacle slots."""
    if layout is None or layout.num_vertices.shape[-1] == 0:
        return None
    return obstacles_lib.clearance(candidates, layout) - own_radius[..., None] - gap


def _with_obstacles(margin, candidates, own_radius, layout, gap):
    """An agent-spacing margin (squared metres) also requiring room from the obstacles."""
    room = obstacle_margin(candidates, own_radius, layout, gap)
    return margin if room is None else jnp.minimum(margin, room)


def spawn_humans(
    key,
    params: EnvParams,
    robot: Robot,
    num_humans: int,
    tries: int,
    active=None,
    sampler: Sampler | None = None,
    index=0,
    layout: Obstacles | None = None,
) -> Humans:
    """Place the active humans one at a time at the scenario's spawn candidates, each clear of the robot, of
    every human placed before (positions and goals) and of the obstacles; the inactive slots are parked.
    `active` (N,) bool defaults to all slots, `sampler` to circle crossing, `layout` to no obstacles."""
    sampler = sampler or _CIRCLE_CROSSING
    layout = obstacles_lib.empty() if layout is None else layout
    k_attr, k_cand = jax.random.split(key)
    radius, v_pref = sample_attributes(k_attr, params, (num_humans,))
    v_pref = sampler.scale_speed(v_pref, index)
    active = jnp.ones((num_humans,), bool) if active is None else active
    if num_humans == 0:
        empty = jnp.zeros((0, 2))
        return Humans(pos=empty, vel=empty, goal=empty, radius=radius, v_pref=v_pref, active=active)
    start, goal = sampler._call("spawn", index, k_cand, params, layout, static=(num_humans, tries))
    candidates = jnp.concatenate([start, goal], -1)  # (N, tries, 4): a start is chosen with its goal
    # room from the obstacles at both ends of each candidate's walk
    room = obstacle_margin(
        jnp.stack([start, goal]), jnp.broadcast_to(radius, (2, num_humans)), layout, params.spawn_clearance
    )
    room = None if room is None else jnp.min(room, axis=0)

    # Slot 0 of the "others" arrays is the robot; slots 1..N fill up with placed humans.
    others_pos = jnp.zeros((num_humans + 1, 2)).at[0].set(robot.pos)
    others_goal = jnp.zeros((num_humans + 1, 2)).at[0].set(robot.goal)
    others_radius = jnp.zeros(num_humans + 1).at[0].set(params.robot_radius).at[1:].set(radius)
    placed = jnp.zeros(num_humans + 1, bool).at[0].set(True)

    def place(carry, i):
        others_pos, others_goal, placed = carry
        margin = clearance(
            candidates[i, :, :2], radius[i], others_pos, others_goal, others_radius, placed, params.spawn_clearance
        )
        if room is not None:
            margin = jnp.minimum(margin, room[i])
        pick = choose(candidates[i], margin)
        carry = (
            others_pos.at[i + 1].set(pick[:2]),
            others_goal.at[i + 1].set(pick[2:]),
            placed.at[i + 1].set(active[i]),
        )
        return carry, None

    (others_pos, others_goal, _), _ = jax.lax.scan(place, (others_pos, others_goal, placed), jnp.arange(num_humans))
    return park(
        Humans(
            pos=others_pos[1:],
            vel=jnp.zeros((num_humans, 2)),
            goal=others_goal[1:],
            radius=radius,
            v_pref=v_pref,
            active=active,
        )
    )


def _others_excluding_self(humans: Humans, robot: Robot, params: EnvParams):
    """Every agent (humans, then the robot) with a (N, N+1) mask hiding each human from itself and the inactive
    slots from everyone."""
    n = humans.pos.shape[0]
    pos = jnp.concatenate([humans.pos, robot.pos[None]], 0)
    goal = jnp.concatenate([humans.goal, robot.goal[None]], 0)
    radius = jnp.concatenate([humans.radius, params.robot_radius[None]], 0)
    present = jnp.concatenate([humans.active, jnp.ones((1,), bool)])
    return pos, goal, radius, ~jnp.eye(n, n + 1, dtype=bool) & present[None, :]


def choose(candidates, margin):
    """Per row, the first candidate with margin >= 0 (else the widest margin): (..., T, D) -> (..., D)."""
    tries = margin.shape[-1]
    first = jnp.argmax(margin >= 0, axis=-1)
    idx = jnp.where(jnp.any(margin >= 0, axis=-1), first, jnp.argmax(margin, axis=-1))
    onehot = (jnp.arange(tries) == idx[..., None]).astype(candidates.dtype)
    return jnp.sum(onehot[..., None] * candidates, axis=-2)


def change_goals(
    key,
    humans: Humans,
    robot: Robot,
    params: EnvParams,
    step_count,
    tries: int,
    sampler: Sampler | None = None,
    index=0,
    layout: Obstacles | None = None,
) -> Humans:
    """Every goal_change_interval seconds each active human switches, with goal_change_prob, to a new goal
    drawn by the scenario.

    The candidates are drawn only on the steps where changes fall due (one in 20 by default), also in a
    vmapped batch of environments, where only the environments that are due do the work (see `cond_gathered`).
    """
    sampler = sampler or _CIRCLE_CROSSING
    layout = obstacles_lib.empty() if layout is None else layout
    due = (step_count % params.goal_change_period) == 0
    return cond_gathered(
        due,
        lambda *args: _switch_goals(*args, tries, sampler),
        _unchanged,
        key,
        humans,
        robot,
        params,
        jnp.asarray(index, jnp.int32),
        layout,
    )


def _unchanged(key, humans: Humans, robot: Robot, params: EnvParams, index, layout) -> Humans:
    return humans


def _switch_goals(key, humans: Humans, robot: Robot, params: EnvParams, index, layout, tries: int, sampler) -> Humans:
    """Each human switches, with goal_change_prob, to a new goal clear of the others and of the obstacles."""
    n = humans.pos.shape[0]
    k_coin, k_cand = jax.random.split(key)
    switch = (uniform(k_coin, (n,)) < params.goal_change_prob) & humans.active
    candidates = sampler._call("new_goal", index, k_cand, params, layout, humans, static=(tries,))
    margin = clearance(
        candidates, humans.radius, *_others_excluding_self(humans, robot, params), params.spawn_clearance
    )
    margin = _with_obstacles(margin, candidates, humans.radius, layout, params.spawn_clearance)
    return humans.replace(goal=jnp.where(switch[:, None], choose(candidates, margin), humans.goal))


def respawn_arrived(
    key,
    humans: Humans,
    robot: Robot,
    params: EnvParams,
    tries: int,
    sampler: Sampler | None = None,
    index=0,
    layout: Obstacles | None = None,
) -> Humans:
    """A human within its own radius of its goal is replaced by a fresh one of the scenario (`random` keeps it
    where it is with a new goal).

    One arrival is served per step (the lowest index); another human arriving in the same step waits at its
    goal until the next one. Serving one instead of all N cuts the rejection-sampling work N-fold, and
    simultaneous arrivals are rare. In a vmapped batch only the environments with an arrival do the work
    (see `cond_gathered`).
    """
    sampler = sampler or _CIRCLE_CROSSING
    layout = obstacles_lib.empty() if layout is None else layout
    return cond_gathered(
        jnp.any(_arrived(humans)),
        lambda *args: _respawn_first(*args, tries, sampler),
        _unchanged,
        key,
        humans,
        robot,
        params,
        jnp.asarray(index, jnp.int32),
        layout,
    )


def _arrived(humans: Humans):
    offset = humans.pos - humans.goal
    return (jnp.square(offset[:, 0]) + jnp.square(offset[:, 1]) < jnp.square(humans.radius)) & humans.active


def _respawn_first(key, humans: Humans, robot: Robot, params: EnvParams, index, layout, tries: int, sampler) -> Humans:
    """Replace the lowest-indexed arrived human (if any) by a fresh one."""
    n = humans.pos.shape[0]
    k_attr, k_cand = jax.random.split(key)
    arrived = _arrived(humans)
    who = jnp.argmax(arrived)
    radius, v_pref = sample_attributes(k_attr, params)
    v_pref = sampler.scale_speed(v_pref, index)
    start, goal = sampler._call(
        "respawn", index, k_cand, params, layout, humans.pos[who], humans.goal[who], static=(tries,)
    )
    pos, goals, radii, valid = _others_excluding_self(humans, robot, params)
    margin = clearance(start, radius, pos, goals, radii, valid[who], params.spawn_clearance)
    margin = _with_obstacles(margin, start, radius, layout, params.spawn_clearance)
    margin = _with_obstacles(margin, goal, radius, layout, params.spawn_clearance)
    pick = choose(jnp.concatenate([start, goal], -1), margin)
    replace = arrived & (jnp.arange(n) == who)
    put = lambda new, old: jnp.where(replace.reshape((n,) + (1,) * (old.ndim - 1)), new, old)
    return Humans(
        pos=put(pick[:2], humans.pos),
        vel=put(jnp.zeros(2), humans.vel),
        goal=put(pick[2:], humans.goal),
        radius=put(radius, humans.radius),
        v_pref=put(v_pref, humans.v_pref),
        active=humans.active,
    )
