"""Training and held-out evaluation of the predictor: bivariate Gaussian NLL, Adam with a step schedule,
one compiled update (a scan of updates per call), orbax checkpoints with bit-identical resume.

CrowdNav++'s GST training recipe (Huang et al., RA-L 2022; docs/predictor.md) is `mean_loss="nll"`,
`dropout=0.1`, `cv_prior=False`, Adam at lr 1e-3 multiplied by 0.3 every quarter of the run, 64 windows per
update. The defaults differ where the simulator's crowds showed it matters (docs/predictor.md): the means are fitted
to the position error (`mean_loss="ade"`), on top of the constant-velocity prior, without dropout. The reference
trains 100 epochs over ~160k windows; our datasets hold ~10x more windows, so a run is counted in updates, not
epochs."""

from __future__ import annotations

import dataclasses
import functools
import json
import pathlib
import time

import jax
import jax.numpy as jnp
import numpy as np
import optax
from flax import struct

from tgrf_jax.env.gst.model import (
    PRED_LEN,
    StepGaussians,
    accumulate,
    init_params,
    step_gaussians,
)
from tgrf_jax.predictor import data as data_lib
from tgrf_jax.storage.checkpoint import Checkpointer, CheckpointError
from tgrf_jax.storage.files import write_atomic
from tgrf_jax.storage.lock import exclusive

# CrowdNav++'s README, its non-rand model on its own ORCA test data (ADE / FDE over 1.25 s).
YARDSTICK = {"ade": 0.158, "fde": 0.322}
MEAN_LOSSES = ("ade", "nll")
# batch_size: a batch's windows are built on the device at once; updates: the step counter is int32
_LIMITS = {
    "updates": 2**31 - 1,
    "batch_size": 65_536,
    "decay_every": 2**31 - 1,
    "log_every": 2**31 - 1,
    "checkpoint_every": 2**31 - 1,
    "eval_windows": 10_000_000,
}
_CORR_LIMIT = 0.999  # keeps log(1 - rho^2) finite; tanh outputs saturate in float32 otherwise


@dataclasses.dataclass(frozen=True)
class TrainConfig:
    updates: int = 6000
    batch_size: int = 64
    lr: float = 1e-3
    decay_rate: float = 0.3
    decay_every: int = 4500
    seed: int = 0
    log_every: int = 100
    checkpoint_every: int = 1000
    eval_windows: int = 20000
    cv_prior: bool = True  # predict corrections to constant velocity (see tgrf_jax.env.gst.model)
    mean_loss: str = "ade"  # what fits the predicted means: "ade" (displacement error) or "nll" (CrowdNav++ GST's loss)
    dropout: float = 0.0  # CrowdNav++'s GST trains with 0.1

    def __post_init__(self):
        for name in ("updates", "batch_size", "decay_every", "log_every", "checkpoint_every", "eval_windows"):
            value = getattr(self, name)
            if not isinstance(value, int) or isinstance(value, bool) or value < 1:
                raise ValueError(f"{name} = {value!r} must be an integer >= 1")
            if value > _LIMITS[name]:
                raise ValueError(f"{name} = {value:,} is out of range; allowed: 1 .. {_LIMITS[name]:,}")
        if not 0 < self.lr <= 1:
            raise ValueError(f"lr = {self.lr!r} must be in (0, 1]")
        if not 0 < self.decay_rate <= 1:
            raise ValueError(f"decay_rate = {self.decay_rate!r} must be in (0, 1]")
        if not 0 <= self.dropout < 1:
            raise ValueError(f"dropout = {self.dropout!r} must be in [0, 1)")
        if self.mean_loss not in MEAN_LOSSES:
            raise ValueError(f"mean_loss = {self.mean_loss!r}: allowed {', '.join(MEAN_LOSSES)}")
        if not isinstance(self.seed, int) or not 0 <= self.seed < 2**31:
            raise ValueError(f"seed = {self.seed!r} must be an integer in [0, 2^31)")


@struct.dataclass
class TrainState:
    params: dict
    opt_state: optax.OptState
    step: jnp.ndarray  # () int32 updates done
    key: jnp.ndarray  # typed PRNG key data (uint32) of the run


def schedule(config: TrainConfig):
    """lr x decay_rate^floor(update / decay_every)."""
    return optax.exponential_decay(config.lr, config.decay_every, config.decay_rate, staircase=True)


def optimizer(config: TrainConfig):
    return optax.adam(schedule(config))


def displacements(batch: data_lib.Batch):
    """True per-step displacements (N, 5, 2) from the last observed position."""
    prev = jnp.concatenate([batch.positions[:, -1:], batch.target[:, :-1]], axis=1)
    return batch.target - prev


