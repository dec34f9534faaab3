"""`run_tune`: a population trained as a sweep's program (batched, or the members in turn), with an
exploit-and-explore step every `interval` updates, in a `RunDirectory` whose root is the tune directory.

Tune directory:
    tune.yaml              the tune: space, population, objective, schedule, each member's seed and start values
    config.yaml            the resolved base config
    progress.log, metrics.csv, checkpoints/, eval_curves.csv   as a sweep's (`tgrf_jax.sweep.run`)
    runs/m000/ ...         one playable run directory per member (config.yaml with the member's final values,
                           metrics.csv, eval.json, final checkpoint): `tgrf-eval runs/m003` works
    lineage.csv            every exploit step: update, member, its score, the member it copied (itself if kept),
                           its searched values after the step
    lineage.png            which member copied which, when
    schedule.csv / .png    the searched values along the best member's ancestry: the schedule the tune found
    tune.md                the population table, the best member and its objective on a separate, larger test

The exploit step runs inside the program's chunk (`TunedProgram.run_chunk`), so every checkpoint holds the state
after it, and its random draws come from the run's seed and the update: a resumed tune repeats it bit for bit.
"""

from __future__ import annotations

import csv
import dataclasses
import functools
import io
import pathlib
from collections.abc import Callable
from typing import Any

import numpy as np
import yaml

from tgrf_jax.config import ConfigError
from tgrf_jax.storage.files import write_atomic
from tgrf_jax.storage.lock import exclusive
from tgrf_jax.sweep.program import BatchedProgram, SequentialProgram, evaluate_runs
from tgrf_jax.sweep.report import RUNS_DIR
from tgrf_jax.sweep.run import export_checkpoint
from tgrf_jax.train.directory import CHECKPOINT_DIR, RunDirectory
from tgrf_jax.train.outer_loop import train_program
from tgrf_jax.tune.objective import parse_objective
from tgrf_jax.tune.pbt import exploit_explore
from tgrf_jax.tune.spec import TUNE_FILE, TuneSpec, load_tune

CONFIG_FILE = "config.yaml"
LINEAGE_FILE = "lineage.csv"
SCHEDULE_FILE = "schedule.csv"
REPORT_FILE = "tune.md"
# the objective's test episodes come from a seed of their own, apart from the final test's (run.eval_seed)
OBJECTIVE_SEED_OFFSET = 7_919


@dataclasses.dataclass
class TuneResult:
    tune_dir: pathlib.Path
    spec: TuneSpec
    updates: int
    best: int | None  # index of the best member (None until the tune is trained to its end)
    best_objective: float | None  # on the final test


