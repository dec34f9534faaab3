"""`run_sweep`: the runs of a `SweepSpec` trained together by the outer loop (`tgrf_jax.train.outer_loop`), in a
`RunDirectory` (`tgrf_jax.train.directory`) whose root is the sweep directory.

Sweep directory:
    sweep.yaml             the grid: axes, seeds, base config, and the run list (name, grid point, seed, values)
    config.yaml            the resolved base config (file + --set; grid values not applied)
    metrics.csv            learning curves of all runs, long format: run, point, seed, grid values + tgrf-train's
                           CSV fields (one row per run per chunk)
    progress.log           the progress lines printed to stdout
    checkpoints/<update>/  orbax checkpoints of the stacked TrainState of all G runs (no padding)
    runs/<name>/           one tgrf-train run directory per run: config.yaml, metrics.csv, eval.json and the final
                           checkpoint (so `tgrf-eval runs/<name>` works)
    evals.csv              final evaluation of every run (the paper's metrics + final training return/success)
    eval_curves.csv        with run.eval_every: test-episode metrics of every run during training (long format)
    eval_curves.png        those curves (SR, NT, PL, ITR) per grid point, mean over seeds with a +-std band
    summary.csv / .md      mean and std over seeds for every grid point
    heatmap.png            success rate and ITR over two gridded parameters (grid_metrics.png with one axis)
    learning_curves.png    training return and success rate per grid point, mean over seeds with a +-std band
"""

from __future__ import annotations

import dataclasses
import datetime
import pathlib
from collections.abc import Callable
from typing import Any

import yaml

from tgrf_jax.config import ConfigError, TrainConfig
from tgrf_jax.storage.checkpoint import Checkpointer, CheckpointError, tree_digest
from tgrf_jax.storage.files import write_atomic
from tgrf_jax.storage.lock import exclusive
from tgrf_jax.sweep.grid import (
    SWEEP_FILE,
    SweepSpec,
    _fmt_value,
    check_layout,
    load_sweep,
)
from tgrf_jax.sweep.program import BatchedProgram, SequentialProgram, barrier
from tgrf_jax.sweep.report import (
    RUNS_DIR,
    format_summary_markdown,
    plot_sweep,
    write_results,
)
from tgrf_jax.train.directory import CHECKPOINT_DIR, RunDirectory
from tgrf_jax.train.outer_loop import train_program

CONFIG_FILE = "config.yaml"


@dataclasses.dataclass
class SweepResult:
    sweep_dir: pathlib.Path
    spec: SweepSpec
    state: Any  # stacked TrainState of the G runs (host numpy, no padding)
    updates: int
    train_seconds: float
    num_devices: int
    evals: list | None  # per run: the eval.json payload (or None when not evaluated)
    compiled_chunks: int = 0


def export_checkpoint(directory, step: int, state, keep: int) -> None:
    """A run's final checkpoint under runs/<name>/checkpoints: saved where missing, damaged or different from
    `state` (a resumed sweep exports again only what it must)."""
    ckpt = Checkpointer(directory, keep=keep)
    try:
        if step in ckpt.all_steps():
            try:
                if tree_digest(ckpt.restore(state, step)) == tree_digest(state):
                    return
            except CheckpointError:
                pass
            ckpt.delete(step)
        ckpt.save(step, state)
    finally:
        ckpt.close()


def default_sweep_dir(config: TrainConfig, root="runs") -> pathlib.Path:
    stamp = datetime.datetime.now().strftime("%Y%m%d-%H%M%S")
    return pathlib.Path(root) / f"{stamp}_sweep_{config.run.name}"


def run_sweep(
    spec: SweepSpec | None,
    sweep_dir,
    *,
    resume: bool = False,
    from_step: int | None = None,
    log: Callable[[str], None] = print,
    stop_after_updates: int | None = None,
    devices=None,
    num_devices: int | None = None,
    export_checkpoints: bool = True,
    layout: str | None = None,
) -> SweepResult:
    """Train every run of `spec` in `sweep_dir` as one batch (or resume the sweep there: `spec=None, resume=True`,
    from its latest checkpoint or from checkpoint `from_step`). Resuming a finished sweep trains nothing and
    re-creates its result files (evals.csv, summaries, plots, the runs' final checkpoints where missing).

    `layout` (with `resume`): continue in this layout instead of the recorded one, which sweep.yaml then records.
    Both layouts checkpoint the same state, so a sweep begun batched on a GPU can go on sequentially on a CPU;
    its runs then continue equal to an unswitched resume up to float rounding, not bit for bit.

    `devices` (default: all, `jax.devices()`; or the first `num_devices` of them) carry the run axis.
    `stop_after_updates` ends early, as an interruption would (for tests). Process 0 holds the sweep directory's
    lock while it writes there (`tgrf_jax.storage.lock`)."""
    import jax

    sweep_dir = pathlib.Path(sweep_dir)
    if from_step is not None and not resume:
        raise ConfigError("from_step needs resume (a sweep restarts from one of its own checkpoints)")
    if layout is not None:
        if not resume:
            raise ConfigError("layout switches the layout of a resumed sweep (a new one takes its spec's layout)")
        check_layout(layout)
    if resume:
        load_sweep(sweep_dir)  # a clear error for a directory that holds no sweep
    elif (sweep_dir / SWEEP_FILE).exists():
        raise ConfigError(f"sweep directory {str(sweep_dir)!r} already holds a sweep; use --resume or another --out")
    args = (
        spec,
        sweep_dir,
        resume,
        from_step,
        log,
        stop_after_updates,
        devices,
        num_devices,
        export_checkpoints,
        layout,
    )
    if jax.process_index() != 0:
        return _run_sweep(*args)
    with exclusive(sweep_dir):
        return _run_sweep(*args)


