"""Command-line entry points."""

from __future__ import annotations

import argparse
import json
import pathlib
import sys
import time

from tgrf_jax.config import ConfigError, EnvConfig, apply_overrides, load_yaml, reward_config_from_dict


def _load_env_and_reward(config_path: str | None, overrides: list[str]):
    data = load_yaml(config_path) if config_path else {}
    data = apply_overrides(data, overrides)
    unknown = set(data) - {"env", "reward"}
    if unknown:
        raise ConfigError(f"unknown config section(s) {sorted(unknown)}; tgrf-eval reads: env, reward")
    return EnvConfig.from_dict(data.get("env")), reward_config_from_dict(data.get("reward"))


def eval_main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="tgrf-eval",
        description="Evaluate a robot policy on N distinct episodes and print the SPEC A.4 metrics table. "
        "With a RUN_DIR (from tgrf-train) the trained policy is evaluated on the run's env/reward config "
        "(plus any --policy baselines on the same scenario); otherwise the baselines on a YAML config.",
    )
    parser.add_argument("config", nargs="?", metavar="RUN_DIR|CONFIG",
                        help="a tgrf-train run directory, or a YAML file with env/reward sections "
                        "(default: paper scenario)")
    parser.add_argument("--policy", action="append", choices=["straight", "orca"],
                        help="baseline robot policy (repeatable; default without RUN_DIR: both)")
    parser.add_argument("--episodes", type=int, default=500)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--step", type=int, default=None, help="RUN_DIR: checkpoint (update) to evaluate; default: latest")
    parser.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                        help="override a config value, e.g. --set env.human_policy=social_force")
    parser.add_argument("--out", help="write the metrics as JSON to this file")
    args = parser.parse_args(argv)
    if args.config and pathlib.Path(args.config).is_dir():
        return _eval_run(args)
    try:
        if args.episodes < 1:
            raise ConfigError(f"--episodes = {args.episodes} must be >= 1")
        env_config, reward_config = _load_env_and_reward(args.config, args.overrides)
    except ConfigError as e:
        print(f"tgrf-eval: error: {e}", file=sys.stderr)
        return 2

    import jax

    from tgrf_jax import compile_cache
    from tgrf_jax.env import CrowdNavEnv
    from tgrf_jax.evaluate import evaluate, format_table
    from tgrf_jax.policies import baseline

    compile_cache.enable()

    env = CrowdNavEnv(env_config, reward_config)
    print(f"{env} on {jax.devices()[0].platform}; {args.episodes} episodes, seed {args.seed}", flush=True)
    results = {}
    for name in args.policy or ["straight", "orca"]:
        start = time.perf_counter()
        results[name] = evaluate(env, baseline(name), jax.random.key(args.seed), args.episodes)
        print(f"  {name}: done in {time.perf_counter() - start:.1f} s (compile included)", flush=True)
    print(format_table(results))
    if args.out:
        path = pathlib.Path(args.out)
        path.parent.mkdir(parents=True, exist_ok=True)
        payload = {"env": repr(env), "seed": args.seed, "results": {k: v.to_dict() for k, v in results.items()}}
        path.write_text(json.dumps(payload, indent=2))
        print(f"wrote {path}")
    return 0


def _eval_run(args) -> int:
    """tgrf-eval RUN_DIR: the trained policy (and optional baselines) on the run's own scenario."""
    from tgrf_jax.config import TrainConfig
    from tgrf_jax.train.checkpoint import CheckpointError

    try:
        if args.episodes < 1:
            raise ConfigError(f"--episodes = {args.episodes} must be >= 1")
        from tgrf_jax.train.loop import load_run_config

        config = load_run_config(args.config)
        if args.overrides:
            bad = [o for o in args.overrides if o.split(".", 1)[0] not in ("env", "reward")]
            if bad:
                raise ConfigError(f"with a RUN_DIR only env.* and reward.* can be overridden, not {bad}")
            config = TrainConfig.from_dict(apply_overrides(config.to_dict(), args.overrides))
    except ConfigError as e:
        print(f"tgrf-eval: error: {e}", file=sys.stderr)
        return 2

    import jax

    from tgrf_jax import compile_cache
    from tgrf_jax.train.loop import evaluate_state, format_eval, restore_run

    compile_cache.enable()

    try:
        _, state = restore_run(args.config, args.step)
    except (CheckpointError, ConfigError) as e:
        print(f"tgrf-eval: error: {e}", file=sys.stderr)
        return 2
    print(f"{args.config}: update {int(state.update)} on {jax.devices()[0].platform}; "
          f"{args.episodes} episodes, seed {args.seed}", flush=True)
    start = time.perf_counter()
    payload = evaluate_state(config, state, args.episodes, args.seed, baselines=args.policy or ())
    payload.update(run_dir=str(args.config), update=int(state.update))
    print(f"  done in {time.perf_counter() - start:.1f} s (compile included)")
    print(format_eval(payload))
    if args.out:
        path = pathlib.Path(args.out)
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(payload, indent=2))
        print(f"wrote {path}")
    return 0


def train_main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="tgrf-train",
        description="Train a PPO crowd-navigation policy. Without a config file the embedded default is used "
        "(configs/default.yaml holds the same values).",
    )
    parser.add_argument("config", nargs="?", help="YAML with env/reward/ppo/network/run sections (all optional)")
    parser.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                        help="override a config value, e.g. --set ppo.lr=1e-4 --set reward.h_disc=2.0")
    parser.add_argument("--out-dir", help="run directory (default: runs/<timestamp>_<run.name>)")
    parser.add_argument("--resume", metavar="RUN_DIR", help="continue the run in RUN_DIR from its last checkpoint")
    parser.add_argument("--print-config", action="store_true", help="print the resolved config and exit")
    args = parser.parse_args(argv)

    from tgrf_jax.config import TrainConfig
    from tgrf_jax.train.checkpoint import CheckpointError

    try:
        if args.resume:
            if args.config or args.overrides or args.out_dir:
                raise ConfigError("--resume RUN_DIR takes no config file, --set or --out-dir (the run's own "
                                  "config.yaml is used)")
            from tgrf_jax.train.loop import load_run_config

            config = load_run_config(args.resume)
        else:
            data = load_yaml(args.config) if args.config else {}
            config = TrainConfig.from_dict(apply_overrides(data, args.overrides))
    except ConfigError as e:
        print(f"tgrf-train: error: {e}", file=sys.stderr)
        return 2
    if args.print_config:
        print(config.to_yaml(), end="")
        return 0

    from tgrf_jax import compile_cache
    from tgrf_jax.train import shards
    from tgrf_jax.train.loop import default_run_dir, train_run

    shards.request_cpu_devices(config.ppo.num_shards)  # one CPU device per env shard, before JAX starts
    cache_dir = compile_cache.enable()
    if cache_dir:
        print(f"compilation cache: {cache_dir} (set {compile_cache.ENV_VAR}=off to disable)", flush=True)
    run_dir = pathlib.Path(args.resume or args.out_dir or default_run_dir(config))
    try:
        train_run(config, run_dir, resume=bool(args.resume), log=lambda m: print(m, flush=True))
    except (CheckpointError, ConfigError) as e:
        print(f"tgrf-train: error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"tgrf-train: interrupted; resume with: tgrf-train --resume {run_dir}", file=sys.stderr)
        return 130
    return 0
