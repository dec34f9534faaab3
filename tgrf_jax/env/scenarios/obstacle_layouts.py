"""The obstacle scenarios: an episode's static obstacles (its layout) and the crowd samplers that read them.

Humans route around the obstacles (`tgrf_jax.env.routing`), so a goal behind a wall is reachable; the scenarios
still draw the flows that make each layout what it is: along a corridor, through a door's gap, down one arm of
an intersection. A layout fills the
scenario obstacle slots (`config.SCENARIO_OBSTACLE_SLOTS` of up to `config.SCENARIO_OBSTACLE_VERTICES`
vertices); the geometry of obstacles (distances, LiDAR) is `tgrf_jax.env.obstacles`.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp

from tgrf_jax.config import SCENARIO_OBSTACLE_SLOTS, SCENARIO_OBSTACLE_VERTICES
from tgrf_jax.env.geometry import norm
from tgrf_jax.env.scenarios import open_space as open_space_lib
from tgrf_jax.env.scenarios.open_space import lane_robot, stream_goal, timeless
from tgrf_jax.env.scenarios.sampling import box, uniform
from tgrf_jax.scenario_registry import Scenario

_WALL_CLEARANCE = 0.6  # how far from a wall the humans' lanes stay (the largest human radius plus a margin)
# A corridor's half-width: two lanes of the largest ORCA humans (1.32 m across with their safety space) side by side
# with room to pass a slower walker; below 3.5 m the two streams of 20 humans overlap, meet head-on and lock.
_CORRIDOR_HALF_WIDTH = (1.75, 2.5)
# How far off the centre line a lane starts, so that the two streams walk past each other rather than into each
# other (ORCA humans meeting head-on in a crowded corridor freeze).
_LANE_OFFSET = 0.6


def slots(*polygons):
    """(vertices (S, V, 2), num_vertices (S,)) of the scenario slots from polygons (V_i, 2) of up to V vertices."""
    vertices = jnp.zeros((SCENARIO_OBSTACLE_SLOTS, SCENARIO_OBSTACLE_VERTICES, 2), jnp.float32)
    counts = jnp.zeros((SCENARIO_OBSTACLE_SLOTS,), jnp.int32)
    for m, polygon in enumerate(polygons):
        vertices = vertices.at[m, : polygon.shape[0]].set(polygon)
        counts = counts.at[m].set(polygon.shape[0])
    return vertices, counts


def box_polygon(cx, cy, hx, hy, angle=0.0):
    """A rectangle's 4 vertices, counter-clockwise, centred at (cx, cy) with half-sizes (hx, hy), rotated."""
    corners = jnp.array([[-1.0, -1.0], [1.0, -1.0], [1.0, 1.0], [-1.0, 1.0]]) * jnp.stack([hx, hy])
    c, s = jnp.cos(angle), jnp.sin(angle)
    return jnp.stack([cx + c * corners[:, 0] - s * corners[:, 1], cy + s * corners[:, 0] + c * corners[:, 1]], -1)


def _segment(x0, y0, x1, y1):
    return jnp.stack([jnp.stack([x0, y0]), jnp.stack([x1, y1])]).astype(jnp.float32)


# corridor: two walls at x = -w and x = +w along the robot's way (a corridor 3.5 to 5 m wide, w drawn per
# episode); humans walk it both ways, each in its right-hand lane, clear of the walls and off the centre line (two
# streams that share the whole width meet head-on and, among ORCA humans, jam for good: people form lanes).
def _corridor_layout(key, params, robot, tries):
    w = uniform(key, (), *_CORRIDOR_HALF_WIDTH)
    r = params.circle_radius
    return slots(_segment(-w, r, -w, -r), _segment(w, -r, w, r))


def _corridor_lane(layout):
    """Half-width of the humans' lanes: inside the corridor, clear of its walls."""
    return jnp.maximum(layout.vertices[1, 0, 0] - _WALL_CLEARANCE, 0.1)


def _keep_right(points, direction, half_width):
    """Points (..., 2) drawn across a lane's [-half_width, half_width] moved into the right-hand lane for walking
    along y in `direction`: |x| from `_LANE_OFFSET` to `half_width`, uniform as drawn."""
    inner = jnp.minimum(_LANE_OFFSET, half_width)
    x = inner + jnp.abs(points[..., 0]) / half_width * (half_width - inner)
    return jnp.stack([direction * x, points[..., 1]], -1)


