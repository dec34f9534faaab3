"""Routing among obstacles: the roadmap's points and shortest paths, and where a human heads."""

from __future__ import annotations

import heapq
import itertools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from tgrf_jax.env import obstacles as obstacle_lib
from tgrf_jax.env import routing

CLEARANCE = 0.4


def _layout(*polygons, slots=None, max_vertices=4):
    return obstacle_lib.from_polygons([np.asarray(p, float) for p in polygons], slots or len(polygons), max_vertices)


def _box(cx, cy, hx, hy):
    return [(cx - hx, cy - hy), (cx + hx, cy - hy), (cx + hx, cy + hy), (cx - hx, cy + hy)]


def _dijkstra(points, valid, obstacles, radius):
    """Reference all-pairs shortest paths over the same visibility links, one Dijkstra per source."""
    n = len(points)
    link = np.asarray(routing.visible(jnp.asarray(points)[:, None], jnp.asarray(points)[None, :], obstacles, radius))
    out = np.full((n, n), routing.UNREACHABLE)
    for s in range(n):
        if not valid[s]:
            continue
        dist = {s: 0.0}
        heap = [(0.0, s)]
        while heap:
            d, u = heapq.heappop(heap)
            if d > dist.get(u, np.inf):
                continue
            for v in range(n):
                if valid[v] and link[u, v] and v != u:
                    nd = d + float(np.linalg.norm(points[u] - points[v]))
                    if nd < dist.get(v, np.inf):
                        dist[v] = nd
                        heapq.heappush(heap, (nd, v))
        for v, d in dist.items():
            out[s, v] = d
    return out


def test_box_corners_are_pushed_out_by_the_clearance():
    obstacles = _layout(_box(0, 0, 1, 0.5))
    roadmap = routing.build_roadmap(obstacles, CLEARANCE)
    points = np.asarray(roadmap.points)[np.asarray(roadmap.valid)]
    assert len(points) == 4  # one per convex corner, none for a box's second slots
    # CLEARANCE from both edges' lines, so sqrt(2) x CLEARANCE from a right-angled corner
    clearance = np.asarray(obstacle_lib.clearance(jnp.asarray(points), obstacles))
    np.testing.assert_allclose(clearance, CLEARANCE * np.sqrt(2.0), rtol=1e-5)


def test_packing_keeps_every_candidate_point_of_boxes_and_walls():
    rng = np.random.default_rng(1)
    boxes = [_box(*rng.uniform(-4, 4, 2), *rng.uniform(0.3, 1.0, 2)) for _ in range(3)]
    walls = [[tuple(rng.uniform(-4, 4, 2)), tuple(rng.uniform(-4, 4, 2))] for _ in range(2)]
    obstacles = _layout(*boxes, *walls, max_vertices=4)
    points, ok = routing._corner_points(obstacles, jnp.float32(CLEARANCE))
    packed, packed_ok = routing._packed(points, ok)
    assert packed.shape == (5 * 4, 2)  # one entry per vertex slot
    expected = np.asarray(points)[np.asarray(ok)]
    kept = np.asarray(packed)[np.asarray(packed_ok)]
    assert len(expected) == 3 * 4 + 2 * 4
    np.testing.assert_array_equal(np.sort(kept, axis=0), np.sort(expected, axis=0))


def test_floyd_warshall_matches_dijkstra_on_random_layouts():
    rng = np.random.default_rng(0)
    for _ in range(5):
        boxes = [_box(*rng.uniform(-4, 4, 2), *rng.uniform(0.3, 1.0, 2)) for _ in range(4)]
        wall = [tuple(rng.uniform(-4, 4, 2)), tuple(rng.uniform(-4, 4, 2))]
        obstacles = _layout(*boxes, wall, max_vertices=4)
        roadmap = routing.build_roadmap(obstacles, CLEARANCE, 0.3)
        points, valid = np.asarray(roadmap.points), np.asarray(roadmap.valid)
        np.testing.assert_allclose(np.asarray(roadmap.cost), _dijkstra(points, valid, obstacles, 0.3), rtol=1e-5)


