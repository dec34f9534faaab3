"""Deployment latency: one policy decision at a time on one CPU core, in the three runtimes of tgrf_jax.deploy,
and the Gymnasium vector env's throughput beside the native batched step.

Per policy (the shipped HH Attn `small` with const-vel and with GST predictions, 20 humans, and the `paper` size
with const-vel predictions, untrained: latency does not depend on the weights), the policy is exported with
tgrf-export's code, and each runtime runs `--decisions` single decisions (after a warm-up), each on one
of a set of observations recorded from env episodes, its recurrent state carried over: JAX (the network
jitted), ONNX Runtime (one intra-op thread) and the deserialized StableHLO artifact (jitted). Reported: median
and p99 milliseconds per decision. `Navigator.act` (observation building from detections, the GST model where
used, the decision, the command) is timed the same way with the JAX and ONNX runtimes.

The process pins itself to one core (`--core`, default 0) and asks XLA for single-threaded CPU code before
JAX starts. The Gymnasium section runs B environments through `tgrf_jax.gym.CrowdNavVectorEnv.step` (NumPy
in and out, infos) and through the jitted `CrowdNavEnv.step_batch` it wraps, with the same actions.

    python -m benchmarks.deploy_latency --quick --out bench_results/deploy_quick.json
    python -m benchmarks.deploy_latency --out bench_results/deploy.json
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time


def _pin(core: int) -> None:
    os.sched_setaffinity(0, {core})
    flags = os.environ.get("XLA_FLAGS", "")
    if "xla_cpu_multi_thread_eigen" not in flags:
        os.environ["XLA_FLAGS"] = f"{flags} --xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1".strip()
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")


def _percentiles(seconds) -> dict:
    import numpy as np

    ms = np.asarray(seconds) * 1e3
    return {"median_ms": float(np.median(ms)), "p99_ms": float(np.percentile(ms, 99)), "n": int(ms.size)}


def _time_each(fn, n: int, warmup: int = 50) -> dict:
    for i in range(warmup):
        fn(i)
    out = []
    for i in range(n):
        t0 = time.perf_counter()
        fn(i)
        out.append(time.perf_counter() - t0)
    return _percentiles(out)


def _recorded(source, episodes: int = 3, steps: int = 40):
    """Observations and world states from env episodes of the policy (or, untrained, a straight-ahead robot)."""
    import jax
    import jax.numpy as jnp
    import numpy as np

    from tgrf_jax.env import CrowdNavEnv

    env = CrowdNavEnv(source.config.env, source.config.reward)
    params = env.default_params
    reset, step = jax.jit(env.reset_env), jax.jit(env.step_env)
    obs_list, world = [], []
    for e in range(episodes):
        key = jax.random.PRNGKey(e)
        obs, state = reset(key, params)
        for t in range(steps):
            o, r, h = jax.device_get((obs, state.robot, state.humans))
            obs_list.append((o.robot_node, o.robot_vel, o.humans, o.human_mask.astype(np.float32)))
            world.append(
                (
                    np.array([r.pos[0], r.pos[1], r.heading, r.vel[0], r.vel[1]]),
                    np.asarray(r.goal),
                    np.concatenate([h.pos, h.vel, h.radius[:, None]], axis=1),
                )
            )
            to_goal = r.goal - r.pos
            action = jnp.asarray(to_goal / max(np.linalg.norm(to_goal), 1e-6), jnp.float32)
            obs, state, _, term, trunc, _ = step(jax.random.fold_in(key, t), state, action, params)
            if bool(term | trunc):
                break
    return obs_list, world


def latency(name: str, source, decisions: int, out_dir) -> dict:
    import numpy as np

    from tgrf_jax.deploy import Navigator, PolicyStep, export, load_source
    from tgrf_jax.deploy.runtimes import make_runtime

    t0 = time.perf_counter()
    path = export(source, os.path.join(out_dir, name), say=lambda _: None)
    exported = load_source(str(path))
    export_s = time.perf_counter() - t0
    obs_list, world = _recorded(source)
    step = PolicyStep(source.config, source.params)
    row = {
        "policy": name,
        "network": f"{source.config.network.name}/{source.config.network.size}",
        "params": int(step.net.num_params(source.params)),
        "predictor": source.config.env.predictor,
        "export_s": round(export_s, 1),
        "decision": {},
        "navigator": {},
    }
    for runtime in ("jax", "onnx", "stablehlo"):
        run = make_runtime(exported, runtime, threads=1)
        state = [np.zeros(step.state_size, np.float32)]

        def decide(i, run=run, state=state):
            _, state[0] = run(*obs_list[i % len(obs_list)], state[0])

        row["decision"][runtime] = _time_each(decide, decisions)
        print(
            f"  {name:>16s} {runtime:>9s}: median {row['decision'][runtime]['median_ms']:.3f} ms, "
            f"p99 {row['decision'][runtime]['p99_ms']:.3f} ms",
            flush=True,
        )
    for runtime in ("jax", "onnx"):
        nav = Navigator(exported, runtime=runtime)
        ids = list(range(source.config.env.num_humans))

        def act(i, nav=nav, ids=ids):
            if i % len(world) == 0:
                nav.reset()
            robot, goal, humans = world[i % len(world)]
            nav.act(robot, goal, humans, ids=ids)

        row["navigator"][runtime] = _time_each(act, decisions)
        print(
            f"  {name:>16s} Navigator.act ({runtime}): median {row['navigator'][runtime]['median_ms']:.3f} ms, "
            f"p99 {row['navigator'][runtime]['p99_ms']:.3f} ms",
            flush=True,
        )
    return row


def gym_throughput(num_envs: int, steps: int, rounds: int = 3) -> dict:
    """env-steps/s of the vector env and of the bare jitted step_batch, timed in alternating rounds (best of
    each), so that a busy moment of a shared machine does not fall on one side only."""
    import jax
    import numpy as np

    from tgrf_jax.gym import CrowdNavVectorEnv

    venv = CrowdNavVectorEnv(num_envs)
    venv.reset(seed=0)
    rng = np.random.default_rng(0)
    actions = [rng.uniform(-1, 1, (num_envs, 2)).astype(np.float32) for _ in range(steps)]
    env, params = venv.env, venv.params
    _, state = jax.vmap(env.reset_env, in_axes=(0, None))(jax.random.split(jax.random.PRNGKey(0), num_envs), params)
    step = jax.jit(env.step_batch, static_argnums=4, donate_argnums=1)
    key = jax.random.PRNGKey(1)
    device_actions = [jax.device_put(a) for a in actions]

    def run_gym():
        for a in actions:
            venv.step(a)

    def run_native():
        nonlocal key, state
        for a in device_actions:
            key, k = jax.random.split(key)
            state = step(k, state, a, params, num_envs)[1]
        jax.block_until_ready(state)

    best = {"gym": float("inf"), "native": float("inf")}
    for r in range(rounds + 1):  # round 0 compiles and warms up
        for name, fn in (("gym", run_gym), ("native", run_native)):
            t0 = time.perf_counter()
            fn()
            if r:
                best[name] = min(best[name], time.perf_counter() - t0)
    result = {
        "num_envs": num_envs,
        "steps": steps,
        "gym_env_steps_per_s": num_envs * steps / best["gym"],
        "native_env_steps_per_s": num_envs * steps / best["native"],
    }
    print(
        f"  gym VectorEnv B={num_envs}: {result['gym_env_steps_per_s']:,.0f} env-steps/s; native step_batch: "
        f"{result['native_env_steps_per_s']:,.0f} env-steps/s",
        flush=True,
    )
    return result


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--quick", action="store_true", help="1,000 decisions per row, a short gym run")
    p.add_argument("--decisions", type=int, default=None, help="timed decisions per row (default 5,000; quick 1,000)")
    p.add_argument("--core", type=int, default=0, help="the CPU core to pin to")
    p.add_argument("--gym-envs", type=int, default=256)
    p.add_argument("--out", help="write the results as JSON")
    args = p.parse_args(argv)
    _pin(args.core)

    import jax

    from benchmarks.common import machine_info, write_json
    from tgrf_jax.config import TrainConfig
    from tgrf_jax.deploy import PolicySource, load_source
    from tgrf_jax.policies import make_network_for

    decisions = args.decisions or (1000 if args.quick else 5000)
    paper_config = TrainConfig.from_dict({"network": {"size": "paper"}})
    paper = PolicySource(
        paper_config,
        jax.device_get(make_network_for(paper_config).init(jax.random.PRNGKey(0))),
        {"benchmark": "untrained paper-size HH Attn"},
    )
    policies = {
        "small-const_vel": load_source("table1-const_vel-tgrf"),
        "small-gst": load_source("table1-gst-tgrf"),
        "paper-const_vel": paper,
    }
    print(f"one core ({args.core}), {decisions} decisions per row", flush=True)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for name, source in policies.items():
            rows.append(latency(name, source, decisions, tmp))
    gym = gym_throughput(args.gym_envs, 20 if args.quick else 50)
    payload = {
        "benchmark": "deploy_latency",
        "machine": machine_info(),
        "core": args.core,
        "decisions": decisions,
        "rows": rows,
        "gym": gym,
        "date": time.strftime("%Y-%m-%d"),
    }
    write_json(args.out, payload)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
