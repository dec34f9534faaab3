"""A sweep's grid and run list: `--grid section.field=v1,v2,...` axes x seeds, validated before anything compiles.

The Cartesian product of the grid values (or, with paired axes, their i-th values together: explicit points such as
random-search draws) times the seeds is a batch of G runs, ordered point-major (point, seed).
Only traced fields (`tgrf_jax.config.griddable_fields`) can be gridded, so all G runs share one compiled program;
run i is exactly the tgrf-train run of its own config (the base config with the grid values and `run.seed`).
"""

from __future__ import annotations

import dataclasses
import difflib
import functools
import itertools
import math
import pathlib

from tgrf_jax.config import ConfigError, TrainConfig, config_fields, griddable_fields
from tgrf_jax.fields import apply_overrides, load_yaml, parse_scalar, set_dotted

SWEEP_FILE = "sweep.yaml"


@dataclasses.dataclass(frozen=True)
class GridAxis:
    name: str  # dotted config field, e.g. reward.h_disc
    values: tuple  # parsed values (YAML scalars: numbers, or scheme names)

    @property
    def short(self) -> str:
        return self.name.split(".", 1)[1]


def _with_values(base: dict, values: dict) -> dict:
    for dotted, value in values.items():
        base = set_dotted(base, dotted, value)
    return base


def parse_grid(items: list[str], base: dict | None = None, paired: bool = False) -> tuple[GridAxis, ...]:
    """Parse `--grid section.field=v1,v2,...` items; validate names (griddable) and every value (the config's own
    range checks against `base`) before anything is compiled. Raises ConfigError naming the field. `paired` axes
    may repeat a value (a point is the i-th value of every axis; `check_paired` refuses repeated points)."""
    base = {} if base is None else base
    griddable, known = griddable_fields(), config_fields()
    axes: list[GridAxis] = []
    for item in items:
        if "=" not in item:
            raise ConfigError(f"--grid {item!r} must look like section.field=v1,v2,... (e.g. reward.h_disc=0.5,1.0)")
        name, raw = item.split("=", 1)
        name = name.strip()
        if name == "run.seed":
            raise ConfigError(
                f"--grid {item!r}: seeds are not a grid axis; give them with --seeds N (run.seed, "
                "run.seed + 1, ...) or --seeds S1,S2,..."
            )
        if name not in griddable:
            listing = ", ".join(griddable)
            if name in known:
                raise ConfigError(
                    f"--grid {name}: cannot be gridded: it is a static setting (array shapes or code paths), so runs "
                    f"with different values cannot share one compiled program; run one sweep per value instead. "
                    f"Griddable (traced) fields: {listing}"
                )
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
                cfg = TrainConfig.from_dict(_with_values(base, {name: parse_scalar(raw_value)}))
            except ConfigError as e:
                raise ConfigError(f"--grid {name}={raw_value.strip()}: {e}") from None
            canon.append(getattr(getattr(cfg, section), field))  # as the config stores it (1 -> 1.0)
        dups = sorted({str(v) for v in canon if canon.count(v) > 1})
        if dups and not paired:
            raise ConfigError(f"--grid {name}: repeated value(s) {', '.join(dups)}")
        axes.append(GridAxis(name, tuple(canon)))
    return tuple(axes)


# every run is a directory and a config checked before anything runs; beyond this a sweep is a typo
MAX_RUNS = 1_000


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
        raise ConfigError(f"--seeds {text!r} must be a count (e.g. 3) or a comma-separated list of seeds (e.g. 0,5,7)")
    if "," in text:
        seeds = numbers
    else:
        if numbers[0] < 1:
            raise ConfigError(f"--seeds {text}: the number of seeds must be >= 1 (a single seed s: --seeds s,)")
        if numbers[0] > MAX_RUNS:
            raise ConfigError(f"--seeds {text}: too many seeds; allowed: 1 .. {MAX_RUNS:,}")
        seeds = tuple(base_seed + i for i in range(numbers[0]))
    if len(seeds) > MAX_RUNS:
        raise ConfigError(f"--seeds: {len(seeds):,} seeds are too many; allowed: 1 .. {MAX_RUNS:,}")
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