def nll_terms(g: StepGaussians, batch: data_lib.Batch):
    """(per-step NLL (N, 5) without the log 2 pi constant, mask (N, 5)) as CrowdNav++'s GST defines the loss."""
    corr = jnp.clip(g.corr, -_CORR_LIMIT, _CORR_LIMIT)
    n = (displacements(batch) - g.mu) / g.sigma
    nx, ny = n[..., 0], n[..., 1]
    one_m = 1.0 - corr * corr
    nll = (
        0.5 * jnp.log(one_m)
        + jnp.log(g.sigma[..., 0])
        + jnp.log(g.sigma[..., 1])
        + (nx * nx - 2.0 * corr * nx * ny + ny * ny) / (2.0 * one_m)
    )
    mask = batch.target_valid & g.out_mask[:, None]
    return jnp.where(mask, nll, 0.0), mask


def gaussians_loss(g: StepGaussians, batch: data_lib.Batch, mean_loss: str = "nll"):
    """Loss of predicted Gaussians for a batch of windows (leading axis), averaged over the valid (human, step)
    pairs.

    "nll": the Gaussian NLL fits means, spreads and correlations together (CrowdNav++'s GST recipe). "ade": the
    means are fitted to the Euclidean error of the predicted positions (what ADE / FDE measure), and the NLL, with the
    means held fixed, fits the spreads and correlations. Under the NLL the heavy-tailed errors of a crowd (abrupt goal
    changes) pull the means away from the typical path: on ORCA crowds NLL-fitted means predict worse than
    constant velocity (docs/predictor.md)."""
    fit_means = mean_loss == "ade"
    nll, mask = jax.vmap(nll_terms)(g.replace(mu=jax.lax.stop_gradient(g.mu)) if fit_means else g, batch)
    count = jnp.maximum(jnp.sum(mask), 1)
    loss = jnp.sum(nll) / count
    if fit_means:
        means = batch.positions[:, :, -1:, :] + jnp.cumsum(g.mu, axis=2)
        # the epsilon keeps the gradient finite where a prediction is exact (the untrained prior's, say)
        err = jnp.sqrt(jnp.sum((means - batch.target) ** 2, axis=-1) + 1e-12)
        loss = loss + jnp.sum(jnp.where(mask, err, 0.0)) / count
    return loss


def loss_fn(params, batch: data_lib.Batch, dropout_key, config: TrainConfig):
    """`gaussians_loss` of the model's predictions under training conditions (dropout). Under "ade" the NLL
    reaches only the output head's spread rows, so the network's state is shaped by the position error alone."""
    keys = jax.random.split(dropout_key, batch.positions.shape[0])
    model = functools.partial(step_gaussians, dropout=config.dropout, detach_spreads=config.mean_loss == "ade")
    g = jax.vmap(lambda b, k: model(params, b.positions, b.visible, dropout_key=k if config.dropout else None))(
        batch, keys
    )
    return gaussians_loss(g, batch, config.mean_loss)


def train_chunk(state: TrainState, data: dict, index, config: TrainConfig, length: int):
    """`length` updates -> (state, mean loss). Batches are drawn from `fold_in(key, step)`, so a resumed run
    draws the same batches as an uninterrupted one."""
    # what the compiled program depends on
    learning = (config.batch_size, config.lr, config.decay_every, config.decay_rate, config.mean_loss, config.dropout)
    return _train_chunk(state, data, index, learning=learning, length=length)


@functools.partial(jax.jit, static_argnames=("learning", "length"))
def _train_chunk(state: TrainState, data: dict, index, *, learning: tuple, length: int):
    batch_size, lr, decay_every, decay_rate, mean_loss, dropout = learning
    config = TrainConfig(
        batch_size=batch_size,
        lr=lr,
        decay_every=decay_every,
        decay_rate=decay_rate,
        mean_loss=mean_loss,
        dropout=dropout,
    )
    opt = optimizer(config)
    windows = jax.vmap(lambda es: data_lib.make_window(data, es))

    def update(state: TrainState, _):
        key = jax.random.fold_in(jax.random.wrap_key_data(state.key), state.step)
        k_batch, k_drop = jax.random.split(key)
        picks = jax.random.randint(k_batch, (config.batch_size,), 0, index.shape[0])
        loss, grads = jax.value_and_grad(loss_fn)(state.params, windows(index[picks]), k_drop, config)
        updates, opt_state = opt.update(grads, state.opt_state, state.params)
        params = optax.apply_updates(state.params, updates)
        return state.replace(params=params, opt_state=opt_state, step=state.step + 1), loss

    state, losses = jax.lax.scan(update, state, None, length=length)
    return state, jnp.mean(losses)


