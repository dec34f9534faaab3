"""What population-based tuning costs on top of the sweep it runs: the exploit-and-explore step and the objective's
evaluation, each against the training time of one exploit interval of the same population (one process, one run),
in each of tgrf-tune's layouts (batched: one vmapped program; sequential: the members in turn).

For a population of P members of a config (the embedded default unless --config), all timed on the same placed
state after compilation, per layout:

  * ``update_s``: one training update of all members (the sweep program's chunk, median over --updates updates),
    and ``env_steps_per_s`` from it
  * ``exploit_s``: the exploit-and-explore step (truncation selection, copying weights, optimiser state and
    hyper-parameters between members, perturbation), median of 5 calls
  * ``objective_s``: scoring every member on --objective-episodes fixed test episodes (median of 3 calls)
  * at the default interval (a tenth of the run's updates, or --interval): ``exploit_share`` = exploit_s /
    (interval x update_s) and ``objective_share`` likewise

    python -m benchmarks.tune_overhead --quick --out bench_results/tune_quick.json
    python -m benchmarks.tune_overhead --population 16 --out bench_results/tune.json
"""

from __future__ import annotations

import argparse
import os
import statistics
import time

import jax
import jax.numpy as jnp

from benchmarks.common import machine_info, write_json
from tgrf_jax import configure_cpu


def _median_seconds(fn, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        jax.block_until_ready(fn())
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def _measure(spec, layout: str, updates: int) -> dict:
    import dataclasses

    from tgrf_jax.tune.run import TunedProgram

    spec = dataclasses.replace(spec, layout=layout)
    program = TunedProgram(spec, jax.devices(), say=lambda line: None)
    state = program.init()
    program.compile(state)
    state, _ = program.train_chunk(state, 1)  # warm
    update_times = []
    for _ in range(updates):
        start = time.perf_counter()
        state, metrics = program.train_chunk(state, 1)
        jax.block_until_ready(metrics)
        update_times.append(time.perf_counter() - start)
    update_s = statistics.median(update_times)

    program.scores(state)  # compiles the evaluation
    objective_s = _median_seconds(lambda: jnp.asarray(program.scores(state)), 3)
    scores = jnp.asarray(program.scores(state), jnp.float32)
    holder = {"state": state}

    def one_step():
        holder["state"], record = program.exploit(holder["state"], scores, jax.random.PRNGKey(0))  # chained
        return record, holder["state"]

    one_step()  # compiles
    exploit_s = _median_seconds(one_step, 5)
    interval = spec.interval
    return {
        "update_s": update_s,
        "env_steps_per_s": spec.population * program.batch_size / update_s,
        "exploit_s": exploit_s,
        "objective_s": objective_s,
        "exploit_share": exploit_s / (interval * update_s),
        "objective_share": objective_s / (interval * update_s),
    }


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--config", default=None, help="YAML config (default: the embedded default)")
    parser.add_argument("--population", type=int, default=8)
    parser.add_argument("--updates", type=int, default=4, help="updates timed for update_s")
    parser.add_argument("--interval", type=int, default=None, help="updates between exploit steps (default: a tenth)")
    parser.add_argument("--objective-episodes", type=int, default=100)
    parser.add_argument(
        "--layouts", default="batched,sequential", help="comma-separated tgrf-tune layouts, each timed in turn"
    )
    parser.add_argument("--quick", action="store_true", help="configs/tiny.yaml, population 4")
    parser.add_argument("--out", default=None, help="JSON file to write")
    args = parser.parse_args(argv)
    if args.quick:
        args.config, args.population = args.config or "configs/tiny.yaml", 4
    configure_cpu(devices=len(os.sched_getaffinity(0)))

    from tgrf_jax.sweep.grid import LAYOUTS
    from tgrf_jax.tune.spec import TuneSpec

    layouts = [name.strip() for name in args.layouts.split(",") if name.strip()]
    unknown = [name for name in layouts if name not in LAYOUTS]
    if unknown or not layouts:
        parser.error(f"--layouts {args.layouts!r}: allowed a comma-separated choice of {', '.join(LAYOUTS)}")
    spec = TuneSpec.create(
        args.config,
        ["reward.h_disc=0.5:5:log", "ppo.lr=1e-4:3e-3:log"],
        population=args.population,
        interval=args.interval,
        objective_episodes=args.objective_episodes,
    )
    result = {
        "machine": machine_info(),
        "config": args.config or "embedded default",
        "population": spec.population,
        "interval": spec.interval,
        "objective_episodes": spec.objective_episodes,
        "layouts": {},
    }
    for layout in layouts:
        m = result["layouts"][layout] = _measure(spec, layout, args.updates)
        print(
            f"{layout}: population {spec.population}, interval {spec.interval} updates: one update "
            f"{m['update_s'] * 1e3:.1f} ms ({m['env_steps_per_s']:,.0f} env-steps/s); exploit step "
            f"{m['exploit_s'] * 1e3:.2f} ms ({100 * m['exploit_share']:.3f}% of an interval); objective on "
            f"{spec.objective_episodes} episodes {m['objective_s']:.2f} s ({100 * m['objective_share']:.2f}% of an "
            "interval)"
        )
    write_json(args.out, result)
    return result


if __name__ == "__main__":
    main()
