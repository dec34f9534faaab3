"""Training throughput: env-steps/s of whole PPO updates (rollout + GAE + epochs x minibatches), per network
and number of parallel envs, with a breakdown of where the time goes.

For each (network, size, num_envs) on the paper scenario (20 humans, TGRF reward, const_vel predictions unless
`--predictor` says otherwise):
  * ``train_sps``: env steps per second of `Trainer.run_chunk` (U updates of num_envs x num_steps steps, compiled once)
  * ``env_s`` / ``rollout_s`` / ``update_s`` per update: env stepping alone (a scan of the same number of
    auto-reset steps with fixed actions), the rollout (env + policy forward + sampling), and the rest
    (GAE, epochs x minibatches of sequence replay + backward + Adam) = update time - rollout time.
  * ``learn_gflops``: the learning's arithmetic rate (FLOPs of one update's gradient slices, from XLA's cost
    analysis, over ``learn_s``), next to ``matmul_reference_gflops``, the rate of one matmul of the small net's
    widest layer shape compiled alone, timed in the same run; ``learn_bound_sps`` is the env-steps/s at which
    the learning alone would need that reference rate: a ceiling on training throughput at these epochs and
    this network on this machine, whatever the environment costs.

    python -m benchmarks.train_throughput --quick --out bench_results/train_quick.json
    python -m benchmarks.train_throughput --out bench_results/train_full.json
    python -m benchmarks.train_throughput --quick --predictor gst --out bench_results/train_gst.json
    python -m benchmarks.train_throughput --nets hh_attn/small --envs 256 --against-plain --env-set scenario=mix \
        --env-set num_humans=30 --env-set active_humans_min=5 --env-set active_humans_max=30   # mix vs paper scenario
"""

from __future__ import annotations

import argparse
import time

import jax
import jax.numpy as jnp
import numpy as np
import yaml

from benchmarks.common import machine_info, time_call, write_json
from tgrf_jax import configure_cpu
from tgrf_jax.config import TrainConfig
from tgrf_jax.policies.nets.hh_attn import HH_ATTN_SIZES
from tgrf_jax.train import make_trainer, shards
from tgrf_jax.train.ppo import Transition, ppo_loss


def learner_flops_per_update(tr, state) -> float:
    """FLOPs of one update's learning (epochs x minibatches x gradient slices x shards), from XLA's cost analysis
    of one gradient slice (forward + backward of the PPO loss). The recurrent cell's time scan is counted once
    (XLA's analysis does not multiply loop bodies), which undercounts the small GRU by a few percent."""
    p = tr.config.ppo
    envs = p.shard_envs // p.num_minibatches // p.num_microbatches
    t = p.num_steps
    obs = tr.net.dummy_obs(1)
    obs = jax.tree_util.tree_map(lambda x: jax.ShapeDtypeStruct((t, envs) + x.shape[1:], x.dtype), obs)
    f32 = lambda: jax.ShapeDtypeStruct((t, envs), jnp.float32)
    flag = lambda: jax.ShapeDtypeStruct((t, envs), bool)
    batch = Transition(
        obs=obs,
        resets=flag(),
        action=jax.ShapeDtypeStruct((t, envs, 2), jnp.float32),
        log_prob=f32(),
        value=f32(),
        reward=f32(),
        done=flag(),
        truncated=flag(),
        final_value=f32(),
    )
    carry = jax.tree_util.tree_map(
        lambda x: jax.ShapeDtypeStruct((envs,) + x.shape[1:], x.dtype), tr.net.initialize_carry(1)
    )
    stats = state.return_stats if p.norm_value else None
    grad = jax.value_and_grad(ppo_loss, argnums=1, has_aux=True)
    fn = jax.jit(lambda params, c0, b, a, r: grad(tr.net, params, c0, b, a, r, state.hparams, p.clip_value, stats))
    cost = fn.lower(state.params, carry, batch, f32(), f32()).compile().cost_analysis()
    cost = cost[0] if isinstance(cost, list) else cost
    return float(cost["flops"]) * p.num_microbatches * p.num_minibatches * p.update_epochs * p.num_shards


