"""What the command-line tools share: the config / `--set` / run-directory arguments and their loading, error
reporting, and the process setup done before JAX starts (CPU flags, compilation cache)."""

from __future__ import annotations

import argparse
import dataclasses
import pathlib
import sys

from tgrf_jax.config import (
    ConfigError, EnvConfig, RewardConfig, TrainConfig, apply_overrides, load_yaml, reward_config_from_dict,
)


def add_config_args(parser: argparse.ArgumentParser, config_help: str, *, run_dir: bool = False) -> None:
    """The positional config (or, with `run_dir`, RUN_DIR|CONFIG) argument and the repeatable `--set`."""
    parser.add_argument("config", nargs="?", metavar="RUN_DIR|CONFIG" if run_dir else "CONFIG", help=config_help)
    parser.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                        help="override a config value, e.g. --set ppo.lr=1e-4 --set env.human_policy=social_force")


def train_config(path: str | None, overrides: list[str]) -> TrainConfig:
    """A TrainConfig from an optional YAML file plus `--set` overrides (the embedded default without a file)."""
    return TrainConfig.from_dict(apply_overrides(load_yaml(path) if path else {}, overrides))


@dataclasses.dataclass(frozen=True)
class Scenario:
    """What tgrf-eval and tgrf-render play: a run directory's env / reward (and its trained policy), or the env /
    reward sections of a YAML file."""

    env: EnvConfig
    reward: RewardConfig
    run_dir: pathlib.Path | None = None
    config: TrainConfig | None = None  # the run's (or pretrained policy's) config
    pretrained: str | None = None  # a pretrained policy's name or directory
    params: dict | None = None  # its network parameters


def add_pretrained_arg(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--pretrained", metavar="NAME|DIR",
                        help="a trained policy shipped with tgrf-jax (see tgrf_jax.pretrained.available()) or "
                        "exported to a directory, played on its own env/reward config")


def scenario(source: str | None, overrides: list[str], tool: str, pretrained: str | None = None) -> Scenario:
    """Resolve RUN_DIR|CONFIG (or a pretrained policy) plus `--set` (only env.* and reward.* apply); raises
    ConfigError."""
    bad = [o for o in overrides if o.split(".", 1)[0] not in ("env", "reward")]
    if pretrained is not None:
        from tgrf_jax import pretrained as pretrained_lib

        if source is not None:
            raise ConfigError(f"--pretrained plays its own config; give no RUN_DIR|CONFIG (got {source!r})")
        if bad:
            raise ConfigError(f"with --pretrained only env.* and reward.* can be overridden, not {bad}")
        config, params, _ = pretrained_lib.load(pretrained)
        config = TrainConfig.from_dict(apply_overrides(config.to_dict(), overrides))
        return Scenario(config.env, config.reward, None, config, pretrained, params)
    if source is not None and pathlib.Path(source).is_dir():
        from tgrf_jax.train.loop import load_run_config

        config = load_run_config(source)
        if bad:
            raise ConfigError(f"with a RUN_DIR only env.* and reward.* can be overridden, not {bad}")
        config = TrainConfig.from_dict(apply_overrides(config.to_dict(), overrides))
        return Scenario(config.env, config.reward, pathlib.Path(source), config)
    data = apply_overrides(load_yaml(source) if source else {}, overrides)
    unknown = set(data) - {"env", "reward"}
    if unknown:
        raise ConfigError(f"unknown config section(s) {sorted(unknown)}; {tool} reads: env, reward")
    return Scenario(EnvConfig.from_dict(data.get("env")), reward_config_from_dict(data.get("reward")))


def error(tool: str, e: Exception) -> int:
    print(f"{tool}: error: {e}", file=sys.stderr)
    return 2


def start(devices: int | None = None, say_cache: bool = False) -> None:
    """Process setup before JAX starts: XLA:CPU flags (`tgrf_jax.configure_cpu`) and the compilation cache."""
    from tgrf_jax import compile_cache
    from tgrf_jax.cpu import configure_cpu

    configure_cpu(devices)
    cache_dir = compile_cache.enable()
    if cache_dir and say_cache:
        print(f"compilation cache: {cache_dir} (set {compile_cache.ENV_VAR}=off to disable)", flush=True)


def write_json(path: str | None, payload: dict) -> None:
    import json

    if path:
        out = pathlib.Path(path)
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(json.dumps(payload, indent=2))
        print(f"wrote {out}")