class TunedProgram:
    """The outer loop's `Program` of a tune: the population trained in the spec's layout, each chunk ending, at
    every multiple of `interval` updates, with the exploit-and-explore step over the population
    (`tgrf_jax.tune.pbt`).

    Batched: the sweep's `BatchedProgram`, one vmapped program with the members split over the devices; the step
    runs where the members live, their parameters never passing through the host (the layout for accelerators).
    Sequential: the sweep's `SequentialProgram`, the members in turn through tgrf-train's own program, faster on
    CPUs, where host and device memory are one; the step runs on the members stacked in host memory."""

    def __init__(self, spec: TuneSpec, devices, say: Callable[[str], None]):
        members = spec.members()
        if spec.layout == "sequential":
            self.base = SequentialProgram(members, devices)
        else:
            self.base = BatchedProgram(members, devices)
            if self.base.g_pad != self.base.num_runs:
                raise ConfigError(
                    f"--population {spec.population} must be a multiple of the {self.base.num_devices} devices the "
                    f"population is split over (or choose the devices with --devices)"
                )
        self.spec, self.say = spec, say
        self.num_runs, self.num_updates = self.base.num_runs, self.base.num_updates
        self.batch_size, self.config = self.base.batch_size, self.base.config
        self.objective = parse_objective(spec.objective)
        self.eval_runs = spec.evaluation_runs()
        self.update = 0
        self.steps: list[dict] = []  # exploit steps of this process since init/restore (for the lineage file)
        self._step = None  # compiled on first use, for the state's placement
        self._key_seed = spec.base["run"]["seed"]

    @property
    def trainer(self):
        return self.base.trainer if self.spec.layout == "sequential" else self.base.batched.trainer

    def init(self):
        self.update = 0
        return self.base.init()

    def restore(self, checkpointer, step: int):
        state, update = self.base.restore(checkpointer, step)
        self.update = update
        return state, update

    def is_compiled(self, state) -> bool:
        return self.base.is_compiled(state)

    def compile(self, state) -> None:
        self.base.compile(state)

    def run_metrics(self, metrics) -> list[dict]:
        return self.base.run_metrics(metrics)

    def host_state(self, state):
        return self.base.host_state(state)

    def evaluate(self, state, episodes: int, seed: int) -> list[dict]:
        return self.base.evaluate(state, episodes, seed)

    def describe(self, state) -> str:
        return self.base.describe(state)

    def member_results(self, state, episodes: int, seed: int, members=None) -> list[dict]:
        """Each member's (or each of `members`') deterministic policy on the same test episodes of the base
        config's env: the evaluation metrics the objective reads."""
        members = range(self.num_runs) if members is None else members
        if self.spec.layout == "sequential":
            from tgrf_jax.evaluate import evaluate_state

            net = self.base.trainer.net  # one compiled evaluation for every member
            return [
                evaluate_state(self.eval_runs[i].config, state[i], episodes, seed, net=net)["results"]["learned"]
                for i in members
            ]
        evals = evaluate_runs(self.base.batched, self.eval_runs, state.params, self.base.g_pad, episodes, seed)
        return [evals[i]["results"]["learned"] for i in members]

    def scores(self, state) -> list[float]:
        seed = self.spec.base["run"]["eval_seed"] + OBJECTIVE_SEED_OFFSET
        return [self.objective.score(r) for r in self.member_results(state, self.spec.objective_episodes, seed)]

    def train_chunk(self, state, n_updates: int):
        """`n_updates` of every member, without the exploit step."""
        return self.base.run_chunk(state, n_updates)

    def run_chunk(self, state, n_updates: int):
        import jax
        import jax.numpy as jnp

        state, metrics = self.train_chunk(state, n_updates)
        self.update += n_updates
        if self.update % self.spec.interval == 0 and self.update < self.num_updates:
            scores = self.scores(state)
            key = jax.random.fold_in(jax.random.PRNGKey(self._key_seed), self.update)
            state, record = self.exploit(state, jnp.asarray(scores, jnp.float32), key)
            donors, values = np.asarray(record.donor), np.asarray(record.values)
            self.steps.append({"update": self.update, "scores": scores, "donor": donors, "values": values})
            best = int(np.argmax(scores))
            copied = [f"{i}<-{d}" for i, d in enumerate(donors) if d != i]
            self.say(
                f"exploit at update {self.update}: best objective {scores[best]:.4f} (m{best:03d}); "
                f"copied {', '.join(copied)}"
            )
        return state, metrics

    def exploit(self, state, scores, key):
        """The exploit-and-explore step on the population's state; returns the new state and its record."""
        import jax

        if self.spec.layout == "sequential":
            if self._step is None:
                self._step = _exploit_program(self.spec)
            stacked, record = self._step(self.base.host_state(state), scores, key)
            stacked = jax.device_get(stacked)
            place = self.base.trainer.place
            return [place(jax.tree.map(lambda x, i=i: x[i], stacked)) for i in range(self.num_runs)], record
        if self._step is None:
            self._step = _exploit_program(self.spec, jax.tree.map(lambda x: x.sharding, state))
        return self._step(state, scores, key)


def _exploit_program(spec: TuneSpec, shardings=None):
    """The exploit-and-explore step compiled for a population-batched state placed as `shardings` (each member
    stays on its device; the copies between devices are the step's only transfers; None: where jit puts it).
    A placed state is donated: the population's parameters are updated where they live."""
    import jax

    step = functools.partial(exploit_explore, dims=spec.dims, fraction=spec.fraction, resample_prob=spec.resample_prob)
    if shardings is None:
        return jax.jit(step)
    return jax.jit(step, donate_argnums=0, out_shardings=(shardings, None))


class LineageWriter:
    """A `state_fn` of the run directory: appends each exploit step of the program to lineage.csv, and on resume
    cuts the file back to the checkpoint's update (`truncate`)."""

    def __init__(self, path: pathlib.Path, program: TunedProgram, write: bool):
        self.path, self.program, self.write = path, program, write
        self.fields = ["update", "member", "score", "donor"] + [d.name for d in program.spec.dims]

    def truncate(self, update: int) -> float:
        if self.write and self.path.is_file():
            rows = [r for r in _read_csv(self.path) if int(r["update"]) <= update]
            write_atomic(self.path, _csv_text(self.fields, rows))
        return 0.0

    def __call__(self, update: int, state: Any) -> None:
        steps = [s for s in self.program.steps if s["update"] == update]
        if not steps or not self.write:
            return
        step = steps[-1]
        rows = _read_csv(self.path) if self.path.is_file() else []
        for i in range(self.program.num_runs):
            row = {"update": update, "member": i, "score": step["scores"][i], "donor": int(step["donor"][i])}
            row.update({d.name: float(step["values"][i, j]) for j, d in enumerate(self.program.spec.dims)})
            rows.append(row)
        write_atomic(self.path, _csv_text(self.fields, rows))