def _run_sweep(
    spec,
    sweep_dir: pathlib.Path,
    resume,
    from_step,
    log,
    stop_after_updates,
    devices,
    num_devices,
    export_checkpoints,
    layout,
) -> SweepResult:
    import jax

    main = jax.process_index() == 0
    ckpt_dir = sweep_dir / CHECKPOINT_DIR
    switched_from = None
    if resume:
        loaded = load_sweep(sweep_dir)
        if spec is not None and spec.to_dict() != loaded.to_dict():
            raise ConfigError(f"{str(sweep_dir)!r} holds a different sweep than the one given")
        spec = loaded
        if layout is not None and layout != spec.layout:
            switched_from, spec = spec.layout, dataclasses.replace(spec, layout=layout)
    elif (sweep_dir / SWEEP_FILE).exists():
        raise ConfigError(f"sweep directory {str(sweep_dir)!r} already holds a sweep; use --resume or another --out")
    if devices is None:
        devices = jax.devices()
        if num_devices is not None:
            if not 1 <= num_devices <= len(devices):
                raise ConfigError(f"--devices {num_devices}: allowed 1..{len(devices)} (devices: {len(devices)})")
            devices = devices[:num_devices]
    runs = spec.runs()
    run_dirs = [sweep_dir / RUNS_DIR / r.name for r in runs]

    barrier("tgrf_sweep_checked")  # every process has checked the directory before process 0 writes to it
    if not resume and main:
        sweep_dir.mkdir(parents=True, exist_ok=True)
        (sweep_dir / CONFIG_FILE).write_text(spec.base_config.to_yaml())
        (sweep_dir / SWEEP_FILE).write_text(yaml.safe_dump(spec.to_dict(), sort_keys=False))
        for r, d in zip(runs, run_dirs):
            d.mkdir(parents=True, exist_ok=True)
            (d / CONFIG_FILE).write_text(r.config.to_yaml())
    if resume and main:
        missing = [(r, d) for r, d in zip(runs, run_dirs) if not (d / CONFIG_FILE).is_file()]
        started = any(p.name.isdigit() and p.name != "0" for p in ckpt_dir.iterdir()) if ckpt_dir.is_dir() else False
        if missing and started:  # its metrics.csv and eval.json cannot be rebuilt from the sweep's checkpoints
            raise ConfigError(
                f"run directory {str(missing[0][1])!r} of the sweep is missing or has no "
                f"{CONFIG_FILE}{f' (and {len(missing) - 1} more)' if len(missing) > 1 else ''}; "
                "restore it, or start the sweep again with --out"
            )
        for r, d in missing:  # a sweep killed while it created them
            d.mkdir(parents=True, exist_ok=True)
            write_atomic(d / CONFIG_FILE, r.config.to_yaml())
    if switched_from is not None and main:
        write_atomic(sweep_dir / SWEEP_FILE, yaml.safe_dump(spec.to_dict(), sort_keys=False))
    barrier("tgrf_sweep_written")

    program = (SequentialProgram if spec.layout == "sequential" else BatchedProgram)(runs, devices)
    run_cfg = runs[0].config.run
    columns = [dict(run=r.name, point=r.point, seed=r.seed, **r.values) for r in runs]
    with RunDirectory.open(
        sweep_dir, program, run_cfg, run_dirs=run_dirs, columns=columns, write=main, log=log, where="sweep dir"
    ) as directory:
        say = directory.say
        if switched_from is not None:
            say(
                f"layout switched from {switched_from} to {spec.layout} (recorded in {SWEEP_FILE}): from here the "
                f"runs equal an unswitched resume up to float rounding, not bit for bit"
            )
        points = "paired points" if spec.paired else "grid points"
        say(f"sweep of {len(runs)} runs ({len(spec.points())} {points} x {len(spec.seeds)} seeds)")
        for a in spec.axes:
            say(f"  grid {a.name}: {', '.join(_fmt_value(v) for v in a.values)}")
        say(f"  seeds: {', '.join(map(str, spec.seeds))}")
        say("  progress: steps per run; steps/s, returns and outcome rates over all runs together")
        out = train_program(
            program, directory, run_cfg, resume=resume, from_step=from_step, stop_after_updates=stop_after_updates
        )
        host_state = program.host_state(out.state)
        result = SweepResult(
            sweep_dir,
            spec,
            host_state,
            out.updates,
            out.train_seconds,
            program.num_devices,
            out.evals,
            out.compiled_chunks,
        )
        if out.updates == program.num_updates:
            if export_checkpoints:  # so that tgrf-eval / tgrf-render work on runs/<name>
                for i, d in enumerate(run_dirs):
                    export_checkpoint(
                        d / CHECKPOINT_DIR,
                        out.updates,
                        jax.tree_util.tree_map(lambda x, i=i: x[i], host_state),
                        run_cfg.keep_checkpoints,
                    )
            if main:
                rows = write_results(sweep_dir, spec, out.evals)
                say(format_summary_markdown(spec, rows))
                directory.plot(lambda: plot_sweep(sweep_dir, spec, rows))
            directory.done(out, program)
    return result
