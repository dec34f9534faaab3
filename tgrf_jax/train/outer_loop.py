"""The outer training loop: G runs on D devices, chunk by chunk, with checkpoints, resume and final evaluation.

Every training driver hands `train_program` two things: a `Program` (what is trained: the compiled program of its
runs and where their env shards are placed) and a `RunDirectory` (`tgrf_jax.train.directory`: where it goes:
progress log, checkpoints, metrics CSVs, periodic evaluation, eval.json per run). tgrf-train
(`tgrf_jax.train.run_dir`: `SoloProgram`, G = 1) and tgrf-sweep (`tgrf_jax.sweep`: `BatchedProgram` or
`SequentialProgram`, G runs) are two such drivers. The directory's `progress_fns(step, metrics)` are called after
every chunk with the env steps per run and a `ChunkMetrics`; its `state_fns(update, state)` with the program's
state (the periodic test evaluation of `tgrf_jax.train.curves`).

Chunk boundaries depend only on absolute update counts (every `run.log_every` updates, cut at checkpoint
multiples and at the end), so a resumed run executes exactly the same chunks as an uninterrupted one and ends
with bit-identical parameters.
"""

from __future__ import annotations

import dataclasses
import json
import pathlib
import time
from collections.abc import Iterator, Sequence
from typing import TYPE_CHECKING, Any, Protocol

import jax

from tgrf_jax.config import RunConfig
from tgrf_jax.storage.checkpoint import Checkpointer, CheckpointError
from tgrf_jax.train.progress import ChunkMetrics, combine_runs, csv_row
from tgrf_jax.train.stop import stop_requests

if TYPE_CHECKING:
    from tgrf_jax.train.directory import RunDirectory

EVAL_FILE = "eval.json"


class Program(Protocol):
    """A compiled training program of `num_runs` runs that share their static settings."""

    num_runs: int
    num_updates: int
    batch_size: int  # env steps per update and run

    def init(self) -> Any: ...  # fresh state of all runs, placed on the devices

    def restore(self, checkpointer: Checkpointer, step: int) -> tuple[Any, int]: ...  # (state, its update)

    def is_compiled(self, state) -> bool: ...  # whether run_chunk is compiled for this state's shapes

    def compile(self, state) -> None: ...  # compile run_chunk for this state's shapes (ahead of time)

    # n_updates updates of every run: (state, metrics); one compiled program for any count (it is traced)
    def run_chunk(self, state, n_updates: int) -> tuple[Any, Any]: ...

    def run_metrics(self, metrics) -> list[dict]: ...  # chunk output -> per-run {metric: float} (blocks)

    def host_state(self, state) -> Any: ...  # what a checkpoint holds

    def evaluate(self, state, episodes: int, seed: int) -> list[dict]: ...  # per run: an eval.json payload

    def describe(self, state) -> str: ...


def chunk_plan(start: int, total: int, log_every: int, *cut_every: int) -> Iterator[int]:
    """Chunk lengths from update `start` to `total`: at most log_every, never crossing a multiple of log_every or
    of any `cut_every` period (checkpoints, periodic evaluations). Lazy: a run may have billions of updates."""
    u = start
    while u < total:
        n = min([total - u] + [p - u % p for p in (log_every, *cut_every)])
        yield n
        u += n


@dataclasses.dataclass
class ProgramResult:
    state: Any  # the program's state after the last chunk
    start: int  # update this process started (or resumed) from
    updates: int  # updates done
    train_seconds: float  # chunk execution time of this process, compilation excluded
    compiled_chunks: int  # training programs compiled by this process (one: chunk lengths are traced)
    evals: list | None  # per run: the final evaluation's payload (None when not evaluated)


