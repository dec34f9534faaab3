"""tgrf-sweep: a grid of hyper-parameters x seeds trained as one vmapped, compiled program, sharded over devices.

    tgrf-sweep configs/tiny.yaml --grid reward.h_disc=0.5,1.0,2.5 --grid reward.sigma_disc=0.1,0.2,0.4 --seeds 3

The Cartesian product of the grid values times the seeds is a batch of G runs. Every gridded field is a *traced*
hyper-parameter (a leaf of `HParams`: PPO coefficients, every reward parameter, every numeric env parameter), so
all G runs share one set of static choices (shapes, network, env code paths) and train as

    state = stack([jit(trainer.init)(key_i, hparams_i) for each run])   # tgrf-train's init, run by run
    chunk = jit(shard_map(vmap(trainer.run_updates)))   # n updates of all G runs, one compiled program
                                                        # (a device holding one run: run_updates unbatched)

with the run axis split over all devices (`jax.sharding.Mesh` with one axis, "runs"; G is padded to a multiple
of the device count with copies of the last run, and the padding is dropped from every result). Chunk lengths
follow `tgrf_jax.train.loop.chunk_plan` exactly as tgrf-train does, so the chunk program is compiled once per
distinct chunk length (once for the usual configs, where the total is a multiple of `run.log_every`). Fields that
change shapes or code paths (ppo.num_envs, network.*, env.num_humans, env.predictor, ...) are rejected with the
list of griddable fields: run one sweep per value of those instead.

Run i of a sweep is the tgrf-train run of its own config (the base config with the grid values and
`run.seed` = its seed, written to `runs/<name>/config.yaml`): same `HParams` (built by `hparams_from_config`
from that config), same key (`jax.random.PRNGKey(run.seed)`), same chunking and the same evaluation. The
batched program is compiled differently from the single-run one, so the two agree up to float32 rounding
(parameters within ~1e-6, the whole state within ~1e-5 after 12 updates of configs/tiny.yaml, Social Force and
ORCA alike), not bit for bit; so do different device counts. Bit-identical: a one-run sweep and the tgrf-train
run, a resumed sweep and an uninterrupted one, and equal numbers of runs per device (e.g. 2 hosts x 2 devices
and 1 host x 4 devices).

Sweep directory:
    sweep.yaml             the grid: axes, seeds, base config, and the run list (name, grid point, seed, values)
    config.yaml            the resolved base config (file + --set; grid values not applied)
    metrics.csv            learning curves of all runs, long format: run, point, seed, grid values + tgrf-train's
                           CSV fields (one row per run per chunk)
    progress.log           the progress lines printed to stdout
    checkpoints/<update>/  orbax checkpoints of the stacked TrainState of all G runs (no padding)
    runs/<name>/           one tgrf-train run directory per run: config.yaml, metrics.csv, eval.json and the final
                           checkpoint (so `tgrf-eval runs/<name>` works)
    evals.csv              final evaluation of every run (SPEC A.4 metrics + final training return/success)
    summary.csv / .md      mean and std over seeds for every grid point
    heatmap.png            success rate and ITR over two gridded parameters (grid_metrics.png with one axis)
    learning_curves.png    training return and success rate per grid point, mean over seeds with a +-std band
"""

from __future__ import annotations

import argparse
import copy
import csv
import dataclasses
import datetime
import difflib
import functools
import itertools
import json
import math
import os
import pathlib
import sys
import time
import warnings
from typing import Any, Callable

import numpy as np
import yaml

from tgrf_jax.config import ConfigError, TrainConfig, apply_overrides, load_yaml

SWEEP_FILE = "sweep.yaml"
CONFIG_FILE = "config.yaml"
METRICS_FILE = "metrics.csv"
EVALS_FILE = "evals.csv"
SUMMARY_CSV = "summary.csv"
SUMMARY_MD = "summary.md"
HEATMAP_FILE = "heatmap.png"
GRID_PLOT_FILE = "grid_metrics.png"
CURVES_FILE = "learning_curves.png"
CHECKPOINT_DIR = "checkpoints"
RUNS_DIR = "runs"
AXIS = "runs"  # mesh axis name of the run dimension

# Metrics of the summary table: final evaluation (SPEC A.4) and the end of training.
EVAL_METRICS = ("success_rate", "collision_rate", "timeout_rate", "nav_time", "path_length", "itr_future",
                "itr_disc", "intrusion_dist_future", "intrusion_dist_disc", "mean_return")
TRAIN_METRICS = ("train_return", "train_success_rate")
_SUMMED = ("episodes", "return_sum", "successes", "collisions", "timeouts")  # chunk metrics that add up
TRAIN_TAIL = 0.1  # training metrics: episode-weighted over the chunks of the last 10% of updates


# ------------------------------------------------------------------------------------------------- the grid


def _section_classes() -> dict[str, type]:
    return {f.name: type(f.default_factory()) for f in dataclasses.fields(TrainConfig)}


def griddable_fields() -> list[str]:
    """Dotted config fields that are traced hyper-parameters (leaves of `HParams`), hence griddable.

    Derived from the pytrees themselves: ppo.* fields of `HParams`, env.* fields of `EnvParams`, reward.* fields
    of `RewardParams`, plus reward.scheme (a scheme is only a set of `RewardParams` values).
    """
    from tgrf_jax.env import EnvParams
    from tgrf_jax.reward import RewardParams
    from tgrf_jax.train.ppo import HParams

    sections = {s: {f.name for f in dataclasses.fields(c)} for s, c in _section_classes().items()}
    names = [f"ppo.{f.name}" for f in dataclasses.fields(HParams) if f.name in sections["ppo"]]
    names += [f"env.{f.name}" for f in dataclasses.fields(EnvParams) if f.name in sections["env"]]
    names += ["reward.scheme"] + [f"reward.{f.name}" for f in dataclasses.fields(RewardParams)
                                  if f.name in sections["reward"]]
    return names


def config_fields() -> list[str]:
    return [f"{s}.{f.name}" for s, c in _section_classes().items() for f in dataclasses.fields(c)]


@dataclasses.dataclass(frozen=True)
class GridAxis:
    name: str  # dotted config field, e.g. reward.h_disc
    values: tuple  # parsed values (YAML scalars: numbers, or scheme names)

    @property
    def short(self) -> str:
        return self.name.split(".", 1)[1]