def _corridor_spawn(key, params, layout, n, tries):
    k_pos, k_goal = jax.random.split(key)
    c, r = _corridor_lane(layout), params.circle_radius
    direction = jnp.where(jnp.arange(n) % 2 == 0, 1.0, -1.0)[:, None]
    start = _keep_right(box(k_pos, (n, tries), -c, c, -r, r), direction, c)
    return start, _keep_right(stream_goal(k_goal, params, direction, (n, tries), c), direction, c)


def _corridor_new_goal(key, params, layout, humans, tries):
    direction = jnp.sign(humans.goal[:, 1:2])
    c = _corridor_lane(layout)
    return _keep_right(stream_goal(key, params, direction, (humans.pos.shape[0], tries), c), direction, c)


def _corridor_respawn(key, params, layout, pos, goal, tries):
    k_pos, k_goal = jax.random.split(key)
    direction, c = jnp.sign(goal[1]), _corridor_lane(layout)
    start = stream_goal(k_pos, params, -direction, (tries,), c)
    goal = stream_goal(k_goal, params, direction, (tries,), c)
    return _keep_right(start, direction, c), _keep_right(goal, direction, c)


CORRIDOR = Scenario(
    lane_robot, _corridor_spawn, _corridor_new_goal, timeless(_corridor_respawn), layout=_corridor_layout
)


# doorway: a wall across the robot's way at y = y_d in [-1, 1] with one gap 2 to 3 m wide (a double door: two
# ORCA humans, each up to 1.32 m across with its safety space, pass side by side) centred at x_d in [-1, 1].
# People leave through the door in waves, towards the robot's start (a room emptying after a lecture while the
# robot enters it): a third of the humans cross at the start, and for the first 6 s of every 30 a human who
# reaches their goal is replaced by a crossing one with probability 1/3; the others walk about on either side of
# the wall. Two-way traffic through a door jams for good among ORCA humans (they have no convention to yield), so
# the flow is one-way, as at a marked exit; and a steady stream against the robot leaves it no gap to pass,
# where people at real doors come in bursts (docs/walls.md, "The doorway").
_DOOR_FLOW = -1.0  # the crossing humans' direction along y: from the robot's goal side to its start side
_CROSSING_SHARE = 1.0 / 3.0
_WAVE_PERIOD, _WAVE_LENGTH = 30.0, 6.0  # s: a wave starts with the episode and every 30 s after


def _doorway_layout(key, params, robot, tries):
    u = uniform(key, (3,))
    y, x, half = 2.0 * u[0] - 1.0, 2.0 * u[1] - 1.0, 1.0 + 0.5 * u[2]
    r = params.circle_radius + 2.0
    return slots(_segment(-r, y, x - half, y), _segment(x + half, y, r, y))


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


def _beside_door(key, params, layout, shape, side):
    """A point 2.5 to 8 m from the wall on its `side` (+1: above), within the crossing circle sideways: far enough
    that people walking about do not brush past the door, where the crossing stream would press them into it, and
    spread over the room rather than gathered on the robot's start and goal."""
    k_x, k_y = jax.random.split(key)
    r = params.circle_radius
    x = uniform(k_x, shape, -r, r)
    y = _door(layout)[0][1] + side * uniform(k_y, shape, 2.5, 8.0)
    return jnp.stack([x, y], -1)


def _doorway_pair(key, params, layout, shape, crossing, side):
    """Start and goal of a crossing human (through the door along the flow) or of one walking on `side`."""
    k_cross, k_start, k_goal = jax.random.split(key, 3)
    cross_start, cross_goal = _through_door(k_cross, layout, shape, _DOOR_FLOW)
    start = jnp.where(crossing[..., None], cross_start, _beside_door(k_start, params, layout, shape, side))
    goal = jnp.where(crossing[..., None], cross_goal, _beside_door(k_goal, params, layout, shape, side))
    return start, goal


def _doorway_spawn(key, params, layout, n, tries):
    i = jnp.arange(n)[:, None]
    crossing = jnp.broadcast_to(i % 3 == 0, (n, tries))
    side = jnp.where(i % 2 == 0, 1.0, -1.0) * jnp.ones((n, tries))
    return _doorway_pair(key, params, layout, (n, tries), crossing, side)


def _doorway_new_goal(key, params, layout, humans, tries):
    # on the side of the current goal: a human on its way through the door keeps going, one beside it stays
    n = humans.pos.shape[0]
    side = jnp.where(humans.goal[:, 1:2] > _door(layout)[0][1], 1.0, -1.0) * jnp.ones((n, tries))
    return _beside_door(key, params, layout, (n, tries), side)