def init_state(config: TrainConfig) -> TrainState:
    key = jax.random.key(config.seed)
    k_init, k_run = jax.random.split(key)
    params = init_params(k_init, cv_prior=config.cv_prior)
    return TrainState(
        params=params,
        opt_state=optimizer(config).init(params),
        step=jnp.zeros((), jnp.int32),
        key=jax.random.key_data(k_run),
    )


# ------------------------------------------------------------------------------------------ evaluation
def eval_subset(index: np.ndarray, count: int) -> np.ndarray:
    """`count` windows spread evenly over the held-out index (deterministic), or all if there are fewer."""
    if len(index) <= count:
        return index
    return index[np.linspace(0, len(index) - 1, count).round().astype(np.int64)]


def _window_sums(params, data: dict, env_start, weight):
    """Sums for ADE / FDE (model and constant velocity) over one window's scored humans, and its NLL sum."""
    b = data_lib.make_window(data, env_start)
    g = step_gaussians(params, b.positions, b.visible)
    pred = accumulate(g, b.positions[:, -1]).means
    last, prev = b.positions[:, -1], b.positions[:, -2]
    steps = jnp.arange(1, PRED_LEN + 1, dtype=jnp.float32)[None, :, None]
    cv = last[:, None] + steps * (last - prev)[:, None]
    w = (g.out_mask & jnp.all(b.target_valid, axis=1)).astype(jnp.float32) * weight
    err = lambda p: jnp.linalg.norm(p - b.target, axis=-1)
    nll, mask = nll_terms(g, b)
    return dict(
        humans=jnp.sum(w),
        ade=jnp.sum(w * jnp.mean(err(pred), -1)),
        fde=jnp.sum(w * err(pred)[:, -1]),
        cv_ade=jnp.sum(w * jnp.mean(err(cv), -1)),
        cv_fde=jnp.sum(w * err(cv)[:, -1]),
        nll=jnp.sum(nll) * weight,
        nll_count=jnp.sum(mask) * weight,
    )


@jax.jit
def _eval_chunk(params, data: dict, index, weight):
    return jax.vmap(_window_sums, in_axes=(None, None, 0, 0))(params, data, index, weight)


BOOTSTRAP_SAMPLES = 2000


def relative_change(model_sums, cv_sums, episode, samples: int = BOOTSTRAP_SAMPLES):
    """(model / cv - 1, its 95% interval) from per-window error sums, resampling whole held-out episodes (the
    windows of one episode share its crowd, so they are not independent). Fixed seed: the same windows give the
    same interval."""
    episodes, inverse = np.unique(episode, return_inverse=True)
    per_model = np.bincount(inverse, weights=model_sums, minlength=len(episodes))
    per_cv = np.bincount(inverse, weights=cv_sums, minlength=len(episodes))
    picks = np.random.default_rng(0).integers(0, len(episodes), (samples, len(episodes)))
    draws = per_model[picks].sum(1) / np.maximum(per_cv[picks].sum(1), 1e-12) - 1.0
    lo, hi = np.percentile(draws, [2.5, 97.5])
    return float(per_model.sum() / max(per_cv.sum(), 1e-12) - 1.0), [float(lo), float(hi)]


def make_evaluator(data: dict, chunk: int = 1000):
    """evaluate(params, index (W, 2)) -> ADE / FDE / NLL of the model and ADE / FDE of constant velocity on
    the same windows and humans: those the model predicts (seen in the last two observed frames) and that are
    seen in all 5 future frames. NLL is over every valid predicted step, as the loss. `ade_change` and
    `fde_change` are the model's errors relative to constant velocity's (-0.05: 5% lower), each with a 95%
    interval from resampling held-out episodes."""

    def evaluate(params, index: np.ndarray) -> dict:
        pad = (-len(index)) % chunk
        padded = np.concatenate([index, np.repeat(index[:1], pad, 0)])
        weight = (np.arange(len(padded)) < len(index)).astype(np.float32)
        parts = [
            jax.device_get(_eval_chunk(params, data, padded[s : s + chunk], weight[s : s + chunk]))
            for s in range(0, len(padded), chunk)
        ]
        per_window = {k: np.concatenate([p[k] for p in parts])[: len(index)].astype(np.float64) for k in parts[0]}
        totals = {k: float(v.sum()) for k, v in per_window.items()}
        h = max(totals["humans"], 1.0)
        ade_change, ade_ci = relative_change(per_window["ade"], per_window["cv_ade"], index[:, 0])
        fde_change, fde_ci = relative_change(per_window["fde"], per_window["cv_fde"], index[:, 0])
        return {
            "windows": int(len(index)),
            "humans": int(totals["humans"]),
            "episodes": int(len(np.unique(index[:, 0]))),
            "ade": totals["ade"] / h,
            "fde": totals["fde"] / h,
            "nll": totals["nll"] / max(totals["nll_count"], 1.0),
            "cv_ade": totals["cv_ade"] / h,
            "cv_fde": totals["cv_fde"] / h,
            "ade_change": ade_change,
            "ade_change_ci95": ade_ci,
            "fde_change": fde_change,
            "fde_change_ci95": fde_ci,
        }

    return evaluate