def _parse_scalar(raw: str):
    raw = raw.strip()
    try:
        return yaml.safe_load(raw)
    except yaml.YAMLError:
        return raw


def _set_dotted(data: dict, dotted: str, value) -> None:
    keys = dotted.split(".")
    node = data
    for k in keys[:-1]:
        node = node.setdefault(k, {})
        if node is None:
            node = {}
    node[keys[-1]] = value


def _with_values(base: dict, values: dict) -> dict:
    data = copy.deepcopy(base)
    for dotted, value in values.items():
        _set_dotted(data, dotted, value)
    return data


def parse_grid(items: list[str], base: dict | None = None) -> tuple[GridAxis, ...]:
    """Parse `--grid section.field=v1,v2,...` items; validate names (griddable) and every value (the config's own
    range checks against `base`) before anything is compiled. Raises ConfigError naming the field."""
    base = {} if base is None else base
    griddable, known = griddable_fields(), config_fields()
    axes: list[GridAxis] = []
    for item in items:
        if "=" not in item:
            raise ConfigError(f"--grid {item!r} must look like section.field=v1,v2,... (e.g. reward.h_disc=0.5,1.0)")
        name, raw = item.split("=", 1)
        name = name.strip()
        if name not in griddable:
            listing = ", ".join(griddable)
            if name in known:
                raise ConfigError(
                    f"--grid {name}: cannot be gridded: it is a static setting (array shapes or code paths), so runs "
                    f"with different values cannot share one compiled program; run one sweep per value instead. "
                    f"Griddable (traced) fields: {listing}")
            close = difflib.get_close_matches(name, known, n=1)
            hint = f" (did you mean {close[0]!r}?)" if close else ""
            raise ConfigError(f"--grid {name}: unknown config key {name!r}{hint}; griddable fields: {listing}")
        if any(a.name == name for a in axes):
            raise ConfigError(f"--grid {name} is given twice; list all its values in one --grid")
        tokens = [t for t in raw.split(",")]
        if not raw.strip() or any(not t.strip() for t in tokens):
            raise ConfigError(f"--grid {item!r}: empty value; expected {name}=v1,v2,... ")
        section, field = name.split(".", 1)
        canon = []
        for raw_value in tokens:
            try:  # the config's own range checks, on the base config with this one value
                cfg = TrainConfig.from_dict(_with_values(base, {name: _parse_scalar(raw_value)}))
            except ConfigError as e:
                raise ConfigError(f"--grid {name}={raw_value.strip()}: {e}") from None
            canon.append(getattr(getattr(cfg, section), field))  # as the config stores it (1 -> 1.0)
        dups = sorted({str(v) for v in canon if canon.count(v) > 1})
        if dups:
            raise ConfigError(f"--grid {name}: repeated value(s) {', '.join(dups)}")
        axes.append(GridAxis(name, tuple(canon)))
    return tuple(axes)


def parse_seeds(text: str | int | None, base_seed: int) -> tuple[int, ...]:
    """`--seeds 3`: run.seed, run.seed + 1, run.seed + 2; `--seeds 0,5,7`: exactly those (a list needs a comma)."""
    if text is None:
        return (base_seed,)
    if isinstance(text, int):
        text = str(text)
    text = text.strip()
    try:
        numbers = tuple(int(t) for t in text.split(",") if t.strip())
    except ValueError:
        numbers = ()
    if not numbers:
        raise ConfigError(f"--seeds {text!r} must be a count (e.g. 3) or a comma-separated list of seeds "
                          f"(e.g. 0,5,7)")
    if "," in text:
        seeds = numbers
    else:
        if numbers[0] < 1:
            raise ConfigError(f"--seeds {text}: the number of seeds must be >= 1 (a single seed s: --seeds s,)")
        seeds = tuple(base_seed + i for i in range(numbers[0]))
    if len(set(seeds)) != len(seeds):
        raise ConfigError(f"--seeds {text}: repeated seed")
    for s in seeds:
        try:
            TrainConfig.from_dict({"run": {"seed": s}})
        except ConfigError as e:
            raise ConfigError(f"--seeds {text}: {e}") from None
    return seeds


def _fmt_value(v) -> str:
    return f"{v:g}" if isinstance(v, float) else str(v)


@dataclasses.dataclass(frozen=True)
class RunSpec:
    index: int  # position in the batch
    point: int  # grid point index
    seed: int
    values: dict  # grid values of the point, {dotted name: value}
    name: str  # directory name under runs/
    config: TrainConfig


@dataclasses.dataclass(frozen=True)
class SweepSpec:
    """A base config (resolved dict), grid axes and seeds. Runs are ordered point-major: (point, seed)."""

    base: dict
    axes: tuple[GridAxis, ...]
    seeds: tuple[int, ...]

    @classmethod
    def create(cls, config_path=None, grid: list[str] = (), seeds: str | int | None = None,
               overrides: list[str] = ()) -> "SweepSpec":
        data = load_yaml(config_path) if config_path else {}
        base = TrainConfig.from_dict(apply_overrides(data, list(overrides))).to_dict()
        axes = parse_grid(list(grid), base)
        spec = cls(base, axes, parse_seeds(seeds, base["run"]["seed"]))
        spec.runs()  # validates every run config (combinations included)
        return spec

    @property
    def base_config(self) -> TrainConfig:
        return TrainConfig.from_dict(self.base)

    def points(self) -> list[dict]:
        return [dict(zip([a.name for a in self.axes], combo)) for combo in
                itertools.product(*[a.values for a in self.axes])]

    def point_label(self, values: dict) -> str:
        return ", ".join(f"{k.split('.', 1)[1]}={_fmt_value(v)}" for k, v in values.items()) or "base"

    @functools.cached_property
    def _runs(self) -> tuple[RunSpec, ...]:
        runs = []
        base_name = self.base["run"]["name"]
        for p, values in enumerate(self.points()):
            tag = "_".join(f"{k.split('.', 1)[1]}={_fmt_value(v)}" for k, v in values.items())
            for seed in self.seeds:
                name = f"p{p:03d}" + (f"_{tag}" if tag else "") + f"_seed={seed}"
                data = _with_values(self.base, dict(values, **{"run.seed": seed, "run.name": f"{base_name}_{name}"}))
                try:
                    config = TrainConfig.from_dict(data)
                except ConfigError as e:
                    raise ConfigError(f"grid point {self.point_label(values)}: {e}") from None
                runs.append(RunSpec(len(runs), p, seed, values, name, config))
        return tuple(runs)

    def runs(self) -> tuple[RunSpec, ...]:
        return self._runs

    def to_dict(self) -> dict:
        return {
            "grid": {a.name: list(a.values) for a in self.axes},
            "seeds": list(self.seeds),
            "runs": [{"name": r.name, "point": r.point, "seed": r.seed, "values": dict(r.values)} for r in self.runs()],
            "base": self.base,
        }

    @classmethod
    def from_dict(cls, data: dict) -> "SweepSpec":
        try:
            base = TrainConfig.from_dict(data["base"]).to_dict()
            axes = tuple(GridAxis(k, tuple(v)) for k, v in (data.get("grid") or {}).items())
            return cls(base, axes, tuple(int(s) for s in data["seeds"]))
        except (KeyError, TypeError) as e:
            raise ConfigError(f"{SWEEP_FILE} is malformed: {e!r}") from None

    def describe(self) -> str:
        runs = self.runs()
        lines = [f"{len(self.points())} grid point(s) x {len(self.seeds)} seed(s) = {len(runs)} runs"]
        for a in self.axes:
            lines.append(f"  {a.name}: {', '.join(_fmt_value(v) for v in a.values)}")
        lines.append(f"  seeds: {', '.join(map(str, self.seeds))}")
        for r in runs:
            lines.append(f"  run {r.index:3d}: {r.name}")
        return "\n".join(lines)


