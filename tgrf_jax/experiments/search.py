"""A search experiment's report: ways of searching one space (a grid, PBT, random search) at equal env steps.

Each repeat of a procedure (one seed of the grid, one tune row, one random row) comes down to

* its members' final policies, scored by the experiment's objective on the test episodes (run.eval_episodes from
  run.eval_seed: the final evaluation every run has), and
* where it tested its members during training (tune and random rows do, on those same episodes), the best member's
  objective at each test, against the env steps the whole procedure had spent by then: its members train side by
  side, so that is the members times the steps each had trained.

The grid's best (the highest objective of any of its runs) is the target: a repeat reaches it at its first test
where some member scores at least as much. The grid itself knows its runs' results only at their end.

Every procedure's best is its best member on the test, the one measure the grid and random search have. PBT also
picks a member without the test (the best on its own selection episodes): that pick is what a user of tgrf-tune
gets, so it is reported beside the best, and its schedule is the one shown.
"""

from __future__ import annotations

import csv
import dataclasses
import io
import json
import math
import pathlib
from collections.abc import Callable, Mapping, Sequence

import numpy as np
import yaml

from tgrf_jax.config import ConfigError
from tgrf_jax.experiments import report
from tgrf_jax.experiments.spec import Experiment, Row, comparable, portable, row_config
from tgrf_jax.storage.files import write_atomic

REPORT_MD = "report.md"
REPORT_CSV = "report.csv"
PROGRESS_PNG = "best_objective.png"
SCHEDULE_PNG = "pbt_schedule.png"
TUNE_SCHEDULE = "schedule.csv"  # tgrf-tune's schedule of its pick: the last row's member is the pick
TUNE_DONE = "tune.md"  # what tgrf-tune writes once its population is trained and scored
PROCEDURES = ("grid", "tune", "random")  # row kinds, in the report's order
_NAMES = {"grid": "grid", "tune": "PBT", "random": "random search"}  # where the rows give no label
_CSV_NAMES = {"grid": "grid", "tune": "pbt", "random": "random"}
_COLOURS = {"grid": "C2", "tune": "C0", "random": "C1"}


@dataclasses.dataclass(frozen=True)
class Member:
    name: str
    objective: float  # on the test episodes; -inf where a metric it reads is undefined
    values: Mapping[str, float]  # the searched fields at the end of training
    success_rate: float
    collision_rate: float


@dataclasses.dataclass(frozen=True)
class Repeat:
    row: str
    name: str  # the row, or for a grid of several seeds '<row>_seed<s>'
    label: str
    procedure: str  # the row's kind: grid, tune or random
    steps_per_member: int
    members: tuple[Member, ...]
    curve: tuple[tuple[int, float], ...]  # (env steps of all members, best member's objective) at each test
    pick: str | None = None  # the member the procedure picked apart from the test (PBT's); None: it has no other

    @property
    def picked(self) -> Member | None:
        return next((m for m in self.members if m.name == self.pick), None)

    @property
    def env_steps(self) -> int:
        return self.steps_per_member * len(self.members)

    @property
    def best(self) -> Member:
        return max(self.members, key=lambda m: m.objective)  # the first of equals


# --------------------------------------------------------------------------------------------- the maths


def _float(x) -> float:
    try:
        return float(x)
    except (TypeError, ValueError):
        return math.nan


def score(objective, metrics: Mapping) -> float:
    """The objective of one evaluation (a CSV row's text or an eval.json's numbers)."""
    return objective.score({k: _float(v) for k, v in metrics.items()})


def best_curve(rows: Sequence[Mapping], objective, members: int) -> tuple[tuple[int, float], ...]:
    """From a long eval-curve file (a row per member per test): at every test that all `members` took, the env
    steps of the whole procedure then and the best member's objective."""
    by_update: dict[int, list[Mapping]] = {}
    for r in rows:
        by_update.setdefault(int(_float(r["update"])), []).append(r)
    curve = []
    for update in sorted(by_update):
        group = by_update[update]
        if len(group) != members:  # a test cut short by an interruption: its rows are rewritten on resume
            continue
        steps = int(_float(group[0]["env_steps"])) * members
        curve.append((steps, max(score(objective, r) for r in group)))
    return tuple(curve)


