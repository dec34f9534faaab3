"""tgrf-train: train a PPO crowd-navigation policy in a run directory, or resume one."""

from __future__ import annotations

import argparse
import pathlib
import sys

from tgrf_jax.cli.common import (
    Recovery,
    add_config_args,
    check_jax,
    check_writable,
    command_line,
    progress_line,
    start,
    train_config,
)
from tgrf_jax.config import ConfigError


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="tgrf-train",
        description="Train a PPO crowd-navigation policy. Without a config file the embedded default is used "
        "(configs/default.yaml holds the same values).",
    )
    add_config_args(p, "YAML with env/reward/ppo/network/run sections (all optional)")
    p.add_argument("--out-dir", help="run directory (default: runs/<timestamp>_<run.name>)")
    p.add_argument(
        "--resume",
        metavar="RUN_DIR",
        help="continue the run in RUN_DIR from its last checkpoint (a finished run: re-create missing result files)",
    )
    p.add_argument(
        "--from-step",
        type=int,
        metavar="N",
        help="with --resume: continue from checkpoint N instead of the latest (a damaged one, say); "
        "the later checkpoints are deleted and their updates trained again",
    )
    p.add_argument("--print-config", action="store_true", help="print the resolved config and exit")
    return p


@command_line("tgrf-train")
def main(argv: list[str] | None, recovery: Recovery) -> int:
    args = parser().parse_args(argv)
    from tgrf_jax.train.run_dir import default_run_dir, load_run_config

    check_jax()
    if args.from_step is not None and not args.resume:
        raise ConfigError("--from-step N continues a run from one of its checkpoints: it needs --resume RUN_DIR")
    if args.from_step is not None and args.from_step < 0:
        raise ConfigError(f"--from-step = {args.from_step} must be >= 0")
    if args.resume:
        if args.config or args.overrides or args.out_dir:
            raise ConfigError(
                "--resume RUN_DIR takes no config file, --set or --out-dir (the run's own config.yaml is used)"
            )
        config = load_run_config(args.resume)
    else:
        config = train_config(args.config, args.overrides)
    run_dir = pathlib.Path(args.resume or args.out_dir or default_run_dir(config))
    if args.print_config:
        print(config.to_yaml(), end="")
        return 0
    check_writable(run_dir, "--resume" if args.resume else "--out-dir", directory=True)

    start(devices=config.ppo.num_shards, say_cache=True)  # one CPU device per env shard
    from tgrf_jax.train.run_dir import train_run

    recovery.resume = f"resume with: tgrf-train --resume {run_dir}"
    recovery.from_checkpoint = f"tgrf-train --resume {run_dir} --from-step"
    train_run(config, run_dir, resume=bool(args.resume), from_step=args.from_step, log=progress_line)
    return 0


if __name__ == "__main__":
    sys.exit(main())
