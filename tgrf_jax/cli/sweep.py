"""tgrf-sweep: a grid of hyper-parameters x seeds trained as one vmapped, compiled program, split over devices."""

from __future__ import annotations

import argparse
import dataclasses
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
from tgrf_jax.config import ConfigError, griddable_fields


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="tgrf-sweep",
        description="Train a grid of hyper-parameters x seeds as one vmapped, compiled program, with the runs split "
        "over all devices. Only traced (numeric, shape-preserving) fields can be gridded; see --list-griddable.",
    )
    add_config_args(p, "YAML config as for tgrf-train (default: the embedded default)")
    p.add_argument(
        "--grid",
        action="append",
        default=[],
        metavar="KEY=V1,V2,...",
        help="a grid axis, e.g. --grid reward.h_disc=0.5,1.0,2.5 (repeatable: Cartesian product)",
    )
    p.add_argument(
        "--paired",
        action="store_true",
        help="pair the --grid axes value by value instead of crossing them: the i-th values of all axes make "
        "point i (explicit points, e.g. random-search draws); every axis needs as many values",
    )
    p.add_argument(
        "--seeds",
        default=None,
        metavar="N|S1,S2,...",
        help="a count (run.seed, run.seed+1, ...) or a comma-separated list of seeds (default: 1)",
    )
    p.add_argument("--out", help="sweep directory (default: runs/<timestamp>_sweep_<run.name>)")
    p.add_argument(
        "--resume",
        metavar="SWEEP_DIR",
        help="continue the sweep in SWEEP_DIR from its last checkpoint (a finished sweep: re-create its result files)",
    )
    p.add_argument(
        "--from-step",
        type=int,
        metavar="N",
        help="with --resume: continue from checkpoint N instead of the latest (a damaged one, say); "
        "the later checkpoints are deleted and their updates trained again",
    )
    p.add_argument(
        "--devices",
        type=int,
        default=None,
        metavar="N",
        help="use the first N devices (default: all of them, across all hosts)",
    )
    add_layout_arg(
        p,
        "batched (default): each device trains its runs as one vmapped program; sequential: the runs "
        "take turns, each through tgrf-train's own program (bit-identical to tgrf-train; faster for "
        "large configs on CPUs); auto: sequential on CPU devices, else batched. Recorded in "
        "sweep.yaml: --resume keeps it, --resume with --layout switches it (a sweep begun on a GPU "
        "continues on a CPU, say; the runs then match an unswitched resume up to float rounding)",
    )
    p.add_argument(
        "--no-run-checkpoints",
        action="store_true",
        help="do not write each run's final checkpoint under runs/<name>/checkpoints",
    )
    dist = p.add_argument_group(
        "multi-host (one process per host, all with the same arguments; the sweep "
        "directory must be on a filesystem all hosts share)"
    )
    dist.add_argument(
        "--distributed",
        action="store_true",
        help="call jax.distributed.initialize() with its auto-detection (SLURM, Cloud TPU, ...)",
    )
    dist.add_argument("--coordinator", metavar="HOST:PORT", help="jax.distributed coordinator (process 0's address)")
    dist.add_argument("--num-processes", type=int, help="with --coordinator: number of processes")
    dist.add_argument("--process-id", type=int, help="with --coordinator: this process's index (0 .. N-1)")
    p.add_argument("--print-plan", action="store_true", help="print the runs and exit (nothing is compiled)")
    p.add_argument("--list-griddable", action="store_true", help="print the griddable fields and exit")
    return p


def init_distributed(
    coordinator: str | None = None, num_processes: int | None = None, process_id: int | None = None
) -> None:
    """jax.distributed.initialize (before any computation); on CPU with gloo collectives for the host gathers."""
    import jax

    if coordinator and (num_processes is None or process_id is None):
        raise ConfigError("--coordinator needs --num-processes and --process-id")
    if jax.config.jax_platforms in ("cpu",) or jax.config.jax_platforms is None:
        try:  # CPU-only processes need a cross-process collectives backend for the gathers; harmless elsewhere
            jax.config.update("jax_cpu_collectives_implementation", "gloo")
        except Exception:
            pass
    if coordinator:
        jax.distributed.initialize(coordinator_address=coordinator, num_processes=num_processes, process_id=process_id)
    else:
        jax.distributed.initialize()


@command_line("tgrf-sweep")
def main(argv: list[str] | None, recovery: Recovery) -> int:
    args = parser().parse_args(argv)
    if args.list_griddable:
        print("\n".join(griddable_fields()))
        return 0
    from tgrf_jax.sweep.grid import SweepSpec, load_sweep
    from tgrf_jax.sweep.run import default_sweep_dir

    check_jax()
    if args.from_step is not None and not args.resume:
        raise ConfigError("--from-step N continues a sweep from one of its checkpoints: it needs --resume SWEEP_DIR")
    if args.from_step is not None and args.from_step < 0:
        raise ConfigError(f"--from-step = {args.from_step} must be >= 0")
    if args.resume:
        if args.config or args.grid or args.overrides or args.seeds or args.out or args.paired:
            raise ConfigError(
                "--resume SWEEP_DIR takes no config file, --grid, --paired, --seeds, --set or --out (the "
                "sweep's own sweep.yaml is used)"
            )
        spec = load_sweep(args.resume)
    else:
        # layout: set below
        spec = SweepSpec.create(args.config, args.grid, args.seeds, args.overrides, paired=args.paired)
    distributed = bool(args.coordinator or args.distributed)
    if distributed and (args.layout or spec.layout) == "sequential":
        raise ConfigError("--layout sequential runs on one host; a multi-host sweep needs the batched layout")
    if distributed and args.out is None and not args.resume:
        raise ConfigError("a multi-host sweep needs --out (the same shared directory on every host)")
    sweep_dir = pathlib.Path(args.resume or args.out or default_sweep_dir(spec.base_config))
    if args.print_plan:
        # "auto" is resolved once JAX knows its devices, which the plan does not start
        print(dataclasses.replace(spec, layout=args.layout or spec.layout).describe())
        return 0
    check_writable(sweep_dir, "--resume" if args.resume else "--out", directory=True)

    # One CPU device per core: the runs split over the devices, and XLA:CPU runs several programs side by side
    # far better than it spreads one over the cores (a user's own count wins).
    start(devices=len(os.sched_getaffinity(0)))
    if distributed:
        init_distributed(args.coordinator, args.num_processes, args.process_id)
    from tgrf_jax.sweep.run import run_sweep

    layout = resolve_layout(args.layout, multi_host=distributed)
    if not args.resume:
        spec = dataclasses.replace(spec, layout=layout or spec.layout)

    recovery.resume = f"resume with: tgrf-sweep --resume {sweep_dir}"
    recovery.from_checkpoint = f"tgrf-sweep --resume {sweep_dir} --from-step"
    run_sweep(
        None if args.resume else spec,
        sweep_dir,
        resume=bool(args.resume),
        from_step=args.from_step,
        log=progress_line,
        num_devices=args.devices,
        export_checkpoints=not args.no_run_checkpoints,
        layout=layout if args.resume else None,
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