def check_paired(axes: tuple[GridAxis, ...]) -> None:
    """Paired axes (`--paired`) give one point per index: every axis needs as many values, and no point twice."""
    if not axes:
        raise ConfigError("--paired pairs the values of --grid axes: give at least one --grid")
    counts = {a.name: len(a.values) for a in axes}
    if len(set(counts.values())) > 1:
        listed = ", ".join(f"{name} has {n}" for name, n in counts.items())
        raise ConfigError(f"--paired: every --grid axis needs the same number of values ({listed})")
    points = list(zip(*[a.values for a in axes]))
    repeated = next((p for i, p in enumerate(points) if p in points[:i]), None)
    if repeated is not None:
        shown = ", ".join(f"{a.short}={_fmt_value(v)}" for a, v in zip(axes, repeated))
        raise ConfigError(f"--paired: the point {shown} is given twice")


# batched: each device trains its share of the runs as one vmapped program (the runs of a device step together);
# sequential: the runs take turns, each through tgrf-train's own program with its env shards on the devices.
LAYOUTS = ("batched", "sequential")


def check_layout(layout, name: str = "--layout") -> str:
    if layout not in LAYOUTS:
        raise ConfigError(f"{name} = {layout!r}: allowed {', '.join(LAYOUTS)}")
    return layout


@dataclasses.dataclass(frozen=True)
class SweepSpec:
    """A base config (resolved dict), grid axes and seeds. Runs are ordered point-major: (point, seed)."""

    base: dict
    axes: tuple[GridAxis, ...]
    seeds: tuple[int, ...]
    layout: str = "batched"  # how the runs share the devices: one of LAYOUTS
    paired: bool = False  # points: the axes' i-th values together (explicit points) instead of their product

    @classmethod
    def create(
        cls,
        config_path=None,
        grid: list[str] = (),
        seeds: str | int | None = None,
        overrides: list[str] = (),
        layout: str = "batched",
        paired: bool = False,
    ) -> SweepSpec:
        check_layout(layout)
        data = load_yaml(config_path) if config_path else {}
        base = TrainConfig.from_dict(apply_overrides(data, list(overrides))).to_dict()
        axes = parse_grid(list(grid), base, paired)
        if paired:
            check_paired(axes)
        spec = cls(base, axes, parse_seeds(seeds, base["run"]["seed"]), layout, paired)
        points = len(axes[0].values) if paired else math.prod(len(a.values) for a in axes)
        count = len(spec.seeds) * points
        if count > MAX_RUNS:
            raise ConfigError(f"the grid and seeds give {count:,} runs; allowed: at most {MAX_RUNS:,} per sweep")
        spec.runs()  # validates every run config (combinations included)
        return spec

    @property
    def base_config(self) -> TrainConfig:
        return TrainConfig.from_dict(self.base)

    def points(self) -> list[dict]:
        combine = zip if self.paired else itertools.product
        return [dict(zip([a.name for a in self.axes], combo)) for combo in combine(*[a.values for a in self.axes])]

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
            "layout": self.layout,
            **({"paired": True} if self.paired else {}),
            "runs": [{"name": r.name, "point": r.point, "seed": r.seed, "values": dict(r.values)} for r in self.runs()],
            "base": self.base,
        }

    @classmethod
    def from_dict(cls, data: dict) -> SweepSpec:
        try:
            base = TrainConfig.from_dict(data["base"]).to_dict()
            axes = tuple(GridAxis(k, tuple(v)) for k, v in (data.get("grid") or {}).items())
            # sweeps written before the layout was recorded ran batched
            layout = check_layout(data.get("layout", "batched"), f"{SWEEP_FILE}: layout")
            paired = data.get("paired", False)
            if not isinstance(paired, bool):
                raise TypeError(f"paired = {paired!r} is not true or false")
            return cls(base, axes, tuple(int(s) for s in data["seeds"]), layout, paired)
        except (KeyError, TypeError) as e:
            raise ConfigError(f"{SWEEP_FILE} is malformed: {e!r}") from None

    def describe(self) -> str:
        runs = self.runs()
        kind = "paired point(s)" if self.paired else "grid point(s)"
        lines = [f"{len(self.points())} {kind} x {len(self.seeds)} seed(s) = {len(runs)} runs, {self.layout} layout"]
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
    data = load_yaml(path)
    try:
        spec = SweepSpec.from_dict(data)
    except ConfigError as e:
        raise ConfigError(f"{str(path)!r}: {e}") from None
    recorded = data.get("runs")
    names = [r.name for r in spec.runs()]
    if not isinstance(recorded, list) or [r.get("name") if isinstance(r, dict) else r for r in recorded] != names:
        # its checkpoints, run directories and results belong to the runs it was written with
        raise ConfigError(
            f"{str(path)!r} was edited: its grid and seeds give {len(names)} runs ({names[0]}, ...) "
            f"that are not the runs it records; restore it, or start a new sweep with --out"
        )
    return spec