def matmul_reference_gflops(rows: int = 3840, repeats: int = 20) -> float:
    """GFLOP/s of one (rows, 64) x (64, 128) float32 matmul + bias + ReLU, the shape of HH Attn small's widest
    per-human layer (the attention's packed q/k/v projection: queries and keys of every head, then the values),
    compiled alone: what XLA:CPU reaches on this machine for the learner's kind of arithmetic when nothing else is
    in the way."""
    s = HH_ATTN_SIZES["small"]
    cols = 2 * s.hh_heads * (s.hh_qk_head_dim or s.hh_attn // s.hh_heads) + s.hh_attn
    x = jax.random.normal(jax.random.PRNGKey(0), (rows, s.hh_attn))
    w = jax.random.normal(jax.random.PRNGKey(1), (s.hh_attn, cols))
    b = jnp.zeros((cols,))
    fn = jax.jit(lambda x, w, b: jax.nn.relu(x @ w + b))
    _, run_s = time_call(fn, x, w, b, repeats=repeats)
    return 2.0 * rows * s.hh_attn * cols / run_s / 1e9


def measure(
    name: str,
    size: str,
    num_envs: int,
    human_policy: str,
    num_steps: int,
    updates: int,
    breakdown: bool,
    repeats: int,
    epochs: int,
    minibatches: int,
    microbatch_envs: int,
    num_shards: int,
    predictor: str = "const_vel",
    env_overrides: dict | None = None,
) -> dict:
    cfg = TrainConfig.from_dict(
        {
            "env": {"num_humans": 20, "human_policy": human_policy, "predictor": predictor, **(env_overrides or {})},
            "network": {"name": name, "size": size},
            "ppo": {
                "num_envs": num_envs,
                "num_steps": num_steps,
                "num_shards": num_shards,
                "num_minibatches": minibatches if num_envs % (num_shards * minibatches) == 0 else 1,
                "update_epochs": epochs,
                "microbatch_envs": microbatch_envs,
                "total_steps": max(num_envs * num_steps * updates, 3_000_000),
            },
        }
    )
    tr = make_trainer(cfg)
    state = tr.jit_init(jax.random.PRNGKey(0), tr.default_hparams)
    jax.block_until_ready(state)
    steps = num_envs * num_steps * updates

    n = np.int32(updates)
    start = time.perf_counter()
    chunk = tr.jit_run_chunk.lower(state, n).compile()
    compile_s = time.perf_counter() - start
    state, _ = jax.block_until_ready(chunk(state, n))  # warm-up; the chunk consumes its state, so it is threaded
    runs = []
    for _ in range(repeats):
        start = time.perf_counter()
        state, _ = jax.block_until_ready(chunk(state, n))
        runs.append(time.perf_counter() - start)
    run_s = sorted(runs)[len(runs) // 2]
    out = {
        "network": name,
        "size": size,
        "num_envs": num_envs,
        "num_steps": num_steps,
        "human_policy": human_policy,
        "predictor": predictor,
        "env_overrides": env_overrides or {},
        "num_shards": num_shards,
        "shard_placement": shards.describe(num_shards, tr.mesh),
        "update_epochs": cfg.ppo.update_epochs,
        "num_minibatches": cfg.ppo.num_minibatches,
        "microbatches": cfg.ppo.num_microbatches,
        "params": tr.net.num_params(state.params),
        "updates_per_call": updates,
        "compile_s": round(compile_s, 2),
        "update_s": round(run_s / updates, 5),
        "train_sps": round(steps / run_s, 1),
    }
    if breakdown:
        # the same pieces as in training: per shard, on the shards' devices
        @jax.jit
        def rollout(state, key):
            return tr.across_shards(lambda s: (tr.rollout(s, tr.shard_key(key))[0], {}))(state)

        _, roll_s = time_call(rollout, state, jax.random.PRNGKey(1), repeats=repeats)

        @jax.jit
        def env_only(state, key):
            def shard(s):
                def body(carry, k):
                    obs, env_state = carry
                    action = jnp.ones((cfg.ppo.shard_envs, 2)) * 0.5
                    obs, env_state, reward, *_ = tr.env.step_batch(
                        k, env_state, action, s.hparams.env, cfg.ppo.reset_slots
                    )
                    return (obs, env_state), reward.sum()

                keys = jax.random.split(tr.shard_key(key), num_steps)
                (obs, env_state), _ = jax.lax.scan(body, (s.obs, s.env_state), keys)
                return s.replace(obs=obs, env_state=env_state), {}

            return tr.across_shards(shard)(state)

        _, env_s = time_call(env_only, state, jax.random.PRNGKey(2), repeats=repeats)
        per_update = run_s / updates
        learn_s = max(per_update - roll_s, 0.0)
        flops = learner_flops_per_update(tr, state)
        ref = matmul_reference_gflops()
        out.update(
            env_s=round(env_s, 5),
            rollout_s=round(roll_s, 5),
            policy_in_rollout_s=round(roll_s - env_s, 5),
            learn_s=round(learn_s, 5),
            env_only_sps=round(num_envs * num_steps / env_s, 1),
            learn_gflop_per_update=round(flops / 1e9, 3),
            learn_gflops=round(flops / learn_s / 1e9, 1) if learn_s > 0 else None,
            matmul_reference_gflops=round(ref, 1),
            # env-steps/s at which the learning alone would have to run at the reference matmul's rate
            learn_bound_sps=round(ref * 1e9 / (flops / (num_envs * num_steps)), 1),
        )
    return out


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument(
        "--quick", action="store_true", help="HH Attn small at the default config's env count, no breakdown (< 1 min)"
    )
    parser.add_argument("--out", help="write results as JSON")
    parser.add_argument("--human-policy", default="orca", choices=["orca", "social_force"])
    parser.add_argument(
        "--predictor",
        default="const_vel",
        choices=["none", "const_vel", "truth", "gst"],
        help="env.predictor (gst: the shipped learned model runs in every env step)",
    )
    parser.add_argument(
        "--envs", type=int, nargs="*", help="env counts (default: 64 256 1024; quick: the default config's)"
    )
    parser.add_argument("--nets", nargs="*", help="name/size pairs, e.g. hh_attn/small mlp/small")
    default_ppo = TrainConfig().ppo
    parser.add_argument(
        "--shards",
        type=int,
        default=default_ppo.num_shards,
        help="ppo.num_shards, one CPU device each (default: the embedded default config's)",
    )
    parser.add_argument(
        "--epochs",
        type=int,
        default=default_ppo.update_epochs,
        help="PPO epochs per update (default: the embedded default config's)",
    )
    parser.add_argument(
        "--minibatches",
        type=int,
        default=default_ppo.num_minibatches,
        help="minibatches per epoch (default: the embedded default config's)",
    )
    parser.add_argument(
        "--num-steps",
        type=int,
        default=default_ppo.num_steps,
        help="rollout length per update (default: the embedded default config's)",
    )
    parser.add_argument(
        "--microbatch-envs",
        type=int,
        default=default_ppo.microbatch_envs,
        help="envs per gradient slice (default: the embedded default config's; 0: whole minibatch)",
    )
    parser.add_argument(
        "--env-set",
        action="append",
        default=[],
        metavar="FIELD=VALUE",
        help="an env setting for every point (repeatable), e.g. --env-set scenario=mix "
        "--env-set num_humans=30 --env-set active_humans_min=5",
    )
    parser.add_argument(
        "--against-plain",
        action="store_true",
        help="with --env-set: also measure the plain paper scenario (20 humans) in the same run and print the ratio",
    )
    args = parser.parse_args(argv)
    overrides = {}
    for item in args.env_set:
        field, sep, value = item.partition("=")
        if not sep or not field:
            parser.error(f"--env-set {item!r}: expected FIELD=VALUE, e.g. scenario=mix")
        overrides[field] = yaml.safe_load(value)
    if args.against_plain and not overrides:
        parser.error("--against-plain compares against --env-set settings: give at least one")
    configure_cpu(args.shards)  # before JAX touches its backend
    if args.quick:
        nets = args.nets or ["hh_attn/small"]
        envs = args.envs or [default_ppo.num_envs]
        updates, breakdown, repeats = 1, False, 1
    else:
        nets = args.nets or ["hh_attn/small", "hh_attn/paper", "dsrnn/paper", "mlp/small"]
        envs = args.envs or [64, 256, 1024]
        updates, breakdown, repeats = 2, True, 3
    results = []
    print(
        f"{'net':>14} {'envs':>5} {'train sps':>10} {'compile s':>9} {'env s':>7} {'rollout s':>9} "
        f"{'learn s':>8} (per update) {'learn GFLOP/s':>13} {'matmul ref':>10} {'learn bound sps':>15}",
        flush=True,
    )
    for spec in nets:
        name, size = spec.split("/")
        for n in envs:
            if size == "paper" and name == "hh_attn" and n > 256 and not args.envs:
                continue  # minutes per point on 2 cores
            variants = ([{}] if args.against_plain else []) + [overrides]
            for env_overrides in variants:
                r = measure(
                    name,
                    size,
                    n,
                    args.human_policy,
                    args.num_steps,
                    updates,
                    breakdown,
                    repeats,
                    args.epochs,
                    args.minibatches,
                    args.microbatch_envs,
                    args.shards,
                    args.predictor,
                    env_overrides,
                )
                results.append(r)
                label = ",".join(f"{k}={v}" for k, v in env_overrides.items()) or "plain"
                print(
                    f"{spec:>14} {n:>5} {r['train_sps']:>10,.0f} {r['compile_s']:>9.1f} "
                    f"{r.get('env_s', 0):>7.3f} {r.get('rollout_s', 0):>9.3f} {r.get('learn_s', 0):>8.3f} "
                    f"{'':>12} {r.get('learn_gflops') or 0:>13.1f} {r.get('matmul_reference_gflops', 0):>10.1f} "
                    f"{r.get('learn_bound_sps', 0):>15,.0f}  [{label}]",
                    flush=True,
                )
            if args.against_plain:
                print(
                    f"{'':>14} {n:>5} ratio {results[-1]['train_sps'] / results[-2]['train_sps']:.2f}x of the "
                    f"plain scenario's rate",
                    flush=True,
                )
    write_json(
        args.out, {"machine": machine_info(), "benchmark": "train_throughput", "quick": args.quick, "results": results}
    )


if __name__ == "__main__":
    main()
