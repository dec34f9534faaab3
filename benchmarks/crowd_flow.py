"""Crowd flow among obstacles: the stuck rate of the humans (docs/walls.md) in each obstacle scenario, with their
routing on and off, in one run.

Each row plays B environments for T steps of one episode each with the robot standing at its start, invisible
to the humans, and never ending the episode (a human walking into it is not an outcome here), so the crowd alone
is measured over the whole window; it reports the share of active human-steps that are stuck, the humans given
new goals for staying stuck, and those whose goal has no path.

    python -m benchmarks.crowd_flow --out bench_results/crowd_flow.json
"""

from __future__ import annotations

import argparse
import time

import jax
import jax.numpy as jnp
import numpy as np

from benchmarks.common import machine_info, write_json
from tgrf_jax import CrowdNavEnv
from tgrf_jax.config import OBSTACLE_SCENARIOS


def flow(scenario: str, routing: bool, human_policy: str, envs: int, steps: int, seed: int) -> dict:
    env = CrowdNavEnv(
        {"scenario": scenario, "num_humans": 20, "human_policy": human_policy, "human_routing": routing}, "tgrf"
    )
    params = env.default_params

    @jax.jit
    def run(key):
        _, state = jax.vmap(env.reset, in_axes=(0, None))(jax.random.split(key, envs), params)
        still = jnp.zeros((envs, env.action_size))

        def body(state, k):
            step = jax.vmap(env.step_env, in_axes=(0, 0, 0, None))  # no auto-reset: the crowd keeps walking
            _, state, _, _, _, info = step(jax.random.split(k, envs), state, still, params)
            return state, (info.humans_stuck, info.humans_active, info.goals_reassigned, info.humans_unreachable)

        return jax.lax.scan(body, state, jax.random.split(jax.random.fold_in(key, 1), steps))[1]

    start = time.perf_counter()
    stuck, active, reassigned, unreachable = (np.asarray(x) for x in run(jax.random.key(seed)))
    # a jam, once formed, tends to stay: the rate by quarter of the window shows whether it grows
    quarters = [slice(q * steps // 4, (q + 1) * steps // 4) for q in range(4)]
    return {
        "scenario": scenario,
        "human_policy": human_policy,
        "routing": routing,
        "stuck_rate_pct": round(100.0 * stuck.sum() / active.sum(), 3),
        "stuck_rate_by_quarter_pct": [round(100.0 * stuck[q].sum() / max(active[q].sum(), 1), 2) for q in quarters],
        "unreachable_rate_pct": round(100.0 * unreachable.sum() / active.sum(), 3),
        "goals_reassigned_per_env": round(float(reassigned.sum()) / envs, 2),
        "seconds": round(time.perf_counter() - start, 1),
    }


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--envs", type=int, default=32)
    parser.add_argument("--steps", type=int, default=200, help="steps per env (200 = one 50 s episode)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--human-policy", default="orca", choices=["orca", "social_force"])
    parser.add_argument("--scenarios", nargs="*", default=list(OBSTACLE_SCENARIOS), choices=list(OBSTACLE_SCENARIOS))
    parser.add_argument("--out", help="write results as JSON here")
    args = parser.parse_args(argv)
    info = machine_info()
    print(f"machine: {info['cpu']} x{info['cpu_count']}, jax {info['jax']} on {info['backend']}")
    print(
        f"{'scenario':>18} {'routing':>8} {'stuck %':>8} {'by quarter of the window (%)':>28} {'unreachable %':>14} "
        f"{'new goals/env':>14}"
    )
    rows = []
    for scenario in args.scenarios:
        for routing in (True, False):
            row = flow(scenario, routing, args.human_policy, args.envs, args.steps, args.seed)
            rows.append(row)
            print(
                f"{scenario:>18} {str(routing):>8} {row['stuck_rate_pct']:>8.2f} "
                f"{' / '.join(f'{x:.2f}' for x in row['stuck_rate_by_quarter_pct']):>28} "
                f"{row['unreachable_rate_pct']:>14.2f} "
                f"{row['goals_reassigned_per_env']:>14.2f}",
                flush=True,
            )
    write_json(
        args.out,
        {"benchmark": "crowd_flow", "envs": args.envs, "steps": args.steps, "machine": info, "results": rows},
    )


if __name__ == "__main__":
    main()
