"""`RunDirectory`: what a training driver writes while the outer loop (`tgrf_jax.train.outer_loop`) trains its
`Program`.

A driver (tgrf-train's `tgrf_jax.train.run_dir`, tgrf-sweep's `tgrf_jax.sweep.run`) prepares its directory
(config files, run list), builds a `Program` and opens a `RunDirectory` on it, hands both to `train_program`, then
reports through the directory (figures, the "done" line). The directory holds the pieces every driver shares:

    progress.log           every progress line (`say`), also printed through `log`
    checkpoints/<update>/  the program's checkpoints (`checkpointer`)
    metrics.csv            one row per run per chunk (with `columns`: the long file of all runs, see below)
    eval_curves.csv        with `columns` and run.eval_every: the long file of every run's periodic evaluations
    <run dir>/metrics.csv, <run dir>/eval_curve.csv, <run dir>/eval.json   per run (`run_dirs`)
    tb/                    with `tensorboard`: run 0's scalars as TensorBoard events

A single run's directory is its own run directory (`run_dirs == (root,)`); a sweep's root holds a run directory
per run and, through `columns` (the constant columns of each run: name, grid point, seed, grid values), the long
files of all runs.
"""

from __future__ import annotations

import dataclasses
import pathlib
from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING, Any

from tgrf_jax.config import RunConfig
from tgrf_jax.storage.checkpoint import Checkpointer
from tgrf_jax.train.curves import CURVE_FIELDS, EVAL_CURVE_CSV, PeriodicEvaluation
from tgrf_jax.train.progress import (
    CSV_FIELDS,
    ChunkMetrics,
    CsvWriter,
    LogFile,
    ProgressPrinter,
    TensorBoardWriter,
    run_rows,
)

if TYPE_CHECKING:
    from tgrf_jax.train.outer_loop import Program, ProgramResult

CHECKPOINT_DIR = "checkpoints"
LOG_FILE = "progress.log"
METRICS_FILE = "metrics.csv"
EVAL_CURVES_FILE = "eval_curves.csv"  # the long file of all runs' periodic evaluations (with `columns`)


@dataclasses.dataclass
class RunDirectory:
    """The files of one training process, open while it trains (a context manager: closed on exit, however the
    training ended). Build it with `RunDirectory.open`."""

    root: pathlib.Path
    run_dirs: tuple[pathlib.Path, ...]  # one per run: eval.json, and the run's own CSV files
    say: Callable[[str], None]  # a line to the log and progress.log
    checkpointer: Checkpointer
    progress_fns: tuple[Callable[[int, ChunkMetrics], None], ...]  # after every chunk
    state_fns: tuple[Callable[[int, Any], None], ...]  # after every chunk, with the program's state
    cut_every: tuple[int, ...]  # where chunks end besides the log and checkpoint periods (a state_fn's period)
    write_evals: bool  # this process writes the final evaluation to the run directories
    where: str  # how the "done" line names the root: "run dir", "sweep dir"
    closing: tuple = ()  # writers closed with the directory

    @classmethod
    def open(
        cls,
        root,
        program: Program,
        run: RunConfig,
        *,
        run_dirs: Sequence[pathlib.Path] | None = None,
        columns: Sequence[dict] | None = None,
        tensorboard: bool = False,
        write: bool = True,
        log: Callable[[str], None] = print,
        where: str = "run dir",
    ) -> RunDirectory:
        """The directory `root` (existing) for `program`'s runs, trained with `run`'s periods.

        `run_dirs`: one directory per run (default: `root` alone, for a single run). `columns`: per run, the
        constant columns that lead its rows in root's long metrics.csv and eval_curves.csv (without them, root
        holds no long files). `write`: whether this process writes files at all (on a multi-host sweep, process
        0 does; every process still checkpoints and evaluates)."""
        root = pathlib.Path(root)
        run_dirs = (root,) if run_dirs is None else tuple(pathlib.Path(d) for d in run_dirs)
        say = LogFile(root / LOG_FILE, log, enabled=write)
        # created if missing: a run stopped before its first checkpoint has none yet
        checkpointer = Checkpointer(root / CHECKPOINT_DIR, keep=run.keep_checkpoints, create=True)
        progress_fns, curve_writers = [], []
        if write:
            progress_fns = _metrics_writers(root, run_dirs, columns)
            if tensorboard:
                progress_fns.append(TensorBoardWriter(root / "tb"))
            progress_fns.append(ProgressPrinter(say))
            if run.eval_every:
                curve_writers = _curve_writers(root, run_dirs, columns)
        state_fns, cut_every = (), ()
        if run.eval_every:
            state_fns = (
                PeriodicEvaluation(program, run.eval_every, run.curve_episodes, run.eval_seed, curve_writers, say),
            )
            cut_every = (run.eval_every,)
        return cls(
            root=root,
            run_dirs=run_dirs,
            say=say,
            checkpointer=checkpointer,
            progress_fns=tuple(progress_fns),
            state_fns=state_fns,
            cut_every=cut_every,
            write_evals=write,
            where=where,
            closing=(*progress_fns, *curve_writers),
        )

    def plot(self, draw: Callable[[], object]) -> None:
        """Draw figures; a failure is logged, not raised: a plotting failure must not lose a finished run."""
        try:
            draw()
        except Exception as e:
            self.say(f"warning: could not plot: {type(e).__name__}: {e}")

    def done(self, result: ProgramResult, program: Program) -> None:
        """The last line of a run trained to its end: its size, this process's share and speed."""
        runs, batch, trained = program.num_runs, program.batch_size, result.updates - result.start
        sps = runs * trained * batch / max(result.train_seconds, 1e-9)
        if runs > 1:
            size = f"{runs} runs x {result.updates} updates = {runs * result.updates * batch:,} env steps"
            speed = f"{sps:,.0f} steps/s over all runs"
        else:
            size = f"{result.updates} updates, {result.updates * batch:,} env steps"
            speed = f"{sps:,.0f} steps/s"
        self.say(
            f"done: {size}; this process trained {trained} updates in {result.train_seconds:.1f} s ({speed}, "
            f"compilation excluded); {self.where} {self.root}"
        )

    def close(self) -> None:
        for writer in self.closing:
            getattr(writer, "close", lambda: None)()
        self.closing = ()
        self.checkpointer.close()
        self.say.close()

    def __enter__(self) -> RunDirectory:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _long_rows(columns: Sequence[dict]) -> Callable[[Sequence[dict]], list[dict]]:
    """Rows of every run, each led by its run's constant columns."""
    return lambda rows: [dict(row, **c) for row, c in zip(rows, columns)]


def _metrics_writers(root: pathlib.Path, run_dirs, columns) -> list:
    writers = []
    if columns is not None:
        long_rows = _long_rows(columns)
        fields = [*columns[0], *CSV_FIELDS]
        writers.append(CsvWriter(root / METRICS_FILE, lambda m: long_rows(m.runs), fields))
    return writers + [CsvWriter(d / METRICS_FILE, run_rows(i)) for i, d in enumerate(run_dirs)]


def _curve_writers(root: pathlib.Path, run_dirs, columns) -> list:
    writers = []
    if columns is not None:
        fields = [*columns[0], *CURVE_FIELDS]
        writers.append(CsvWriter(root / EVAL_CURVES_FILE, _long_rows(columns), fields, every_chunk=False))
    return writers + [
        CsvWriter(d / EVAL_CURVE_CSV, lambda rows, i=i: rows[i : i + 1], CURVE_FIELDS, every_chunk=False)
        for i, d in enumerate(run_dirs)
    ]