def steps_to_reach(curve: Sequence[tuple[int, float]], target: float) -> int | None:
    """The env steps of the first test whose best member scores at least `target`; None if none does."""
    return next((steps for steps, value in curve if value >= target), None)


def grid_best(repeats: Sequence[Repeat]) -> tuple[float, Repeat] | None:
    """The highest objective of the grid's runs over all its repeats, and the repeat holding it."""
    grid = [r for r in repeats if r.procedure == "grid" and math.isfinite(r.best.objective)]
    if not grid:
        return None
    holder = max(grid, key=lambda r: r.best.objective)
    return holder.best.objective, holder


def mean_std(values: Sequence[float]) -> tuple[float, float]:
    """The mean and sample std of the finite values (nan where none are finite; the std needs two)."""
    finite = np.array([v for v in values if math.isfinite(v)], float)
    return (
        float(finite.mean()) if finite.size else math.nan,
        float(finite.std(ddof=1)) if finite.size > 1 else math.nan,
    )


def summary(repeats: Sequence[Repeat], target: float | None) -> dict:
    """One procedure's repeats: their best objectives' mean and sample std, and the env steps each took to reach
    the target (None: not reached)."""
    best = [r.best.objective for r in repeats]
    mean, std = mean_std(best)
    return {
        "repeats": len(repeats),
        "env_steps": sorted({r.env_steps for r in repeats}),
        "best_mean": mean,
        "best_std": std,
        "best": max((b for b in best if math.isfinite(b)), default=math.nan),
        "to_target": [None if target is None else steps_to_reach(r.curve, target) for r in repeats],
    }


# --------------------------------------------------------------------------------------------- reading rows


def _read_csv(path: pathlib.Path) -> list[dict]:
    if not path.is_file():
        return []
    with open(path, newline="", encoding="utf-8") as f:
        return list(csv.DictReader(f))


def _curve_or_end(row_dir: pathlib.Path, runs: set, objective, members: list[Member], steps: int):
    rows = [r for r in _read_csv(row_dir / "eval_curves.csv") if r.get("run") in runs]
    curve = best_curve(rows, objective, len(members))
    # without tests during training, the final evaluation is the only one
    return curve or ((steps * len(members), max(m.objective for m in members)),)


def sweep_repeats(row: Row, sweep_dir: pathlib.Path, objective, names: Sequence[str]) -> list[Repeat]:
    """A finished sweep's runs as repeats, one per seed (a seed's runs make one search of the space)."""
    from tgrf_jax.sweep.grid import load_sweep

    sweep = load_sweep(sweep_dir)
    base = sweep.base_config.ppo
    steps = base.num_updates * base.batch_size
    evals = report.read_evals(sweep_dir)
    seeds = sorted({int(r["seed"]) for r in evals})
    repeats = []
    for seed in seeds:
        runs = [r for r in evals if int(r["seed"]) == seed]
        members = [
            Member(
                name=r["run"],
                objective=score(objective, r),
                values={n: _float(r[n]) for n in names},
                success_rate=_float(r.get("success_rate")),
                collision_rate=_float(r.get("collision_rate")),
            )
            for r in runs
        ]
        name = row.name if len(seeds) == 1 else f"{row.name}_seed{seed}"
        label = row.label if len(seeds) == 1 else f"{row.label}, seed {seed}"
        curve = _curve_or_end(sweep_dir, {r["run"] for r in runs}, objective, members, steps)
        repeats.append(Repeat(row.name, name, label, row.kind, steps, tuple(members), curve))
    return repeats