def load_sweep(sweep_dir) -> SweepSpec:
    path = pathlib.Path(sweep_dir) / SWEEP_FILE
    if not path.is_file():
        raise ConfigError(f"{str(path)!r} does not exist: {str(sweep_dir)!r} is not a tgrf-sweep directory")
    return SweepSpec.from_dict(load_yaml(path))


# ---------------------------------------------------------------------------------------- compiled programs


def _host(tree):
    """Device arrays -> host numpy (all processes get the full arrays, also when sharded over several hosts)."""
    import jax
    from jax.experimental import multihost_utils

    def one(x):
        if isinstance(x, jax.Array) and not x.is_fully_addressable:
            return np.asarray(multihost_utils.process_allgather(x, tiled=True))
        return np.asarray(jax.device_get(x))

    return jax.tree_util.tree_map(one, tree)


def _place(tree, sharding):
    """Host arrays with a leading run axis -> global jax.Arrays split over the mesh (works across hosts)."""
    import jax

    def one(x):
        x = np.asarray(x)
        return jax.make_array_from_callback(x.shape, sharding, lambda idx: x[idx])

    return jax.tree_util.tree_map(one, tree)


def _pad(tree, g_pad: int):
    """Pad the leading run axis to g_pad with copies of the last run."""
    def one(x):
        x = np.asarray(x)
        if x.shape[0] == g_pad:
            return x
        return np.concatenate([x, np.repeat(x[-1:], g_pad - x.shape[0], axis=0)], axis=0)

    import jax

    return jax.tree_util.tree_map(one, tree)


def _stack(trees):
    import jax

    return jax.tree_util.tree_map(lambda *xs: np.stack([np.asarray(x) for x in xs]), *trees)


def _take(tree, i):
    import jax

    return jax.tree_util.tree_map(lambda x: x[i], tree)


def _per_run(f, n_batched: int | None = None):
    """f over the leading (run) axis of the first `n_batched` arguments (default: all): vmapped, except where a
    device holds a single run, which runs f itself (tgrf-train's unbatched program, without vmap's overheads,
    e.g. a `lax.cond` turned into a select that evaluates both branches)."""
    import jax

    def g(*args):
        k = len(args) if n_batched is None else n_batched
        batched, rest = args[:k], args[k:]
        if jax.tree_util.tree_leaves(batched)[0].shape[0] == 1:
            out = f(*jax.tree_util.tree_map(lambda x: x[0], batched), *rest)
            return jax.tree_util.tree_map(lambda x: x[None], out)
        return jax.vmap(f, in_axes=(0,) * k + (None,) * len(rest))(*batched, *rest)

    return g


class SweepProgram:
    """The compiled pieces of a sweep for one static configuration and one device mesh.

    `chunk(state, n)` and `eval_stats(params, env_params, key, n_episodes)` take and return pytrees with a leading
    run axis split over the mesh; inside `shard_map` each device vmaps over its own runs (or, holding one run, runs
    the unbatched function), so the runs never communicate. `init_one(key, hparams)` is tgrf-train's single-run
    init.
    """

    def __init__(self, config: TrainConfig, devices):
        import jax
        from jax.sharding import Mesh, NamedSharding, PartitionSpec as P

        from tgrf_jax.env import CrowdNavEnv
        from tgrf_jax.evaluate import run_episodes
        from tgrf_jax.train.policy import LearnedPolicy
        from tgrf_jax.train.ppo import make_train

        self.config = config
        self.devices = tuple(devices)
        self.mesh = Mesh(np.array(self.devices), (AXIS,))
        self.sharding = NamedSharding(self.mesh, P(AXIS))
        # the run axis takes the devices; a run's env shards (ppo.num_shards) are vmapped on its device
        self.train = make_train(config, devices=None)
        trainer = self.train.trainer
        self.trainer = trainer
        spec = P(AXIS)

        def smap(f, n_in, replicated_last=False):
            in_specs = tuple([spec] * n_in + ([P()] if replicated_last else []))
            # check_vma off: the runs never communicate, and loops that start from replicated values (the shared
            # evaluation key) would otherwise need explicit casts
            return jax.shard_map(f, mesh=self.mesh, in_specs=in_specs, out_specs=spec, check_vma=False)

        # Runs are initialised one at a time with tgrf-train's own jit(trainer.init) (bit-identical initial states),
        # not with vmap(trainer.init): on XLA:CPU the vmapped init (batched LAPACK QR of the orthogonal
        # initialisers) can deadlock at execution, every worker thread idle.
        self.init_one = jax.jit(trainer.init)

        def chunk(ts, n_updates):
            return smap(_per_run(functools.partial(trainer.run_updates, n_updates=n_updates)), 1)(ts)

        self.chunk = jax.jit(chunk, static_argnums=1, donate_argnums=0)
        net = trainer.net
        self.eval_env = CrowdNavEnv(dataclasses.replace(config.env, track_future_intrusion=True), config.reward)

        def eval_stats(params, env_params, key, n_episodes):
            def one(p, ep, k):
                return run_episodes(self.eval_env, LearnedPolicy(net, p), k, n_episodes, ep)

            return smap(_per_run(one, n_batched=2), 2, replicated_last=True)(params, env_params, key)

        self.eval_stats = jax.jit(eval_stats, static_argnums=3)
        self.compiled: dict[tuple, Any] = {}  # (n_updates, G_pad) -> AOT-compiled chunk

    def compiled_chunk(self, state, n: int):
        """(compiled chunk for `n` updates at this batch size, compile seconds or None if cached)."""
        key = (n, int(np.shape(state.update)[0]))
        if key in self.compiled:
            return self.compiled[key], None
        c0 = time.perf_counter()
        self.compiled[key] = self.chunk.lower(state, n).compile()
        return self.compiled[key], time.perf_counter() - c0


