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
    f = lambda x: np.asarray(x, np.float32)  # noqa: E731
    return Scene(f(pos), f(vel), f(radius), pref_towards(f(pos), f(goal)), f(max_speed))


def make_sim(scene: Scene, *, time_horizon, dt, neighbor_dist, max_neighbors) -> rvo2.PyRVOSimulator:
    sim = rvo2.PyRVOSimulator(dt, neighbor_dist, max_neighbors, time_horizon, time_horizon, 0.3, 1.0)
    for i in range(len(scene.radius)):
        sim.addAgent(tuple(map(float, scene.pos[i])), neighbor_dist, max_neighbors, time_horizon, time_horizon,
                     float(scene.radius[i]), float(scene.max_speed[i]), tuple(map(float, scene.vel[i])))
        sim.setAgentPrefVelocity(i, tuple(map(float, scene.pref[i])))
    return sim


def rvo2_step(scene: Scene, **settings) -> np.ndarray:
    """New velocities (N, 2) after one RVO2 doStep from ``scene``."""
    sim = make_sim(scene, **settings)
    sim.doStep()
    return np.array([sim.getAgentVelocity(i) for i in range(len(scene.radius))], np.float32)


def error_summary(errors: np.ndarray, tol: float = 1e-3) -> dict:
    """Distribution of per-agent velocity errors (m/s)."""
    e = np.asarray(errors, np.float64).ravel()
    return dict(n=int(e.size), max=float(e.max()), p99=float(np.quantile(e, 0.99)),
                p50=float(np.median(e)), frac_within=float(np.mean(e <= tol)), tol=tol)