def format_eval(metrics: dict, label: str) -> str:
    y = YARDSTICK
    change = lambda k: (
        f"{k.upper()} {metrics[k + '_change']:+.1%} "
        f"(95% interval {metrics[k + '_change_ci95'][0]:+.1%} to {metrics[k + '_change_ci95'][1]:+.1%})"
    )
    return "\n".join(
        [
            f"held-out {label}: {metrics['windows']:,} windows of {metrics['episodes']} episodes, "
            f"{metrics['humans']:,} predicted humans seen for 1.25 s",
            f"  {'predictor':<28} {'ADE m':>7} {'FDE m':>7} {'NLL':>7}",
            f"  {'GST (this model)':<28} {metrics['ade']:>7.3f} {metrics['fde']:>7.3f} {metrics['nll']:>7.3f}",
            f"  {'constant velocity':<28} {metrics['cv_ade']:>7.3f} {metrics['cv_fde']:>7.3f} {'-':>7}",
            f"  {'CrowdNav++ non-rand (README)':<28} {y['ade']:>7.3f} {y['fde']:>7.3f} {'-':>7}   (its own ORCA data)",
            f"  GST against constant velocity: {change('ade')}, {change('fde')}; episodes resampled",
        ]
    )


# ------------------------------------------------------------------------------------------ run
_EXTENSIBLE = ("updates", "checkpoint_every", "eval_windows")  # may change when a run is resumed


class TrainingError(ValueError):
    """Training cannot go on (a non-finite loss); the message says where and what is kept."""


def _run_meta(config: TrainConfig, dataset: dict) -> dict:
    sha = dataset.get("sha256") or data_lib.content_hash(dataset["arrays"])
    return {"train": dataclasses.asdict(config), "dataset": dataset["config"], "dataset_sha256": sha}


def _fixed(meta: dict) -> dict:
    return {"train": {k: v for k, v in meta["train"].items() if k not in _EXTENSIBLE}, "dataset": meta["dataset"]}


def _saved_meta(path: pathlib.Path) -> dict:
    try:
        saved = json.loads(path.read_text())
        if not (
            isinstance(saved, dict) and isinstance(saved.get("train"), dict) and isinstance(saved.get("dataset"), dict)
        ):
            raise ValueError("no train and dataset sections")
    except (OSError, UnicodeDecodeError, ValueError) as e:
        raise CheckpointError(
            f"{str(path)!r} is damaged ({type(e).__name__}: {str(e)[:80]}): the run's settings are "
            "unknown; use a new --run-dir"
        ) from None
    return saved


def _check_run_dir(run_dir: pathlib.Path, meta: dict) -> None:
    """The run directory holds nothing, or this run: the same settings and the same dataset content."""
    meta_path = run_dir / "run.json"
    if not meta_path.is_file():
        others = [name for name in ("config.yaml", "sweep.yaml", "experiment.yaml") if (run_dir / name).exists()]
        if others or (run_dir / "checkpoints").exists():
            what = others[0] if others else "checkpoints/"
            raise CheckpointError(
                f"--run-dir {str(run_dir)!r} holds {what} but no run.json: it is not a "
                "tgrf-predictor run directory; use a new --run-dir"
            )
        return
    saved = _saved_meta(meta_path)
    saved_fixed, wanted = _fixed(saved), _fixed(meta)
    if saved_fixed != wanted:
        diff = sorted(
            k
            for part in ("train", "dataset")
            for k in set(saved_fixed[part]) | set(wanted[part])
            if saved_fixed[part].get(k) != wanted[part].get(k)
        )
        raise CheckpointError(
            f"run directory {str(run_dir)!r} holds a run with another config (differs in "
            f"{', '.join(diff)}); use a new --run-dir or the same options"
        )
    if saved.get("dataset_sha256") != meta["dataset_sha256"]:
        raise CheckpointError(
            f"run directory {str(run_dir)!r} was trained on another dataset (content SHA-256 "
            f"{str(saved.get('dataset_sha256'))[:12]}, this one {meta['dataset_sha256'][:12]}); "
            "resume with the same dataset file, or use a new --run-dir"
        )