def tune_problem(row_dir: pathlib.Path) -> str | None:
    """What keeps a tune row from being finished (no tune.md yet, a member without its final evaluation), or None."""
    if not (row_dir / TUNE_DONE).is_file():
        return f"{TUNE_DONE} is missing"
    try:
        names = [m["name"] for m in yaml.safe_load((row_dir / "tune.yaml").read_text())["members"]]
    except Exception:  # missing, unreadable or edited: the tune's own resume names it
        return "tune.yaml does not list the members"
    if _tune_pick(row_dir, len(names)) is None:
        return f"{TUNE_SCHEDULE} is missing or does not name one of the {len(names)} members last"
    for name in names:
        path = row_dir / "runs" / name / "eval.json"
        try:
            sr = json.loads(path.read_text())["results"]["learned"]["success_rate"]
        except (OSError, ValueError, KeyError, TypeError):
            return f"{portable(str(path))} is missing or damaged"
        if not math.isfinite(_float(sr)):
            return f"{portable(str(path))}: success_rate = {str(sr)[:20]!r} is not a finite number"
    return None


def _tune_pick(row_dir: pathlib.Path, members: int) -> int | None:
    """The index of the member a finished tune picked (its schedule's last holder), or None if unreadable."""
    try:
        pick = int(_read_csv(row_dir / TUNE_SCHEDULE)[-1]["member"])
    except (OSError, ValueError, KeyError, TypeError, IndexError, csv.Error):
        return None
    return pick if 0 <= pick < members else None


def tune_repeat(row: Row, row_dir: pathlib.Path, objective, names: Sequence[str]) -> Repeat:
    """A finished tune row: its members' final evaluations, their searched values at the end, its test curve."""
    from tgrf_jax.tune.spec import load_tune

    spec = load_tune(row_dir)
    members, steps = [], 0
    for m in spec.members():
        payload = json.loads((row_dir / "runs" / m.name / "eval.json").read_text())
        res = payload["results"]["learned"]
        config = yaml.safe_load((row_dir / "runs" / m.name / "config.yaml").read_text())
        values = {n: _float(config[n.split(".", 1)[0]][n.split(".", 1)[1]]) for n in names}
        steps = int(payload["env_steps"])
        members.append(
            Member(
                m.name,
                score(objective, res),
                values,
                _float(res.get("success_rate")),
                _float(res.get("collision_rate")),
            )
        )
    curve = _curve_or_end(row_dir, {m.name for m in members}, objective, members, steps)
    pick = members[_tune_pick(row_dir, len(members))].name
    return Repeat(row.name, row.name, row.label, row.kind, steps, tuple(members), curve, pick)


# --------------------------------------------------------------------------------------------- the grid it reads


def check_grid(exp: Experiment, row: Row) -> str | None:
    """The grid row's finished sweep against the experiment: over the searched fields, within the space, trained
    and tested as the other rows are. Raises ConfigError naming what differs; returns a note when only the budget
    per run differs (a shortened quick look), else None."""
    from tgrf_jax.sweep.grid import SWEEP_FILE, load_sweep
    from tgrf_jax.tune.space import parse_space

    where = f"experiment {exp.name!r}, row {row.name!r}: {portable(row.results)!r}"
    results = pathlib.Path(row.results)
    if not (results / SWEEP_FILE).is_file():
        raise ConfigError(f"{where} is not a tgrf-sweep directory (it has no {SWEEP_FILE})")
    sweep = load_sweep(results)
    problem = report.evals_problem(results)
    if problem:
        raise ConfigError(f"{where} is not a finished sweep: {problem}")
    dims = {d.name: d for d in parse_space(list(exp.space))}
    axes = [a.name for a in sweep.axes]
    if sorted(axes) != sorted(dims):
        raise ConfigError(f"{where} is a grid over {', '.join(axes) or 'nothing'}; the space is {', '.join(dims)}")
    for axis in sweep.axes:
        d = dims[axis.name]
        outside = [v for v in axis.values if not d.low * (1 - 1e-6) <= v <= d.high * (1 + 1e-6)]
        if outside:
            raise ConfigError(f"{where}: its {axis.name} = {outside[0]:g} lies outside the space ({d.spec()})")
    ours, theirs = comparable(row_config(exp, row).to_dict(), set(dims)), comparable(sweep.base, set(dims))
    differ = [
        f"{k} = {theirs.get(k)!r} there, {ours.get(k)!r} here"
        for k in sorted(set(ours) | set(theirs))
        if k != "ppo.total_steps" and ours.get(k) != theirs.get(k)
    ]
    if differ:
        raise ConfigError(
            f"{where} trained or tested other settings than the experiment's rows ({'; '.join(differ[:4])}"
            f"{f'; and {len(differ) - 4} more' if len(differ) > 4 else ''}): its objective would not be comparable"
        )
    mine, its = row_config(exp, row).ppo, sweep.base_config.ppo
    if mine.num_updates * mine.batch_size != its.num_updates * its.batch_size:
        return (
            f"The grid's runs trained {its.num_updates * its.batch_size:,} env steps each, this experiment's rows "
            f"{mine.num_updates * mine.batch_size:,}: the procedures did not spend equal env steps."
        )
    return None