def test_a_goal_behind_a_wall_is_reached_around_its_end():
    wall = [(-3.0, 0.0), (3.0, 0.0)]  # a 6 m wall across the way
    obstacles = _layout(wall, max_vertices=2)
    roadmap = routing.build_roadmap(obstacles, CLEARANCE)
    position, goal = jnp.array([0.5, -2.0]), jnp.array([0.5, 2.0])
    to_goal = routing.goal_costs(roadmap, goal, obstacles)
    target, reachable = routing.aim(roadmap, to_goal, position, goal, obstacles)
    target = np.asarray(target)
    assert bool(reachable)
    assert abs(target[0]) > 3.0 and target[1] < 0.0  # beyond an end of the wall, on the human's side
    # walking to the target and aiming again heads for the goal side, then for the goal itself
    target2, _ = routing.aim(roadmap, to_goal, jnp.asarray(target), goal, obstacles)
    assert np.asarray(target2)[1] > 0.0
    target3, _ = routing.aim(roadmap, to_goal, target2, goal, obstacles)
    np.testing.assert_allclose(np.asarray(target3), np.asarray(goal))


def test_a_human_walking_the_route_arrives():
    room = [(-2.0, -2.0), (2.0, -2.0), (2.0, 2.0), (-2.0, 2.0)]
    # a U-shaped alcove: three walls around the human, the opening away from the goal
    walls = [[(-1.0, -1.0), (1.0, -1.0)], [(1.0, -1.0), (1.0, 1.0)], [(-1.0, -1.0), (-1.0, 1.0)]]
    obstacles = _layout(*walls, slots=4, max_vertices=2)
    del room
    roadmap = routing.build_roadmap(obstacles, CLEARANCE)
    goal = jnp.array([0.0, -3.0])
    to_goal = routing.goal_costs(roadmap, goal, obstacles)
    position = jnp.array([0.0, 0.0])
    step = jax.jit(lambda p: routing.aim(roadmap, to_goal, p, goal, obstacles))
    for _ in range(200):
        target, reachable = step(position)
        assert bool(reachable)
        heading = target - position
        dist = float(jnp.linalg.norm(heading))
        if float(jnp.linalg.norm(goal - position)) < 0.05:
            break
        move = heading / max(dist, 1e-9) * min(0.1, dist)
        assert bool(routing.visible(position, position + move, obstacles))  # never walks through a wall
        position = position + move
    np.testing.assert_allclose(np.asarray(position), np.asarray(goal), atol=0.05)


def test_an_enclosed_goal_is_flagged_unreachable_without_nans():
    obstacles = _layout(_box(0, 0, 1, 1))
    ring = [[(-2, -2), (2, -2)], [(2, -2), (2, 2)], [(2, 2), (-2, 2)], [(-2, 2), (-2, -2)]]
    obstacles = _layout(*ring, slots=4, max_vertices=2)
    roadmap = routing.build_roadmap(obstacles, CLEARANCE)
    goal = jnp.array([0.0, 0.0])
    to_goal = routing.goal_costs(roadmap, goal, obstacles)
    target, reachable = routing.aim(roadmap, to_goal, jnp.array([3.0, 3.0]), goal, obstacles)
    assert not bool(reachable)
    assert np.all(np.isfinite(np.asarray(target)))


@pytest.mark.parametrize("gap", [0.5, 1.2])
def test_a_gap_narrower_than_a_human_is_routed_around(gap):
    radius = 0.3
    left, right = _box(-1.0 - gap / 2, 0.0, 1.0, 0.5), _box(1.0 + gap / 2, 0.0, 1.0, 0.5)
    obstacles = _layout(left, right)
    roadmap = routing.build_roadmap(obstacles, radius + 0.1, radius)
    position, goal = jnp.array([0.0, -2.0]), jnp.array([0.0, 2.0])
    to_goal = routing.goal_costs(roadmap, goal, obstacles, radius)
    target, reachable = routing.aim(roadmap, to_goal, position, goal, obstacles, radius)
    assert bool(reachable)
    through_gap = np.allclose(np.asarray(target), np.asarray(goal))
    assert through_gap == (gap > 2 * radius)


def test_roadmap_is_batched_under_vmap():
    layouts = [_layout(_box(x, 0, 0.5, 0.5), slots=2) for x in (-1.0, 0.0, 1.0)]
    batch = jax.tree.map(lambda *x: jnp.stack(x), *layouts)
    roadmaps = jax.vmap(routing.build_roadmap, in_axes=(0, None))(batch, CLEARANCE)
    for i, layout in enumerate(layouts):
        single = routing.build_roadmap(layout, CLEARANCE)
        for a, b in itertools.zip_longest(jax.tree.leaves(single), jax.tree.leaves(roadmaps)):
            np.testing.assert_array_equal(np.asarray(a), np.asarray(b)[i])