def _doorway_respawn(key, params, layout, pos, goal, t, tries):
    # a crossing human only while a wave lasts, so the door clears between waves
    k_kind, k_pair = jax.random.split(key)
    u = uniform(k_kind, (2,))
    in_wave = jnp.mod(t, _WAVE_PERIOD) < _WAVE_LENGTH
    crossing = jnp.broadcast_to((u[0] < _CROSSING_SHARE) & in_wave, (tries,))
    side = jnp.where(u[1] < 0.5, 1.0, -1.0) * jnp.ones((tries,))
    return _doorway_pair(k_pair, params, layout, (tries,), crossing, side)


DOORWAY = Scenario(lane_robot, _doorway_spawn, _doorway_new_goal, _doorway_respawn, layout=_doorway_layout)


# intersection: two corridors of half-width w (1.75 to 2.5 m, as the corridor's) crossing at the origin, walled by
# four corner blocks, so people coming along the cross corridor are hidden until they reach the crossing (a blind
# corner). The robot goes straight up its corridor; two humans in three walk the cross corridor, the others the
# robot's. Four streams meeting in the crossing (both corridors two-way) lock among ORCA humans, each waiting on
# the next, and the queues reach back along the arms; so the cross corridor is one-way, its direction drawn per
# episode, and a human who reaches their goal walks their own stream again.
def _intersection_layout(key, params, robot, tries):
    w = uniform(key, (), *_CORRIDOR_HALF_WIDTH)
    r = params.circle_radius
    half, mid = 0.5 * (r - w), 0.5 * (r + w)
    return slots(*(box_polygon(sx * mid, sy * mid, half, half) for sx, sy in ((1, 1), (-1, 1), (-1, -1), (1, -1))))


def _intersection_lane(layout):
    return jnp.maximum(layout.vertices[0, 0, 0] - _WALL_CLEARANCE, 0.1)  # the NE block's inner corner is (w, w)


def _arm_pair(key, params, layout, shape, across, direction):
    """Start and goal at the two ends of a corridor (`across`: the cross corridor along x), in its right-hand
    lane (two-way traffic over the whole width jams, as in the corridor)."""
    k_s, k_g = jax.random.split(key)
    c = _intersection_lane(layout)
    # keeping right: +x along the cross corridor has its right-hand side at -y, after the swap below
    right = jnp.where(across, -direction, direction)
    start = _keep_right(stream_goal(k_s, params, -direction, shape, c), right, c)
    goal = _keep_right(stream_goal(k_g, params, direction, shape, c), right, c)
    swap = lambda p: jnp.where(across[..., None], p[..., ::-1], p)  # noqa: E731  (x, y) -> (y, x)
    return swap(start), swap(goal)


def _intersection_spawn(key, params, layout, n, tries):
    k_pair, k_dir, k_flow = jax.random.split(key, 3)
    across = jnp.broadcast_to((jnp.arange(n) % 3 != 2)[:, None], (n, tries))
    own = jnp.where(uniform(k_dir, (n, 1)) < 0.5, -1.0, 1.0)  # the robot's corridor: both ways
    flow = jnp.where(uniform(k_flow, ()) < 0.5, -1.0, 1.0)  # the cross corridor: one way
    direction = jnp.where(across, flow, own) * jnp.ones((n, tries))
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
    # the same stream again: the corridor and direction of the goal just reached
    across = jnp.abs(goal[0]) > jnp.abs(goal[1])
    direction = jnp.sign(jnp.where(across, goal[0], goal[1])) * jnp.ones((tries,))
    return _arm_pair(key, params, layout, (tries,), jnp.broadcast_to(across, (tries,)), direction)


INTERSECTION = Scenario(
    lane_robot,
    _intersection_spawn,
    _intersection_new_goal,
    timeless(_intersection_respawn),
    layout=_intersection_layout,
)


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
        box = box_polygon(centre[m, pick, 0], centre[m, pick, 1], half[m, pick, 0], half[m, pick, 1], angle[m, pick])
        return carry, (box, jnp.where(use, 4, 0).astype(jnp.int32))

    init = (
        jnp.zeros((SCENARIO_OBSTACLE_SLOTS, 2)),
        jnp.zeros((SCENARIO_OBSTACLE_SLOTS,)),
        jnp.zeros((SCENARIO_OBSTACLE_SLOTS,), bool),
    )
    _, (boxes, counts) = jax.lax.scan(place, init, jnp.arange(SCENARIO_OBSTACLE_SLOTS))
    return boxes.astype(jnp.float32), counts


RANDOM_OBSTACLES = dataclasses.replace(open_space_lib.CIRCLE_CROSSING, layout=_random_obstacles_layout)
