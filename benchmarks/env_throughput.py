"""Environment throughput: env-steps/s of jit(vmap(step)) for batch sizes x human counts x human policies.

Each measurement runs a compiled `lax.scan` of T auto-reset steps over B parallel environments, with
constant-velocity predictions (K = 5), the TGRF reward and a straight-to-goal robot, and reports B * T / time
(compile time separately). Timed calls start from the state one untimed call left (T steps after a reset:
the crowd mid-crossing, where ORCA is slowest, as in training). For batches of 16 and more it also times
`CrowdNavEnv.step_batch`, the trainer's auto-reset, which samples B / 8 fresh episodes per step instead of B
(`ppo.reset_ratio: 8`), and the same split over D CPU devices (`--devices`, default: one per core), each
stepping B / D envs under `shard_map`, as the trainer's env shards do: one XLA program spreads its small ops
over the cores poorly, D programs side by side do not. In the same run, Python-RVO2's raw 20-agent doStep rate is
timed as the on-machine reference for a compiled ORCA step. Rows with predictor `gst` run the learned predictor (the
shipped weights) inside every step; its XLA-counted FLOPs per env step are printed beside them (`--gst-only`: just
const_vel against gst).

    python -m benchmarks.env_throughput --quick --out bench_results/env_quick.json
    python -m benchmarks.env_throughput --out bench_results/env_full.json
    python -m benchmarks.env_throughput --gst-only --out bench_results/env_gst.json
    python -m benchmarks.env_throughput --obstacles --out bench_results/env_obstacles.json
    python -m benchmarks.env_throughput --replay eth-ucy --out bench_results/env_replay.json
"""

from __future__ import annotations

import argparse
import os
import statistics
import time

import jax
import jax.numpy as jnp

from benchmarks.common import machine_info, time_call, write_json
from tgrf_jax import CrowdNavEnv, configure_cpu
from tgrf_jax.policies import StraightPolicy

ENV_AXIS = "envs"


def step_scan(env: CrowdNavEnv, n_steps: int, num_resets: int | None = None):
    """(key, obs, state) -> scan of n_steps auto-reset steps: per-env resets (`step`), or `step_batch` with
    num_resets fresh episodes per step."""
    params = env.default_params
    step = jax.vmap(env.step, in_axes=(0, 0, 0, None))
    act = jax.vmap(StraightPolicy.action)

    def body(carry, key):
        obs, state = carry
        if num_resets is None:
            obs, state, reward, *_ = step(jax.random.split(key, obs.robot_node.shape[0]), state, act(obs), params)
        else:
            obs, state, reward, *_ = env.step_batch(key, state, act(obs), params, num_resets)
        return (obs, state), reward.mean()

    def run(key, obs, state):
        return jax.lax.scan(body, (obs, state), jax.random.split(key, n_steps))

    return run


def make_runner(env: CrowdNavEnv, n_steps: int, num_resets: int | None = None):
    """`step_scan`, jitted."""
    return jax.jit(step_scan(env, n_steps, num_resets)), env.default_params


def make_sharded_runner(env: CrowdNavEnv, n_steps: int, num_resets: int, mesh):
    """`step_scan` with step_batch on every device of `mesh`, each over its slice of the batch with its own key
    (no communication: the envs are independent) and `num_resets` fresh episodes per step and device."""
    from jax.sharding import PartitionSpec as P

    scan = step_scan(env, n_steps, num_resets)

    def shard(key, obs, state):
        return scan(jax.random.fold_in(key, jax.lax.axis_index(ENV_AXIS)), obs, state)

    env_spec = P(ENV_AXIS)
    run = jax.shard_map(
        shard,
        mesh=mesh,
        in_specs=(P(), env_spec, env_spec),
        out_specs=((env_spec, env_spec), env_spec),
        check_vma=False,
    )
    return jax.jit(run)


def time_from_mid_crossing(run, obs, state, repeats: int) -> tuple[float, float]:
    """(compile_s, median run_s) of a runner, timed from the state its first (compiling) call leaves: the crowd
    mid-crossing, as a training run sees it; ORCA costs up to twice as much there as in the first steps after
    a reset, when the humans are still spread out on their circle."""
    start = time.perf_counter()
    (obs, state), _ = jax.block_until_ready(run(jax.random.key(1), obs, state))
    first_s = time.perf_counter() - start
    runs = []
    for _ in range(repeats):
        start = time.perf_counter()
        jax.block_until_ready(run(jax.random.key(2), obs, state))
        runs.append(time.perf_counter() - start)
    run_s = statistics.median(runs)
    return max(first_s - run_s, 0.0), run_s


