"""Routing among static obstacles: a visibility roadmap built once per episode, queried by every human every step.

ORCA and Social Force avoid walls only locally, so a human whose goal lies behind a wall presses against it. As
RVO2's own examples do, humans instead head for a point of their shortest path around the obstacles:

* **Roadmap** (`build_roadmap`, at reset; the layout is static within an episode): every convex polygon corner
  is pushed out along its bisector until it lies `clearance` (the humans' largest radius plus a margin) from
  both of its edges; each end of a wall (a 2-vertex polygon) gives two points, `clearance` beyond the end on
  either side. Points too close to another obstacle (a gap narrower than 2 x clearance) are dropped. Two
  points are linked when the straight line between them crosses no edge, and all-pairs shortest path lengths
  follow from Floyd-Warshall (dense, N^3 / N on an N x N table: N is small and fixed by the layout's capacity).
* **Goal costs** (`goal_costs`, when a human's goal changes): each roadmap point's shortest distance to the goal.
* **Aim** (`aim`, every step): the goal itself when it is in sight, else the visible roadmap point that
  minimises (distance to it + its goal cost); by the triangle inequality that is the farthest point of the
  shortest path that the human can see. A goal that cannot be reached at all (enclosed) leaves the human
  aiming straight at it, flagged, never a NaN.

Everything is dense, masked array code over fixed slot counts, so it runs under `jax.vmap` and `jit` like the
rest of the environment; with no obstacle slots none of it is called.

The environment keeps a `Routing` in its state: the roadmap (`plan`, at reset) and each human's goal costs,
recomputed for the humans whose goal changed (`replan`; in a vmapped batch only the environments with a change do
that work), and asks `targets` every step where each human heads.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from flax import struct

from tgrf_jax.env import obstacles as obstacle_lib
from tgrf_jax.env.batching import cond_gathered
from tgrf_jax.env.obstacles import Obstacles

__all__ = [
    "UNREACHABLE",
    "Roadmap",
    "Routing",
    "aim",
    "build_roadmap",
    "goal_costs",
    "plan",
    "replan",
    "targets",
    "visible",
]

UNREACHABLE = 1.0e9  # path length of a pair with no path (finite, so sums and minima stay finite)
_TINY = 1e-12
# A corner sharper than this (cosine of the half-angle between its edges' normals) would push its point far
# out; the push is capped at clearance / _MIN_COS.
_MIN_COS = 0.25


@struct.dataclass
class Roadmap:
    """An episode's routing graph.

    points (N, 2) float32 and valid (N,) bool: N is one per vertex slot when slots hold 4 vertices or more (a
    polygon's corners; a wall's two ends on either side), else two (`_packed`); cost (N, N) float32: shortest
    path lengths between points along visible links (UNREACHABLE where there is no path or a point is invalid,
    0 on the diagonal of valid points).
    """

    points: jnp.ndarray
    valid: jnp.ndarray
    cost: jnp.ndarray


def _cross(ux, uy, vx, vy):
    return ux * vy - uy * vx


def _unit(x, y):
    norm = jnp.sqrt(x * x + y * y)
    return x / jnp.maximum(norm, _TINY), y / jnp.maximum(norm, _TINY)


def _sq_dist_to_segment(px, py, ax, ay, bx, by):
    ex, ey = bx - ax, by - ay
    t = jnp.clip(((px - ax) * ex + (py - ay) * ey) / jnp.maximum(ex * ex + ey * ey, _TINY), 0.0, 1.0)
    dx, dy = px - (ax + t * ex), py - (ay + t * ey)
    return dx * dx + dy * dy


def visible(p, q, obstacles: Obstacles, radius=0.0) -> jnp.ndarray:
    """Whether a disc of `radius` can move along segments p -> q (..., 2): the segment crosses no obstacle edge
    (touching counts as crossing) and passes no edge closer than `radius`. An edge already within `radius` of
    p only blocks by crossing, so a human pressed against a wall can still see along it and away from it."""
    start, end, edge_valid = obstacle_lib.edges(obstacles)
    px, py, qx, qy = p[..., 0], p[..., 1], q[..., 0], q[..., 1]
    r2 = jnp.square(jnp.asarray(radius, jnp.float32))

    def blocked_by(e, blocked):
        ax, ay, bx, by = start[e, 0], start[e, 1], end[e, 0], end[e, 1]
        s1 = jnp.sign(_cross(bx - ax, by - ay, px - ax, py - ay))
        s2 = jnp.sign(_cross(bx - ax, by - ay, qx - ax, qy - ay))
        s3 = jnp.sign(_cross(qx - px, qy - py, ax - px, ay - py))
        s4 = jnp.sign(_cross(qx - px, qy - py, bx - px, by - py))
        crosses = (s1 * s2 <= 0) & (s3 * s4 <= 0) & ~((s1 == 0) & (s2 == 0))
        from_start = _sq_dist_to_segment(px, py, ax, ay, bx, by)
        near = jnp.minimum(
            jnp.minimum(from_start, _sq_dist_to_segment(qx, qy, ax, ay, bx, by)),
            jnp.minimum(_sq_dist_to_segment(ax, ay, px, py, qx, qy), _sq_dist_to_segment(bx, by, px, py, qx, qy)),
        )
        too_close = (near < r2) & (from_start >= r2)
        return blocked | (edge_valid[e] & (crosses | too_close))

    blocked = jnp.zeros(jnp.broadcast_shapes(px.shape, qx.shape), bool)
    blocked = jax.lax.fori_loop(0, start.shape[0], blocked_by, blocked)
    return ~blocked


def _corner_points(obstacles: Obstacles, clearance):
    """Candidate points (M, V, 2, 2) and their validity (M, V, 2) before the clearance check."""
    v = obstacles.vertices
    num_v = v.shape[1]
    n = jnp.minimum(obstacles.num_vertices.astype(jnp.int32), num_v)[:, None]  # (M, 1)
    i = jnp.arange(num_v, dtype=jnp.int32)[None, :]
    prev = jnp.take_along_axis(v, ((i - 1) % jnp.maximum(n, 1))[..., None], axis=1)
    nxt = jnp.take_along_axis(v, ((i + 1) % jnp.maximum(n, 1))[..., None], axis=1)
    x, y = v[..., 0], v[..., 1]
    used = i < n
    # Polygon corner: outward normals of both edges (polygons are counter-clockwise, `Obstacles`: interior on
    # the left, so outward is right of each edge).
    in_x, in_y = _unit(x - prev[..., 0], y - prev[..., 1])
    out_x, out_y = _unit(nxt[..., 0] - x, nxt[..., 1] - y)
    n1x, n1y = in_y, -in_x
    n2x, n2y = out_y, -out_x
    bx, by = _unit(n1x + n2x, n1y + n2y)
    push = clearance / jnp.maximum(bx * n1x + by * n1y, _MIN_COS)
    convex = _cross(in_x, in_y, out_x, out_y) > 0.0
    corner = jnp.stack([x + bx * push, y + by * push], -1)
    # Wall end: beyond the end, on either side of the wall.
    dx, dy = _unit(x - nxt[..., 0], y - nxt[..., 1])  # away from the other end
    side = jnp.stack([-dy, dx], -1)
    ahead = jnp.stack([x + clearance * dx, y + clearance * dy], -1)
    wall = n == 2
    first = jnp.where(wall[..., None], ahead + clearance * side, corner)
    second = ahead - clearance * side
    points = jnp.stack([first, second], axis=2)
    ok = jnp.stack([used & (wall | ((n >= 3) & convex)), used & wall], axis=2)
    return points, ok


def _packed(points, ok):
    """The candidate points (M, V, 2, 2) as a flat list (N, 2), N = M * V when a slot holds 4 vertices or more:
    a polygon's corner i in the slot's entry i, a wall's four points in its entries 0-3 (its two ends, on either
    side). Every step's routing work grows with N, and only walls need a second point per vertex. With
    fewer vertices per slot, N = 2 * M * V."""
    num_v = points.shape[1]
    if num_v < 4:
        return points.reshape(-1, 2), ok.reshape(-1)
    wall = jnp.sum(ok[..., 1], axis=1) > 0  # (M,): only a wall's end has a second point
    i = jnp.arange(num_v)
    # a wall's entries 2 and 3 take the second points of its vertices 0 and 1
    second = jnp.take_along_axis(points[:, :, 1], jnp.clip(i - 2, 0, num_v - 1)[None, :, None], axis=1)
    second_ok = jnp.take_along_axis(ok[:, :, 1], jnp.clip(i - 2, 0, num_v - 1)[None, :], axis=1) & (i >= 2)
    use_second = wall[:, None] & (i >= 2)[None, :]
    flat = jnp.where(use_second[..., None], second, points[:, :, 0])
    flat_ok = jnp.where(use_second, second_ok, ok[:, :, 0])
    return flat.reshape(-1, 2), flat_ok.reshape(-1)


def build_roadmap(obstacles: Obstacles, clearance, radius=0.0) -> Roadmap:
    """The episode's roadmap for humans of radius up to `radius`, its points `clearance` (> radius) from the
    obstacles (see the module doc); links pass no edge closer than `radius`."""
    points, ok = _packed(*_corner_points(obstacles, jnp.asarray(clearance, jnp.float32)))
    # Dropped: points too close to another obstacle (a narrow gap) or inside a polygon.
    clear = obstacle_lib.clearance(points, obstacles) >= 0.95 * clearance
    valid = ok & clear
    link = visible(points[:, None, :], points[None, :, :], obstacles, radius) & valid[:, None] & valid[None, :]
    diff = points[:, None, :] - points[None, :, :]
    length = jnp.sqrt(jnp.sum(diff * diff, axis=-1))
    cost = jnp.where(link, length, UNREACHABLE)
    cost = jnp.where(jnp.eye(points.shape[0], dtype=bool) & valid[:, None], 0.0, cost)

    def relax(k, c):
        return jnp.minimum(c, jnp.minimum(c[:, k, None] + c[None, k, :], UNREACHABLE))

    cost = jax.lax.fori_loop(0, points.shape[0], relax, cost)
    return Roadmap(points=points, valid=valid, cost=cost)


def goal_costs(roadmap: Roadmap, goal, obstacles: Obstacles, radius=0.0) -> jnp.ndarray:
    """Shortest path length (N,) from every roadmap point to `goal` (2,) (UNREACHABLE where there is none)."""
    seen = visible(goal[None, :], roadmap.points, obstacles, radius) & roadmap.valid
    last_leg = jnp.where(seen, jnp.linalg.norm(roadmap.points - goal, axis=-1), UNREACHABLE)
    return jnp.minimum(jnp.min(roadmap.cost + last_leg[None, :], axis=1), UNREACHABLE)


def aim(roadmap: Roadmap, to_goal, position, goal, obstacles: Obstacles, radius=0.0):
    """Where a human at `position` (2,) heads for `goal` (2,): (target (2,), reachable () bool).

    `to_goal` is `goal_costs(roadmap, goal, obstacles)`. Among visible points of equal total length the one
    nearer the goal wins, so the human never turns back to a point it has already passed."""
    goal_in_sight = visible(position, goal, obstacles, radius)
    seen = visible(position[None, :], roadmap.points, obstacles, radius) & roadmap.valid
    first_leg = jnp.where(seen, jnp.linalg.norm(roadmap.points - position, axis=-1), UNREACHABLE)
    total = jnp.minimum(first_leg + to_goal, UNREACHABLE)
    best = jnp.min(total)
    # Ties (within float rounding) go to the point with the smaller remaining cost: the farther one on the path.
    candidates = total <= best * (1.0 + 1e-6) + 1e-6
    pick = jnp.argmin(jnp.where(candidates, to_goal, jnp.inf))
    reachable = goal_in_sight | (best < UNREACHABLE)
    via = jnp.where(best < UNREACHABLE, roadmap.points[pick], goal)
    return jnp.where(goal_in_sight, goal, via), reachable


@struct.dataclass
class Routing:
    """The humans' routing state of an episode: its roadmap (built for humans of radius up to `radius`, points
    `clearance` from the obstacles) and each human's goal costs `to_goal` (H, N) (`goal_costs` of its goal)."""

    roadmap: Roadmap
    to_goal: jnp.ndarray
    radius: jnp.ndarray
    clearance: jnp.ndarray


