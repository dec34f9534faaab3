"""Experiments as data: a YAML file lists rows (the static choices of a sweep) and what is compared inside
each row (grid axes over traced fields, e.g. the reward scheme), the seeds, the budget and the paper's numbers.

Schema (configs/experiments/*.yaml):

    title: "Table 1: humans follow ORCA"
    layout: table | curves | heatmap     # how the results are reported
    config: null                         # base config file, relative to the experiment file (default: embedded)
    set: {ppo.total_steps: 5990400}      # overrides of every row
    seeds: 3
    grid: {reward.scheme: [crowdnav_pp, tgrf]}   # compared inside each row (one tgrf-sweep --grid per key)
    columns: {crowdnav_pp: "Without TGRF", tgrf: "With TGRF"}   # labels of the first grid axis' values
    rows:
      - name: const_vel
        label: Const vel + HH Attn
        set: {env.predictor: const_vel}
        grid: {reward.scheme: [crowdnav_pp, tgrf, tgrf_circle]}   # optional: this row compares more
        paper: {crowdnav_pp: {sr_mean: 65.0, sr_std: 8.023, sr: 81.0, nt: 17.34, pl: 21.95, itr: 6.15}, ...}

Every row runs as one `tgrf-sweep` (all grid points x seeds of the row train as one program).

A row may be tested apart from where it trains (leave-one-scene-out: train on four scenes, test on the fifth):
its `test` lists env settings that every run's final policy is then played under by `tgrf-eval` (the final
evaluation's episodes and seed), and `compare` (top level) names other policies played there too, shipped ones
(`tgrf_jax.pretrained`) or the baseline robots:

    compare: [table1-const_vel-tgrf, orca]
    rows:
      - name: eth
        set: {env.replay_files: [hotel, univ, zara1, zara2]}
        test: {env.replay_files: [eth]}

A search experiment (`layout: search`) compares ways of searching one space at equal env steps; its rows say
what they are (`kind`), and it has no grid, columns or seeds:

    layout: search
    space: [reward.h_disc=0.625:5.0:log, reward.sigma_disc=0.1:0.5:log]   # as tgrf-tune --space
    objective: "success - 0.5 * collision"                              # scored on the same test episodes
    rows:
      - {name: grid, kind: grid, results: ../../docs/reproduction/sensitivity/const_vel}  # a finished sweep, read
      - {name: pbt_1, kind: tune, population: 16, set: {run.seed: 0}}     # one tgrf-tune (interval: optional)
      - {name: random_1, kind: random, draws: 16, set: {run.seed: 0}}     # one tgrf-sweep over seeded draws

A random row's draws are those a tune with the same run.seed starts from (`tgrf_jax.tune.space.draw_values`),
trained as a `tgrf-sweep --paired` with that one seed. Tune and random rows test their policies every tenth of
training on the final evaluation's episodes (run.eval_every, run.curve_episodes = run.eval_episodes).
"""

from __future__ import annotations

import dataclasses
import math
import pathlib
from collections.abc import Mapping
from typing import Any

import yaml

from tgrf_jax.config import ConfigError, TrainConfig, apply_overrides, load_yaml

LAYOUTS = ("table", "curves", "heatmap", "search")
PAPER_FIELDS = ("sr_mean", "sr_std", "sr", "nt", "pl", "itr")
_TOP_KEYS = (
    "compare",
    "title",
    "description",
    "layout",
    "config",
    "set",
    "seeds",
    "grid",
    "columns",
    "rows",
    "notes",
    "space",
    "objective",
)
_ROW_KEYS = ("name", "label", "kind", "set", "grid", "paper", "test")
BASELINES = ("orca", "straight")  # the baseline robots a `compare` list may name beside shipped policies
# search experiments: what each kind of row takes besides name, label, kind and set
SEARCH_KINDS = {"grid": ("results",), "tune": ("population", "interval"), "random": ("draws",)}
_SEARCH_ONLY = ("space", "objective")
_NOT_IN_SEARCH = ("seeds", "grid", "columns")
TEST_POINTS = 10  # tests of a search row's policies over training: every tenth, as often as PBT exploits by default
MAX_MEMBERS = 1_000
EXPERIMENTS_DIR = pathlib.Path(__file__).resolve().parents[2] / "configs" / "experiments"
REPO_ROOT = EXPERIMENTS_DIR.parents[1]