def train_program(
    program: Program,
    directory: RunDirectory,
    run: RunConfig,
    *,
    resume: bool = False,
    from_step: int | None = None,
    stop_after_updates: int | None = None,
) -> ProgramResult:
    """Train (or, with `resume`, continue from the latest checkpoint, or from checkpoint `from_step`) every run of
    `program` to its end, writing to `directory`.

    Chunks end at multiples of `run.log_every`, `run.checkpoint_every` and every period in `directory.cut_every`
    (where a `state_fn` wants to see the state). The run directories receive the final evaluation as eval.json
    (where `directory.write_evals`: on a multi-host sweep, process 0). Resuming a run that is trained to its end
    trains and evaluates nothing: the eval.json files already written are its evaluation, and only missing ones are
    made again. `stop_after_updates` ends early, as an interruption would (for tests)."""
    checkpointer, say, run_dirs = directory.checkpointer, directory.say, directory.run_dirs
    progress_fns, state_fns = directory.progress_fns, directory.state_fns
    total, batch, G = program.num_updates, program.batch_size, program.num_runs
    start_time = time.perf_counter()
    steps = checkpointer.all_steps() if resume else []
    if from_step is not None and from_step not in steps:
        raise CheckpointError(
            f"--from-step {from_step}: {str(checkpointer.directory)!r} holds no checkpoint of "
            f"update {from_step}; it holds: {', '.join(map(str, steps)) or 'none'}"
        )
    step = from_step if from_step is not None else (steps[-1] if steps else None)
    if resume and step is None:
        say("no checkpoint yet (the run stopped before its first one): starting from the beginning")
        for fn in (*progress_fns, *state_fns):
            getattr(fn, "truncate", lambda update: 0.0)(0)
    if step is not None:
        state, start = program.restore(checkpointer, step)
        if start != step:
            raise CheckpointError(f"checkpoint {str(checkpointer.path(step))!r} holds update {start}, not {step}")
        if checkpointer.delete_after(start):  # --from-step: the later updates are trained again
            for run_dir in run_dirs if directory.write_evals else ():
                (pathlib.Path(run_dir) / EVAL_FILE).unlink(missing_ok=True)
        # the one place where files written after the checkpoint are cut back to it
        wall_offset = max(
            [fn.truncate(start) for fn in (*progress_fns, *state_fns) if hasattr(fn, "truncate")], default=0.0
        )
        say(
            f"resumed at update {start}/{total} ({start * batch:,} env steps{' per run' if G > 1 else ''})"
            + (": trained to the end already" if start == total else "")
        )
    else:
        state, start, wall_offset = program.init(), 0, 0.0
        checkpointer.save(0, program.host_state(state))
    say(program.describe(state))

    end = total if stop_after_updates is None else min(total, stop_after_updates)
    # the ETA spreads everything done between compiled chunks (periodic evaluations, checkpoints) over the updates,
    # compilation apart; train_seconds (chunks alone) gives the throughput
    train_seconds, loop_seconds, compiled, update = 0.0, 0.0, 0, start
    # the hosts of a multi-host sweep could see a signal at different chunks: there Ctrl-C stops at once
    with stop_requests(enabled=jax.process_count() == 1) as stop:
        for n in chunk_plan(start, end, run.log_every, run.checkpoint_every, *directory.cut_every):
            if not program.is_compiled(state):
                what = f"the training program{f' for {G} runs' if G > 1 else ''}"
                say(f"compiling {what} ...")
                c0 = time.perf_counter()
                program.compile(state)
                compiled += 1
                say(f"compiled {what} in {time.perf_counter() - c0:.1f} s")
            c0 = time.perf_counter()
            state, raw = program.run_chunk(state, n)
            per_run = program.run_metrics(raw)  # blocks: the chunk is done
            dt = time.perf_counter() - c0
            train_seconds += dt
            update += n
            wall = wall_offset + time.perf_counter() - start_time
            metrics = ChunkMetrics(
                update=update,
                total_updates=total,
                env_steps=update * batch,
                total_env_steps=total * batch,
                eta_s=(total - update) * (loop_seconds + dt) / (update - start),
                runs=tuple(csv_row(m, update, update * batch, wall, n * batch / dt) for m in per_run),
                total=csv_row(combine_runs(per_run), update, update * batch, wall, G * n * batch / dt),
            )
            for progress_fn in progress_fns:
                progress_fn(update * batch, metrics)
            for state_fn in state_fns:
                state_fn(update, state)
            if stop or update % run.checkpoint_every == 0 or update == total:
                checkpointer.save(update, program.host_state(state))
            loop_seconds += time.perf_counter() - c0
            if stop:
                say(f"stopped by {stop.signal_name} at update {update}/{total}, with a checkpoint of that update")
                raise KeyboardInterrupt

    result = ProgramResult(state, start, update, train_seconds, compiled, None)
    if update == total and run.eval_episodes > 0:
        result.evals = written_evals(run_dirs, total, run) if start == total else None
        if result.evals is None:
            say(
                f"evaluating the final polic{'ies' if G > 1 else 'y'} on {run.eval_episodes} episodes"
                f"{' each' if G > 1 else ''} ..."
            )
            c0 = time.perf_counter()
            result.evals = program.evaluate(state, run.eval_episodes, run.eval_seed)
            say(f"  done in {time.perf_counter() - c0:.1f} s (compilation included)")
            for run_dir, payload in zip(run_dirs, result.evals):
                payload.update(run_dir=str(run_dir), updates=update, env_steps=update * batch)
                if directory.write_evals:
                    (pathlib.Path(run_dir) / EVAL_FILE).write_text(json.dumps(payload, indent=2))
    return result


def written_evals(run_dirs: Sequence[pathlib.Path], total: int, run: RunConfig) -> list[dict] | None:
    """The final evaluations already written to `run_dirs` (eval.json of update `total` with `run`'s episodes and
    seed in every one), or None where any is missing or stale."""
    payloads = []
    for run_dir in run_dirs:
        try:
            payload = json.loads((pathlib.Path(run_dir) / EVAL_FILE).read_text())
        except (OSError, ValueError):
            return None
        if (payload.get("updates"), payload.get("episodes"), payload.get("seed")) != (
            total,
            run.eval_episodes,
            run.eval_seed,
        ):
            return None
        payloads.append(payload)
    return payloads
