"""Python-RVO2 reference runs and random scenes shared by the ORCA fidelity tests and benchmark.

All scene arrays are float32 numpy; RVO2 receives exactly the same float32 values (as Python floats), so both
solvers start from bit-identical states.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import rvo2

ENV_SETTINGS = dict(time_horizon=5.0, dt=0.25, neighbor_dist=10.0, max_neighbors=19)


@dataclasses.dataclass
class Scene:
    pos: np.ndarray  # (N, 2)
    vel: np.ndarray  # (N, 2)
    radius: np.ndarray  # (N,)
    pref: np.ndarray  # (N, 2)
    max_speed: np.ndarray  # (N,)


def pref_towards(pos, goal):
    """Unit vector to the goal, the raw vector when closer than 1 m (the environment's preferred velocity)."""
    d = goal - pos
    norm = np.linalg.norm(d, axis=-1, keepdims=True)
    return (d / np.maximum(norm, 1.0)).astype(np.float32)


def random_scene(rng: np.random.Generator, n: int = 20, side: float = 8.0) -> Scene:
    """n agents uniformly in a side x side square with random velocities and goals.

    Radii are U(0.3, 0.5) + 0.16 (the environment's human radius plus ORCA padding), max speeds U(0.5, 1.5).
    Small ``side`` gives dense, overlapping scenes where the 2-D LP is often infeasible.
    """
    pos = rng.uniform(-side / 2, side / 2, (n, 2))
    radius = rng.uniform(0.3, 0.5, n) + 0.16
    max_speed = rng.uniform(0.5, 1.5, n)
    ang = rng.uniform(0, 2 * np.pi, n)
    speed = rng.uniform(0, 1, n) * max_speed
    vel = np.stack([np.cos(ang), np.sin(ang)], -1) * speed[:, None]
    goal = rng.uniform(-side / 2 - 2, side / 2 + 2, (n, 2))
    f = lambda x: np.asarray(x, np.float32)
    return Scene(f(pos), f(vel), f(radius), pref_towards(f(pos), f(goal)), f(max_speed))


def make_sim(
    scene: Scene, *, time_horizon, dt, neighbor_dist, max_neighbors, obstacles=None, time_horizon_obst=None
) -> rvo2.PyRVOSimulator:
    """An RVO2 simulator holding the scene's agents and, optionally, obstacles (vertices (M, V, 2),
    num_vertices (M,)), added slot by slot as ``orca.solve`` reads them, then processed (the kd-tree)."""
    th_obst = time_horizon if time_horizon_obst is None else time_horizon_obst
    sim = rvo2.PyRVOSimulator(dt, neighbor_dist, max_neighbors, time_horizon, th_obst, 0.3, 1.0)
    for i in range(len(scene.radius)):
        sim.addAgent(
            tuple(map(float, scene.pos[i])),
            neighbor_dist,
            max_neighbors,
            time_horizon,
            th_obst,
            float(scene.radius[i]),
            float(scene.max_speed[i]),
            tuple(map(float, scene.vel[i])),
        )
        sim.setAgentPrefVelocity(i, tuple(map(float, scene.pref[i])))
    if obstacles is not None:
        for polygon in polygons(*obstacles):
            sim.addObstacle([tuple(map(float, v)) for v in polygon])
        sim.processObstacles()
    return sim


def rvo2_step(scene: Scene, **settings) -> np.ndarray:
    """New velocities (N, 2) after one RVO2 doStep from ``scene`` (settings as :func:`make_sim`'s)."""
    sim = make_sim(scene, **settings)
    sim.doStep()
    return np.array([sim.getAgentVelocity(i) for i in range(len(scene.radius))], np.float32)


# ---------------------------------------------------------------------------------------------------------
# static obstacles: polygons counter-clockwise (RVO2's addObstacle), 2 vertices = a wall segment


def polygons(vertices, num_vertices):
    """The used slots of (vertices (M, V, 2), num_vertices (M,)) as a list of (n, 2) arrays (RVO2 ignores
    polygons of fewer than 2 vertices)."""
    return [np.asarray(vertices[m, :n]) for m, n in enumerate(np.asarray(num_vertices)) if n >= 2]


def pack_obstacles(polys, slots: int, max_vertices: int):
    """(vertices (slots, max_vertices, 2) float32, num_vertices (slots,) int32) holding ``polys`` first."""
    vertices = np.zeros((slots, max_vertices, 2), np.float32)
    counts = np.zeros((slots,), np.int32)
    for m, p in enumerate(polys):
        vertices[m, : len(p)] = p
        counts[m] = len(p)
    return vertices, counts


def _rotated(points, centre, angle):
    c, s = np.cos(angle), np.sin(angle)
    p = np.asarray(points, np.float64)
    return np.stack([centre[0] + c * p[:, 0] - s * p[:, 1], centre[1] + s * p[:, 0] + c * p[:, 1]], -1)


def box(centre, half_w, half_h, angle=0.0):
    """A rectangle (convex 4-gon), counter-clockwise."""
    return _rotated([(-half_w, -half_h), (half_w, -half_h), (half_w, half_h), (-half_w, half_h)], centre, angle)


def l_shape(centre, size, thickness, angle=0.0):
    """An L (non-convex 6-gon, one reflex vertex), counter-clockwise: legs of length ``size`` along +x and +y."""
    s, t = size, thickness
    return _rotated([(0, 0), (s, 0), (s, t), (t, t), (t, s), (0, s)], centre, angle)


def wall(a, b):
    """A wall segment: RVO2 makes it two directed edges a -> b and b -> a."""
    return np.array([a, b], np.float64)


def random_obstacles(rng: np.random.Generator, kind: str, side: float = 10.0) -> list:
    """Polygons of one random layout in a side x side square: 'walls' (2-4 segments), 'boxes' (2-8 rotated
    boxes), 'mixed' (L shapes, boxes and a wall), 'doorway' (a wall across with a gap, and a box), 'corridor'
    (two parallel walls with an L at one end)."""
    h = side / 2
    u = lambda lo, hi, size=None: rng.uniform(lo, hi, size)
    if kind == "walls":
        out = []
        for _ in range(rng.integers(2, 5)):
            a = u(-h, h, 2)
            ang = u(0, 2 * np.pi)
            out.append(wall(a, a + u(2, 6) * np.array([np.cos(ang), np.sin(ang)])))
        return out
    if kind == "boxes":
        return [box(u(-h, h, 2), u(0.2, 0.9), u(0.2, 0.9), u(0, np.pi)) for _ in range(rng.integers(2, 9))]
    if kind == "mixed":
        out = [l_shape(u(-h, h, 2), u(1.5, 3), u(0.3, 0.8), u(0, 2 * np.pi)) for _ in range(rng.integers(1, 4))]
        out += [box(u(-h, h, 2), u(0.2, 0.8), u(0.2, 0.8), u(0, np.pi)) for _ in range(rng.integers(1, 4))]
        a = u(-h, h, 2)
        return out + [wall(a, a + u(-4, 4, 2))]
    if kind == "doorway":
        y, x, gap = u(-2, 2), u(-2, 2), u(0.6, 1.0)
        out = [wall((-h - 2, y), (x - gap, y)), wall((x + gap, y), (h + 2, y))]
        return out + [box(u(-h, h, 2), u(0.2, 0.8), u(0.2, 0.8), u(0, np.pi))]
    if kind == "corridor":
        w = u(1.0, 2.0)
        out = [wall((-w, -h), (-w, h)), wall((w, h), (w, -h))]
        return out + [l_shape((u(-w, w - 1.0), h - 1.0), 1.2, 0.4, u(0, 2 * np.pi))]
    raise ValueError(kind)


OBSTACLE_KINDS = ("walls", "boxes", "mixed", "doorway", "corridor")


def scene_near_obstacles(rng: np.random.Generator, polys, n: int = 20, side: float = 10.0, near: float = 0.3) -> Scene:
    """``random_scene``-like agents in a side x side square, a share ``near`` of them placed just off an
    obstacle edge (on its outer side, the centre at the radius plus U(-0.05, 0.15) from the edge: touching,
    slightly overlapping or close), with random velocities and goals."""
    scene = random_scene(rng, n, side)
    edges = [(p[i], p[(i + 1) % len(p)]) for p in polys for i in range(len(p))]
    pos = scene.pos.astype(np.float64)
    for i in np.flatnonzero(rng.uniform(size=n) < near):
        a, b = edges[rng.integers(len(edges))]
        d = b - a
        normal = np.array([d[1], -d[0]]) / max(np.linalg.norm(d), 1e-9)  # the right side of a -> b: outside
        pos[i] = a + rng.uniform(0.05, 0.95) * d + normal * (scene.radius[i] + rng.uniform(-0.05, 0.15))
    goal = rng.uniform(-side / 2 - 2, side / 2 + 2, (n, 2))
    pos = pos.astype(np.float32)
    return Scene(pos, scene.vel, scene.radius, pref_towards(pos, goal.astype(np.float32)), scene.max_speed)


def error_summary(errors: np.ndarray, tol: float = 1e-3) -> dict:
    """Distribution of per-agent velocity errors (m/s)."""
    e = np.asarray(errors, np.float64).ravel()
    return dict(
        n=int(e.size),
        max=float(e.max()),
        p99=float(np.quantile(e, 0.99)),
        p50=float(np.median(e)),
        frac_within=float(np.mean(e <= tol)),
        tol=tol,
    )