def portable(path: str) -> str:
    """`path` relative to the repository when it lies inside it: what result files record, so that a results
    directory moved to another machine or checkout still matches (absolute paths elsewhere are kept)."""
    try:
        return pathlib.Path(path).resolve().relative_to(REPO_ROOT).as_posix()
    except ValueError:
        return path


@dataclasses.dataclass(frozen=True)
class Row:
    name: str
    label: str
    overrides: tuple[str, ...]  # `section.field=value` items for this row (experiment-wide ones first)
    grid: tuple[tuple[str, tuple], ...]  # (dotted field, values) per axis; the first axis is the compared one
    paper: Mapping[str, Mapping[str, float]]  # grid value -> paper field -> number
    kind: str = "sweep"  # sweep; in search experiments grid, tune or random
    members: int = 0  # tune: the population; random: the draws (the paired points of `grid`)
    interval: int | None = None  # tune: updates between exploit steps (None: tgrf-tune's default, a tenth)
    results: str | None = None  # grid: the absolute path of the finished tgrf-sweep directory it reads
    test: tuple[str, ...] = ()  # `env.field=value` items its policies are tested under (none: as trained)


@dataclasses.dataclass(frozen=True)
class Experiment:
    name: str
    title: str
    layout: str
    config: str | None  # absolute path of the base config file, or None for the embedded default
    seeds: int
    columns: Mapping[str, str]
    rows: tuple[Row, ...]
    notes: str = ""
    space: tuple[str, ...] = ()  # search: FIELD=LO:HI[:log] items
    objective: str = ""  # search: what every procedure is scored by
    compare: tuple[str, ...] = ()  # policies played on the rows' test episodes beside the rows' own

    @property
    def search(self) -> bool:
        return self.layout == "search"

    def size(self) -> str:
        """What the experiment trains, for its progress header."""
        if self.search:
            parts = []
            for kind, noun in (("grid", None), ("tune", "members"), ("random", "draws")):
                rows = [r for r in self.rows if r.kind == kind]
                if rows and noun is None:
                    parts += [f"{r.kind} row {r.name} read from {portable(r.results)}" for r in rows]
                elif rows:
                    members = "/".join(sorted({str(r.members) for r in rows}))
                    parts.append(f"{len(rows)} {kind} row{'s' if len(rows) > 1 else ''} x {members} {noun}")
            return ", ".join(parts)
        axes = " x ".join(f"{len(self.axis_values(name))} {name}" for name in self.grid_names)
        return f"{len(self.rows)} rows x {axes} values x {self.seeds} seeds"

    @property
    def column_axis(self) -> str:
        return self.rows[0].grid[0][0]

    @property
    def grid_names(self) -> list[str]:
        return [name for name, _ in self.rows[0].grid]

    @property
    def column_values(self) -> tuple:
        """Values of the compared axis over all rows, in order of first appearance."""
        return self.axis_values(self.column_axis)

    def axis_values(self, name: str) -> tuple:
        """Values of one grid axis over all rows, in order of first appearance."""
        seen = []
        for row in self.rows:
            for axis, values in row.grid:
                if axis == name:
                    seen += [v for v in values if v not in seen]
        return tuple(seen)

    def column_label(self, value) -> str:
        return self.columns.get(str(value), str(value))

    def row(self, name: str) -> Row:
        for r in self.rows:
            if r.name == name:
                return r
        raise ConfigError(f"experiment {self.name!r} has no row {name!r}; rows: {', '.join(r.name for r in self.rows)}")

    def shrunk(
        self, *, steps: int | None = None, seeds: int | None = None, rows: list[str] | None = None
    ) -> Experiment:
        """The same experiment with a smaller budget, fewer seeds or a subset of rows (for a quick look)."""
        out = self
        if steps is not None:
            if steps < 1:
                raise ConfigError(f"--steps = {steps} must be >= 1")
            extra = (f"ppo.total_steps={steps}",)
            out = dataclasses.replace(
                out, rows=tuple(dataclasses.replace(r, overrides=r.overrides + extra) for r in out.rows)
            )
            for row in out.rows:  # a tune's interval, say, must fit the smaller budget
                check_row(out, row)
        if seeds is not None:
            if self.search:
                raise ConfigError(
                    f"--seeds: experiment {self.name!r} compares searches, whose rows set their own run.seed"
                )
            if not 1 <= seeds <= 100:
                raise ConfigError(f"--seeds = {seeds} is out of range; allowed: 1 to 100")
            out = dataclasses.replace(out, seeds=seeds)
        if rows:
            out = dataclasses.replace(out, rows=tuple(out.row(n) for n in rows))
        return out

    def to_dict(self) -> dict:
        data = {
            "name": self.name,
            "title": self.title,
            "layout": self.layout,
            "config": portable(self.config) if self.config else None,
            "seeds": self.seeds,
            "rows": [_row_dict(r) for r in self.rows],
        }
        if self.search:
            data.update(space=list(self.space), objective=self.objective)
        if self.compare:
            data["compare"] = list(self.compare)
        return data


