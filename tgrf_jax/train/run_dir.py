"""A tgrf-train run directory: one run (`SoloProgram`) trained by the outer loop (`tgrf_jax.train.outer_loop`)
in a `RunDirectory` (`tgrf_jax.train.directory`), restored, evaluated.

Run directory:
    config.yaml          resolved TrainConfig (every field, after overrides); ppo.total_steps may be raised before
                         --resume to extend training
    config.started.yaml  the config the run started with (any other edit of config.yaml is refused on --resume)
    metrics.csv          one row per compiled chunk (reduced scalars only)
    progress.log         the progress lines printed to stdout
    checkpoints/<update>/  orbax checkpoints of the full TrainState (atomic; the last `run.keep_checkpoints` kept)
    tb/                  TensorBoard events (only if tensorboardX or torch.utils.tensorboard is installed)
    eval.json            final evaluation (the paper's metrics) of the deterministic policy
    eval_curve.csv, eval_curve.png   with run.eval_every: test episodes during training (`tgrf_jax.train.curves`)
    learning_curve.png
"""

from __future__ import annotations

import dataclasses
import datetime
import pathlib
from collections.abc import Callable

import jax
import numpy as np

from tgrf_jax.config import ConfigError, TrainConfig, load_yaml
from tgrf_jax.evaluate import evaluate_state, format_eval
from tgrf_jax.storage.checkpoint import Checkpointer
from tgrf_jax.storage.lock import exclusive
from tgrf_jax.train import shards
from tgrf_jax.train.curves import EVAL_CURVE_CSV, EVAL_CURVE_PNG, plot_curves, read_curve
from tgrf_jax.train.directory import CHECKPOINT_DIR, METRICS_FILE, RunDirectory
from tgrf_jax.train.outer_loop import EVAL_FILE, train_program
from tgrf_jax.train.ppo import TrainState, make_trainer

CONFIG_FILE = "config.yaml"
STARTED_FILE = "config.started.yaml"  # the config the run started with: what --resume checks edits against
RESUME_EDITABLE = ("ppo.total_steps",)  # "extend training"
CURVE_FILE = "learning_curve.png"

__all__ = ["EVAL_FILE", "RunResult", "SoloProgram", "load_run_config", "restore_run", "train_run"]


def default_run_dir(config: TrainConfig, root="runs") -> pathlib.Path:
    stamp = datetime.datetime.now().strftime("%Y%m%d-%H%M%S")
    return pathlib.Path(root) / f"{stamp}_{config.run.name}"


def check_resume_config(run_dir, config: TrainConfig) -> None:
    """Edits of config.yaml since the run started: only `RESUME_EDITABLE` fields may change (raises ConfigError
    listing every other difference, before anything compiles)."""
    started = pathlib.Path(run_dir) / STARTED_FILE
    if not started.is_file():
        return
    old, new = TrainConfig.from_dict(load_yaml(started)).to_dict(), config.to_dict()
    diffs = [
        f"{section}.{key}: {old[section].get(key)!r} -> {value!r}"
        for section, fields in new.items()
        for key, value in fields.items()
        if old[section].get(key) != value and f"{section}.{key}" not in RESUME_EDITABLE
    ]
    if diffs:
        raise ConfigError(
            f"{str(pathlib.Path(run_dir) / CONFIG_FILE)!r} was edited since the run started; on --resume "
            f"only {', '.join(RESUME_EDITABLE)} may change (to extend training), not: {'; '.join(diffs)}"
        )


def load_run_config(run_dir) -> TrainConfig:
    path = pathlib.Path(run_dir) / CONFIG_FILE
    if not path.is_file():
        raise ConfigError(f"{str(path)!r} does not exist: {str(run_dir)!r} is not a tgrf-train run directory")
    return TrainConfig.from_dict(load_yaml(path))


class SoloProgram:
    """The `Program` of one run (`make_trainer`): its env shards on one device each where there are enough, else
    vmapped."""

    num_runs = 1

    def __init__(self, config: TrainConfig, devices="auto"):
        self.config = config
        self.trainer = make_trainer(config, devices)
        self.num_updates = self.trainer.num_updates
        self.batch_size = config.ppo.batch_size
        self.key = jax.random.PRNGKey(config.run.seed)
        self.compiled: Callable | None = None  # jit_run_chunk compiled ahead of time; the update count is traced

    def init(self) -> TrainState:
        return self.trainer.jit_init(self.key, self.trainer.default_hparams)

    def restore(self, checkpointer: Checkpointer, step: int) -> tuple[TrainState, int]:
        template = jax.eval_shape(self.trainer.init, self.key, self.trainer.default_hparams)
        state = self.trainer.place(checkpointer.restore(template, step))
        return state, int(state.update)

    def is_compiled(self, state: TrainState) -> bool:
        return self.compiled is not None

    def compile(self, state: TrainState) -> None:
        self.compiled = self.trainer.jit_run_chunk.lower(state, np.int32(1)).compile()

    def run_chunk(self, state: TrainState, n_updates: int) -> tuple[TrainState, dict]:
        return self.compiled(state, np.int32(n_updates))

    def run_metrics(self, metrics) -> list[dict]:
        return [{k: float(v) for k, v in jax.device_get(metrics).items()}]

    def host_state(self, state: TrainState) -> TrainState:
        return state

    def evaluate(self, state: TrainState, episodes: int, seed: int) -> list[dict]:
        # the trainer's own network: one compiled evaluation for every checkpoint of the run
        return [evaluate_state(self.config, state, episodes, seed, net=self.trainer.net)]

    def describe(self, state: TrainState) -> str:
        t, p = self.trainer, self.config.ppo
        return (
            f"{t.env} | {self.config.network.name}/{self.config.network.size} "
            f"({t.net.num_params(state.params):,} params) | {p.num_envs} envs x {p.num_steps} steps, "
            f"{self.num_updates} updates = {self.num_updates * p.batch_size:,} env steps | "
            f"{shards.describe(p.num_shards, t.mesh)} | {jax.devices()[0].platform}"
        )


