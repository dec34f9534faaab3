"""The chunked outer loop of a training run: progress, CSV / TensorBoard, checkpoints, resume, final evaluation.

Run directory:
    config.yaml          resolved TrainConfig (every field, after overrides)
    metrics.csv          one row per compiled chunk (reduced scalars only)
    progress.log         the progress lines printed to stdout
    checkpoints/<update>/  orbax checkpoints of the full TrainState (atomic; the last `run.keep_checkpoints` kept)
    tb/                  TensorBoard events (only if tensorboardX or torch.utils.tensorboard is installed)
    eval.json            final evaluation (SPEC A.4 metrics) of the deterministic policy
    learning_curve.png

Chunk boundaries depend only on absolute update counts (every `run.log_every` updates, cut at checkpoint
multiples and at the end), so a resumed run executes exactly the same chunks as an uninterrupted one and ends
with bit-identical parameters.
"""

from __future__ import annotations

import csv
import dataclasses
import datetime
import json
import math
import pathlib
import time
from typing import Callable

import jax
import numpy as np

from tgrf_jax.config import ConfigError, TrainConfig, load_yaml
from tgrf_jax.train.checkpoint import CheckpointError, Checkpointer
from tgrf_jax.train import shards
from tgrf_jax.train.ppo import METRIC_NAMES, TrainState, make_train

CSV_FIELDS = (
    "update", "env_steps", "wall_s", "sps", "episodes", "episode_return", "success_rate", "collision_rate",
    "timeout_rate", "loss", "pg_loss", "vf_loss", "entropy", "approx_kl", "clip_frac", "grad_norm", "lr",
    "reward_mean",
)
CONFIG_FILE = "config.yaml"
METRICS_FILE = "metrics.csv"
EVAL_FILE = "eval.json"
CURVE_FILE = "learning_curve.png"
CHECKPOINT_DIR = "checkpoints"


def default_run_dir(config: TrainConfig, root="runs") -> pathlib.Path:
    stamp = datetime.datetime.now().strftime("%Y%m%d-%H%M%S")
    return pathlib.Path(root) / f"{stamp}_{config.run.name}"


def load_run_config(run_dir) -> TrainConfig:
    path = pathlib.Path(run_dir) / CONFIG_FILE
    if not path.is_file():
        raise ConfigError(f"{str(path)!r} does not exist: {str(run_dir)!r} is not a tgrf-train run directory")
    return TrainConfig.from_dict(load_yaml(path))