def _row_dict(row: Row) -> dict:
    """A row's settings as experiment.yaml records them (a sweep row's as before search rows existed)."""
    data = {"name": row.name, "set": list(row.overrides), "grid": {k: list(v) for k, v in row.grid}}
    if row.kind == "sweep":
        return {**data, "test": list(row.test)} if row.test else data
    extra = {"tune": {"population": row.members, "interval": row.interval}, "random": {"draws": row.members}}
    data = {"name": row.name, "kind": row.kind, **data, **extra.get(row.kind, {})}
    if row.kind == "grid":
        data = {"name": row.name, "kind": row.kind, "results": portable(row.results)}
    return data


def available() -> list[str]:
    return sorted(p.stem for p in EXPERIMENTS_DIR.glob("*.yaml")) if EXPERIMENTS_DIR.is_dir() else []


def resolve_path(name_or_path: str) -> pathlib.Path:
    """An experiment name (a file under configs/experiments/) or a path to an experiment YAML."""
    path = pathlib.Path(name_or_path)
    if path.suffix in (".yaml", ".yml") or path.parent != pathlib.Path("."):
        if path.is_dir():
            raise ConfigError(f"experiment {str(path)!r} is a directory, not an experiment YAML file")
        if not path.is_file():
            raise ConfigError(f"experiment file {str(path)!r} does not exist")
        return path
    candidate = EXPERIMENTS_DIR / f"{name_or_path}.yaml"
    if not candidate.is_file():
        names = ", ".join(available()) or f"none found under {EXPERIMENTS_DIR}"
        raise ConfigError(f"unknown experiment {name_or_path!r}; experiments: {names} (or give a path to a YAML file)")
    return candidate


def _short(value: Any, limit: int = 60) -> str:
    text = repr(value)
    return text if len(text) <= limit else text[:limit] + "..."


def _overrides(mapping: Any, where: str) -> tuple[str, ...]:
    if mapping is None:
        return ()
    if not isinstance(mapping, Mapping):
        raise ConfigError(f"{where} must be a mapping of section.field: value")
    items = []
    for key, value in mapping.items():
        if not isinstance(key, str) or "." not in key:
            raise ConfigError(f"{where}: key {key!r} must be a dotted config field such as ppo.total_steps")
        text = yaml.safe_dump(value, default_flow_style=True, width=math.inf).strip().removesuffix("...").strip()
        items.append(f"{key}={text}")
    return tuple(items)


def _paper(raw: Any, where: str, column_values) -> dict:
    if raw is None:
        return {}
    if not isinstance(raw, Mapping):
        raise ConfigError(f"{where} must map grid values to the paper's numbers")
    out = {}
    for value, numbers in raw.items():
        if str(value) not in {str(v) for v in column_values}:
            raise ConfigError(
                f"{where}: {value!r} is not a value of the compared axis ({', '.join(map(str, column_values))})"
            )
        if not isinstance(numbers, Mapping):
            raise ConfigError(f"{where}.{value} must map {', '.join(PAPER_FIELDS)} to numbers")
        unknown = set(numbers) - set(PAPER_FIELDS)
        if unknown:
            raise ConfigError(
                f"{where}.{value}: unknown field(s) {sorted(unknown)}; allowed: {', '.join(PAPER_FIELDS)}"
            )
        for k, v in numbers.items():
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
                raise ConfigError(f"{where}.{value}.{k} = {_short(v)} must be a finite number")
        out[str(value)] = {k: float(v) for k, v in numbers.items()}
    return out


