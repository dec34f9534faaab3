"""Throughput of ``jax.jit(jax.vmap(tgrf_jax.env.orca.solve))`` against Python-RVO2's doStep on this machine.

    PYTHONPATH=. python benchmarks/orca_throughput.py [--quick] [--block both] [--batches 256 4096] [--no-rvo2]
        [--obstacles] [--out FILE]

Scenes are environment-like: N agents uniformly in a square whose area grows with N (about 3.2 m^2 per
agent, i.e. a 8 m square for 20), radii U(0.3, 0.5) + 0.16, max speeds U(0.5, 1.5), random current velocities
and goals; ORCA settings as in the environment (time horizon 5 s, dt 0.25 s, neighbour distance 10 m, all
other agents as neighbours).  These random "initial" scenes are dense: about 64% of the agents need
linearProgram3.  A second set, "crossing", holds mid-rollout states of circle crossings (20 agents on an 8 m
ring heading to the antipode, 200-step JAX rollouts, states of steps 40-120 sampled), where about 7% need it.
Timings: compile (first call) separately, then the median of several ``block_until_ready`` runs.

``--obstacles`` times static obstacles instead: 20 agents among 8 boxes per scene (an environment-like
``random_obstacles`` layout: half sides U(0.25, 0.75) m, rotated, centres in a 12 m square at least 0.6 m
apart; agents as above but outside the boxes; obstacle time horizon 5 s), the same scenes without their
obstacles (the cost of the obstacle lines, which includes rebuilding RVO2's kd-tree every call), and Python-RVO2
with the same layouts (processObstacles once per layout, as a simulator would), each ratio measured in the same
run.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import time

import jax
import jax.numpy as jnp
import numpy as np

from tgrf_jax import configure_cpu
from tgrf_jax.env import orca

SETTINGS = dict(time_horizon=5.0, dt=0.25, neighbor_dist=10.0)


def random_scenes(n_scenes: int, n_agents: int, seed: int = 0) -> dict:
    """Batch of environment-like scenes as float32 numpy arrays (leading axis: scene)."""
    rng = np.random.default_rng(seed)
    side = 8.0 * np.sqrt(n_agents / 20.0)
    shape = (n_scenes, n_agents)
    pos = rng.uniform(-side / 2, side / 2, shape + (2,))
    goal = rng.uniform(-side / 2 - 2, side / 2 + 2, shape + (2,))
    max_speed = rng.uniform(0.5, 1.5, shape)
    ang = rng.uniform(0, 2 * np.pi, shape)
    vel = np.stack([np.cos(ang), np.sin(ang)], -1) * (rng.uniform(0, 1, shape) * max_speed)[..., None]
    d = goal - pos
    pref = d / np.maximum(np.linalg.norm(d, axis=-1, keepdims=True), 1.0)
    f = lambda x: np.asarray(x, np.float32)
    return dict(
        pos=f(pos), vel=f(vel), radius=f(rng.uniform(0.3, 0.5, shape) + 0.16), pref=f(pref), max_speed=f(max_speed)
    )


def crossing_states(n_scenes: int, n_agents: int, seed: int = 0, n_rollouts: int = 64) -> dict:
    """``n_scenes`` states sampled from steps 40-120 of circle-crossing rollouts (the crowd crossing the centre).

    ``n_rollouts`` scenes: agents evenly on an 8 m ring (angles jittered by U(-0.1, 0.1) rad, positions by
    N(0, 0.05) m), goal the antipode, radii U(0.3, 0.5) + 0.16, max speeds U(0.5, 1.5), preferred velocity
    towards the goal (unit, or the raw offset within 1 m), rolled out with this solver (dt 0.25 s).
    """
    rng = np.random.default_rng(seed)
    ang = np.linspace(0, 2 * np.pi, n_agents, endpoint=False)[None] + rng.uniform(-0.1, 0.1, (n_rollouts, n_agents))
    pos0 = np.stack([np.cos(ang), np.sin(ang)], -1) * 8.0 + rng.normal(0, 0.05, (n_rollouts, n_agents, 2))
    f = lambda x: jnp.asarray(x, jnp.float32)
    pos0, goal = f(pos0), f(-pos0)
    radius = f(rng.uniform(0.3, 0.5, (n_rollouts, n_agents)) + 0.16)
    max_speed = f(rng.uniform(0.5, 1.5, (n_rollouts, n_agents)))
    solve = jax.vmap(lambda p, v, r, pr, m: orca.solve(p, v, r, pr, m, max_neighbors=n_agents - 1, **SETTINGS))

    @jax.jit
    def rollout(pos0):
        def step(carry, _):
            p, v = carry
            d = goal - p
            pref = d / jnp.maximum(jnp.linalg.norm(d, axis=-1, keepdims=True), 1.0)
            v = solve(p, v, radius, pref, max_speed)
            return (p + v * SETTINGS["dt"], v), (p, carry[1], pref)

        return jax.lax.scan(step, (pos0, jnp.zeros_like(pos0)), None, length=121)[1]

    p, v, pref = (np.asarray(x[40:121]).reshape((-1, n_agents, 2)) for x in rollout(pos0))
    steps = 121 - 40
    rad = np.broadcast_to(np.asarray(radius), (steps, n_rollouts, n_agents)).reshape(-1, n_agents)
    vmax = np.broadcast_to(np.asarray(max_speed), (steps, n_rollouts, n_agents)).reshape(-1, n_agents)
    idx = rng.integers(0, p.shape[0], n_scenes)
    return dict(pos=p[idx], vel=v[idx], radius=rad[idx], pref=pref[idx], max_speed=vmax[idx])


def rvo2_dostep_rate(n_agents: int, n_steps: int, seed: int = 0) -> float:
    """Python-RVO2 doSteps per second for one simulator of ``n_agents`` (the on-machine reference).

    Each step sets every agent's position, velocity and preferred velocity (from a pool of random scenes, so
    the kd-tree and LPs see fresh states) and calls doStep; the setter calls are included in the time, as an
    environment driving RVO2 from Python would pay them.
    """
    import rvo2  # imported here so that --no-rvo2 runs where the reference is not installed

    pool = random_scenes(16, n_agents, seed)
    sim = rvo2.PyRVOSimulator(
        SETTINGS["dt"],
        SETTINGS["neighbor_dist"],
        max(n_agents - 1, 0),
        SETTINGS["time_horizon"],
        SETTINGS["time_horizon"],
        0.3,
        1.0,
    )
    for i in range(n_agents):
        sim.addAgent(
            (0.0, 0.0),
            SETTINGS["neighbor_dist"],
            max(n_agents - 1, 0),
            SETTINGS["time_horizon"],
            SETTINGS["time_horizon"],
            float(pool["radius"][0, i]),
            float(pool["max_speed"][0, i]),
            (0.0, 0.0),
        )
    states = [
        [
            (
                tuple(map(float, pool["pos"][s, i])),
                tuple(map(float, pool["vel"][s, i])),
                tuple(map(float, pool["pref"][s, i])),
            )
            for i in range(n_agents)
        ]
        for s in range(16)
    ]
    start = time.perf_counter()
    for step in range(n_steps):
        for i, (p, v, pr) in enumerate(states[step % 16]):
            sim.setAgentPosition(i, p)
            sim.setAgentVelocity(i, v)
            sim.setAgentPrefVelocity(i, pr)
        sim.doStep()
    return n_steps / (time.perf_counter() - start)


TIME_HORIZON_OBST = 5.0
N_BOXES = 8


def box_layouts(n_scenes: int, seed: int = 0, n_boxes: int = N_BOXES, arena: float = 6.0) -> dict:
    """``n_scenes`` layouts of ``n_boxes`` boxes like the environment's ``random_obstacles`` scenario: centres
    U(-arena, arena)^2 whose circumcircles stay 0.6 m apart, half sides U(0.25, 0.75), angle U(0, pi/2).
    Returns vertices (S, n_boxes, 4, 2) counter-clockwise and num_vertices (S, n_boxes)."""
    rng = np.random.default_rng(seed)
    corners = np.array([[-1.0, -1.0], [1.0, -1.0], [1.0, 1.0], [-1.0, 1.0]])
    vertices = np.zeros((n_scenes, n_boxes, 4, 2), np.float32)
    for s in range(n_scenes):
        placed = []
        while len(placed) < n_boxes:
            c, half = rng.uniform(-arena, arena, 2), rng.uniform(0.25, 0.75, 2)
            reach = float(np.hypot(*half))
            if all(np.linalg.norm(c - c2) - reach - r2 >= 0.6 for c2, r2 in placed):
                a = rng.uniform(0, np.pi / 2)
                rot = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
                vertices[s, len(placed)] = c + (corners * half) @ rot.T
                placed.append((c, reach))
    return dict(vertices=vertices, num_vertices=np.full((n_scenes, n_boxes), 4, np.int32))


def obstacle_scenes(n_scenes: int, n_agents: int, seed: int = 0) -> dict:
    """:func:`random_scenes` among :func:`box_layouts` (agents moved out of the boxes: each agent whose centre
    is within a box's circumradius plus its own radius is redrawn)."""
    scenes = random_scenes(n_scenes, n_agents, seed)
    layouts = box_layouts(n_scenes, seed)
    rng = np.random.default_rng(seed + 1)
    side = 8.0 * np.sqrt(n_agents / 20.0)
    centres = layouts["vertices"].mean(axis=2)  # (S, boxes, 2)
    reach = np.linalg.norm(layouts["vertices"][:, :, 0] - centres, axis=-1)
    for s in range(n_scenes):
        for i in range(n_agents):
            while np.any(np.linalg.norm(scenes["pos"][s, i] - centres[s], axis=-1) < reach[s] + scenes["radius"][s, i]):
                scenes["pos"][s, i] = rng.uniform(-side / 2, side / 2, 2)
    return dict(scenes, vertices=layouts["vertices"], num_vertices=layouts["num_vertices"])


def _median_run(compiled, args, repeats):
    jax.block_until_ready(compiled(*args))  # warm-up (allocations)
    runs = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(compiled(*args))
        runs.append(time.perf_counter() - t0)
    return statistics.median(runs), min(runs)


def time_jax_obstacles(batch: int, n_agents: int, repeats: int, seed: int = 0, block: int | None = None) -> dict:
    """Compile and median run times of the batched solver on ``batch`` :func:`obstacle_scenes`, with their
    boxes and without (the same agents), interleaved so that both see the same machine."""
    sc = {k: jnp.asarray(v) for k, v in obstacle_scenes(batch, n_agents, seed).items()}
    agents = (sc["pos"], sc["vel"], sc["radius"], sc["pref"], sc["max_speed"])
    settings = dict(SETTINGS, max_neighbors=n_agents - 1, block=block)
    with_obst = jax.jit(
        jax.vmap(
            lambda p, v, r, pr, m, ov, onv: orca.solve_with_info(
                p, v, r, pr, m, obstacles=(ov, onv), time_horizon_obst=TIME_HORIZON_OBST, **settings
            )
        )
    )
    without = jax.jit(jax.vmap(lambda p, v, r, pr, m: orca.solve_with_info(p, v, r, pr, m, **settings)))
    out = dict(batch=batch, n_agents=n_agents, n_boxes=N_BOXES, block=block or orca.default_block(), repeats=repeats)
    for name, fn, args in (
        ("obstacles", with_obst, agents + (sc["vertices"], sc["num_vertices"])),
        ("no_obstacles", without, agents),
    ):
        t0 = time.perf_counter()
        compiled = fn.lower(*args).compile()
        out[f"{name}_compile_s"] = time.perf_counter() - t0
        out[f"{name}_lp3_share"] = float(np.mean(np.asarray(compiled(*args)[1])))
        out[f"_{name}"] = (compiled, args)
    for _ in range(2):  # interleaved: the machine's load changes
        for name in ("obstacles", "no_obstacles"):
            med, best = _median_run(*out[f"_{name}"], max(1, repeats // 2))
            out.setdefault(f"{name}_runs", []).extend([med])
            out[f"{name}_min_s"] = min(out.get(f"{name}_min_s", best), best)
    for name in ("obstacles", "no_obstacles"):
        del out[f"_{name}"]
        out[f"{name}_median_s"] = statistics.median(out.pop(f"{name}_runs"))
        out[f"{name}_agent_steps_per_s"] = batch * n_agents / out[f"{name}_median_s"]
    out["obstacle_cost"] = out["obstacles_median_s"] / out["no_obstacles_median_s"]
    return out


def rvo2_obstacle_rate(n_agents: int, n_steps: int, seed: int = 0, n_layouts: int = 16) -> dict:
    """Python-RVO2 doSteps per second among :func:`obstacle_scenes`' boxes, and without them, on one core.

    One simulator per layout (its obstacles added and processed once, as a simulation would); each step takes
    the next layout's simulator, sets every agent's position, velocity and preferred velocity (setters timed,
    as in :func:`rvo2_dostep_rate`) and calls doStep.
    """
    import rvo2

    pool = obstacle_scenes(n_layouts, n_agents, seed)
    rates = {}
    for with_obst in (True, False):
        sims = []
        for s in range(n_layouts):
            sim = rvo2.PyRVOSimulator(
                SETTINGS["dt"],
                SETTINGS["neighbor_dist"],
                max(n_agents - 1, 0),
                SETTINGS["time_horizon"],
                TIME_HORIZON_OBST,
                0.3,
                1.0,
            )
            for i in range(n_agents):
                sim.addAgent(
                    (0.0, 0.0),
                    SETTINGS["neighbor_dist"],
                    max(n_agents - 1, 0),
                    SETTINGS["time_horizon"],
                    TIME_HORIZON_OBST,
                    float(pool["radius"][s, i]),
                    float(pool["max_speed"][s, i]),
                    (0.0, 0.0),
                )
            if with_obst:
                for m in range(pool["vertices"].shape[1]):
                    sim.addObstacle(
                        [tuple(map(float, v)) for v in pool["vertices"][s, m, : pool["num_vertices"][s, m]]]
                    )
                sim.processObstacles()
            sims.append(sim)
        states = [
            [
                (
                    tuple(map(float, pool["pos"][s, i])),
                    tuple(map(float, pool["vel"][s, i])),
                    tuple(map(float, pool["pref"][s, i])),
                )
                for i in range(n_agents)
            ]
            for s in range(n_layouts)
        ]
        start = time.perf_counter()
        for step in range(n_steps):
            sim = sims[step % n_layouts]
            for i, (p, v, pr) in enumerate(states[step % n_layouts]):
                sim.setAgentPosition(i, p)
                sim.setAgentVelocity(i, v)
                sim.setAgentPrefVelocity(i, pr)
            sim.doStep()
        rates["obstacles" if with_obst else "no_obstacles"] = n_steps / (time.perf_counter() - start)
    return dict(
        n_agents=n_agents,
        n_boxes=N_BOXES,
        dostep_per_s=rates["obstacles"],
        agent_steps_per_s=rates["obstacles"] * n_agents,
        no_obstacles_dostep_per_s=rates["no_obstacles"],
        obstacle_cost=rates["no_obstacles"] / rates["obstacles"],
    )


def run_obstacles(args) -> dict:
    """The ``--obstacles`` mode: JAX with and without the boxes per batch size, then RVO2, and their ratios."""
    batches = args.batches or ([1, 16, 256] if args.quick else [1, 16, 256, 1024, 4096])
    repeats, rvo2_steps = (4, 300) if args.quick else (6, 2000)
    blocks = {
        "default": [None],
        "cpu": [orca.CPU_BLOCK],
        "whole": [orca.WHOLE_BATCH],
        "both": [orca.CPU_BLOCK, orca.WHOLE_BATCH],
    }[args.block]
    results = dict(
        machine=machine_info(),
        settings=dict(SETTINGS, time_horizon_obst=TIME_HORIZON_OBST),
        obstacles=[],
        rvo2_obstacles=None,
    )
    rvo2_rate = None if args.no_rvo2 else rvo2_obstacle_rate(20, rvo2_steps)
    results["rvo2_obstacles"] = rvo2_rate
    print(
        f"{'batch':>6} {'block':>6} {'LP3 %':>6} {'compile s':>10} {'median ms':>10} {'agent-steps/s':>14} "
        f"{'no-obst ms':>10} {'obst cost':>9} {'vs RVO2':>8}"
    )
    for batch in batches:
        for block in blocks:
            r = time_jax_obstacles(batch, 20, repeats, block=block)
            if rvo2_rate is not None:
                r["vs_rvo2"] = r["obstacles_agent_steps_per_s"] / rvo2_rate["agent_steps_per_s"]
            results["obstacles"].append(r)
            name = "whole" if r["block"] == orca.WHOLE_BATCH else r["block"]
            vs = f"{r['vs_rvo2']:>7.1f}x" if "vs_rvo2" in r else f"{'-':>8}"
            print(
                f"{batch:>6} {name:>6} {100 * r['obstacles_lp3_share']:>6.1f} {r['obstacles_compile_s']:>10.1f} "
                f"{1e3 * r['obstacles_median_s']:>10.2f} {r['obstacles_agent_steps_per_s']:>14.0f} "
                f"{1e3 * r['no_obstacles_median_s']:>10.2f} {r['obstacle_cost']:>8.2f}x {vs}",
                flush=True,
            )
    if rvo2_rate is not None:
        print(
            f"RVO2 doStep, 20 agents, {N_BOXES} boxes: {rvo2_rate['dostep_per_s']:.0f} steps/s "
            f"({rvo2_rate['agent_steps_per_s']:.0f} agent-steps/s), one core; without the boxes "
            f"{rvo2_rate['no_obstacles_dostep_per_s']:.0f} steps/s ({rvo2_rate['obstacle_cost']:.2f}x)"
        )
    return results


def time_jax(
    batch: int, n_agents: int, repeats: int, seed: int = 0, kind: str = "initial", block: int | None = None
) -> dict:
    """Compile time and median run time of the batched solver on ``batch`` scenes of ``n_agents``
    (kind: "initial" random scenes or "crossing" mid-rollout states; block: the solver's LP block size,
    None: the backend's default)."""
    make = random_scenes if kind == "initial" else crossing_states
    scenes = {k: jnp.asarray(v) for k, v in make(batch, n_agents, seed).items()}
    fn = jax.jit(
        jax.vmap(
            lambda p, v, r, pr, m: orca.solve_with_info(
                p, v, r, pr, m, max_neighbors=n_agents - 1, block=block, **SETTINGS
            )
        )
    )
    args = (scenes["pos"], scenes["vel"], scenes["radius"], scenes["pref"], scenes["max_speed"])
    t0 = time.perf_counter()
    compiled = fn.lower(*args).compile()
    compile_s = time.perf_counter() - t0
    lp3_share = float(np.mean(np.asarray(compiled(*args)[1])))  # also the warm-up (allocations)
    runs = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(compiled(*args))
        runs.append(time.perf_counter() - t0)
    med = statistics.median(runs)
    return dict(
        kind=kind,
        batch=batch,
        n_agents=n_agents,
        block=block or orca.default_block(),
        lp3_share=lp3_share,
        compile_s=compile_s,
        median_s=med,
        min_s=min(runs),
        scenes_per_s=batch / med,
        agent_steps_per_s=batch * n_agents / med,
        repeats=repeats,
    )


def machine_info() -> dict:
    return dict(
        node=platform.node(),
        processor=platform.processor() or platform.machine(),
        platform=platform.platform(),
        python=platform.python_version(),
        cpu_count=os.cpu_count(),
        jax=jax.__version__,
        device=str(jax.devices()[0]),
        backend=jax.default_backend(),
        xla_flags=os.environ.get("XLA_FLAGS", ""),
        load_avg=list(os.getloadavg()),
    )


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="fewer sizes and repeats (< 1 minute)")
    parser.add_argument("--out", help="write the results as JSON to this file")
    parser.add_argument(
        "--block",
        choices=("default", "cpu", "whole", "both"),
        default="default",
        help="the solver's LP blocks: the backend's default, 128 problems (a CPU's), one block "
        "of the whole batch (a GPU's), or both, timed one after the other per case",
    )
    parser.add_argument("--batches", type=int, nargs="*", help="scene batch sizes of the 20-agent cases")
    parser.add_argument(
        "--no-rvo2",
        action="store_true",
        help="time the JAX solver only (for a machine without Python-RVO2, e.g. a GPU box)",
    )
    parser.add_argument(
        "--obstacles",
        action="store_true",
        help="time scenes with static obstacles (20 agents, 8 boxes) instead: with and without "
        "the boxes, and against RVO2 with them (--batches sets the batch sizes)",
    )
    args = parser.parse_args(argv)
    if not args.no_rvo2:
        try:
            import rvo2  # noqa: F401
        except ImportError:
            parser.error(
                "Python-RVO2 (module rvo2, the package pyrvo2-danieldugas) is not installed; install it "
                "or pass --no-rvo2 to time the JAX solver alone"
            )
    configure_cpu()  # 512-bit vectors on AVX-512, as the command-line tools use

    if args.obstacles:
        results = run_obstacles(args)
        if args.out:
            with open(args.out, "w") as fh:
                json.dump(results, fh, indent=2)
        return results

    if args.quick:
        cases = [(b, 20, k) for k in ("initial", "crossing") for b in (1, 16, 256)] + [
            (64, n, "initial") for n in (5, 10)
        ]
        repeats, rvo2_steps = 3, 300
    else:
        cases = [(b, 20, k) for k in ("initial", "crossing") for b in (1, 16, 256, 1024, 4096)] + [
            (b, n, "initial") for n in (5, 10, 50) for b in (256, 1024)
        ]
        repeats, rvo2_steps = 5, 2000

    if args.batches:
        cases = [(b, 20, k) for k in ("initial", "crossing") for b in args.batches]
    blocks = {
        "default": [None],
        "cpu": [orca.CPU_BLOCK],
        "whole": [orca.WHOLE_BATCH],
        "both": [orca.CPU_BLOCK, orca.WHOLE_BATCH],
    }[args.block]

    results = dict(machine=machine_info(), settings=SETTINGS, jax=[], rvo2=[])
    print(
        f"{'scenes':>9} {'agents':>6} {'batch':>6} {'block':>6} {'LP3 %':>6} {'compile s':>10} {'median ms':>10} "
        f"{'scenes/s':>12} {'agent-steps/s':>14}"
    )
    for batch, n, kind in cases:
        for block in blocks:
            r = time_jax(batch, n, repeats, kind=kind, block=block)
            results["jax"].append(r)
            name = "whole" if r["block"] == orca.WHOLE_BATCH else r["block"]
            print(
                f"{kind:>9} {n:>6} {batch:>6} {name:>6} {100 * r['lp3_share']:>6.1f} {r['compile_s']:>10.1f} "
                f"{1e3 * r['median_s']:>10.2f} {r['scenes_per_s']:>12.0f} {r['agent_steps_per_s']:>14.0f}",
                flush=True,
            )
    for n in sorted({n for _, n, _ in cases}) if not args.no_rvo2 else []:
        rate = rvo2_dostep_rate(n, rvo2_steps)
        results["rvo2"].append(dict(n_agents=n, dostep_per_s=rate, agent_steps_per_s=rate * n))
        print(f"RVO2 doStep, {n:>3} agents: {rate:>10.0f} steps/s ({rate * n:.0f} agent-steps/s), one core")
    if args.out:
        with open(args.out, "w") as fh:
            json.dump(results, fh, indent=2)
    return results


if __name__ == "__main__":
    main()