# --------------------------------------------------------------------------------------------- collecting


@dataclasses.dataclass
class Collected:
    repeats: list[Repeat]
    status: dict[str, str]  # row -> 'done', '…' (not finished) or why it cannot be reported
    note: str | None  # about the grid's budget
    wall: dict[str, dict]  # row -> its provenance (report._provenance)


def collect(exp: Experiment, out: pathlib.Path) -> Collected:
    from tgrf_jax.tune.objective import parse_objective
    from tgrf_jax.tune.space import parse_space

    objective = parse_objective(exp.objective)
    names = [d.name for d in parse_space(list(exp.space))]
    got = Collected([], {}, None, {})
    for row in exp.rows:
        row_dir = pathlib.Path(row.results) if row.kind == "grid" else out / row.name
        rerun = f"rerun tgrf-reproduce {exp.name} --rows {row.name}"
        try:
            if row.kind == "grid":
                got.note = check_grid(exp, row)
                got.repeats += sweep_repeats(row, row_dir, objective, names)
            elif not (row_dir / ("evals.csv" if row.kind == "random" else TUNE_DONE)).is_file():
                got.status[row.name] = "…"
                continue
            elif row.kind == "random":
                problem = report.evals_problem(row_dir)
                if problem:
                    got.status[row.name] = f"damaged ({problem}): {rerun}"
                    continue
                got.repeats += sweep_repeats(row, row_dir, objective, names)
            else:
                problem = tune_problem(row_dir)
                if problem:
                    got.status[row.name] = f"damaged ({problem}): {rerun}"
                    continue
                got.repeats.append(tune_repeat(row, row_dir, objective, names))
        except ConfigError as e:
            got.status[row.name] = f"cannot be read: {e}"
            continue
        got.status[row.name] = "done"
        got.wall[row.name] = report._provenance(row_dir)
    return got


# --------------------------------------------------------------------------------------------- writing


def _mean_std_text(mean: float, std: float) -> str:
    return _num(mean) + (f" ± {std:.4f}" if math.isfinite(std) else "")


def _num(x, fmt: str = "{:.4f}") -> str:
    return "–" if x is None or not math.isfinite(x) else fmt.format(x)


def _steps(x: int | None) -> str:
    return "not reached" if x is None else f"{x:,}"


def _short(name: str) -> str:
    return name.split(".", 1)[1]


def csv_fields(names: Sequence[str]) -> list[str]:
    return [
        "experiment",
        "row",
        "repeat",
        "label",
        "procedure",
        "members",
        "env_steps_per_member",
        "env_steps",
        "best_objective",
        "best_member",
        *names,
        "success_rate",
        "collision_rate",
        "own_pick",
        "own_pick_objective",
        "grid_best",
        "reached_grid_best",
        "env_steps_to_grid_best",
        "row_wall_s",
        "commit",
    ]