def _grid(raw: Any, where: str) -> tuple[tuple[str, tuple], ...]:
    if not isinstance(raw, Mapping) or not raw:
        raise ConfigError(f"{where} must map at least one dotted field to a list of values")
    axes = []
    for key, values in raw.items():
        if not isinstance(values, list) or not values:
            raise ConfigError(f"{where}.{key} must be a non-empty list of values")
        for v in values:
            # a row runs as `tgrf-sweep --grid key=v1,v2`: a comma inside a value would split it in two
            if (
                isinstance(v, bool)
                or not isinstance(v, (int, float, str))
                or (isinstance(v, str) and (not v.strip() or "," in v))
            ):
                raise ConfigError(
                    f"{where}.{key}: value {_short(v)} is not allowed; allowed: numbers and names "
                    "without commas, one list item each"
                )
        axes.append((str(key), tuple(values)))
    return tuple(axes)


def load(name_or_path: str) -> Experiment:
    """Load and validate an experiment file (every row's config is checked before anything runs)."""
    path = resolve_path(name_or_path)
    data = load_yaml(path)
    unknown = set(data) - set(_TOP_KEYS)
    if unknown:
        raise ConfigError(f"{path}: unknown key(s) {sorted(unknown)}; allowed: {', '.join(_TOP_KEYS)}")
    layout = data.get("layout", "table")
    if layout not in LAYOUTS:
        raise ConfigError(f"{path}: layout = {layout!r} is not allowed; allowed: {', '.join(LAYOUTS)}")
    config = data.get("config")
    if config is not None:
        config = str((path.parent / config).resolve())
        if not pathlib.Path(config).is_file():
            raise ConfigError(f"{path}: config {config!r} does not exist")
    common = _overrides(data.get("set"), f"{path}: set")
    raw_rows = data.get("rows")
    if not isinstance(raw_rows, list) or not raw_rows:
        raise ConfigError(f"{path}: rows must be a non-empty list")
    if layout == "search":
        return _load_search(path, data, config, common, raw_rows)
    for key in _SEARCH_ONLY:
        if key in data:
            raise ConfigError(f"{path}: {key} belongs to a search experiment (layout: search)")
    seeds = data.get("seeds", 1)
    if not isinstance(seeds, int) or isinstance(seeds, bool) or not 1 <= seeds <= 100:
        raise ConfigError(f"{path}: seeds = {seeds!r} must be an integer from 1 to 100")
    axes = _grid(data.get("grid"), f"{path}: grid")
    rows, seen = [], set()
    for i, raw in enumerate(raw_rows):
        where = f"{path}: rows[{i}]"
        name = _row_name(raw, where, seen)
        kind = raw.get("kind", "sweep")
        if kind != "sweep":
            raise ConfigError(
                f"{where}: kind = {_short(kind)} belongs to a search experiment (layout: search); rows of a "
                f"{layout} experiment are sweeps"
            )
        unknown = set(raw) - set(_ROW_KEYS)
        if unknown:
            raise ConfigError(f"{where}: unknown key(s) {sorted(unknown)}; allowed: {', '.join(_ROW_KEYS)}")
        grid = _grid(raw["grid"], f"{where}.grid") if "grid" in raw else axes
        if [k for k, _ in grid] != [k for k, _ in axes]:
            raise ConfigError(
                f"{where}.grid must have the experiment's axes ({', '.join(k for k, _ in axes)}); "
                "only their values may differ"
            )
        test = _overrides(raw.get("test"), f"{where}.test")
        if "test" in raw and not test:
            raise ConfigError(f"{where}.test must set at least one env field (or be left out: tested as trained)")
        for item in test:
            if not item.startswith("env."):
                raise ConfigError(
                    f"{where}.test: {item.split('=', 1)[0]} is not an env field; a test changes only env.* "
                    "settings (the policy is the row's)"
                )
        rows.append(
            Row(
                name=name,
                label=str(raw.get("label", name)),
                overrides=common + _overrides(raw.get("set"), f"{where}.set"),
                grid=grid,
                paper=_paper(raw.get("paper"), f"{where}.paper", grid[0][1]),
                test=test,
            )
        )
    compare = _compare(data.get("compare"), f"{path}: compare", any(r.test for r in rows))
    columns = {str(k): str(v) for k, v in (data.get("columns") or {}).items()}
    exp = Experiment(
        name=path.stem,
        title=str(data.get("title", path.stem)),
        layout=layout,
        config=config,
        seeds=seeds,
        columns=columns,
        rows=tuple(rows),
        notes=str(data.get("notes", "")),
        compare=compare,
    )
    for row in exp.rows:
        sweep_spec(exp, row)  # a typo in any row fails here, before anything runs
        if row.test:
            tested_config(exp, row)
    return exp