_PROGRAMS: dict[tuple, SweepProgram] = {}


def _static_signature(config: TrainConfig) -> str:
    """Everything of a config except the griddable fields and the run section (which the trainer never reads)."""
    data = config.to_dict()
    for name in griddable_fields():
        section, field = name.split(".", 1)
        data[section].pop(field, None)
    data.pop("run", None)
    return yaml.safe_dump(data, sort_keys=True)


def get_program(config: TrainConfig, devices) -> SweepProgram:
    """One SweepProgram per (static config, devices) per process (repeated sweeps reuse compilations)."""
    key = (_static_signature(config), tuple(d.id for d in devices))
    if key not in _PROGRAMS:
        _PROGRAMS[key] = SweepProgram(config, devices)
    return _PROGRAMS[key]


# ------------------------------------------------------------------------------------------------ the loop


@dataclasses.dataclass
class SweepResult:
    sweep_dir: pathlib.Path
    spec: SweepSpec
    state: Any  # stacked TrainState of the G runs (host numpy, no padding)
    updates: int
    train_seconds: float
    num_devices: int
    evals: list | None  # per run: the eval.json payload (or None when not evaluated)


def _barrier(name: str) -> None:
    import jax

    if jax.process_count() > 1:
        from jax.experimental import multihost_utils

        multihost_utils.sync_global_devices(name)


def _csv_rewrite_upto(path: pathlib.Path, update: int, fields) -> float:
    if not path.is_file():
        return 0.0
    with open(path, newline="") as f:
        rows = [r for r in csv.DictReader(f) if int(float(r["update"])) <= update]
    with open(path, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=fields)
        w.writeheader()
        w.writerows(rows)
    return max((float(r["wall_s"]) for r in rows), default=0.0)


def _aggregate(metrics_runs: list[dict]) -> dict:
    """Chunk metrics of all runs in one: episode sums added, the other scalars averaged over runs."""
    from tgrf_jax.train import ppo

    summed = getattr(ppo, "_SUMMED", _SUMMED)
    out = {}
    for k in metrics_runs[0]:
        vals = [float(m[k]) for m in metrics_runs]
        out[k] = sum(vals) if k in summed else float(np.mean(vals))
    return out