def _read_csv(path: pathlib.Path) -> list[dict]:
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def _csv_text(fields: list[str], rows: list[dict]) -> str:
    out = io.StringIO()
    writer = csv.DictWriter(out, fieldnames=fields)
    writer.writeheader()
    writer.writerows(rows)
    return out.getvalue()


def ancestry_schedule(spec: TuneSpec, lineage: list[dict], member: int) -> list[dict]:
    """The searched values along `member`'s ancestry, from its root ancestor's start values to the last step:
    rows of {update, member (the ancestor holding the values then), field: value}."""
    updates = sorted({int(r["update"]) for r in lineage})
    by_step = {u: {int(r["member"]): r for r in lineage if int(r["update"]) == u} for u in updates}
    rows, current = [], member
    for u in reversed(updates):
        row = by_step[u][current]
        rows.append({"update": u, "member": current, **{d.name: float(row[d.name]) for d in spec.dims}})
        current = int(row["donor"])
    start = spec.members()[current]
    rows.append({"update": 0, "member": current, **{d.name: start.values[d.name] for d in spec.dims}})
    return rows[::-1]


def run_tune(
    spec: TuneSpec | None,
    tune_dir,
    *,
    resume: bool = False,
    log: Callable[[str], None] = print,
    stop_after_updates: int | None = None,
    num_devices: int | None = None,
    layout: str | None = None,
) -> TuneResult:
    """Train the population of `spec` in `tune_dir` (or, with `spec=None, resume=True`, continue the tune there
    from its latest checkpoint); at the end, score the best member on the final test and write the report.
    `layout` (with `resume`): continue in this layout instead of the recorded one, which tune.yaml then records
    (both layouts checkpoint the same stacked state)."""
    tune_dir = pathlib.Path(tune_dir)
    if layout is not None and not resume:
        raise ConfigError("layout switches the layout of a resumed tune (a new one takes its spec's layout)")
    if resume:
        loaded = load_tune(tune_dir)
        if spec is not None and spec.to_dict() != loaded.to_dict():
            raise ConfigError(f"{str(tune_dir)!r} holds a different tune than the one given")
        spec = loaded
        if layout is not None and layout != spec.layout:
            spec = dataclasses.replace(spec, layout=layout)
            spec.check(spec.base_config.ppo.num_updates)
    elif (tune_dir / TUNE_FILE).exists():
        raise ConfigError(f"tune directory {str(tune_dir)!r} already holds a tune; use --resume or another --out")
    with exclusive(tune_dir):
        if resume and layout is not None and layout != loaded.layout:
            write_atomic(tune_dir / TUNE_FILE, yaml.safe_dump(spec.to_dict(), sort_keys=False))
            log(f"tune continues in the {layout} layout (was {loaded.layout})")
        return _run_tune(spec, tune_dir, resume, log, stop_after_updates, num_devices)


def split_devices(available: int, population: int) -> int:
    """The most devices, at most `available`, that split the population evenly (the members are not padded: a
    padded copy would be scored and could be copied)."""
    return max(d for d in range(1, available + 1) if population % d == 0)


def _devices(num_devices, population: int):
    import jax

    devices = jax.devices()
    if num_devices is None:
        return devices[: split_devices(len(devices), population)]
    if not 1 <= num_devices <= len(devices):
        raise ConfigError(f"--devices {num_devices}: allowed 1..{len(devices)} (devices: {len(devices)})")
    return devices[:num_devices]