def _compare(raw: Any, where: str, tested: bool) -> tuple[str, ...]:
    """The policies a `compare` list names: shipped policies (tgrf_jax.pretrained) or the baseline robots."""
    from tgrf_jax import pretrained

    if raw is None:
        return ()
    if not tested:
        raise ConfigError(f"{where}: policies are compared on the rows' test episodes, and no row has a test")
    known = (*pretrained.available(), *BASELINES)
    if not isinstance(raw, list) or not raw or not all(isinstance(n, str) for n in raw):
        raise ConfigError(f"{where} must be a list of policy names; allowed: {', '.join(known)}")
    for name in raw:
        if name not in known:
            raise ConfigError(f"{where}: unknown policy {name!r}; allowed: {', '.join(known)}")
    if len(set(raw)) != len(raw):
        raise ConfigError(f"{where} names a policy twice")
    return tuple(raw)


def tested_config(exp: Experiment, row: Row) -> TrainConfig:
    """The config a row's policies are tested under: the row's with its `test` settings (raises ConfigError
    naming the row)."""
    try:
        return _resolved(exp.config, row.overrides + row.test)
    except ConfigError as e:
        raise ConfigError(f"experiment {exp.name!r}, row {row.name!r}, test: {e}") from None


def _row_name(raw: Any, where: str, seen: set) -> str:
    if not isinstance(raw, Mapping) or "name" not in raw:
        raise ConfigError(f"{where} must be a mapping with at least a name")
    name = str(raw["name"])
    if not name.replace("_", "").replace("-", "").isalnum() or name in seen:
        raise ConfigError(f"{where}: name {name!r} must be unique and made of letters, digits, '_' and '-'")
    seen.add(name)
    return name


def _count(raw: Mapping, key: str, where: str, required: bool = True) -> int | None:
    value = raw.get(key)
    if value is None and not required:
        return None
    if value is None:
        raise ConfigError(f"{where}: {key} is missing")
    if isinstance(value, bool) or not isinstance(value, int) or not 1 <= value <= MAX_MEMBERS:
        raise ConfigError(f"{where}: {key} = {_short(value)} must be an integer from 1 to {MAX_MEMBERS:,}")
    return value


def _space(raw: Any, where: str, base: dict):
    from tgrf_jax.tune.space import parse_space

    if not isinstance(raw, list) or not raw or not all(isinstance(item, str) for item in raw):
        raise ConfigError(
            f"{where} must be a list of FIELD=LO:HI[:log] items (as tgrf-tune --space), e.g. "
            "[reward.h_disc=0.625:5.0:log, reward.sigma_disc=0.1:0.5:log]"
        )
    try:
        return parse_space(raw, base)
    except ConfigError as e:
        raise ConfigError(f"{where}: {e}") from None


def _objective(raw: Any, where: str):
    """The objective, which must read only metrics that the tests during training record."""
    from tgrf_jax.train.curves import CURVE_METRICS
    from tgrf_jax.tune.objective import METRICS, parse_objective

    if not isinstance(raw, str):
        raise ConfigError(f"{where} must be an expression over test metrics, e.g. 'success - 0.5 * collision'")
    try:
        objective = parse_objective(raw)
    except ConfigError as e:
        raise ConfigError(f"{where}: {e}") from None
    recorded = [short for short, (field, _) in METRICS.items() if field in CURVE_METRICS]
    for name in objective.metrics:
        if METRICS.get(name, (name, 1.0))[0] not in CURVE_METRICS:
            raise ConfigError(
                f"{where}: {name!r} is not recorded by the tests during training, so the procedures cannot be "
                f"compared on it; allowed: {', '.join(recorded)} (or {', '.join(CURVE_METRICS)})"
            )
    return objective