def records(exp: Experiment, got: Collected, names: Sequence[str]) -> list[dict]:
    """One CSV record per repeat."""
    target = grid_best(got.repeats)
    out = []
    for r in got.repeats:
        best, picked = r.best, r.picked
        reached = None if target is None else steps_to_reach(r.curve, target[0])
        prov = got.wall.get(r.row, {})
        out.append(
            {
                "experiment": exp.name,
                "row": r.row,
                "repeat": r.name,
                "label": r.label,
                "procedure": _CSV_NAMES[r.procedure],
                "members": len(r.members),
                "env_steps_per_member": r.steps_per_member,
                "env_steps": r.env_steps,
                "best_objective": best.objective,
                "best_member": best.name,
                **{n: best.values.get(n) for n in names},
                "success_rate": best.success_rate,
                "collision_rate": best.collision_rate,
                "own_pick": None if picked is None else picked.name,
                "own_pick_objective": None if picked is None else picked.objective,
                "grid_best": None if target is None else target[0],
                "reached_grid_best": None if target is None else reached is not None,
                "env_steps_to_grid_best": reached,
                "row_wall_s": prov.get("row_wall_s"),
                "commit": prov.get("commit"),
            }
        )
    return out


def best_tune(repeats: Sequence[Repeat]) -> Repeat | None:
    """The PBT repeat whose own pick scores best on the test (the first of equals)."""
    tunes = [r for r in repeats if r.procedure == "tune" and r.picked and math.isfinite(r.picked.objective)]
    return max(tunes, key=lambda r: r.picked.objective) if tunes else None


def schedule_of(out: pathlib.Path, repeat: Repeat):
    """(the tune's spec, the searched values along its pick's ancestry) from the tune row's lineage."""
    from tgrf_jax.tune.run import ancestry_schedule
    from tgrf_jax.tune.spec import load_tune

    row_dir = out / repeat.row
    spec = load_tune(row_dir)
    member = [m.name for m in spec.members()].index(repeat.pick)
    return spec, ancestry_schedule(spec, _read_csv(row_dir / "lineage.csv"), member)


def _figure(size):
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=size)
    FigureCanvasAgg(fig)
    return fig, fig.subplots()


def plot_progress(
    path: pathlib.Path, repeats: Sequence[Repeat], target: float | None, objective: str, names: Mapping[str, str]
):
    """The best member's objective at each test against the env steps its procedure had spent, every repeat a
    line (a grid, tested only at the end, a marker), the grid's best a dashed line. `names`: each kind's name."""
    fig, ax = _figure((8, 4.8))
    for kind in PROCEDURES:
        labelled = False
        for r in (x for x in repeats if x.procedure == kind):
            points = [(s / 1e6, v) for s, v in r.curve if math.isfinite(v)]
            if not points:
                continue
            xs, ys = zip(*points)
            style = dict(marker="s", linestyle="none", ms=7) if len(points) == 1 else dict(marker="o", ms=3, lw=1.2)
            label = None if labelled else names[kind]
            ax.plot(xs, ys, color=_COLOURS[kind], label=label, alpha=0.85, **style)
            labelled = True
    if target is not None:
        ax.axhline(target, color="k", linestyle="--", linewidth=0.9, label="the grid's best")
    ax.set(
        xlabel="million env steps spent by the procedure (all its members)",
        ylabel=f"best member's {objective}",
        title="best objective on the test episodes against env steps",
    )
    ax.grid(alpha=0.3)
    ax.legend(loc="lower right")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    return path


def _space_text(exp: Experiment) -> str:
    from tgrf_jax.tune.space import parse_space

    return ", ".join(
        f"`{d.name}` in [{d.low:g}, {d.high:g}]" + (" (log)" if d.log else "") for d in parse_space(list(exp.space))
    )