@dataclasses.dataclass
class RunResult:
    run_dir: pathlib.Path
    state: TrainState
    updates: int
    train_seconds: float
    eval: dict | None
    compiled_chunks: int = 0


def train_run(
    config: TrainConfig,
    run_dir,
    *,
    resume: bool = False,
    from_step: int | None = None,
    log: Callable[[str], None] = print,
    stop_after_updates: int | None = None,
) -> RunResult:
    """Train `config` in `run_dir` (or resume the run there: from its latest checkpoint, or from checkpoint
    `from_step`, whose later checkpoints are deleted and trained again). Resuming a finished run trains nothing and
    re-creates only missing result files. `stop_after_updates` ends early (for tests).
    The process holds the run directory's lock while it writes there (`tgrf_jax.storage.lock`)."""
    run_dir = pathlib.Path(run_dir)
    if from_step is not None and not resume:
        raise ConfigError("from_step needs resume (a run restarts from one of its own checkpoints)")
    if resume:
        load_run_config(run_dir)  # a clear error for a directory that holds no run
    elif (run_dir / CONFIG_FILE).exists():
        raise ConfigError(f"run directory {str(run_dir)!r} already holds a run; use --resume or another --out-dir")
    with exclusive(run_dir):
        return _train_run(config, run_dir, resume, from_step, log, stop_after_updates)


def _train_run(config, run_dir: pathlib.Path, resume: bool, from_step, log, stop_after_updates) -> RunResult:
    if resume:
        config = load_run_config(run_dir)
        check_resume_config(run_dir, config)
    else:
        if (run_dir / CONFIG_FILE).exists():
            raise ConfigError(f"run directory {str(run_dir)!r} already holds a run; use --resume or another --out-dir")
        run_dir.mkdir(parents=True, exist_ok=True)
        (run_dir / STARTED_FILE).write_text(config.to_yaml())
        (run_dir / CONFIG_FILE).write_text(config.to_yaml())

    program = SoloProgram(config)
    with RunDirectory.open(run_dir, program, config.run, tensorboard=True, log=log) as directory:
        if resume:
            directory.say(f"resuming {run_dir}")
        for note in config.notes():
            directory.say(f"note: {note}")
        out = train_program(
            program, directory, config.run, resume=resume, from_step=from_step, stop_after_updates=stop_after_updates
        )
        result = RunResult(
            run_dir, out.state, out.updates, out.train_seconds, out.evals and out.evals[0], out.compiled_chunks
        )
        if out.updates == program.num_updates:
            directory.plot(lambda: _plot(config, run_dir, program.trainer.env))
            if result.eval is not None:
                directory.say(format_eval(result.eval))
            directory.done(out, program)
    return result


def _plot(config: TrainConfig, run_dir: pathlib.Path, env) -> None:
    from tgrf_jax.train.plots import plot_learning_curve

    plot_learning_curve(run_dir / METRICS_FILE, run_dir / CURVE_FILE, title=f"{config.run.name}: {env}")
    if config.run.eval_every:
        plot_curves(
            {config.run.name: [read_curve(run_dir / EVAL_CURVE_CSV)]},
            run_dir / EVAL_CURVE_PNG,
            title=f"{config.run.name}: test episodes during training",
        )


def restore_run(run_dir, step: int | None = None) -> tuple[TrainConfig, TrainState]:
    """Config and TrainState of a run directory (latest checkpoint unless `step`)."""
    run_dir = pathlib.Path(run_dir)
    config = load_run_config(run_dir)
    trainer = make_trainer(config)
    ckpt = Checkpointer(run_dir / CHECKPOINT_DIR, keep=config.run.keep_checkpoints, create=False)
    template = jax.eval_shape(trainer.init, jax.random.PRNGKey(0), trainer.default_hparams)
    try:
        state = ckpt.restore(template, step)
    finally:
        ckpt.close()
    return config, state