def _all_goal_costs(roadmap: Roadmap, goals, obstacles: Obstacles, radius):
    return jax.vmap(goal_costs, in_axes=(None, 0, None, None))(roadmap, goals, obstacles, radius)


def plan(obstacles: Obstacles, goals, radius, clearance) -> Routing:
    """An episode's routing (at reset): the roadmap of `obstacles` and the goal costs of `goals` (H, 2)."""
    radius = jnp.asarray(radius, jnp.float32)
    clearance = jnp.asarray(clearance, jnp.float32)
    roadmap = build_roadmap(obstacles, clearance, radius)
    return Routing(roadmap, _all_goal_costs(roadmap, goals, obstacles, radius), radius, clearance)


def replan(routing: Routing, goals, changed, obstacles: Obstacles) -> Routing:
    """`routing` with the goal costs of the humans whose goal `changed` (H,) recomputed for their `goals` (H, 2).

    Goals change rarely (every goal_change_interval, or on arrival), so under `vmap` only the environments with a
    change compute any (`cond_gathered`)."""

    def recompute(routing, goals, changed, obstacles):
        fresh = _all_goal_costs(routing.roadmap, goals, obstacles, routing.radius)
        return routing.replace(to_goal=jnp.where(changed[:, None], fresh, routing.to_goal))

    def keep(routing, goals, changed, obstacles):
        return routing

    return cond_gathered(jnp.any(changed), recompute, keep, routing, goals, changed, obstacles)


def targets(routing: Routing, positions, goals, radii, obstacles: Obstacles):
    """Where each human heads now: (targets (H, 2), aims_at_goal (H,) bool: the target is the goal itself,
    reachable (H,) bool: a path to the goal exists)."""
    aimed = jax.vmap(aim, in_axes=(None, 0, 0, 0, None, 0))
    target, reachable = aimed(routing.roadmap, routing.to_goal, positions, goals, obstacles, radii)
    at_goal = jnp.all(target == goals, axis=-1)
    return target, at_goal, reachable