def _procedure_names(exp: Experiment) -> dict[str, str]:
    """Each kind of row's name in the report: the label of its first row."""
    names = dict(_NAMES)
    for row in reversed(exp.rows):
        if row.label != row.name:
            names[row.kind] = row.label
    return names


def format_report(exp: Experiment, got: Collected, names: Sequence[str], recs: list[dict], figures: dict) -> str:
    procedure = _procedure_names(exp)
    config = row_config(exp, exp.rows[0])  # the rows share their test episodes (`spec.load` checks)
    target = grid_best(got.repeats)
    done = sum(1 for s in got.status.values() if s == "done")
    parts = [
        f"# {exp.title}",
        "",
        f"Searched: {_space_text(exp)}. Objective `{exp.objective}`, for every procedure on the same "
        f"{config.run.eval_episodes} test episodes (run.eval_seed {config.run.eval_seed}): each run's final "
        "evaluation, and for PBT and random search the same test every tenth of training. PBT chooses whom to copy "
        "on test episodes of its own (another seed), never on these. A repeat's best objective is its best "
        "member's on these episodes at the end, the one measure the grid and random search have; PBT's own pick, the "
        "member it ranks best on its own episodes (what tgrf-tune hands its user), is scored on them beside it. A "
        "repeat's env steps are all its members' together.",
        "",
        f"Rows finished: {done}/{len(exp.rows)}.",
    ]
    if got.note:
        parts += ["", got.note]
    if target is not None:
        value, holder = target
        shown = ", ".join(f"{_short(n)} = {holder.best.values[n]:.4g}" for n in names)
        parts += [
            "",
            f"**The grid's best**: {value:.4f} ({holder.label}: {shown}), the target of the column "
            '"env steps to the grid\'s best".',
        ]
    parts += [
        "",
        "| procedure | repeats | env steps each | best objective (mean ± std) | highest | own pick (mean ± std) "
        "| reached the grid's best | env steps to reach it |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for kind in PROCEDURES:
        reps = [r for r in got.repeats if r.procedure == kind]
        rows = [r for r in exp.rows if r.kind == kind]
        if not rows:
            continue
        if not reps:
            parts.append(f"| {procedure[kind]} | 0/{len(rows)} | … | … | … | … | … | … |")
            continue
        s = summary(reps, None if target is None else target[0])
        mean = _mean_std_text(s["best_mean"], s["best_std"])
        picks = [r.picked.objective for r in reps if r.picked is not None]
        own = _mean_std_text(*mean_std(picks)) if picks else "–"
        reached = "–" if target is None else f"{sum(x is not None for x in s['to_target'])}/{len(reps)}"
        to_target = "–" if target is None else "; ".join(_steps(x) for x in s["to_target"])
        total = len(rows) if kind != "grid" else len(reps)
        parts.append(
            f"| {procedure[kind]} | {len(reps)}/{total} | {', '.join(f'{x:,}' for x in s['env_steps'])} | {mean} | "
            f"{_num(s['best'])} | {own} | {reached} | {to_target} |"
        )
    parts += [
        "",
        "## Repeats",
        "",
        "| repeat | procedure | members | env steps | best objective | best member | "
        + " | ".join(f"{_short(n)}" for n in names)
        + " | SR (%) | collision (%) | own pick | env steps to the grid's best |",
        "|" + "---|" * (10 + len(names)),
    ]
    for row in exp.rows:  # in the experiment's order, rows not (yet) reported included
        status = got.status.get(row.name, "…")
        if status != "done":
            parts.append(f"| {row.name} | {procedure[row.kind]} | {status} |" + " |" * (7 + len(names)))
        for rec in (r for r in recs if r["row"] == row.name):
            parts.append(
                f"| {rec['repeat']} | {procedure[row.kind]} | {rec['members']} | {rec['env_steps']:,} | "
                f"{_num(rec['best_objective'])} | {rec['best_member']} | "
                + " | ".join(_num(rec[n], "{:.4g}") for n in names)
                + f" | {_num(100 * rec['success_rate'], '{:.1f}')} | {_num(100 * rec['collision_rate'], '{:.1f}')} | "
                + ("–" if rec["own_pick"] is None else f"{rec['own_pick']}: {_num(rec['own_pick_objective'])}")
                + " | "
                + ("–" if rec["grid_best"] is None else _steps(rec["env_steps_to_grid_best"]))
                + " |"
            )
    if "schedule" in figures:
        repeat, schedule = figures["schedule"]
        parts += [
            "",
            "## The schedule PBT found",
            "",
            f"The PBT repeat whose own pick scores best on the test, {repeat.name} ({repeat.pick}: "
            f"{repeat.picked.objective:.4f}): the searched values along {repeat.pick}'s ancestry (the row's "
            f"`{TUNE_SCHEDULE}`), each held from the update given to the next.",
            "",
            "| update | held by | " + " | ".join(f"`{n}`" for n in names) + " |",
            "|---" * (2 + len(names)) + "|",
        ]
        for r in schedule:
            parts.append(f"| {r['update']} | m{r['member']:03d} | " + " | ".join(f"{r[n]:.4g}" for n in names) + " |")
        if "schedule_png" in figures:
            parts += ["", f"![the schedule of the best PBT repeat]({SCHEDULE_PNG})"]
    if "progress" in figures:
        parts += ["", f"![best objective against env steps]({PROGRESS_PNG})"]
    if got.wall:
        parts += ["", "| row | wall time | invocations | commits | machines | finished |", "|---|---|---|---|---|---|"]
        for row in exp.rows:
            prov = got.wall.get(row.name)
            if prov and prov.get("commit"):
                where = f" (read from {portable(row.results)})" if row.kind == "grid" else ""
                parts.append(
                    f"| {row.name}{where} | {(prov['row_wall_s'] or 0.0) / 60:.1f} min | {prov['invocations']} | "
                    f"{prov['commits']} | {prov['machines']} | {prov['finished']} |"
                )
    if exp.notes:
        parts += ["", exp.notes.strip()]
    return "\n".join(parts) + "\n"


def _csv_text(fields: list[str], rows: list[dict]) -> str:
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=fields, extrasaction="ignore")
    w.writeheader()
    w.writerows(rows)
    return buf.getvalue()


