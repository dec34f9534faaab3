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
"""

from __future__ import annotations

import dataclasses
import math
import pathlib
from collections.abc import Mapping
from typing import Any

import yaml

from tgrf_jax.config import ConfigError, load_yaml

LAYOUTS = ("table", "curves", "heatmap")
PAPER_FIELDS = ("sr_mean", "sr_std", "sr", "nt", "pl", "itr")
_TOP_KEYS = ("title", "description", "layout", "config", "set", "seeds", "grid", "columns", "rows", "notes")
_ROW_KEYS = ("name", "label", "set", "grid", "paper")
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
        if seeds is not None:
            if not 1 <= seeds <= 100:
                raise ConfigError(f"--seeds = {seeds} is out of range; allowed: 1 to 100")
            out = dataclasses.replace(out, seeds=seeds)
        if rows:
            out = dataclasses.replace(out, rows=tuple(out.row(n) for n in rows))
        return out

    def to_dict(self) -> dict:
        return {
            "name": self.name,
            "title": self.title,
            "layout": self.layout,
            "config": portable(self.config) if self.config else None,
            "seeds": self.seeds,
            "rows": [
                {"name": r.name, "set": list(r.overrides), "grid": {k: list(v) for k, v in r.grid}} for r in self.rows
            ],
        }


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
        items.append(f"{key}={yaml.safe_dump(value, default_flow_style=True).strip().removesuffix('...').strip()}")
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
    seeds = data.get("seeds", 1)
    if not isinstance(seeds, int) or isinstance(seeds, bool) or not 1 <= seeds <= 100:
        raise ConfigError(f"{path}: seeds = {seeds!r} must be an integer from 1 to 100")
    axes = _grid(data.get("grid"), f"{path}: grid")
    config = data.get("config")
    if config is not None:
        config = str((path.parent / config).resolve())
        if not pathlib.Path(config).is_file():
            raise ConfigError(f"{path}: config {config!r} does not exist")
    common = _overrides(data.get("set"), f"{path}: set")
    raw_rows = data.get("rows")
    if not isinstance(raw_rows, list) or not raw_rows:
        raise ConfigError(f"{path}: rows must be a non-empty list")
    rows, seen = [], set()
    for i, raw in enumerate(raw_rows):
        where = f"{path}: rows[{i}]"
        if not isinstance(raw, Mapping) or "name" not in raw:
            raise ConfigError(f"{where} must be a mapping with at least a name")
        unknown = set(raw) - set(_ROW_KEYS)
        if unknown:
            raise ConfigError(f"{where}: unknown key(s) {sorted(unknown)}; allowed: {', '.join(_ROW_KEYS)}")
        name = str(raw["name"])
        if not name.replace("_", "").replace("-", "").isalnum() or name in seen:
            raise ConfigError(f"{where}: name {name!r} must be unique and made of letters, digits, '_' and '-'")
        seen.add(name)
        grid = _grid(raw["grid"], f"{where}.grid") if "grid" in raw else axes
        if [k for k, _ in grid] != [k for k, _ in axes]:
            raise ConfigError(
                f"{where}.grid must have the experiment's axes ({', '.join(k for k, _ in axes)}); "
                "only their values may differ"
            )
        rows.append(
            Row(
                name=name,
                label=str(raw.get("label", name)),
                overrides=common + _overrides(raw.get("set"), f"{where}.set"),
                grid=grid,
                paper=_paper(raw.get("paper"), f"{where}.paper", grid[0][1]),
            )
        )
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
    )
    for row in exp.rows:
        sweep_spec(exp, row)  # a typo in any row fails here, before anything runs
    return exp


def sweep_args(exp: Experiment, row: Row, layout: str = "auto") -> list[str]:
    """The tgrf-sweep arguments of one row (without --out / --resume)."""
    args = [exp.config] if exp.config else []
    for key, values in row.grid:
        args += ["--grid", f"{key}={','.join(str(v) for v in values)}"]
    args += ["--seeds", str(exp.seeds)]
    for item in row.overrides:
        args += ["--set", item]
    # auto: on CPUs the runs of a row train fastest one after another (each as tgrf-train trains it); elsewhere
    # batched
    return args + ["--layout", layout]


def sweep_spec(exp: Experiment, row: Row):
    """The validated SweepSpec of a row (raises ConfigError naming the row)."""
    from tgrf_jax.sweep import SweepSpec

    grid = [f"{k}={','.join(str(v) for v in values)}" for k, values in row.grid]
    try:
        return SweepSpec.create(exp.config, grid, exp.seeds, list(row.overrides))
    except ConfigError as e:
        raise ConfigError(f"experiment {exp.name!r}, row {row.name!r}: {e}") from None
