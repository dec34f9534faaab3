"""`TuneSpec`: a population-based tune as data (base config, search space, population, objective, schedule),
validated before anything compiles, and the members it starts from."""

from __future__ import annotations

import dataclasses
import math
import pathlib

import numpy as np
import yaml

from tgrf_jax.config import ConfigError, TrainConfig
from tgrf_jax.fields import apply_overrides, load_yaml, set_dotted
from tgrf_jax.sweep.grid import LAYOUTS, RunSpec
from tgrf_jax.tune.objective import parse_objective
from tgrf_jax.tune.pbt import num_replaced
from tgrf_jax.tune.space import SearchDim, draw_values, parse_space

TUNE_FILE = "tune.yaml"
MAX_POPULATION = 1_000


@dataclasses.dataclass(frozen=True)
class TuneSpec:
    base: dict  # resolved base config
    dims: tuple[SearchDim, ...]
    population: int
    objective: str
    interval: int  # updates between exploit-and-explore steps
    fraction: float = 0.25  # share of the population replaced (and of donors) per step
    resample_prob: float = 0.25  # chance that a copied value is drawn afresh instead of perturbed
    objective_episodes: int = 100  # fixed test episodes per member and step
    final_episodes: int = 500  # the best member's separate, larger test
    layout: str = "batched"  # one vmapped program for the population, or the members in turn (faster on CPUs)

    @classmethod
    def create(
        cls,
        config_path=None,
        space: list[str] = (),
        population: int = 8,
        objective: str = "success - 0.5 * collision",
        interval: int | None = None,
        overrides: list[str] = (),
        **options,
    ) -> TuneSpec:
        data = load_yaml(config_path) if config_path else {}
        base = TrainConfig.from_dict(apply_overrides(data, list(overrides))).to_dict()
        dims = parse_space(list(space), base)
        num_updates = TrainConfig.from_dict(base).ppo.num_updates
        if interval is None:
            interval = max(1, num_updates // 10)
        spec = cls(base, dims, population, objective, interval, **options)
        spec.check(num_updates)
        return spec

    def check(self, num_updates: int) -> None:
        """Every setting against what the tune can do; raises ConfigError naming the option."""
        parse_objective(self.objective)
        if not isinstance(self.population, int) or not 2 <= self.population <= MAX_POPULATION:
            raise ConfigError(f"--population {self.population}: allowed 2 .. {MAX_POPULATION:,}")
        if not 0.0 < self.fraction <= 0.5:
            raise ConfigError(f"--fraction {self.fraction}: allowed (0, 0.5] (the worst and the best share)")
        if math.floor(self.population * self.fraction + 1e-9) < 1:
            raise ConfigError(
                f"--population {self.population} with --fraction {self.fraction} replaces no member; "
                f"use a population of at least {math.ceil(1 / self.fraction)} or a larger fraction"
            )
        if not 0.0 <= self.resample_prob <= 1.0:
            raise ConfigError(f"--resample {self.resample_prob}: allowed [0, 1]")
        if not isinstance(self.interval, int) or not 1 <= self.interval < num_updates:
            raise ConfigError(
                f"--interval {self.interval}: allowed 1 .. {num_updates - 1} (updates between exploit steps; "
                f"the run has {num_updates} updates)"
            )
        if self.layout not in LAYOUTS:
            raise ConfigError(f"--layout {self.layout!r}: allowed {', '.join(LAYOUTS)}")
        for name in ("objective_episodes", "final_episodes"):
            if int(getattr(self, name)) < 1:
                raise ConfigError(f"--{name.replace('_', '-')} {getattr(self, name)}: must be >= 1")

    @property
    def base_config(self) -> TrainConfig:
        return TrainConfig.from_dict(self.base)

    @property
    def replaced(self) -> int:
        return num_replaced(self.population, self.fraction)

    def initial_values(self) -> np.ndarray:
        """(P, D) starting values: uniform (log-uniform on a log scale) within the bounds, from the run's seed."""
        return draw_values(self.dims, self.population, self.base["run"]["seed"])

    def members(self) -> tuple[RunSpec, ...]:
        """One run per member: the base config with its starting values and its own seed (run.seed + i)."""
        seed0, name0 = self.base["run"]["seed"], self.base["run"]["name"]
        out = []
        for i, row in enumerate(self.initial_values()):
            values = {d.name: float(v) for d, v in zip(self.dims, row)}
            data = self.base
            for name, value in {**values, "run.seed": seed0 + i, "run.name": f"{name0}_m{i:03d}"}.items():
                data = set_dotted(data, name, value)
            try:
                config = TrainConfig.from_dict(data)
            except ConfigError as e:
                raise ConfigError(f"member {i}: {e}") from None
            out.append(RunSpec(i, i, seed0 + i, values, f"m{i:03d}", config))
        return tuple(out)

    def evaluation_runs(self) -> tuple[RunSpec, ...]:
        """What every member is scored on: the base config's env (the same fixed episodes for all)."""
        base = self.base_config
        return tuple(dataclasses.replace(m, config=base) for m in self.members())

    def to_dict(self) -> dict:
        return {
            "space": [d.spec() for d in self.dims],
            "population": self.population,
            "objective": self.objective,
            "interval": self.interval,
            "fraction": self.fraction,
            "resample_prob": self.resample_prob,
            "objective_episodes": self.objective_episodes,
            "final_episodes": self.final_episodes,
            "layout": self.layout,
            "members": [{"name": m.name, "seed": m.seed, "values": m.values} for m in self.members()],
            "base": self.base,
        }

    @classmethod
    def from_dict(cls, data: dict) -> TuneSpec:
        try:
            base = TrainConfig.from_dict(data["base"]).to_dict()
            dims = parse_space(list(data["space"]), base)
            options = {k: data[k] for k in ("fraction", "resample_prob", "objective_episodes", "final_episodes")}
            options["layout"] = str(data.get("layout", "batched"))  # tunes written before it was recorded: batched
            spec = cls(base, dims, int(data["population"]), str(data["objective"]), int(data["interval"]), **options)
        except (KeyError, TypeError, ValueError) as e:
            raise ConfigError(f"{TUNE_FILE} is malformed: {e!r}") from None
        spec.check(spec.base_config.ppo.num_updates)
        return spec

    def describe(self, layout: str | None = None) -> str:
        """The plan; `layout`: the one to name instead of the spec's (a plan's 'auto', a resume's switch)."""
        lines = [
            f"population {self.population}, exploit every {self.interval} updates (worst {self.replaced} take the "
            f"best {self.replaced}'s weights and hyper-parameters), objective: {self.objective}, "
            f"{self.objective_episodes} test episodes per member, {layout or self.layout} layout"
        ]
        lines += [f"  search {d.spec()}" for d in self.dims]
        for m in self.members():
            shown = ", ".join(f"{k.split('.', 1)[1]}={v:.4g}" for k, v in m.values.items())
            lines.append(f"  member {m.name}: seed {m.seed}, {shown}")
        return "\n".join(lines)


def load_tune(tune_dir) -> TuneSpec:
    path = pathlib.Path(tune_dir) / TUNE_FILE
    if not path.is_file():
        raise ConfigError(f"{str(path)!r} does not exist: {str(tune_dir)!r} is not a tgrf-tune directory")
    try:
        return TuneSpec.from_dict(yaml.safe_load(path.read_text()))
    except ConfigError as e:
        raise ConfigError(f"{str(path)!r}: {e}") from None