def _load_search(path: pathlib.Path, data: dict, config: str | None, common: tuple, raw_rows: list) -> Experiment:
    """A search experiment: rows of kind grid (a finished sweep, read), tune and random, one space and objective."""
    from tgrf_jax.tune.space import draw_values

    for key in _NOT_IN_SEARCH:
        if key in data:
            raise ConfigError(
                f"{path}: {key} is not used by a search experiment (layout: search); its rows set their own"
            )
    for key in _SEARCH_ONLY:
        if key not in data:
            raise ConfigError(f"{path}: a search experiment (layout: search) needs {key}")
    dims = _space(data["space"], f"{path}: space", _resolved(config, common).to_dict())
    _objective(data["objective"], f"{path}: objective")
    rows, seen = [], set()
    for i, raw in enumerate(raw_rows):
        where = f"{path}: rows[{i}]"
        name = _row_name(raw, where, seen)
        kind = raw.get("kind")
        if kind not in SEARCH_KINDS:
            shown = "is missing" if kind is None else f"= {_short(kind)} is not allowed"
            raise ConfigError(f"{where}: kind {shown}; allowed: {', '.join(SEARCH_KINDS)}")
        allowed = ("name", "label", "kind", *(() if kind == "grid" else ("set",)), *SEARCH_KINDS[kind])
        unknown = set(raw) - set(allowed)
        if unknown:
            raise ConfigError(
                f"{where}: unknown key(s) {sorted(unknown)} for a {kind} row; allowed: {', '.join(allowed)}"
            )
        row = Row(name=name, label=str(raw.get("label", name)), overrides=common, grid=(), paper={}, kind=kind)
        if kind == "grid":
            results = raw.get("results")
            if not isinstance(results, str) or not results.strip():
                raise ConfigError(
                    f"{where}: results is missing; give the finished tgrf-sweep directory of the grid, relative to "
                    "the experiment file"
                )
            row = dataclasses.replace(row, results=str((path.parent / results).resolve()))
        else:
            overrides = common + _overrides(raw.get("set"), f"{where}.set")
            row = dataclasses.replace(row, overrides=overrides, members=_count(raw, SEARCH_KINDS[kind][0], where))
        if kind == "tune":
            row = dataclasses.replace(row, interval=_count(raw, "interval", where, required=False))
        if kind == "random":
            try:
                seed = _resolved(config, row.overrides).run.seed
            except ConfigError as e:
                raise ConfigError(f"{where}.set: {e}") from None
            values = draw_values(dims, row.members, seed)
            row = dataclasses.replace(
                row, grid=tuple((d.name, tuple(float(v) for v in values[:, j])) for j, d in enumerate(dims))
            )
        rows.append(row)
    grids = [r.name for r in rows if r.kind == "grid"]
    if len(grids) > 1:
        raise ConfigError(f"{path}: rows {', '.join(grids)} are all of kind grid; a search experiment reads one grid")
    exp = Experiment(
        name=path.stem,
        title=str(data.get("title", path.stem)),
        layout="search",
        config=config,
        seeds=1,
        columns={},
        rows=tuple(rows),
        notes=str(data.get("notes", "")),
        space=tuple(data["space"]),
        objective=str(data["objective"]),
    )
    shared = comparable(_resolved(config, common).to_dict(), {d.name for d in dims})
    for row in exp.rows:
        check_row(exp, row)
        mine = comparable(row_config(exp, row).to_dict(), {d.name for d in dims})
        differ = sorted(k for k in shared if mine[k] != shared[k])
        if differ:  # the procedures would not search the same problem, or not be tested alike
            raise ConfigError(
                f"{path}: row {row.name!r} sets {', '.join(differ)}; the rows of a search experiment may set only "
                "run fields (run.seed, ...): give the others in the experiment's set"
            )
    return exp


def _resolved(config: str | None, overrides) -> TrainConfig:
    return TrainConfig.from_dict(apply_overrides(load_yaml(config) if config else {}, list(overrides)))


