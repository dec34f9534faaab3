"""tgrf-eval: the paper's metrics table of a trained policy (RUN_DIR) and / or baseline robots."""

from __future__ import annotations

import argparse
import sys
import time

from tgrf_jax.cli.common import (
    add_config_args,
    add_pretrained_arg,
    check_jax,
    check_observation_fits,
    check_seed,
    check_writable,
    checkpoint_error,
    episode_progress,
    error,
    scenario,
    start,
    write_json,
)
from tgrf_jax.config import MAX_EPISODES, ConfigError


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="tgrf-eval",
        description="Evaluate a robot policy on N distinct episodes and print the paper's metrics table (docs/reference.md). "
        "With a RUN_DIR (from tgrf-train) the trained policy is evaluated on the run's env/reward config "
        "(plus any --policy baselines on the same scenario); otherwise the baselines on a YAML config.",
    )
    add_config_args(
        p,
        "a tgrf-train run directory, or a YAML file with env/reward sections, such as a tgrf-train "
        "config (default: paper scenario)",
        run_dir=True,
    )
    p.add_argument(
        "--policy",
        action="append",
        choices=["straight", "orca"],
        help="baseline robot policy (repeatable; default without RUN_DIR: both)",
    )
    p.add_argument(
        "--episodes", type=int, default=500, help="distinct episodes, played in batches of 1000 (default 500)"
    )
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--step", type=int, default=None, help="RUN_DIR: checkpoint (update) to evaluate; default: latest")
    add_pretrained_arg(p)
    p.add_argument("--out", help="write the metrics as JSON to this file")
    p.add_argument(
        "--suite",
        metavar="DIR",
        help="benchmark: play the policy (RUN_DIR, --pretrained, or the --policy baselines; default orca) "
        "on every scenario x 5, 10, 20, 30 humans, --episodes each with the fixed --seed, and write "
        "DIR/suite.md, DIR/suite.csv and a thumbnail per scenario (docs/scenarios.md)",
    )
    p.add_argument(
        "--all-metrics",
        action="store_true",
        help="print every metric (SPL, clearance, personal space, speed, acceleration, jerk, path "
        "irregularity, time-to-collision, time stalled; docs/metrics.md), not only the paper's; "
        "the JSON always holds all of them",
    )
    return p


def main(argv: list[str] | None = None) -> int:
    args = parser().parse_args(argv)
    try:
        check_jax()
        if not 1 <= args.episodes <= MAX_EPISODES:
            raise ConfigError(f"--episodes = {args.episodes} is out of range; allowed: 1 .. {MAX_EPISODES:,}")
        check_seed(args.seed)
        sc = scenario(args.config, args.overrides, "tgrf-eval", args.pretrained)
        if args.step is not None and sc.run_dir is None:
            raise ConfigError("--step selects a checkpoint of a RUN_DIR; no RUN_DIR given")
        if args.out:
            check_writable(args.out, "--out", directory=False)
    except ConfigError as e:
        return error("tgrf-eval", e)

    start()
    import jax

    if args.suite:
        return _suite(args, sc)

    from tgrf_jax.evaluate import evaluate_params, evaluate_state, format_eval

    if sc.params is not None:
        print(
            f"pretrained {sc.pretrained} on {jax.devices()[0].platform}; {args.episodes} episodes, seed {args.seed}",
            flush=True,
        )
        t0 = time.perf_counter()
        payload = evaluate_params(
            sc.config, sc.params, args.episodes, args.seed, baselines=args.policy or (), progress=episode_progress
        )
        payload.update(pretrained=sc.pretrained)
    elif sc.run_dir is not None:
        state, status = _restore(sc, args.step, f"tgrf-eval {sc.run_dir} --step")
        if state is None:
            return status
        print(
            f"{sc.run_dir}: update {int(state.update)} on {jax.devices()[0].platform}; {args.episodes} episodes, "
            f"seed {args.seed}",
            flush=True,
        )
        t0 = time.perf_counter()
        payload = evaluate_state(
            sc.config, state, args.episodes, args.seed, baselines=args.policy or (), progress=episode_progress
        )
        payload.update(run_dir=str(sc.run_dir), update=int(state.update))
    else:
        from tgrf_jax.env import CrowdNavEnv
        from tgrf_jax.evaluate import evaluate
        from tgrf_jax.policies import baseline

        env = CrowdNavEnv(sc.env, sc.reward)
        print(f"{env} on {jax.devices()[0].platform}; {args.episodes} episodes, seed {args.seed}", flush=True)
        t0 = time.perf_counter()
        results = {
            name: evaluate(
                env, baseline(name), jax.random.key(args.seed), args.episodes, progress=episode_progress(name)
            )
            for name in args.policy or ["straight", "orca"]
        }
        payload = {"env": repr(env), "seed": args.seed, "results": {k: v.to_dict() for k, v in results.items()}}
    print(f"  done in {time.perf_counter() - t0:.1f} s (compile included)", flush=True)
    print(format_eval(payload, args.all_metrics))
    write_json(args.out, payload)
    return 0


def _restore(sc, step, resume_hint: str):
    """(the run's training state, None), or (None, the exit status) after printing why it cannot be restored."""
    from tgrf_jax.storage.checkpoint import CheckpointError
    from tgrf_jax.train.run_dir import restore_run

    try:
        check_observation_fits(sc)
        return restore_run(sc.run_dir, step)[1], None
    except CheckpointError as e:
        return None, checkpoint_error("tgrf-eval", e, resume_hint)
    except ConfigError as e:
        return None, error("tgrf-eval", e)


def _suite(args, sc) -> int:
    import dataclasses

    from tgrf_jax.cli.suite import SUITE_SIZES, run_suite
    from tgrf_jax.policies import baseline, make_network_for
    from tgrf_jax.policies.learned import LearnedPolicy

    policies, capacity, config = {}, None, sc.config
    if sc.params is not None or sc.run_dir is not None:
        params = sc.params
        if params is None:
            state, status = _restore(sc, args.step, f"tgrf-eval {sc.run_dir} --suite {args.suite} --step")
            if state is None:
                return status
            params = state.params
        # Attention over the humans (HH Attn, DS-RNN) has no parameter that depends on the number of human
        # slots, so the same weights play any crowd size; the MLP reads a fixed-size input.
        if config.network.name != "mlp":
            config = dataclasses.replace(config, env=dataclasses.replace(config.env, num_humans=max(SUITE_SIZES)))
        policies["learned"] = LearnedPolicy(make_network_for(config), params)
        capacity = config.env.num_humans
    else:
        from tgrf_jax.config import TrainConfig

        config = TrainConfig(env=sc.env, reward=sc.reward)
    for name in args.policy or ([] if policies else ["orca"]):
        policies[name] = baseline(name)
    run_suite(
        config,
        policies,
        args.suite,
        episodes=args.episodes,
        seed=args.seed,
        capacity=capacity,
        log=lambda line: print(line, flush=True),
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
