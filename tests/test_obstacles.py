"""Static obstacles: polygon geometry, occlusion, the simulated LiDAR, validation and the Social Force wall term."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from tgrf_jax.config import ConfigError
from tgrf_jax.env import obstacles as ob
from tgrf_jax.env import social_force

BOX = [(0.0, 0.0), (2.0, 0.0), (2.0, 1.0), (0.0, 1.0)]  # [0, 2] x [0, 1], counter-clockwise
L_SHAPE = [(0.0, 0.0), (2.0, 0.0), (2.0, 1.0), (1.0, 1.0), (1.0, 2.0), (0.0, 2.0)]  # notch at [1, 2] x [1, 2]
NO_DISCS = (jnp.zeros((0, 2)), jnp.zeros((0,)), jnp.zeros((0,), bool))

# Jitted once each: run eagerly, every jnp operation compiles on its own for every new shape (3x slower here).
distance = jax.jit(ob.distance_to_obstacles)
inside = jax.jit(ob.inside)
clearance = jax.jit(ob.clearance)
swept = jax.jit(ob.swept_distance)
sight = jax.jit(ob.line_of_sight)
wall_force = jax.jit(ob.wall_force)
lidar = jax.jit(ob.lidar_scan, static_argnames="num_rays")
sf_step = jax.jit(social_force.step)


def scan(origin, heading, obstacles, discs=NO_DISCS, num_rays=8, max_range=100.0):
    return np.asarray(
        lidar(
            jnp.asarray(origin, jnp.float32),
            jnp.float32(heading),
            obstacles,
            *discs,
            num_rays=num_rays,
            max_range=max_range,
        )
    )


def discs(*specs, mask=None):
    pos = jnp.array([s[0] for s in specs], jnp.float32)
    radius = jnp.array([s[1] for s in specs], jnp.float32)
    return pos, radius, jnp.ones(len(specs), bool) if mask is None else jnp.asarray(mask)


# ---------------------------------------------------------------------------------------------- LiDAR


def test_ray_hits_wall_at_the_analytic_distance():
    wall = ob.from_polygons([[(3.0, -10.0), (3.0, 10.0)]])
    origin = np.array([0.5, 0.2])
    for heading in (0.0, 0.3, -0.5, 0.9, -1.2, 1.3):
        ranges = scan(origin, heading, wall, num_rays=8)
        # The rays' float32 angles, so that the reference checks the intersection, not the angle's rounding.
        angles = np.float32(heading) + np.float32(2 * np.pi / 8) * np.arange(8, dtype=np.float32)
        angles = angles.astype(np.float64)
        for k, angle in enumerate(angles):
            t = (3.0 - origin[0]) / np.cos(angle) if np.cos(angle) > 1e-9 else np.inf
            y = origin[1] + t * np.sin(angle) if np.isfinite(t) else np.inf
            want = t if abs(y) <= 10.0 else 100.0
            assert ranges[k] == pytest.approx(min(want, 100.0), abs=1e-5), (heading, k)
    # Perpendicular exactly, and from the other side through the same wall.
    assert scan(origin, 0.0, wall)[0] == pytest.approx(2.5, abs=1e-6)
    assert scan([6.0, 0.0], np.pi, wall)[0] == pytest.approx(3.0, abs=1e-5)


def test_ray_hits_disc_at_the_analytic_distance():
    center, r = np.array([4.0, 1.0]), 0.5
    d = discs((center, r))
    toward = math.atan2(1.0, 4.0)
    assert scan([0.0, 0.0], toward, ob.empty(), d)[0] == pytest.approx(np.hypot(4, 1) - r, abs=1e-5)
    for offset in (0.05, -0.08, 0.1):  # off-centre rays: entry at b - sqrt(r^2 - h^2)
        heading = toward + offset
        along, h = np.hypot(4, 1) * np.cos(offset), np.hypot(4, 1) * np.sin(offset)
        want = along - np.sqrt(r * r - h * h)
        assert scan([0.0, 0.0], heading, ob.empty(), d)[0] == pytest.approx(want, abs=1e-5), offset
    # A ray passing beside the disc misses it.
    assert scan([0.0, 0.0], toward + 0.3, ob.empty(), d, max_range=20.0)[0] == 20.0


def test_nearest_hit_wins_and_masked_discs_are_not_there():
    obstacles = ob.from_polygons([[(5.0, -1.0), (5.0, 1.0)], [(7.0, -1.0), (8.0, -1.0), (8.0, 1.0), (7.0, 1.0)]])
    d = discs(([3.0, 0.0], 0.5), ([10.0, 0.0], 1.0))
    assert scan([0.0, 0.0], 0.0, obstacles, d)[0] == pytest.approx(2.5, abs=1e-6)
    no_near_disc = (d[0], d[1], jnp.array([False, True]))
    assert scan([0.0, 0.0], 0.0, obstacles, no_near_disc)[0] == pytest.approx(5.0, abs=1e-6)
    only_box = ob.from_polygons([[(7.0, -1.0), (8.0, -1.0), (8.0, 1.0), (7.0, 1.0)]])
    assert scan([0.0, 0.0], 0.0, only_box, no_near_disc)[0] == pytest.approx(7.0, abs=1e-6)
    assert scan([0.0, 0.0], 0.0, ob.empty(), no_near_disc)[0] == pytest.approx(9.0, abs=1e-6)


def test_misses_return_max_range():
    assert np.all(scan([0.0, 0.0], 0.4, ob.empty(), max_range=7.5) == 7.5)
    wall = ob.from_polygons([[(3.0, -1.0), (3.0, 1.0)]])
    ranges = scan([0.0, 0.0], 0.0, wall, num_rays=4, max_range=7.5)
    np.testing.assert_allclose(ranges, [3.0, 7.5, 7.5, 7.5], atol=1e-6)  # only ray 0 points at the wall
    assert scan([0.0, 0.0], 0.0, wall, max_range=2.0)[0] == 2.0  # beyond the range: capped


def test_ray_zero_follows_the_heading_and_rays_turn_counter_clockwise():
    num_rays = 36
    step = 2 * np.pi / num_rays
    for heading in (0.0, 1.0, -2.5):
        target = 5.0 * np.array([np.cos(heading), np.sin(heading)])
        ranges = scan([0.0, 0.0], heading, ob.empty(), discs((target, 0.3)), num_rays=num_rays, max_range=50.0)
        assert ranges[0] == pytest.approx(4.7, abs=1e-5) and np.all(ranges[1:] == 50.0), heading
    # A disc one step counter-clockwise of the heading is seen by ray 1, not by ray R - 1.
    target = 5.0 * np.array([np.cos(1.0 + step), np.sin(1.0 + step)])
    ranges = scan([0.0, 0.0], 1.0, ob.empty(), discs((target, 0.3)), num_rays=num_rays, max_range=50.0)
    assert ranges[1] == pytest.approx(4.7, abs=1e-5) and ranges[-1] == 50.0 and ranges[0] == 50.0


def test_origin_inside_a_disc_or_polygon_blocks_the_sensor():
    assert np.all(scan([0.1, 0.0], 0.0, ob.empty(), discs(([0.0, 0.0], 0.5))) == 0.0)
    assert np.all(scan([1.0, 0.5], 0.0, ob.from_polygons([BOX])) == 0.0)
    masked = discs(([0.0, 0.0], 0.5), mask=[False])
    assert np.all(scan([0.1, 0.0], 0.0, ob.empty(), masked) == 100.0)


# ---------------------------------------------------------------------------------------------- occlusion


def test_line_of_sight_blocked_behind_a_wall_and_clear_beside_it():
    wall = ob.from_polygons([[(2.0, -1.0), (2.0, 1.0)]])
    targets = jnp.array([[4.0, 0.0], [4.0, 3.0], [1.0, 0.0], [4.0, -0.9], [0.0, 5.0]])
    np.testing.assert_array_equal(sight(jnp.zeros(2), targets, wall), [False, True, True, False, True])
    box = ob.from_polygons([[(2.0, -1.0), (3.0, -1.0), (3.0, 1.0), (2.0, 1.0)]])
    np.testing.assert_array_equal(sight(jnp.zeros(2), targets, box), [False, True, True, False, True])
    assert bool(jnp.all(sight(jnp.zeros(2), targets, ob.empty())))


# ---------------------------------------------------------------------------------------------- geometry


def test_inside_clearance_and_distance_on_a_box():
    box = ob.from_polygons([BOX])
    points = jnp.array([[1.0, 0.5], [1.8, 0.5], [3.0, 0.5], [3.0, 2.0], [1.0, -0.25]])
    np.testing.assert_array_equal(inside(points, box), [True, True, False, False, False])
    np.testing.assert_allclose(distance(points, box), [0.5, 0.2, 1.0, np.sqrt(2), 0.25], atol=1e-6)
    np.testing.assert_allclose(clearance(points, box), [-0.5, -0.2, 1.0, np.sqrt(2), 0.25], atol=1e-6)


def test_inside_clearance_and_distance_on_a_non_convex_polygon():
    ell = ob.from_polygons([L_SHAPE])
    points = jnp.array([[0.5, 0.5], [1.5, 0.5], [0.5, 1.5], [1.5, 1.5], [1.2, 1.1], [2.5, 2.5], [0.9, 1.8]])
    np.testing.assert_array_equal(inside(points, ell), [True, True, True, False, False, False, True])
    np.testing.assert_allclose(
        clearance(points, ell), [-0.5, -0.5, -0.5, 0.5, 0.1, np.hypot(0.5, 1.5), -0.1], atol=1e-6
    )
    # Diagonally off the convex corner (2, 0) the corner itself is the nearest point.
    np.testing.assert_allclose(distance(jnp.array([[2.3, -0.4]]), ell), [0.5], atol=1e-6)


def test_swept_distance_catches_a_motion_through_a_thin_wall():
    wall = ob.from_polygons([[(0.0, -1.0), (0.0, 1.0)]])
    p0 = jnp.array([[-5.0, 0.0], [-5.0, 2.0], [1.0, -3.0], [3.0, 0.5], [-0.5, 0.0]])
    p1 = jnp.array([[5.0, 0.0], [5.0, 2.0], [1.0, 3.0], [3.0, 0.5], [-0.5, 0.0]])
    # Both endpoints of the first motion are 5 m from the wall, yet it crosses it.
    np.testing.assert_allclose(distance(p0[:1], wall), [5.0])
    np.testing.assert_allclose(swept(p0, p1, wall), [0.0, 1.0, 1.0, 3.0, 0.5], atol=1e-6)
    assert np.isinf(swept(p0, p1, ob.empty())).all()


def test_unused_slots_and_vertices_are_ignored():
    # The same shapes as `messy` below (one compile per function), only the values differ.
    clean = ob.from_polygons([[(0.0, 0.0), (1.0, 0.0), (0.0, 1.0)]], num_slots=3, max_vertices=5)
    # Unused slot 1 holds a box around every test point, unused slot 2 a wall across the scene, and slot 0
    # garbage beyond its 3 vertices: all must be ignored.
    vertices = np.zeros((3, 5, 2), np.float32)
    vertices[0, :3] = [(0.0, 0.0), (1.0, 0.0), (0.0, 1.0)]
    vertices[0, 3:] = [(9.0, 9.0), (-9.0, 9.0)]
    vertices[1, :4] = [(-20.0, -20.0), (20.0, -20.0), (20.0, 20.0), (-20.0, 20.0)]
    vertices[2, :2] = [(-20.0, 1.5), (20.0, 1.5)]
    messy = ob.Obstacles(vertices=jnp.asarray(vertices), num_vertices=jnp.array([3, 0, 0], jnp.int32))
    points = jnp.array([[0.2, 0.2], [2.0, 2.0], [-1.0, 0.5], [5.0, 8.0]])
    for fn in (distance, inside, clearance):
        np.testing.assert_array_equal(fn(points, messy), fn(points, clean))
    np.testing.assert_array_equal(swept(points, points[::-1], messy), swept(points, points[::-1], clean))
    targets = jnp.array([[3.0, -2.0], [0.5, 0.2], [-1.0, 0.5]])  # through slot 2's wall; into the triangle; clear
    np.testing.assert_array_equal(sight(jnp.array([3.0, 3.0]), targets, messy), [True, False, True])
    np.testing.assert_array_equal(sight(jnp.array([3.0, 3.0]), targets, clean), [True, False, True])
    np.testing.assert_array_equal(scan([3.0, 3.0], 0.2, messy, num_rays=16), scan([3.0, 3.0], 0.2, clean, num_rays=16))
    np.testing.assert_allclose(
        wall_force(points, jnp.full(4, 0.3), messy, a=2.0, b=0.5),
        wall_force(points, jnp.full(4, 0.3), clean, a=2.0, b=0.5),
        rtol=1e-6,
    )
    assert int(ob.edges(messy)[2].sum()) == 3


def test_no_slots_give_the_obstacle_free_answer():
    none = ob.empty(0, 4)
    points = jnp.array([[0.0, 0.0], [1.0, 2.0]])
    assert np.isinf(distance(points, none)).all() and np.isinf(clearance(points, none)).all()
    assert not inside(points, none).any() and sight(points[0], points, none).all()
    assert ob.edges(none)[0].shape == (0, 2)
    np.testing.assert_array_equal(wall_force(points, jnp.ones(2), none, a=2.0, b=0.5), np.zeros((2, 2)))
    np.testing.assert_array_equal(
        scan([0.0, 0.0], 0.0, none, discs(([2.0, 0.0], 0.5)), num_rays=4, max_range=9.0), [1.5, 9.0, 9.0, 9.0]
    )


def test_jit_vmap_and_finite_on_degenerate_input():
    box = ob.from_polygons([BOX, [(3.0, 0.0), (3.0, 1.0)]], num_slots=3, max_vertices=4)
    # A hand-built zero-length edge (check_polygons refuses it; the traced code must still stay finite).
    zero_edge = ob.Obstacles(vertices=box.vertices.at[2, :2].set(5.0), num_vertices=jnp.array([4, 2, 2], jnp.int32))
    batch = jax.tree_util.tree_map(lambda x, y: jnp.stack([x, y]), box, zero_edge)
    # On an edge, on a vertex, on the wall, on the zero-length edge, far away.
    points = jnp.array([[1.0, 0.0], [2.0, 1.0], [3.0, 0.5], [5.0, 5.0], [40.0, -7.0]])

    @jax.jit
    @jax.vmap
    def everything(obstacles):
        origin = points[0]
        return (
            ob.distance_to_obstacles(points, obstacles),
            ob.clearance(points, obstacles),
            ob.swept_distance(points, points, obstacles),
            ob.swept_distance(points, points[::-1], obstacles),
            ob.line_of_sight(origin, points, obstacles).astype(jnp.float32),
            ob.lidar_scan(
                origin,
                jnp.float32(0.0),
                obstacles,
                points,
                jnp.zeros(5),
                jnp.ones(5, bool),
                num_rays=16,
                max_range=10.0,
            ),
            ob.lidar_scan(
                points[3],
                jnp.float32(0.0),
                obstacles,
                points[:0],
                jnp.zeros(0),
                jnp.zeros(0, bool),
                num_rays=16,
                max_range=10.0,
            ),
            ob.wall_force(points, jnp.full(5, 0.3), obstacles, a=2.0, b=0.5),
        )

    outs = everything(batch)
    for out in outs:
        assert np.all(np.isfinite(np.asarray(out))), out
    np.testing.assert_allclose(outs[0][0, :3], 0.0, atol=1e-6)  # points on edges are at distance 0
    np.testing.assert_allclose(outs[2][:, 3], [np.hypot(2.0, 4.0), 0.0], atol=1e-5)  # zero-length motion


# ---------------------------------------------------------------------------------------------- validation


@pytest.mark.parametrize(
    "polygon, says",
    [
        ([(0.0, 0.0)], "2 (a wall segment)"),
        ([], "2 (a wall segment)"),
        ([(0.0, 0.0), (1.0, float("nan"))], "finite"),
        ([(0.0, 0.0), (float("inf"), 1.0)], "finite"),
        ([(0.0, 0.0), ("a", 1.0)], "pair of numbers"),
        ([(0.0, 0.0), ("1.5", 1.0)], "pair of numbers"),
        ([(0.0, 0.0), (1.0, 0.0, 2.0)], "pair of numbers"),
        ([(0.0, 0.0), None], "pair of numbers"),
        ([(0.0, 0.0), (0.0, 1.0), (1.0, 1.0), (1.0, 0.0)], "counter-clockwise"),
        ([(0.0, 0.0), (0.0, 0.0)], "zero-length edge"),
        ([(0.0, 0.0), (1.0, 0.0), (1.0, 0.0), (0.0, 1.0)], "zero-length edge"),
        ([(0.0, 0.0), (1.0, 0.0), (0.0, 1.0), (0.0, 0.0)], "zero-length edge"),
        ([(0.0, 0.0), (1.0, 1.0), (1.0, 0.0), (0.0, 1.0)], "intersects itself"),  # bow tie
        ([(0.0, 0.0), (4.0, 0.0), (4.0, 2.0), (2.0, -1.0), (0.0, 2.0)], "intersects itself"),
        ([(0.0, 0.0), (2.0, 0.0), (1.0, 0.0), (1.0, 1.0)], "intersects itself"),  # folds back on itself
        ([(0.0, 0.0), (1.0, 0.0), (2.0, 0.0)], "intersects itself"),  # collinear: the closing edge folds back
    ],
)
def test_check_polygons_names_the_field_and_the_polygon(polygon, says):
    good = [(0.0, 0.0), (1.0, 0.0)]
    with pytest.raises(ConfigError, match=r"env\.obstacles\[1\]") as err:
        ob.check_polygons([good, polygon], "env.obstacles")
    assert says in str(err.value)
    with pytest.raises(ConfigError, match="env.obstacles"):
        ob.check_polygons("not polygons", "env.obstacles")


def test_check_polygons_accepts_and_returns_floats():
    out = ob.check_polygons([L_SHAPE, [(0, 0), (3, 4)], np.array(BOX)], "obstacles")
    assert out[1] == ((0.0, 0.0), (3.0, 4.0)) and all(isinstance(c, float) for c in out[1][1])
    assert out[0] == tuple(map(tuple, L_SHAPE)) and out[2] == tuple(map(tuple, BOX))
    with pytest.raises(ConfigError, match="at most 1 polygons"):
        ob.from_polygons([BOX, BOX], num_slots=1, field="env.obstacles")
    with pytest.raises(ConfigError, match="at most 4"):
        ob.from_polygons([L_SHAPE], max_vertices=4)


# ---------------------------------------------------------------------------------------------- wall force


def test_wall_force_points_away_and_decays():
    wall = ob.from_polygons([[(0.0, -5.0), (0.0, 5.0)]])
    x = jnp.array([0.5, 1.0, 2.0, -1.0])
    positions = jnp.stack([x, jnp.zeros(4)], -1)
    force = np.asarray(wall_force(positions, jnp.full(4, 0.3), wall, a=2.0, b=0.5))
    np.testing.assert_allclose(force[:, 0], np.sign(x) * 2.0 * np.exp((0.3 - np.abs(x)) / 0.5), rtol=1e-5)
    np.testing.assert_array_equal(force[:, 1], 0.0)
    assert force[0, 0] > force[1, 0] > force[2, 0] > 0.0 and force[3, 0] < 0.0
    # Without obstacles, or with unused slots only, there is no force.
    for none in (ob.empty(), ob.empty(3, 4)):
        np.testing.assert_array_equal(wall_force(positions, jnp.full(4, 0.3), none, a=2.0, b=0.5), 0.0)


def test_wall_force_counts_a_corner_once_and_sums_over_polygons():
    box = ob.from_polygons([BOX])
    # Diagonally off the corner (2, 1): the nearest point is the corner, shared by two edges.
    p = jnp.array([[2.6, 1.8]])
    force = np.asarray(wall_force(p, jnp.array([0.2]), box, a=3.0, b=0.4))[0]
    d = np.hypot(0.6, 0.8)
    np.testing.assert_allclose(force, 3.0 * np.exp((0.2 - d) / 0.4) * np.array([0.6, 0.8]) / d, rtol=1e-5)
    # Two walls either side at the same distance cancel; two on the same side add.
    two = ob.from_polygons([[(-1.0, -5.0), (-1.0, 5.0)], [(1.0, -5.0), (1.0, 5.0)]])
    np.testing.assert_allclose(wall_force(jnp.zeros((1, 2)), jnp.array([0.3]), two, a=2.0, b=0.5), 0.0, atol=1e-6)
    same_side = ob.from_polygons([[(-1.0, -5.0), (-1.0, 5.0)], [(-1.0, 6.0), (-1.0, 7.0)]])
    single = ob.from_polygons([[(-1.0, -5.0), (-1.0, 5.0)]])
    f2 = wall_force(jnp.zeros((1, 2)), jnp.array([0.3]), same_side, a=2.0, b=0.5)[0, 0]
    f1 = wall_force(jnp.zeros((1, 2)), jnp.array([0.3]), single, a=2.0, b=0.5)[0, 0]
    assert f2 > f1 > 0.0


def test_wall_force_pushes_out_of_a_polygon():
    box = ob.from_polygons([BOX])
    force = np.asarray(wall_force(jnp.array([[1.9, 0.5], [1.0, 0.9]]), jnp.full(2, 0.3), box, a=2.0, b=0.5))
    assert force[0, 0] > 0.0 and abs(force[0, 1]) < 1e-6  # out through the right side
    assert force[1, 1] > 0.0 and abs(force[1, 0]) < 1e-6  # out through the top
    np.testing.assert_allclose(force[0, 0], 2.0 * np.exp((0.3 + 0.1) / 0.5), rtol=1e-5)


def _sf(obstacles, positions, velocities, step=sf_step):
    goals = jnp.array([[5.0, 0.0], [-5.0, 1.0], [0.0, 4.0]])
    return step(
        positions,
        velocities,
        goals,
        jnp.array([0.3, 0.4, 0.35]),
        jnp.array([1.0, 1.2, 0.8]),
        a=2.0,
        b=0.5,
        ki=1.0,
        dt=0.25,
        neighbor_mask=jnp.array([True, True, False]),
        obstacles=obstacles,
    )


def test_social_force_step_with_obstacles():
    positions = jnp.array([[0.0, 0.0], [1.0, 1.0], [-1.0, 2.0]])
    velocities = jnp.array([[0.5, 0.0], [-0.2, 0.1], [0.0, 0.3]])
    base = _sf(None, positions, velocities)

    # No obstacle slots: the very program of a step without obstacles, hence the same bits.
    def program(obstacles):
        return str(jax.make_jaxpr(lambda: _sf(obstacles, positions, velocities, step=social_force.step))())

    assert program(ob.empty(0, 4)) == program(None)
    assert program(ob.empty(1, 4)) != program(None)  # (the comparison can tell programs apart)
    np.testing.assert_array_equal(_sf(ob.empty(0, 4), positions, velocities), base)
    np.testing.assert_array_equal(_sf(ob.empty(2, 3), positions, velocities), base)  # unused slots: no force
    # A wall ahead of agent 0 (walking towards +x) slows it and turns it away.
    wall = ob.from_polygons([[(0.8, -3.0), (0.8, -0.5)]], num_slots=2, max_vertices=3)
    with_wall = np.asarray(_sf(wall, positions, velocities))
    assert with_wall[0, 0] < base[0, 0] and with_wall[0, 1] > base[0, 1]
    # Speeds below v_pref are not rescaled: the change is exactly the wall force times dt.
    push = wall_force(positions, jnp.array([0.3, 0.4, 0.35]), wall, a=2.0, b=0.5)
    np.testing.assert_allclose(with_wall[2] - base[2], push[2] * 0.25, atol=1e-6)