def comparable(config: dict, searched) -> dict:
    """section.field -> value of what decides a run's results and its test, as a resolved config dict holds them:
    not the run section (names, logging, seeds) apart from the test episodes, nor the `searched` fields."""
    out = {}
    for section, fields in config.items():
        for field, value in fields.items():
            name = f"{section}.{field}"
            if name in searched or (section == "run" and field not in ("eval_episodes", "eval_seed")):
                continue
            out[name] = value
    return out


def row_config(exp: Experiment, row: Row) -> TrainConfig:
    """The base config a row trains (its grid values or searched fields not applied)."""
    return _resolved(exp.config, row_overrides(exp, row))


def row_overrides(exp: Experiment, row: Row) -> tuple[str, ...]:
    """A row's overrides. Tune and random rows also test their policies during training, every tenth unless the
    config says how often, on the final evaluation's episodes: so every procedure is scored on the same episodes."""
    if row.kind not in ("tune", "random"):
        return row.overrides
    try:
        run = _resolved(exp.config, row.overrides)
    except ConfigError as e:
        raise ConfigError(f"experiment {exp.name!r}, row {row.name!r}: {e}") from None
    every = run.run.eval_every or max(1, run.ppo.num_updates // TEST_POINTS)
    return row.overrides + (f"run.eval_every={every}", f"run.curve_episodes={run.run.eval_episodes}")


def check_row(exp: Experiment, row: Row) -> None:
    """A row's settings through the checks of the tool that trains it (raises ConfigError naming the row)."""
    if row.kind == "tune":
        tune_spec(exp, row)
    elif row.kind != "grid":
        sweep_spec(exp, row)


def tune_spec(exp: Experiment, row: Row):
    """The validated TuneSpec of a tune row (raises ConfigError naming the row)."""
    from tgrf_jax.tune.spec import TuneSpec

    try:
        return TuneSpec.create(
            exp.config,
            list(exp.space),
            population=row.members,
            objective=exp.objective,
            interval=row.interval,
            overrides=list(row_overrides(exp, row)),
        )
    except ConfigError as e:
        raise ConfigError(f"experiment {exp.name!r}, row {row.name!r}: {e}") from None


def tune_args(exp: Experiment, row: Row, layout: str = "auto") -> list[str]:
    """The tgrf-tune arguments of a tune row (without --out / --resume)."""
    args = [exp.config] if exp.config else []
    for item in exp.space:
        args += ["--space", item]
    args += ["--population", str(row.members), "--objective", exp.objective]
    if row.interval is not None:
        args += ["--interval", str(row.interval)]
    for item in row_overrides(exp, row):
        args += ["--set", item]
    return args + ["--layout", layout]


def row_command(exp: Experiment, row: Row, layout: str = "auto") -> list[str]:
    """The command that trains a row from the start, tool name first (without --out)."""
    if row.kind == "grid":
        raise ConfigError(f"row {row.name!r} reads the finished sweep {portable(row.results)!r}; nothing trains it")
    if row.kind == "tune":
        return ["tgrf-tune", *tune_args(exp, row, layout)]
    return ["tgrf-sweep", *sweep_args(exp, row, layout)]


def sweep_args(exp: Experiment, row: Row, layout: str = "auto") -> list[str]:
    """The tgrf-sweep arguments of one row (without --out / --resume)."""
    args = [exp.config] if exp.config else []
    for key, values in row.grid:
        args += ["--grid", f"{key}={','.join(str(v) for v in values)}"]
    if row.kind == "random":
        args.append("--paired")
    args += ["--seeds", str(exp.seeds)]
    for item in row_overrides(exp, row):
        args += ["--set", item]
    # auto: on CPUs the runs of a row train fastest one after another (each as tgrf-train trains it); elsewhere
    # batched
    return args + ["--layout", layout]


def sweep_spec(exp: Experiment, row: Row):
    """The validated SweepSpec of a row (raises ConfigError naming the row)."""
    from tgrf_jax.sweep import SweepSpec

    grid = [f"{k}={','.join(str(v) for v in values)}" for k, values in row.grid]
    try:
        return SweepSpec.create(exp.config, grid, exp.seeds, list(row_overrides(exp, row)), paired=row.kind == "random")
    except ConfigError as e:
        raise ConfigError(f"experiment {exp.name!r}, row {row.name!r}: {e}") from None
