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
        description="Evaluate a robot policy on N distinct episodes and print the SPEC A.4 metrics table.",
    )
    parser.add_argument("config", nargs="?", help="YAML file with env/reward sections (default: paper scenario)")
    parser.add_argument("--policy", action="append", choices=["straight", "orca"],
                        help="baseline robot policy (repeatable; default: both)")
    parser.add_argument("--episodes", type=int, default=500)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                        help="override a config value, e.g. --set env.human_policy=social_force")
    parser.add_argument("--out", help="write the metrics as JSON to this file")
    args = parser.parse_args(argv)
    try:
        if args.episodes < 1:
            raise ConfigError(f"--episodes = {args.episodes} must be >= 1")
        env_config, reward_config = _load_env_and_reward(args.config, args.overrides)
    except ConfigError as e:
        print(f"tgrf-eval: error: {e}", file=sys.stderr)
        return 2

    import jax

    from tgrf_jax.env import CrowdNavEnv
    from tgrf_jax.evaluate import evaluate, format_table
    from tgrf_jax.policies import baseline

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