def chunk_plan(start: int, total: int, log_every: int, checkpoint_every: int) -> list[int]:
    """Chunk lengths from update `start` to `total`: at most log_every, never crossing a checkpoint multiple."""
    plan, u = [], start
    while u < total:
        next_ckpt = (u // checkpoint_every + 1) * checkpoint_every
        n = min(log_every - u % log_every, next_ckpt - u, total - u)
        plan.append(n)
        u += n
    return plan


def chunk_row(metrics: dict, update: int, env_steps: int, wall_s: float, sps: float) -> dict:
    m = {k: float(v) for k, v in metrics.items()}
    episodes = m["episodes"]
    rate = lambda x: x / episodes if episodes > 0 else float("nan")  # noqa: E731
    row = dict(
        update=update, env_steps=env_steps, wall_s=round(wall_s, 3), sps=round(sps, 1), episodes=int(episodes),
        episode_return=rate(m["return_sum"]), success_rate=rate(m["successes"]),
        collision_rate=rate(m["collisions"]), timeout_rate=rate(m["timeouts"]),
    )
    for k in METRIC_NAMES:
        if k not in ("episodes", "return_sum", "successes", "collisions", "timeouts"):
            row[k] = m[k]
    return row


def _fmt_steps(n: float) -> str:
    for unit, scale in (("G", 1e9), ("M", 1e6), ("k", 1e3)):
        if n >= scale:
            return f"{n / scale:.2f}{unit}"
    return f"{int(n)}"


def _fmt_time(s: float) -> str:
    if not math.isfinite(s):
        return "?"
    s = int(round(s))
    return f"{s // 3600}h{s % 3600 // 60:02d}m" if s >= 3600 else f"{s // 60}m{s % 60:02d}s"


def progress_line(row: dict, total_steps: int, eta_s: float) -> str:
    f = lambda x, spec: "  -  " if x is None or (isinstance(x, float) and math.isnan(x)) else format(x, spec)  # noqa
    return (
        f"[{_fmt_steps(row['env_steps'])}/{_fmt_steps(total_steps)} steps, update {row['update']}] "
        f"{row['sps']:,.0f} steps/s | return {f(row['episode_return'], '7.2f')} | "
        f"success {f(row['success_rate'], '.2f')} coll {f(row['collision_rate'], '.2f')} "
        f"timeout {f(row['timeout_rate'], '.2f')} ({row['episodes']} eps) | "
        f"ent {row['entropy']:.3f} vf {row['vf_loss']:.3g} | ETA {_fmt_time(eta_s)}"
    )


class _TensorBoard:
    """Optional TensorBoard writer (tensorboardX, else torch.utils.tensorboard, else nothing)."""

    def __init__(self, logdir):
        self.writer = None
        for module in ("tensorboardX", "torch.utils.tensorboard"):
            try:
                mod = __import__(module, fromlist=["SummaryWriter"])
                self.writer = mod.SummaryWriter(str(logdir))
                break
            except Exception:
                continue

    def write(self, row: dict):
        if self.writer is None:
            return
        step = int(row["env_steps"])
        for k, v in row.items():
            if k not in ("update", "env_steps") and isinstance(v, (int, float)) and math.isfinite(v):
                self.writer.add_scalar(f"train/{k}", v, step)
        self.writer.flush()

    def close(self):
        if self.writer is not None:
            self.writer.close()


def _rewrite_csv_upto(path: pathlib.Path, update: int) -> float:
    """Keep rows with update <= `update` (drop rows of chunks after the restored checkpoint); returns last wall_s."""
    if not path.is_file():
        return 0.0
    with open(path, newline="") as f:
        rows = [r for r in csv.DictReader(f) if int(float(r["update"])) <= update]
    with open(path, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=CSV_FIELDS)
        w.writeheader()
        w.writerows(rows)
    return float(rows[-1]["wall_s"]) if rows else 0.0


@dataclasses.dataclass
class RunResult:
    run_dir: pathlib.Path
    state: TrainState
    updates: int
    train_seconds: float
    eval: dict | None


def train_run(
    config: TrainConfig,
    run_dir,
    *,
    resume: bool = False,
    log: Callable[[str], None] = print,
    stop_after_updates: int | None = None,
) -> RunResult:
    """Train `config` in `run_dir` (or resume the run there). `stop_after_updates` ends early (for tests)."""
    run_dir = pathlib.Path(run_dir)
    ckpt_dir = run_dir / CHECKPOINT_DIR
    if resume:
        config = load_run_config(run_dir)
        if not ckpt_dir.is_dir():
            raise CheckpointError(f"cannot resume: checkpoint directory {str(ckpt_dir)!r} does not exist")
    else:
        if (run_dir / CONFIG_FILE).exists():
            raise ConfigError(f"run directory {str(run_dir)!r} already holds a run; use --resume or another --out-dir")
        run_dir.mkdir(parents=True, exist_ok=True)
        (run_dir / CONFIG_FILE).write_text(config.to_yaml())

    logfile = open(run_dir / "progress.log", "a")

    def say(msg: str):
        log(msg)
        logfile.write(msg + "\n")
        logfile.flush()

    p, r = config.ppo, config.run
    t = make_train(config)
    total = t.trainer.num_updates
    batch = p.batch_size
    ckpt = Checkpointer(ckpt_dir, keep=r.keep_checkpoints, create=not resume)

    start_time = time.perf_counter()
    key = jax.random.PRNGKey(r.seed)
    if resume:
        step = ckpt.latest_step()
        if step is None:
            raise CheckpointError(f"cannot resume: no checkpoint in {str(ckpt.directory)!r}")
        template = jax.eval_shape(t.init, key, t.default_hparams)
        state = t.place(ckpt.restore(template, step))
        start = int(state.update)
        if start != step:
            raise CheckpointError(f"checkpoint {str(ckpt.directory / str(step))!r} holds update {start}, not {step}")
        wall_offset = _rewrite_csv_upto(run_dir / METRICS_FILE, start)
        say(f"resumed {run_dir} at update {start}/{total} ({start * batch:,} env steps)")
    else:
        state = t.init(key, t.default_hparams)
        start, wall_offset = 0, 0.0
        ckpt.save(0, state)

    say(f"{t.trainer.env} | {config.network.name}/{config.network.size} "
        f"({t.trainer.net.num_params(state.params):,} params) | {p.num_envs} envs x {p.num_steps} steps, "
        f"{total} updates = {total * batch:,} env steps | {shards.describe(p.num_shards, t.trainer.mesh)} | "
        f"{jax.devices()[0].platform}")

    csv_path = run_dir / METRICS_FILE
    new_csv = not csv_path.is_file()
    csv_file = open(csv_path, "a", newline="")
    writer = csv.DictWriter(csv_file, fieldnames=CSV_FIELDS)
    if new_csv:
        writer.writeheader()
    tb = _TensorBoard(run_dir / "tb")

    end = total if stop_after_updates is None else min(total, stop_after_updates)
    plan = chunk_plan(start, end, r.log_every, r.checkpoint_every)
    compiled = {}
    train_seconds = 0.0  # excluding compilation
    updates_timed = 0
    update = start
    for n in plan:
        if n not in compiled:
            c0 = time.perf_counter()
            compiled[n] = t.run_chunk.lower(state, n).compile()
            say(f"compiled a {n}-update chunk in {time.perf_counter() - c0:.1f} s")
        c0 = time.perf_counter()
        state, metrics = compiled[n](state)
        metrics = jax.device_get(metrics)  # blocks: the chunk is done
        dt = time.perf_counter() - c0
        train_seconds += dt
        updates_timed += n
        update += n
        sec_per_update = train_seconds / updates_timed
        row = chunk_row(metrics, update, update * batch, wall_offset + time.perf_counter() - start_time,
                        n * batch / dt)
        writer.writerow(row)
        csv_file.flush()
        tb.write(row)
        say(progress_line(row, total * batch, (total - update) * sec_per_update))
        if update % r.checkpoint_every == 0 or update == total:
            ckpt.save(update, state)
    csv_file.close()
    tb.close()

    result = RunResult(run_dir, state, update, train_seconds, None)
    if update == total:
        try:
            from tgrf_jax.train.plots import plot_learning_curve

            plot_learning_curve(csv_path, run_dir / CURVE_FILE, title=f"{config.run.name}: {t.trainer.env}")
        except Exception as e:  # a plotting failure must not lose a finished run
            say(f"warning: could not plot the learning curve: {e}")
        if r.eval_episodes > 0:
            say(f"evaluating the final policy on {r.eval_episodes} episodes ...")
            result.eval = evaluate_state(config, state, r.eval_episodes, r.eval_seed)
            payload = dict(result.eval, run_dir=str(run_dir), updates=update, env_steps=update * batch)
            (run_dir / EVAL_FILE).write_text(json.dumps(payload, indent=2))
            say(format_eval(result.eval))
        say(f"done: {update} updates, {update * batch:,} env steps; this session trained {update - start} updates "
            f"in {train_seconds:.1f} s ({(update - start) * batch / max(train_seconds, 1e-9):,.0f} steps/s, "
            f"compilation excluded); run dir {run_dir}")
    ckpt.close()
    logfile.close()
    return result


# ------------------------------------------------------------------------------------------------ evaluation


def restore_run(run_dir, step: int | None = None) -> tuple[TrainConfig, TrainState]:
    """Config and TrainState of a run directory (latest checkpoint unless `step`)."""
    run_dir = pathlib.Path(run_dir)
    config = load_run_config(run_dir)
    t = make_train(config)
    ckpt = Checkpointer(run_dir / CHECKPOINT_DIR, keep=config.run.keep_checkpoints, create=False)
    template = jax.eval_shape(t.init, jax.random.PRNGKey(0), t.default_hparams)
    state = ckpt.restore(template, step)
    ckpt.close()
    return config, state


def evaluate_state(config: TrainConfig, state: TrainState, episodes: int, seed: int, baselines=()) -> dict:
    """SPEC A.4 metrics of the trained (deterministic) policy and optional baselines on the run's env/reward."""
    from tgrf_jax.env import CrowdNavEnv
    from tgrf_jax.evaluate import evaluate
    from tgrf_jax.policies import baseline
    from tgrf_jax.train.policy import LearnedPolicy
    from tgrf_jax.train.ppo import make_network_for

    env = CrowdNavEnv(config.env, config.reward)
    key = jax.random.key(seed)
    params = jax.device_get(state.params)  # off the shards' devices: evaluation runs on the default device
    results = {"learned": evaluate(env, LearnedPolicy(make_network_for(config), params), key, episodes)}
    for name in baselines:
        results[name] = evaluate(env, baseline(name), key, episodes)
    return {"env": repr(env), "episodes": episodes, "seed": seed,
            "results": {k: v.to_dict() for k, v in results.items()}}


def format_eval(payload: dict) -> str:
    from tgrf_jax.evaluate import EvalResult, format_table

    results = {k: EvalResult(**{f: (float("nan") if v is None else v) for f, v in d.items()})
               for k, d in payload["results"].items()}
    return format_table(results)


def params_digest(params) -> str:
    """SHA-256 of all parameter bytes (bitwise identity check across runs)."""
    import hashlib

    h = hashlib.sha256()
    for leaf in jax.tree_util.tree_leaves(jax.device_get(params)):
        h.update(np.asarray(leaf).tobytes())
    return h.hexdigest()