def gst_flops_per_env_step(num_humans: int) -> float:
    """FLOPs of one learned-predictor call (one env, one step) as XLA's cost analysis counts them."""
    from tgrf_jax.env.gst import predict, pretrained

    pos = jnp.zeros((num_humans, 5, 2))
    compiled = jax.jit(predict).lower(pretrained("orca"), pos, jnp.ones((num_humans, 5), bool)).compile()
    cost = compiled.cost_analysis()
    cost = cost[0] if isinstance(cost, (list, tuple)) else cost
    return float(cost["flops"])


def measure(
    policy: str,
    num_humans: int,
    batch: int,
    n_steps: int,
    repeats: int,
    plain: bool = True,
    mesh=None,
    predictor: str = "const_vel",
    extra: dict | None = None,
) -> dict:
    """One grid point: `vmap(step)` (unless not `plain`) and, from batch 16, `step_batch`, also over the devices
    of `mesh` (if given and the batch splits into slices of at least 16). `extra`: more env settings."""
    env = CrowdNavEnv({"num_humans": num_humans, "human_policy": policy, "predictor": predictor, **(extra or {})})
    params = env.default_params
    obs, state = jax.jit(jax.vmap(env.reset, in_axes=(0, None)))(jax.random.split(jax.random.key(0), batch), params)
    row = {
        "policy": policy,
        "num_humans": num_humans,
        "batch": batch,
        "steps_per_call": n_steps,
        "predictor": predictor,
        **(extra or {}),
    }
    runners = {}
    if plain or batch < 16:
        runners["env_steps_per_s"] = make_runner(env, n_steps)[0]
    if batch >= 16:
        row["reset_slots"] = batch // 8
        runners["step_batch_env_steps_per_s"] = make_runner(env, n_steps, batch // 8)[0]
    for name, run in runners.items():
        compile_s, run_s = time_from_mid_crossing(run, obs, state, repeats)
        row.setdefault("compile_s", round(compile_s, 3))
        row[name] = batch * n_steps / run_s
    d = 0 if mesh is None else mesh.devices.size
    if d > 1 and batch % d == 0 and batch // d >= 16:
        from jax.sharding import NamedSharding
        from jax.sharding import PartitionSpec as P

        run = make_sharded_runner(env, n_steps, batch // d // 8, mesh)
        placed = jax.device_put((obs, state), NamedSharding(mesh, P(ENV_AXIS)))
        _, run_s = time_from_mid_crossing(run, *placed, repeats)
        row["devices"] = d
        row["step_batch_devices_env_steps_per_s"] = batch * n_steps / run_s
    return row


def _routing_pieces(env: CrowdNavEnv, params, state) -> dict:
    """The humans' routing among obstacles: its roadmap (built at reset) and their targets (every step)."""
    if state.routing is None:
        return {}
    from tgrf_jax.env import routing

    def roadmap(s):
        return routing.build_roadmap(s.obstacles, s.routing.clearance, s.routing.radius)

    def targets(s):
        h = s.humans
        return routing.targets(s.routing, h.pos, h.goal, h.radius, s.obstacles)

    return {"routing_roadmap": (roadmap, (state,)), "routing_targets": (targets, (state,))}


def breakdown(policy: str, num_humans: int, batch: int, repeats: int, extra: dict | None = None) -> dict:
    """Milliseconds per batched call of the pieces of one auto-reset step."""
    from tgrf_jax.env import humans as humans_lib

    env = CrowdNavEnv({"num_humans": num_humans, "human_policy": policy, "predictor": "const_vel", **(extra or {})})
    params = env.default_params
    keys = jax.random.split(jax.random.key(0), batch)
    obs, state = jax.jit(jax.vmap(env.reset, in_axes=(0, None)))(keys, params)
    actions = jax.vmap(StraightPolicy.action)(obs)
    pieces = {
        "human_policy": (
            lambda s: humans_lib.human_velocities(
                s.humans, None, params, env.config, s.orca_neighbor_dist, s.obstacles, s.obstacle_table
            ),
            (state,),
        ),
        "reset": (lambda k: env.reset(k, params), (keys,)),
        **_routing_pieces(env, params, state),
        "step_without_reset": (lambda k, s, a: env.step_env(k, s, a, params), (keys, state, actions)),
        "step_with_auto_reset": (lambda k, s, a: env.step(k, s, a, params), (keys, state, actions)),
    }
    out = {}
    for name, (fn, args) in pieces.items():
        _, run_s = time_call(jax.jit(jax.vmap(fn)), *args, repeats=repeats)
        out[name] = round(run_s * 1e3, 3)
    return out


def replay_rows(files: list[str]) -> tuple:
    """`--replay`: recorded people in 80 slots (students001 shows up to 75 at once), walking their recordings or
    steered by ORCA around each other and the robot, beside the paper's 20 ORCA humans and ORCA with 80."""
    replay = {"scenario": "replay", "replay_files": files, "num_humans": 80}
    return (
        ("circle_crossing, 20 ORCA humans", "orca", 20, {}),
        ("replay, 80 slots, recorded", "replay", 80, replay),
        ("replay, 80 slots, reactive ORCA", "orca", 80, {**replay, "robot_visible": True}),
        ("circle_crossing, 80 ORCA humans", "orca", 80, {}),
    )


OBSTACLE_ROWS = (
    ("open space", "orca", 20, {}),
    ("open space + LiDAR 180", "orca", 20, {"lidar_rays": 180}),
    ("random_obstacles", "orca", 20, {"scenario": "random_obstacles"}),
    ("random_obstacles + LiDAR 180", "orca", 20, {"scenario": "random_obstacles", "lidar_rays": 180}),
    ("random_obstacles, no routing", "orca", 20, {"scenario": "random_obstacles", "human_routing": False}),
)


def compare_envs(mesh, out, rows: tuple, what: str, breakdown_rows: tuple = ()) -> None:
    """Envs (label, human policy, humans, settings) on the trainer's path at batch 1024, each as a ratio to the
    first, in one run; `breakdown_rows`: those whose step is also split into its pieces."""
    batch, repeats = 1024, 3
    info = machine_info()
    print(f"machine: {info['cpu']} x{info['cpu_count']}, jax {info['jax']} on {info['backend']}")
    d = 1 if mesh is None else mesh.devices.size
    print(f"{'env':>34} {'compile s':>9} {'step_batch':>12} {f'on {d} devices':>14} {'ratio':>6}")
    results = []
    for label, policy, humans, extra in rows:
        row = measure(policy, humans, batch, scan_length(batch, False), repeats, plain=False, mesh=mesh, extra=extra)
        row["label"] = label
        results.append(row)
        rate = lambda r: r.get("step_batch_devices_env_steps_per_s", r["step_batch_env_steps_per_s"])  # noqa: E731
        row["ratio_to_first"] = rate(row) / rate(results[0])
        print(
            f"{label:>34} {row['compile_s']:>9.1f} {row['step_batch_env_steps_per_s']:>12,.0f} "
            f"{row.get('step_batch_devices_env_steps_per_s', float('nan')):>14,.0f} {row['ratio_to_first']:>6.2f}",
            flush=True,
        )
    parts = {label: breakdown(policy, humans, batch, repeats, extra) for label, policy, humans, extra in breakdown_rows}
    for label, ms in parts.items():
        print(f"where the time goes, {label}, batch {batch} (ms per batched call): {ms}")
    write_json(
        out,
        {
            "benchmark": "env_throughput",
            what: True,
            "machine": info,
            "results": results,
            "breakdown_ms_batch1024": parts,
        },
    )


def scan_length(batch: int, quick: bool) -> int:
    """Steps per timed call: long enough to amortise the call, short enough for the large batches."""
    if batch <= 16:
        return 50 if quick else 200
    return 20 if quick or batch > 1024 else 50


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument(
        "--quick",
        action="store_true",
        help="20 humans: ORCA at batches 128 and 1024, Social Force at 1024; step_batch only, "
        "shorter scans, no breakdown (< 1 minute)",
    )
    parser.add_argument("--out", help="write results as JSON here")
    parser.add_argument(
        "--gst-only",
        action="store_true",
        help="only 20 ORCA humans at batches 256 and 1024, const_vel against the learned gst predictor",
    )
    parser.add_argument(
        "--obstacles",
        action="store_true",
        help="20 ORCA humans at batch 1024 on the trainer's path: the paper's open space against "
        "random_obstacles (up to 8 boxes), each with and without a 180-ray LiDAR, and what "
        "the obstacles cost in the ORCA solve",
    )
    parser.add_argument(
        "--replay",
        nargs="+",
        metavar="FILES",
        help="the replay scenario over these env.replay_files entries (catalogue names, e.g. eth-ucy, in the data "
        "directory): recorded and reactive people in 80 slots against 20 and 80 ORCA humans, batch 1024",
    )
    parser.add_argument(
        "--devices",
        type=int,
        default=len(os.sched_getaffinity(0)),
        help="CPU devices for the sharded step_batch column (default: one per core; 1: skip it)",
    )
    args = parser.parse_args(argv)
    configure_cpu(args.devices)  # before JAX touches its backend
    mesh = None
    if args.devices > 1 and len(jax.devices()) >= args.devices:
        mesh = jax.sharding.Mesh(jax.devices()[: args.devices], (ENV_AXIS,))

    if args.obstacles:
        return compare_envs(mesh, args.out, OBSTACLE_ROWS, "obstacles", OBSTACLE_ROWS[::2])
    if args.replay:
        return compare_envs(mesh, args.out, replay_rows(args.replay), "replay")
    if args.gst_only:
        grid = [("orca", 20, b, p) for b in (256, 1024) for p in ("const_vel", "gst")]
        repeats = 2
    elif args.quick:
        grid = [("orca", 20, 128), ("orca", 20, 1024), ("social_force", 20, 1024), ("orca", 20, 1024, "gst")]
        repeats = 2  # and only step_batch (the trainer's path): each ORCA program takes ~10 s to compile
    else:
        grid = [
            (p, n, b) for p in ("orca", "social_force") for n in (5, 10, 20, 50) for b in (1, 16, 256, 1024, 4096)
        ] + [("orca", 20, b, "gst") for b in (256, 1024)]
        repeats = 3
    quick = args.quick or args.gst_only
    info = machine_info()
    print(f"machine: {info['cpu']} x{info['cpu_count']}, jax {info['jax']} on {info['backend']}")
    rows = []
    d = "-" if mesh is None else mesh.devices.size
    print(
        f"{'policy':>13} {'humans':>6} {'predictor':>9} {'batch':>6} {'compile s':>9} {'env-steps/s':>12} "
        f"{'step_batch':>12} {f'on {d} devices':>14}"
    )
    for policy, n, batch, *pred in grid:
        predictor = pred[0] if pred else "const_vel"
        row = measure(
            policy, n, batch, scan_length(batch, quick), repeats, plain=not quick, mesh=mesh, predictor=predictor
        )
        rows.append(row)
        cells = (
            f"{row[k]:>12,.0f}" if k in row else f"{'-':>12}" for k in ("env_steps_per_s", "step_batch_env_steps_per_s")
        )
        sharded = row.get("step_batch_devices_env_steps_per_s")
        print(
            f"{policy:>13} {n:>6} {predictor:>9} {batch:>6} {row['compile_s']:>9.1f} {' '.join(cells)} "
            f"{'-' if sharded is None else f'{sharded:,.0f}':>14}",
            flush=True,
        )

    gst_flops = None
    if any(r["predictor"] == "gst" for r in rows):
        gst_flops = gst_flops_per_env_step(20)
        for r in (r for r in rows if r["predictor"] == "gst"):
            best_rate = max(
                r.get(k, 0.0)
                for k in ("env_steps_per_s", "step_batch_env_steps_per_s", "step_batch_devices_env_steps_per_s")
            )
            print(
                f"gst predictor: {gst_flops / 1e6:.1f} MFLOP per env step (XLA cost analysis, 20 humans); at "
                f"{best_rate:,.0f} env-steps/s (batch {r['batch']}) that is {gst_flops * best_rate / 1e9:.1f} GFLOP/s"
            )
    if args.gst_only:
        write_json(
            args.out,
            {
                "benchmark": "env_throughput",
                "gst_only": True,
                "machine": machine_info(),
                "gst_flops_per_env_step": gst_flops,
                "results": rows,
            },
        )
        return

    from benchmarks.orca_throughput import rvo2_dostep_rate

    rvo2 = rvo2_dostep_rate(20, 2000 if args.quick else 20000)
    print(f"Python-RVO2 raw doStep, 20 agents, one core: {rvo2:,.0f} steps/s")
    rate = lambda r: max(
        r.get("env_steps_per_s", 0.0),
        r.get("step_batch_env_steps_per_s", 0.0),
        r.get("step_batch_devices_env_steps_per_s", 0.0),
    )
    best = max(
        (r for r in rows if r["policy"] == "orca" and r["num_humans"] == 20 and r["predictor"] == "const_vel"), key=rate
    )
    print(
        f"best ORCA-20 env: {rate(best):,.0f} env-steps/s at batch {best['batch']} "
        f"= {rate(best) / rvo2:.1f}x RVO2's raw doStep"
    )
    parts = {} if args.quick else {p: breakdown(p, 20, 1024, repeats) for p in ("orca", "social_force")}
    for p, ms in parts.items():
        print(f"where the time goes, {p}, 20 humans, batch 1024 (ms per batched call): {ms}")
    write_json(
        args.out,
        {
            "benchmark": "env_throughput",
            "quick": args.quick,
            "machine": info,
            "gst_flops_per_env_step": gst_flops,
            "rvo2_dostep_20_per_s": rvo2,
            "results": rows,
            "breakdown_ms_batch1024": parts,
        },
    )


if __name__ == "__main__":
    main()