def _run_tune(spec: TuneSpec, tune_dir: pathlib.Path, resume, log, stop_after_updates, num_devices) -> TuneResult:
    import jax

    members = spec.members()
    run_dirs = [tune_dir / RUNS_DIR / m.name for m in members]
    if not resume:
        tune_dir.mkdir(parents=True, exist_ok=True)
        write_atomic(tune_dir / CONFIG_FILE, spec.base_config.to_yaml())
        write_atomic(tune_dir / TUNE_FILE, yaml.safe_dump(spec.to_dict(), sort_keys=False))
        for m, d in zip(members, run_dirs):
            d.mkdir(parents=True, exist_ok=True)
            write_atomic(d / CONFIG_FILE, m.config.to_yaml())
    run_cfg = members[0].config.run
    columns = [dict(run=m.name, point=m.point, seed=m.seed, **m.values) for m in members]
    say_box: list[Callable[[str], None]] = [log]
    program = TunedProgram(spec, _devices(num_devices, spec.population), lambda line: say_box[0](line))
    with RunDirectory.open(
        tune_dir, program, run_cfg, run_dirs=run_dirs, columns=columns, log=log, where="tune dir"
    ) as directory:
        say_box[0] = directory.say
        lineage = LineageWriter(tune_dir / LINEAGE_FILE, program, write=True)
        directory = dataclasses.replace(
            directory, state_fns=(*directory.state_fns, lineage), cut_every=(*directory.cut_every, spec.interval)
        )
        say = directory.say
        say(spec.describe())
        out = train_program(program, directory, run_cfg, resume=resume, stop_after_updates=stop_after_updates)
        result = TuneResult(tune_dir, spec, out.updates, None, None)
        if out.updates < program.num_updates:
            return result
        host_state = program.host_state(out.state)
        final = _final_values(spec, program, out.state)
        for i, (m, d) in enumerate(zip(members, run_dirs)):
            data = m.config.to_dict()
            for name, value in final[i].items():
                section, field = name.split(".", 1)
                data[section][field] = value
            write_atomic(d / CONFIG_FILE, yaml.safe_dump(data, sort_keys=False))
            export_checkpoint(
                d / CHECKPOINT_DIR,
                out.updates,
                jax.tree_util.tree_map(lambda x, i=i: x[i], host_state),
                run_cfg.keep_checkpoints,
            )
        scores = program.scores(out.state)
        best = int(np.argmax(scores))
        (final_eval,) = program.member_results(out.state, spec.final_episodes, spec.base["run"]["eval_seed"], [best])
        result.best, result.best_objective = best, program.objective.score(final_eval)
        lineage_rows = _read_csv(tune_dir / LINEAGE_FILE) if (tune_dir / LINEAGE_FILE).is_file() else []
        schedule = ancestry_schedule(spec, lineage_rows, best)
        write_atomic(tune_dir / SCHEDULE_FILE, _csv_text(["update", "member", *[d.name for d in spec.dims]], schedule))
        report = format_report(spec, scores, final, best, result.best_objective, final_eval, out.evals, schedule)
        write_atomic(tune_dir / REPORT_FILE, report)
        from tgrf_jax.tune.plots import plot_lineage, plot_schedule

        directory.plot(lambda: plot_lineage(tune_dir / "lineage.png", spec, lineage_rows))
        directory.plot(lambda: plot_schedule(tune_dir / "schedule.png", spec, schedule))
        say(
            f"best member: {members[best].name} (objective {scores[best]:.4f} on {spec.objective_episodes} episodes, "
            f"{result.best_objective:.4f} on the final {spec.final_episodes}); {run_dirs[best]}"
        )
        directory.done(out, program)
    return result


def _final_values(spec: TuneSpec, program: TunedProgram, state) -> list[dict]:
    from tgrf_jax.tune.pbt import get_values

    values = np.asarray(get_values(program.host_state(state).hparams, spec.dims))
    return [{d.name: float(values[i, j]) for j, d in enumerate(spec.dims)} for i in range(program.num_runs)]


def format_report(spec, scores, final, best, best_objective, final_eval, evals, schedule) -> str:
    """tune.md: the population at the end, the best member, and its schedule."""
    names = [d.name for d in spec.dims]
    lines = [
        "# Tune",
        "",
        f"Objective `{spec.objective}`; population {spec.population}; exploit every {spec.interval} updates.",
        "",
        f"| member | objective ({spec.objective_episodes} episodes) | final test SR | "
        + " | ".join(f"`{n}`" for n in names)
        + " |",
        "|---" * (3 + len(names)) + "|",
    ]
    for i, score in enumerate(scores):
        sr = (evals[i]["results"]["learned"].get("success_rate") if evals else None) or float("nan")
        mark = " **best**" if i == best else ""
        values = " | ".join(f"{final[i][n]:.4g}" for n in names)
        lines.append(f"| m{i:03d}{mark} | {score:.4f} | {100 * sr:.1f}% | {values} |")
    lines += [
        "",
        f"Best member m{best:03d}: objective {best_objective:.4f} on a separate test of {spec.final_episodes} episodes "
        f"(success {100 * final_eval['success_rate']:.1f}%, collision {100 * final_eval['collision_rate']:.1f}%).",
        "",
        "Its schedule (the values along its ancestry, `schedule.csv`):",
        "",
        "| update | held by | " + " | ".join(f"`{n}`" for n in names) + " |",
        "|---" * (2 + len(names)) + "|",
    ]
    for row in schedule:
        lines.append(f"| {row['update']} | m{row['member']:03d} | " + " | ".join(f"{row[n]:.4g}" for n in names) + " |")
    return "\n".join(lines) + "\n"
