"""What population-based tuning costs on top of the sweep it runs: the exploit-and-explore step and the objective's
evaluation, each against the training time of one exploit interval of the same population (one process, one run).

For a population of P members of a config (the embedded default unless --config), all timed on the same placed
state after compilation:

  * ``update_s``: one training update of all members (the sweep program's chunk, median over --updates updates)
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


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--config", default=None, help="YAML config (default: the embedded default)")
    parser.add_argument("--population", type=int, default=8)
    parser.add_argument("--updates", type=int, default=4, help="updates timed for update_s")
    parser.add_argument("--interval", type=int, default=None, help="updates between exploit steps (default: a tenth)")
    parser.add_argument("--objective-episodes", type=int, default=100)
    parser.add_argument("--quick", action="store_true", help="configs/tiny.yaml, population 4")
    parser.add_argument("--out", default=None, help="JSON file to write")
    args = parser.parse_args(argv)
    if args.quick:
        args.config, args.population = args.config or "configs/tiny.yaml", 4
    configure_cpu(devices=len(os.sched_getaffinity(0)))

    from tgrf_jax.tune.run import TunedProgram, _exploit_program
    from tgrf_jax.tune.spec import TuneSpec

    spec = TuneSpec.create(
        args.config,
        ["reward.h_disc=0.5:5:log", "ppo.lr=1e-4:3e-3:log"],
        population=args.population,
        interval=args.interval,
        objective_episodes=args.objective_episodes,
    )
    program = TunedProgram(spec, jax.devices(), say=lambda line: None)
    state = program.init()
    program.compile(state)
    step = super(TunedProgram, program).run_chunk  # the sweep's chunk, without the exploit step

    state, _ = step(state, 1)  # warm
    update_times = []
    for _ in range(args.updates):
        start = time.perf_counter()
        state, metrics = step(state, 1)
        jax.block_until_ready(metrics)
        update_times.append(time.perf_counter() - start)
    update_s = statistics.median(update_times)

    program.scores(state)  # compiles the evaluation
    objective_s = _median_seconds(lambda: jnp.asarray(program.scores(state)), 3)
    scores = jnp.asarray(program.scores(state), jnp.float32)
    exploit = _exploit_program(spec, jax.tree.map(lambda x: x.sharding, state))
    holder = {"state": state}

    def one_step():
        holder["state"], record = exploit(holder["state"], scores, jax.random.PRNGKey(0))  # donated: chained
        return record

    one_step()  # compiles
    exploit_s = _median_seconds(one_step, 5)

    interval = spec.interval
    result = {
        "machine": machine_info(),
        "config": args.config or "embedded default",
        "population": spec.population,
        "interval": interval,
        "objective_episodes": spec.objective_episodes,
        "update_s": update_s,
        "exploit_s": exploit_s,
        "objective_s": objective_s,
        "exploit_share": exploit_s / (interval * update_s),
        "objective_share": objective_s / (interval * update_s),
    }
    print(
        f"population {spec.population}, interval {interval} updates: one update {update_s * 1e3:.1f} ms; "
        f"exploit step {exploit_s * 1e3:.2f} ms ({100 * result['exploit_share']:.3f}% of an interval); "
        f"objective on {spec.objective_episodes} episodes {objective_s:.2f} s "
        f"({100 * result['objective_share']:.2f}% of an interval)"
    )
    write_json(args.out, result)
    return result


if __name__ == "__main__":
    main()