def run_sweep(
    spec: SweepSpec | None,
    sweep_dir,
    *,
    resume: bool = False,
    log: Callable[[str], None] = print,
    stop_after_updates: int | None = None,
    devices=None,
    num_devices: int | None = None,
    export_checkpoints: bool = True,
) -> SweepResult:
    """Train every run of `spec` in `sweep_dir` as one batch (or resume the sweep there: `spec=None, resume=True`).

    `devices` (default: all, `jax.devices()`; or the first `num_devices` of them) carry the run axis.
    `stop_after_updates` ends early, as an interruption would (for tests)."""
    import jax

    from tgrf_jax.train.checkpoint import CheckpointError, Checkpointer
    from tgrf_jax.train.loop import CSV_FIELDS, chunk_plan, chunk_row, progress_line
    from tgrf_jax.train.ppo import hparams_from_config

    sweep_dir = pathlib.Path(sweep_dir)
    main = jax.process_index() == 0
    ckpt_dir = sweep_dir / CHECKPOINT_DIR
    if resume:
        loaded = load_sweep(sweep_dir)
        if spec is not None and spec.to_dict() != loaded.to_dict():
            raise ConfigError(f"{str(sweep_dir)!r} holds a different sweep than the one given")
        spec = loaded
        if not ckpt_dir.is_dir():
            raise CheckpointError(f"cannot resume: checkpoint directory {str(ckpt_dir)!r} does not exist")
    elif (sweep_dir / SWEEP_FILE).exists():
        raise ConfigError(f"sweep directory {str(sweep_dir)!r} already holds a sweep; use --resume or another --out")

    runs = spec.runs()
    configs = [r.config for r in runs]
    config0 = configs[0]
    G = len(runs)
    if devices is None:
        devices = jax.devices()
        if num_devices is not None:
            if not 1 <= num_devices <= len(devices):
                raise ConfigError(f"--devices {num_devices}: allowed 1..{len(devices)} (devices: {len(devices)})")
            devices = devices[:num_devices]
    D = len(devices)
    g_pad = -(-G // D) * D

    _barrier("tgrf_sweep_checked")  # every process has checked the directory before process 0 writes to it
    if not resume and main:
        sweep_dir.mkdir(parents=True, exist_ok=True)
        (sweep_dir / CONFIG_FILE).write_text(spec.base_config.to_yaml())
        (sweep_dir / SWEEP_FILE).write_text(yaml.safe_dump(spec.to_dict(), sort_keys=False))
        for r in runs:
            (sweep_dir / RUNS_DIR / r.name).mkdir(parents=True, exist_ok=True)
            (sweep_dir / RUNS_DIR / r.name / CONFIG_FILE).write_text(r.config.to_yaml())
    _barrier("tgrf_sweep_written")
    logfile = open(sweep_dir / "progress.log", "a") if main else None

    def say(msg: str):
        if main:
            log(msg)
            logfile.write(msg + "\n")
            logfile.flush()

    # Per-run traced hyper-parameters and keys, exactly as tgrf-train derives them from each run's config.
    hps = [hparams_from_config(c) for c in configs]
    shapes = [jax.tree_util.tree_map(lambda x: (np.shape(x), np.asarray(x).dtype), h) for h in hps]
    struct0 = jax.tree_util.tree_structure(hps[0])
    for r, h, s in zip(runs, hps, shapes):
        if jax.tree_util.tree_structure(h) != struct0 or s != shapes[0]:
            raise ConfigError(f"run {r.name}: its hyper-parameters have another structure than run {runs[0].name}'s; "
                              "it cannot share the compiled program")
    hparams = _stack(hps)
    keys = _stack([jax.random.PRNGKey(c.run.seed) for c in configs])

    program = get_program(config0, devices)
    trainer = program.trainer
    p, rcfg = config0.ppo, config0.run
    total, batch = trainer.num_updates, p.batch_size
    ckpt = Checkpointer(ckpt_dir, keep=rcfg.keep_checkpoints, create=not resume)

    start_time = time.perf_counter()
    metric_fields = ["run", "point", "seed"] + [a.name for a in spec.axes] + list(CSV_FIELDS)
    if resume:
        step = ckpt.latest_step()
        if step is None:
            raise CheckpointError(f"cannot resume: no checkpoint in {str(ckpt.directory)!r}")
        template = jax.eval_shape(jax.vmap(trainer.init), keys, hparams)
        host_state = _host(ckpt.restore(template, step))
        start = int(host_state.update[0])
        if start != step or not np.all(host_state.update == start):
            raise CheckpointError(f"checkpoint {str(ckpt.directory / str(step))!r} holds updates "
                                  f"{sorted(set(host_state.update.tolist()))}, not {step}")
        wall_offset = 0.0
        if main:
            wall_offset = _csv_rewrite_upto(sweep_dir / METRICS_FILE, start, metric_fields)
            for r in runs:
                _csv_rewrite_upto(sweep_dir / RUNS_DIR / r.name / METRICS_FILE, start, CSV_FIELDS)
        state = _place(_pad(host_state, g_pad), program.sharding)
        say(f"resumed {sweep_dir} at update {start}/{total} ({start * batch:,} env steps per run)")
    else:
        c0 = time.perf_counter()
        host_state = _stack([_host(program.init_one(keys[i], _take(hparams, i))) for i in range(G)])
        state = _place(_pad(host_state, g_pad), program.sharding)
        say(f"initialised {G} runs in {time.perf_counter() - c0:.1f} s (compilation included)")
        start, wall_offset = 0, 0.0
        ckpt.save(0, host_state)

    n_params = trainer.net.num_params(_take(_host(state.params), 0))
    pad_note = f", padded to {g_pad}" if g_pad != G else ""
    say(f"sweep of {G} runs ({len(spec.points())} grid points x {len(spec.seeds)} seeds{pad_note}) on {D} "
        f"{jax.devices()[0].platform} device(s), {g_pad // D} run(s) per device | {trainer.env} | "
        f"{config0.network.name}/{config0.network.size} ({n_params:,} params) | {p.num_envs} envs x {p.num_steps} "
        f"steps, {total} updates = {total * batch:,} env steps per run")
    for a in spec.axes:
        say(f"  grid {a.name}: {', '.join(_fmt_value(v) for v in a.values)}")
    say(f"  seeds: {', '.join(map(str, spec.seeds))}")
    say("  progress: steps per run; steps/s, returns and outcome rates over all runs together")

    csv_files, writers = {}, {}
    if main:
        def open_csv(path, fields):
            new = not path.is_file()
            f = open(path, "a", newline="")
            w = csv.DictWriter(f, fieldnames=fields)
            if new:
                w.writeheader()
            return f, w

        csv_files["all"], writers["all"] = open_csv(sweep_dir / METRICS_FILE, metric_fields)
        for r in runs:
            csv_files[r.name], writers[r.name] = open_csv(sweep_dir / RUNS_DIR / r.name / METRICS_FILE, CSV_FIELDS)

    end = total if stop_after_updates is None else min(total, stop_after_updates)
    plan = chunk_plan(start, end, rcfg.log_every, rcfg.checkpoint_every)
    train_seconds, updates_timed, update = 0.0, 0, start
    for n in plan:
        fn, compile_s = program.compiled_chunk(state, n)
        if compile_s is not None:
            say(f"compiled a {n}-update chunk for {g_pad} runs in {compile_s:.1f} s")
        c0 = time.perf_counter()
        state, metrics = fn(state)
        metrics = _host(metrics)  # blocks: the chunk is done
        dt = time.perf_counter() - c0
        train_seconds += dt
        updates_timed += n
        update += n
        wall = wall_offset + time.perf_counter() - start_time
        per_run = [{k: v[i] for k, v in metrics.items()} for i in range(G)]
        if main:
            for r, m in zip(runs, per_run):
                row = chunk_row(m, update, update * batch, wall, n * batch / dt)
                writers[r.name].writerow(row)
                writers["all"].writerow(dict(row, run=r.name, point=r.point, seed=r.seed,
                                             **{k: v for k, v in r.values.items()}))
            for f in csv_files.values():
                f.flush()
        agg = chunk_row(_aggregate(per_run), update, update * batch, wall, G * n * batch / dt)
        line = progress_line(agg, total * batch, (total - update) * train_seconds / updates_timed)
        say(f"[{G} runs] " + line.replace(" steps, update ", " steps per run, update ", 1))
        if update % rcfg.checkpoint_every == 0 or update == total:
            ckpt.save(update, _take(_host(state), slice(0, G)))
    for f in csv_files.values():
        f.close()

    host_state = _take(_host(state), slice(0, G))
    result = SweepResult(sweep_dir, spec, host_state, update, train_seconds, D, None)
    if update == total:
        if export_checkpoints:
            for i, r in enumerate(runs):
                run_ckpt = Checkpointer(sweep_dir / RUNS_DIR / r.name / CHECKPOINT_DIR, keep=rcfg.keep_checkpoints)
                run_ckpt.save(update, _take(host_state, i))
                run_ckpt.close()
        if rcfg.eval_episodes > 0:
            say(f"evaluating the {G} final policies on {rcfg.eval_episodes} episodes each ...")
            c0 = time.perf_counter()
            result.evals = evaluate_runs(program, runs, state.params, g_pad, rcfg.eval_episodes, rcfg.eval_seed)
            say(f"  done in {time.perf_counter() - c0:.1f} s (compilation included)")
            if main:
                for r, payload in zip(runs, result.evals):
                    payload.update(run_dir=str(sweep_dir / RUNS_DIR / r.name), updates=update,
                                   env_steps=update * batch)
                    (sweep_dir / RUNS_DIR / r.name / "eval.json").write_text(json.dumps(payload, indent=2))
        if main:
            rows = write_results(sweep_dir, spec, result.evals)
            say(format_summary_markdown(spec, rows))
            try:
                plot_sweep(sweep_dir, spec, rows)
            except Exception as e:  # a plotting failure must not lose a finished sweep
                say(f"warning: could not plot: {type(e).__name__}: {e}")
        trained = update - start
        say(f"done: {G} runs x {update} updates = {G * update * batch:,} env steps; this session trained {trained} "
            f"updates in {train_seconds:.1f} s ({G * trained * batch / max(train_seconds, 1e-9):,.0f} steps/s over "
            f"all runs, compilation excluded); sweep dir {sweep_dir}")
    ckpt.close()
    if logfile:
        logfile.close()
    return result


def evaluate_runs(program: SweepProgram, runs, params, g_pad: int, episodes: int, seed: int) -> list[dict]:
    """The final evaluation of every run in one batched program: per run the same episodes (keys) and env
    parameters as `tgrf_jax.train.loop.evaluate_state` / `tgrf_jax.evaluate.evaluate` use for that run alone."""
    import jax

    from tgrf_jax.env import CrowdNavEnv
    from tgrf_jax.evaluate import summarize

    envs = [CrowdNavEnv(dataclasses.replace(r.config.env, track_future_intrusion=True), r.config.reward)
            for r in runs]
    env_params = _place(_pad(_stack([e.default_params for e in envs]), g_pad), program.sharding)
    key = jax.random.fold_in(jax.random.key(seed), 0)  # `evaluate` with one batch of all episodes
    stats = _host(program.eval_stats(params, env_params, key, episodes))
    out = []
    for i, r in enumerate(runs):
        res = summarize(_take(stats, i))
        out.append({"env": repr(CrowdNavEnv(r.config.env, r.config.reward)), "episodes": episodes, "seed": seed,
                    "results": {"learned": res.to_dict()}})
    return out


# ------------------------------------------------------------------------------------- tables and plots


def _read_csv(path) -> list[dict]:
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def _float(x) -> float:
    try:
        return float(x)
    except (TypeError, ValueError):
        return float("nan")


def training_tail(rows: list[dict], total_updates: int) -> dict:
    """Episode-weighted training return and success rate over the chunks of the last 10% of updates."""
    last = max(int(float(r["update"])) for r in rows) if rows else 0
    cut = last - max(1, int(math.ceil(TRAIN_TAIL * total_updates)))
    tail = [r for r in rows if int(float(r["update"])) > cut] or rows[-1:]
    eps = np.array([_float(r["episodes"]) for r in tail])
    if eps.sum() == 0:
        return {"train_return": float("nan"), "train_success_rate": float("nan")}
    ret = np.array([_float(r["episode_return"]) for r in tail])
    sr = np.array([_float(r["success_rate"]) for r in tail])
    w = eps / eps.sum()
    return {"train_return": float(np.nansum(w * np.where(eps > 0, ret, 0.0))),
            "train_success_rate": float(np.nansum(w * np.where(eps > 0, sr, 0.0)))}


def write_results(sweep_dir, spec: SweepSpec, evals: list | None) -> list[dict]:
    """evals.csv (one row per run) and summary.csv / summary.md (mean and std over seeds per grid point).
    Returns the summary rows."""
    sweep_dir = pathlib.Path(sweep_dir)
    runs = spec.runs()
    total = spec.base_config.ppo.num_updates
    per_run = []
    for i, r in enumerate(runs):
        row = {"run": r.name, "point": r.point, "seed": r.seed, **r.values}
        row.update(training_tail(_read_csv(sweep_dir / RUNS_DIR / r.name / METRICS_FILE), total))
        if evals is not None:
            res = evals[i]["results"]["learned"]
            row.update({k: (float("nan") if res.get(k) is None else res[k]) for k in EVAL_METRICS})
            row["eval_episodes"] = res["n_episodes"]
        per_run.append(row)
    metric_names = (list(EVAL_METRICS) if evals is not None else []) + list(TRAIN_METRICS)
    run_fields = ["run", "point", "seed"] + [a.name for a in spec.axes] + metric_names + (
        ["eval_episodes"] if evals is not None else [])
    with open(sweep_dir / EVALS_FILE, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=run_fields)
        w.writeheader()
        w.writerows(per_run)

    summary = []
    for p, values in enumerate(spec.points()):
        members = [row for row in per_run if row["point"] == p]
        srow = {"point": p, **values, "seeds": len(members)}
        for m in metric_names:
            x = np.array([_float(row[m]) for row in members], float)
            x = x[np.isfinite(x)]
            srow[f"{m}_mean"] = float(np.mean(x)) if x.size else float("nan")
            srow[f"{m}_std"] = float(np.std(x, ddof=1)) if x.size > 1 else float("nan")
        summary.append(srow)
    fields = ["point"] + [a.name for a in spec.axes] + ["seeds"] + [f"{m}_{s}" for m in metric_names
                                                                   for s in ("mean", "std")]
    with open(sweep_dir / SUMMARY_CSV, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=fields)
        w.writeheader()
        w.writerows(summary)
    (sweep_dir / SUMMARY_MD).write_text(format_summary_markdown(spec, summary) + "\n")
    return summary


_LABELS = {
    "success_rate": ("SR", "{:.1%}"), "collision_rate": ("collision", "{:.1%}"), "timeout_rate": ("timeout", "{:.1%}"),
    "nav_time": ("NT (s)", "{:.2f}"), "path_length": ("PL (m)", "{:.2f}"), "itr_future": ("ITR future (%)", "{:.2f}"),
    "itr_disc": ("ITR disc (%)", "{:.2f}"), "intrusion_dist_future": ("dist ITR future (m)", "{:.3f}"),
    "intrusion_dist_disc": ("dist ITR disc (m)", "{:.3f}"), "mean_return": ("return", "{:.2f}"),
    "train_return": ("train return", "{:.2f}"), "train_success_rate": ("train SR", "{:.1%}"),
}


def format_summary_markdown(spec: SweepSpec, summary: list[dict]) -> str:
    """Markdown table: one row per grid point, 'mean ± std' over seeds (sample std; '–' with one seed)."""
    if not summary:
        return ""
    metrics = [m for m in list(EVAL_METRICS) + list(TRAIN_METRICS) if f"{m}_mean" in summary[0]]
    axes = [a.name for a in spec.axes]
    header = "| " + " | ".join([a.split(".", 1)[1] for a in axes] + ["seeds"] + [_LABELS[m][0] for m in metrics]) + " |"
    lines = [header, "|" + "---|" * (len(axes) + 1 + len(metrics))]
    for row in summary:
        cells = [_fmt_value(row[a]) for a in axes] + [str(row["seeds"])]
        for m in metrics:
            fmt = _LABELS[m][1]
            mean, std = row[f"{m}_mean"], row[f"{m}_std"]
            if not math.isfinite(mean):
                cells.append("n/a")
            else:
                cells.append(fmt.format(mean) + (" ± " + fmt.format(std) if math.isfinite(std) else " ± –"))
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def _figure(figsize, ncols: int):
    """A figure on its own Agg canvas (no pyplot: no display needed, a Jupyter session's backend is left alone)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=figsize)
    FigureCanvasAgg(fig)
    return fig, fig.subplots(1, ncols, squeeze=False)[0]


def plot_sweep(sweep_dir, spec: SweepSpec, summary: list[dict]) -> list[pathlib.Path]:
    """learning_curves.png, plus heatmap.png (two multi-valued axes) or grid_metrics.png (one)."""
    sweep_dir = pathlib.Path(sweep_dir)
    out = [plot_learning_curves(sweep_dir, spec)]
    multi = [a for a in spec.axes if len(a.values) > 1]
    have_eval = bool(summary) and "success_rate_mean" in summary[0]
    metrics = ["success_rate", "itr_disc", "itr_future"] if have_eval else ["train_success_rate", "train_return"]
    if len(multi) == 2:
        out.append(plot_heatmap(sweep_dir / HEATMAP_FILE, spec, summary, multi[0], multi[1], metrics))
    elif len(multi) == 1:
        out.append(plot_grid_metrics(sweep_dir / GRID_PLOT_FILE, spec, summary, multi[0], metrics))
    return out


def _title(m: str) -> str:
    return {"success_rate": "success rate (eval)", "itr_disc": "ITR disc (%) (eval)",
            "itr_future": "ITR future (%) (eval)", "train_success_rate": "success rate (training, end)",
            "train_return": "return (training, end)"}.get(m, m)


def plot_heatmap(path, spec: SweepSpec, summary, ax_y: GridAxis, ax_x: GridAxis, metrics) -> pathlib.Path:
    """Mean over seeds of each metric over two gridded parameters (other axes: their single value)."""
    fig, axs = _figure((4.8 * len(metrics), 4.2), len(metrics))
    for ax, m in zip(axs, metrics):
        mean = np.full((len(ax_y.values), len(ax_x.values)), np.nan)
        std = np.full_like(mean, np.nan)
        for row in summary:
            i, j = ax_y.values.index(row[ax_y.name]), ax_x.values.index(row[ax_x.name])
            mean[i, j], std[i, j] = row[f"{m}_mean"], row[f"{m}_std"]
        im = ax.imshow(mean, origin="lower", cmap="viridis" if "success" in m else "magma_r", aspect="auto")
        fig.colorbar(im, ax=ax, shrink=0.85)
        pct = "success" in m
        for i in range(mean.shape[0]):
            for j in range(mean.shape[1]):
                if np.isfinite(mean[i, j]):
                    s = f"{mean[i, j]:.0%}" if pct else f"{mean[i, j]:.2f}"
                    if np.isfinite(std[i, j]):
                        s += "\n±" + (f"{std[i, j]:.0%}" if pct else f"{std[i, j]:.2f}")
                    r, g, b, _ = im.cmap(im.norm(mean[i, j]))
                    ax.text(j, i, s, ha="center", va="center", fontsize=8,
                            color="k" if 0.299 * r + 0.587 * g + 0.114 * b > 0.5 else "w")
        ax.set_xticks(range(len(ax_x.values)), [_fmt_value(v) for v in ax_x.values])
        ax.set_yticks(range(len(ax_y.values)), [_fmt_value(v) for v in ax_y.values])
        ax.set(xlabel=ax_x.name, ylabel=ax_y.name, title=_title(m))
    fig.suptitle(f"mean over {len(spec.seeds)} seed(s)")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    return pathlib.Path(path)


def plot_grid_metrics(path, spec: SweepSpec, summary, axis: GridAxis, metrics) -> pathlib.Path:
    fig, axs = _figure((4.5 * len(metrics), 3.8), len(metrics))
    xs = np.arange(len(axis.values))
    for ax, m in zip(axs, metrics):
        mean = [next(r[f"{m}_mean"] for r in summary if r[axis.name] == v) for v in axis.values]
        std = [next(r[f"{m}_std"] for r in summary if r[axis.name] == v) for v in axis.values]
        ax.errorbar(xs, mean, yerr=np.nan_to_num(std), marker="o", capsize=3)
        ax.set_xticks(xs, [_fmt_value(v) for v in axis.values])
        ax.set(xlabel=axis.name, title=_title(m))
        ax.grid(alpha=0.3)
    fig.suptitle(f"mean ± std over {len(spec.seeds)} seed(s)")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    return pathlib.Path(path)


def plot_learning_curves(sweep_dir, spec: SweepSpec) -> pathlib.Path:
    """Training return and success rate per grid point: mean over seeds, band = ± std over seeds."""
    import matplotlib

    sweep_dir = pathlib.Path(sweep_dir)
    rows = _read_csv(sweep_dir / METRICS_FILE)
    fig, (ax_ret, ax_sr) = _figure((13, 4.5), 2)
    points = spec.points()
    cmap = matplotlib.colormaps["viridis" if len(points) > 10 else "tab10"]
    for p, values in enumerate(points):
        color = cmap(p / max(len(points) - 1, 1)) if len(points) > 10 else cmap(p % 10)
        by_seed = {}
        for r in rows:
            if int(r["point"]) == p:
                by_seed.setdefault(int(r["seed"]), {})[int(float(r["update"]))] = r
        if not by_seed:
            continue
        updates = sorted(set.intersection(*[set(d) for d in by_seed.values()]))
        if not updates:
            continue
        steps = [_float(next(iter(by_seed.values()))[u]["env_steps"]) for u in updates]
        for ax, key in ((ax_ret, "episode_return"), (ax_sr, "success_rate")):
            y = np.array([[_float(d[u][key]) for u in updates] for d in by_seed.values()])
            with np.errstate(all="ignore"), warnings.catch_warnings():
                warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN columns (chunks without episodes)
                mean = np.nanmean(y, axis=0)
                std = np.nanstd(y, axis=0, ddof=1) if y.shape[0] > 1 else np.zeros_like(mean)
            ax.plot(steps, mean, color=color, label=spec.point_label(values))
            if y.shape[0] > 1:
                ax.fill_between(steps, mean - std, mean + std, color=color, alpha=0.2, linewidth=0)
    ax_ret.set(xlabel="env steps per run", ylabel="mean episode return", title="return (training episodes)")
    ax_sr.set(xlabel="env steps per run", ylabel="success rate", ylim=(-0.02, 1.02),
              title="success rate (training episodes)")
    for ax in (ax_ret, ax_sr):
        ax.grid(alpha=0.3)
    ax_sr.legend(loc="center left", bbox_to_anchor=(1.02, 0.5), fontsize=7 if len(points) > 10 else 8,
                 ncol=1 if len(points) <= 20 else 2)
    fig.suptitle(f"{len(points)} grid point(s): mean over {len(spec.seeds)} seed(s), band ± std")
    fig.tight_layout()
    path = sweep_dir / CURVES_FILE
    fig.savefig(path, dpi=100)
    return path


# ------------------------------------------------------------------------------------------------------ CLI


def default_sweep_dir(config: TrainConfig, root="runs") -> pathlib.Path:
    stamp = datetime.datetime.now().strftime("%Y%m%d-%H%M%S")
    return pathlib.Path(root) / f"{stamp}_sweep_{config.run.name}"


def init_distributed(coordinator: str | None = None, num_processes: int | None = None,
                     process_id: int | None = None) -> None:
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
        jax.distributed.initialize(coordinator_address=coordinator, num_processes=num_processes,
                                   process_id=process_id)
    else:
        jax.distributed.initialize()


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="tgrf-sweep",
        description="Train a grid of hyper-parameters x seeds as one vmapped, compiled program, with the runs split "
        "over all devices. Only traced (numeric, shape-preserving) fields can be gridded; see --list-griddable.",
    )
    parser.add_argument("config", nargs="?", help="YAML config as for tgrf-train (default: the embedded default)")
    parser.add_argument("--grid", action="append", default=[], metavar="KEY=V1,V2,...",
                        help="a grid axis, e.g. --grid reward.h_disc=0.5,1.0,2.5 (repeatable: Cartesian product)")
    parser.add_argument("--seeds", default=None, metavar="N|S1,S2,...",
                        help="a count (run.seed, run.seed+1, ...) or a comma-separated list of seeds (default: 1)")
    parser.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                        help="override a base config value (as tgrf-train --set)")
    parser.add_argument("--out", help="sweep directory (default: runs/<timestamp>_sweep_<run.name>)")
    parser.add_argument("--resume", metavar="SWEEP_DIR",
                        help="continue the sweep in SWEEP_DIR from its last checkpoint")
    parser.add_argument("--devices", type=int, default=None, metavar="N",
                        help="use the first N devices (default: all of them, across all hosts)")
    parser.add_argument("--no-run-checkpoints", action="store_true",
                        help="do not write each run's final checkpoint under runs/<name>/checkpoints")
    dist = parser.add_argument_group("multi-host (one process per host, all with the same arguments; the sweep "
                                     "directory must be on a filesystem all hosts share)")
    dist.add_argument("--distributed", action="store_true",
                      help="call jax.distributed.initialize() with its auto-detection (SLURM, Cloud TPU, ...)")
    dist.add_argument("--coordinator", metavar="HOST:PORT", help="jax.distributed coordinator (process 0's address)")
    dist.add_argument("--num-processes", type=int, help="with --coordinator: number of processes")
    dist.add_argument("--process-id", type=int, help="with --coordinator: this process's index (0 .. N-1)")
    parser.add_argument("--print-plan", action="store_true", help="print the runs and exit (nothing is compiled)")
    parser.add_argument("--list-griddable", action="store_true", help="print the griddable fields and exit")
    args = parser.parse_args(argv)

    if args.list_griddable:
        print("\n".join(griddable_fields()))
        return 0
    from tgrf_jax.train.checkpoint import CheckpointError

    try:
        if args.resume:
            if args.config or args.grid or args.overrides or args.seeds or args.out:
                raise ConfigError("--resume SWEEP_DIR takes no config file, --grid, --seeds, --set or --out (the "
                                  "sweep's own sweep.yaml is used)")
            spec = load_sweep(args.resume)
        else:
            spec = SweepSpec.create(args.config, args.grid, args.seeds, args.overrides)
    except ConfigError as e:
        print(f"tgrf-sweep: error: {e}", file=sys.stderr)
        return 2
    if args.print_plan:
        print(spec.describe())
        return 0

    # One CPU device per core before JAX starts: the runs split over the devices, and XLA:CPU runs several
    # programs side by side far better than it spreads one over the cores (a user's own count wins).
    from tgrf_jax.train import shards

    shards.request_cpu_devices(len(os.sched_getaffinity(0)))
    if args.coordinator or args.distributed:
        try:
            init_distributed(args.coordinator, args.num_processes, args.process_id)
        except ConfigError as e:
            print(f"tgrf-sweep: error: {e}", file=sys.stderr)
            return 2
    if args.out is None and not args.resume and (args.coordinator or args.distributed):
        print("tgrf-sweep: error: a multi-host sweep needs --out (the same shared directory on every host)",
              file=sys.stderr)
        return 2
    from tgrf_jax import compile_cache

    compile_cache.enable()
    sweep_dir = pathlib.Path(args.resume or args.out or default_sweep_dir(spec.base_config))
    try:
        run_sweep(None if args.resume else spec, sweep_dir, resume=bool(args.resume),
                  log=lambda m: print(m, flush=True), num_devices=args.devices,
                  export_checkpoints=not args.no_run_checkpoints)
    except (CheckpointError, ConfigError) as e:
        print(f"tgrf-sweep: error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"tgrf-sweep: interrupted; resume with: tgrf-sweep --resume {sweep_dir}", file=sys.stderr)
        return 130
    return 0


if __name__ == "__main__":
    sys.exit(main())
