"""tgrf-eval: the paper's metrics table of a trained policy (RUN_DIR) and / or baseline robots."""

from __future__ import annotations

import argparse
import pathlib
import sys
import time

from tgrf_jax.cli.common import (
    Playable,
    Recovery,
    add_config_args,
    add_pretrained_arg,
    check_jax,
    check_policy_fits,
    check_seed,
    check_writable,
    command_line,
    episode_progress,
    load_playable,
    start,
    write_json,
)
from tgrf_jax.config import MAX_EPISODES, ConfigError


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="tgrf-eval",
        description="Evaluate a robot policy on N distinct episodes and print the paper's metrics table "
        "(docs/reference.md). With a RUN_DIR (from tgrf-train) the trained policy is evaluated on the run's "
        "env/reward config (plus any --policy baselines on the same scenario); otherwise the baselines on a YAML "
        "config.",
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
        "DIR/suite.md, DIR/suite.csv and a thumbnail per scenario (docs/scenarios.md); a DIR that holds an "
        "earlier suite is refused unless --overwrite",
    )
    p.add_argument(
        "--suite-rows",
        nargs="+",
        metavar="NAME",
        help="--suite DIR: play only these rows: scenario names, 'real' (the five recorded scenes, which need the "
        "ETH/UCY recordings) or 'synthetic' (every scenario); default: every scenario and, when the recordings "
        "are downloaded, the real scenes",
    )
    p.add_argument("--overwrite", action="store_true", help="--suite DIR: replace the earlier suite in DIR")
    p.add_argument(
        "--all-metrics",
        action="store_true",
        help="print every metric (SPL, clearance, personal space, speed, acceleration, jerk, path "
        "irregularity, time-to-collision, time stalled; docs/metrics.md), not only the paper's; "
        "the JSON always holds all of them",
    )
    return p


SUITE_FILES = ("suite.md", "suite.csv")  # what --suite writes besides its thumbnails


@command_line("tgrf-eval")
def main(argv: list[str] | None, recovery: Recovery) -> int:
    args = parser().parse_args(argv)
    check_jax()
    if not 1 <= args.episodes <= MAX_EPISODES:
        raise ConfigError(f"--episodes = {args.episodes} is out of range; allowed: 1 .. {MAX_EPISODES:,}")
    check_seed(args.seed)
    playable = load_playable(args.config, args.overrides, "tgrf-eval", args.pretrained)
    if args.step is not None and playable.run_dir is None:
        raise ConfigError("--step selects a checkpoint of a RUN_DIR; no RUN_DIR given")
    if args.out:
        check_writable(args.out, "--out", directory=False)
    if args.overwrite and not args.suite:
        raise ConfigError("--overwrite lets --suite DIR replace an earlier suite; no --suite given")
    if args.suite_rows and not args.suite:
        raise ConfigError("--suite-rows chooses the rows of --suite DIR; no --suite given")
    if args.suite:
        check_suite_dir(args.suite, args.overwrite)
        args.suite_scenarios, args.suite_real = suite_rows(args.suite_rows)
        if args.suite_real:
            from tgrf_jax.cli.suite import check_recordings

            check_recordings()

    start()
    check_policy_fits(playable)
    if playable.run_dir is not None:
        suite = f" --suite {args.suite}" if args.suite else ""
        recovery.from_checkpoint = f"tgrf-eval {playable.run_dir}{suite} --step"
    if args.suite:
        return _suite(args, playable)

    import jax

    from tgrf_jax.evaluate import evaluate_params, evaluate_state, format_eval

    platform = jax.devices()[0].platform
    if playable.params is not None:
        print(f"pretrained {playable.pretrained} on {platform}; {args.episodes} episodes, seed {args.seed}", flush=True)
        _say_compiling()
        t0 = time.perf_counter()
        payload = evaluate_params(
            playable.config,
            playable.params,
            args.episodes,
            args.seed,
            baselines=args.policy or (),
            progress=episode_progress,
        )
        payload.update(pretrained=playable.pretrained)
    elif playable.run_dir is not None:
        from tgrf_jax.train.run_dir import restore_run

        state = restore_run(playable.run_dir, args.step)[1]
        print(
            f"{playable.run_dir}: update {int(state.update)} on {platform}; {args.episodes} episodes, seed {args.seed}",
            flush=True,
        )
        _say_compiling()
        t0 = time.perf_counter()
        payload = evaluate_state(
            playable.config, state, args.episodes, args.seed, baselines=args.policy or (), progress=episode_progress
        )
        payload.update(run_dir=str(playable.run_dir), update=int(state.update))
    else:
        from tgrf_jax.env import CrowdNavEnv
        from tgrf_jax.evaluate import evaluate
        from tgrf_jax.policies import baseline

        env = CrowdNavEnv(playable.env, playable.reward)
        print(f"{env} on {platform}; {args.episodes} episodes, seed {args.seed}", flush=True)
        _say_compiling()
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


def _say_compiling() -> None:
    print("  compiling the evaluation program, then playing the episodes ...", flush=True)


def suite_rows(names) -> tuple[tuple[str, ...] | None, bool | None]:
    """--suite-rows as run_suite's (scenarios, real): None, None for every row (the real scenes if downloaded)."""
    from tgrf_jax.config import SCENARIOS

    if not names:
        return None, None
    allowed = ("synthetic", "real", *SCENARIOS)
    unknown = [n for n in names if n not in allowed]
    if unknown:
        raise ConfigError(f"--suite-rows: unknown row {unknown[0]!r}; allowed: {', '.join(allowed)}")
    scenarios = SCENARIOS if "synthetic" in names else tuple(n for n in SCENARIOS if n in names)
    return scenarios, "real" in names


def check_suite_dir(path: str, overwrite: bool) -> None:
    """--suite DIR must be writable, and hold no earlier suite unless --overwrite (raises ConfigError)."""
    check_writable(path, "--suite", directory=True)
    earlier = [name for name in SUITE_FILES if (pathlib.Path(path) / name).exists()]
    if earlier and not overwrite:
        raise ConfigError(
            f"--suite {path!r} holds an earlier suite ({', '.join(earlier)}); give another directory, or "
            "--overwrite to replace it"
        )


def _suite(args, playable: Playable) -> int:
    import dataclasses

    from tgrf_jax.cli.suite import SUITE_SIZES, run_suite
    from tgrf_jax.policies import baseline, make_network_for
    from tgrf_jax.policies.learned import LearnedPolicy

    policies, capacity, config = {}, None, playable.config
    if playable.has_policy:
        params = playable.params
        if params is None:
            from tgrf_jax.train.run_dir import restore_run

            params = restore_run(playable.run_dir, args.step)[1].params
        # Attention over the humans (HH Attn, DS-RNN) has no parameter that depends on the number of human
        # slots, so the same weights play any crowd size; the MLP reads a fixed-size input.
        if config.network.name != "mlp":
            config = dataclasses.replace(config, env=dataclasses.replace(config.env, num_humans=max(SUITE_SIZES)))
        policies["learned"] = LearnedPolicy(make_network_for(config), params)
        capacity = config.env.num_humans
    else:
        from tgrf_jax.config import TrainConfig

        config = TrainConfig(env=playable.env, reward=playable.reward)
    for name in args.policy or ([] if policies else ["orca"]):
        policies[name] = baseline(name)
    run_suite(
        config,
        policies,
        args.suite,
        episodes=args.episodes,
        seed=args.seed,
        capacity=capacity,
        scenarios=args.suite_scenarios,
        real=args.suite_real,
        log=lambda line: print(line, flush=True),
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