def _steps(ckpt_dir: pathlib.Path) -> list[int]:
    if not ckpt_dir.is_dir():
        return []
    reader = Checkpointer(ckpt_dir, create=False)
    try:
        return reader.all_steps()
    finally:
        reader.close()


def train(
    config: TrainConfig, dataset: dict, run_dir, log=print, resume: bool = True, from_step: int | None = None
) -> tuple[dict, dict]:
    """Train (resuming from `run_dir`'s latest checkpoint if there is one, or from checkpoint `from_step`, whose
    later checkpoints are deleted); returns (params, run metadata). The process holds the run directory's lock
    (`tgrf_jax.storage.lock`) while it writes there; everything is checked before run.json is written."""
    run_dir = pathlib.Path(run_dir)
    data_lib.check_arrays(dataset["arrays"], "dataset")
    meta = _run_meta(config, dataset)
    _check_run_dir(run_dir, meta)
    with exclusive(run_dir):
        _check_run_dir(run_dir, meta)  # again, now that no other process can write it
        steps = _steps(run_dir / "checkpoints") if resume else []
        if from_step is not None and from_step not in steps:
            raise CheckpointError(
                f"--from-step {from_step}: {str(run_dir / 'checkpoints')!r} holds no checkpoint "
                f"of update {from_step}; it holds: {', '.join(map(str, steps)) or 'none'}"
            )
        step = from_step if from_step is not None else (steps[-1] if steps else None)
        if step is not None and step > config.updates:
            raise CheckpointError(
                f"--updates {config.updates} is below the progress of {str(run_dir)!r}: its "
                f"checkpoint of update {step} would be labelled {config.updates}; give --updates "
                f">= {step}, or --from-step N to go back to an earlier checkpoint (it holds: "
                f"{', '.join(map(str, steps))})"
            )
        write_atomic(run_dir / "run.json", json.dumps(meta, indent=2, sort_keys=True))
        return _train(config, dataset, run_dir, meta, step, log)


def _train(config: TrainConfig, dataset: dict, run_dir: pathlib.Path, meta: dict, step, log):
    arrays = dataset["arrays"]
    train_index, val_index = data_lib.split_index(arrays)
    log(f"windows: {len(train_index):,} train, {len(val_index):,} held out")
    data = data_lib.device_arrays(arrays)
    ckpt = Checkpointer(run_dir / "checkpoints", keep=2)
    state = init_state(config)
    try:
        if step is not None:
            state = ckpt.restore(state, step)
            ckpt.delete_after(step)
            log(f"resumed from {run_dir / 'checkpoints'} at update {int(state.step)}")
        index = jnp.asarray(train_index)
        start = time.perf_counter()
        while int(state.step) < config.updates:
            left = config.updates - int(state.step)
            before, tick = int(state.step), time.perf_counter()
            state, loss = train_chunk(state, data, index, config, min(left, config.log_every))
            step = int(state.step)
            if not np.isfinite(float(loss)):  # nothing of this chunk is saved: its weights are not finite
                kept = ckpt.latest_step()
                raise TrainingError(
                    f"the training loss is {float(loss)} in the updates {before + 1}..{step}: the "
                    f"training diverged (lower --lr) or the data is not finite; the checkpoints up "
                    f"to update {kept} in {str(run_dir / 'checkpoints')!r} are kept"
                )
            rate = (step - before) / (time.perf_counter() - tick)  # this chunk's (the first includes compilation)
            lr = schedule(config)(step - 1)
            log(
                f"update {step:>6}/{config.updates}  loss {float(loss):8.4f}  lr {float(lr):.2e}  "
                f"{rate:6.1f} updates/s ({rate * config.batch_size:,.0f} windows/s)"
            )
            if step % config.checkpoint_every == 0 or step == config.updates:
                ckpt.save(step, state)
    finally:
        ckpt.close()
    meta["train_seconds_this_process"] = time.perf_counter() - start
    evaluate = make_evaluator(data)
    metrics = evaluate(state.params, eval_subset(val_index, config.eval_windows))
    meta["eval"] = metrics
    log(format_eval(metrics, dataset["config"].get("crowd", "?")))
    return jax.device_get(state.params), meta
