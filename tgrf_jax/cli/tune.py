"""tgrf-tune: population-based training of any traced fields (TGRF's h and sigma, PPO's rates, ...) as a sweep's
program, members scored on the same test episodes by an objective over evaluation metrics."""

from __future__ import annotations

import argparse
import dataclasses
import datetime
import os
import pathlib
import sys

from tgrf_jax.cli.common import (
    Recovery,
    add_config_args,
    add_layout_arg,
    check_jax,
    check_writable,
    command_line,
    progress_line,
    resolve_layout,
    start,
)
from tgrf_jax.config import ConfigError


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="tgrf-tune",
        description="Tune traced fields by population-based training: P members train as a sweep does; every "
        "--interval updates the worst take the weights and hyper-parameters of the best, then perturb them.",
    )
    add_config_args(p, "YAML config as for tgrf-train (default: the embedded default)")
    p.add_argument(
        "--space",
        action="append",
        default=[],
        metavar="FIELD=LO:HI[:log]",
        help="a searched field and its bounds, e.g. --space reward.h_disc=0.5:5:log (repeatable); any numeric "
        "traced field (tgrf-sweep --list-griddable)",
    )
    p.add_argument("--population", type=int, default=8, help="members (default 8)")
    p.add_argument(
        "--objective",
        default="success - 0.5 * collision",
        help="expression over evaluation metrics to maximise (default: 'success - 0.5 * collision'); metrics: "
        "success, collision, timeout, nav_time, path_length, itr, spl, psc, ... (rates as fractions)",
    )
    p.add_argument("--interval", type=int, default=None, help="updates between exploit steps (default: a tenth)")
    p.add_argument("--fraction", type=float, default=0.25, help="share replaced per step (default 0.25)")
    p.add_argument("--resample", type=float, default=0.25, help="chance of a fresh draw instead of x0.8 / x1.25")
    p.add_argument("--objective-episodes", type=int, default=100, help="test episodes per member and step")
    p.add_argument("--final-episodes", type=int, default=500, help="the best member's final test episodes")
    p.add_argument("--out", help="tune directory (default: runs/<timestamp>_tune_<run.name>)")
    p.add_argument("--resume", metavar="TUNE_DIR", help="continue the tune in TUNE_DIR from its last checkpoint")
    p.add_argument(
        "--devices",
        type=int,
        default=None,
        metavar="N",
        help="use the first N devices, N dividing the population (default: the most devices that divide it)",
    )
    add_layout_arg(
        p,
        "batched: the population as one vmapped program, members split over the devices; sequential: the "
        "members take turns, each through tgrf-train's own program (faster on CPUs); auto (default for a new "
        "tune): sequential on CPU devices, else batched. Recorded in tune.yaml: --resume keeps it, --resume with "
        "--layout switches it (the members then match an unswitched resume up to float rounding)",
    )
    p.add_argument("--print-plan", action="store_true", help="print the members and exit (nothing is compiled)")
    return p


@command_line("tgrf-tune")
def main(argv: list[str] | None, recovery: Recovery) -> int:
    args = parser().parse_args(argv)
    from tgrf_jax.tune.spec import TuneSpec, load_tune

    check_jax()
    if args.resume:
        if args.config or args.space or args.overrides or args.out:
            raise ConfigError("--resume TUNE_DIR takes no config file, --space, --set or --out (its tune.yaml is used)")
        spec = load_tune(args.resume)
    else:
        spec = TuneSpec.create(
            args.config,
            args.space,
            population=args.population,
            objective=args.objective,
            interval=args.interval,
            overrides=args.overrides,
            fraction=args.fraction,
            resample_prob=args.resample,
            objective_episodes=args.objective_episodes,
            final_episodes=args.final_episodes,
        )
    if args.print_plan:
        # "auto" is resolved once JAX knows its devices, which the plan does not start
        print(spec.describe(layout=args.layout or (spec.layout if args.resume else "auto")))
        return 0
    stamp = datetime.datetime.now().strftime("%Y%m%d-%H%M%S")
    tune_dir = pathlib.Path(args.resume or args.out or f"runs/{stamp}_tune_{spec.base['run']['name']}")
    check_writable(tune_dir, "--resume" if args.resume else "--out", directory=True)
    start(devices=len(os.sched_getaffinity(0)))
    from tgrf_jax.tune.run import run_tune

    layout = resolve_layout(args.layout or (None if args.resume else "auto"))
    recovery.resume = f"resume with: tgrf-tune --resume {tune_dir}"
    run_tune(
        None if args.resume else dataclasses.replace(spec, layout=layout),
        tune_dir,
        resume=bool(args.resume),
        log=progress_line,
        num_devices=args.devices,
        layout=layout if args.resume else None,
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