def write(exp: Experiment, out, say: Callable[[str], None] = print) -> list[pathlib.Path]:
    """report.md, report.csv and the figures of a search experiment in `out`; returns the written paths."""
    from tgrf_jax.tune.space import parse_space

    out = pathlib.Path(out)
    names = [d.name for d in parse_space(list(exp.space))]
    got = collect(exp, out)
    recs = records(exp, got, names)
    target = grid_best(got.repeats)
    figures: dict = {}
    written = [out / REPORT_MD, out / REPORT_CSV]
    best = best_tune(got.repeats)
    if best is not None:
        spec, schedule = schedule_of(out, best)
        figures["schedule"] = (best, schedule)
    try:  # a figure that fails to draw must not cost the tables
        if got.repeats:
            value = None if target is None else target[0]
            plot_progress(out / PROGRESS_PNG, got.repeats, value, exp.objective, _procedure_names(exp))
            figures["progress"], written = True, written + [out / PROGRESS_PNG]
        if best is not None:
            from tgrf_jax.tune.plots import plot_schedule

            plot_schedule(out / SCHEDULE_PNG, spec, schedule)
            figures["schedule_png"], written = True, written + [out / SCHEDULE_PNG]
    except Exception as e:
        say(f"warning: could not plot: {type(e).__name__}: {e}")
    write_atomic(out / REPORT_CSV, _csv_text(csv_fields(names), recs))
    write_atomic(out / REPORT_MD, format_report(exp, got, names, recs, figures))
    return written
