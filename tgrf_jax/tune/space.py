"""The search space of a tune: `--space FIELD=LO:HI[:log]` items, checked before anything compiles.

A searchable field is any traced field that holds one real number (`tgrf_jax.config.griddable_fields`, less
`reward.scheme`, the whole-number counts and the per-entry weight lists), so every member of a population shares
one compiled program and PBT's multiplicative steps stay within the field's kind. Each bound is checked by the
config's own range checks, so a space can never hand a member a value that `tgrf-train` would refuse.
"""

from __future__ import annotations

import dataclasses
import difflib
import math

import numpy as np

from tgrf_jax.config import ConfigError, TrainConfig, config_field, config_fields, griddable_fields
from tgrf_jax.fields import set_dotted

__all__ = ["SearchDim", "draw_values", "hparams_path", "parse_space", "searchable_fields"]


@dataclasses.dataclass(frozen=True)
class SearchDim:
    """One searched field: its dotted name, bounds and scale (log: sampled and perturbed multiplicatively)."""

    name: str
    low: float
    high: float
    log: bool = False

    def spec(self) -> str:
        return f"{self.name}={self.low!r}:{self.high!r}" + (":log" if self.log else "")  # exact round trip


def _unsearchable_reason(name: str) -> str | None:
    """Why a griddable field cannot be searched, or None when it can."""
    if name == "reward.scheme":
        return "a scheme is a set of reward values, not one number"
    field = config_field(name)
    if field.metadata.get("whole"):
        return (
            "it is a whole-number count, which PBT's x0.8 / x1.25 steps would not keep whole; "
            f"train its values as a grid instead (tgrf-sweep --grid {name}=V1,V2,...)"
        )
    if str(field.type).startswith("tuple"):
        return "it holds one weight per entry of a list, not one number; set it per run with --set"
    return None


def searchable_fields() -> list[str]:
    """Dotted names that `--space` accepts: the traced fields that hold one real number."""
    return [name for name in griddable_fields() if _unsearchable_reason(name) is None]


def hparams_path(name: str) -> tuple[str, ...]:
    """Attribute path of a searchable field inside the trainer's `HParams` pytree.

    PPO coefficients are top-level leaves, env fields live in `hparams.env`, reward fields in
    `hparams.env.reward` (`tgrf_jax.train.ppo.HParams`, `tgrf_jax.env.types.EnvParams`)."""
    section, field = name.split(".", 1)
    return {"ppo": (field,), "env": ("env", field), "reward": ("env", "reward", field)}[section]


def _bound(text: str, item: str, which: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise ConfigError(f"--space {item!r}: {which} bound {text!r} is not a number") from None
    if not math.isfinite(value):
        raise ConfigError(f"--space {item!r}: {which} bound must be finite, got {text!r}")
    return value


def _check_in_config(dim: SearchDim, item: str, base: dict) -> None:
    """Both bounds through the config's own checks (range, relations with the base config's other fields)."""
    for value in (dim.low, dim.high):
        try:
            TrainConfig.from_dict(set_dotted(base, dim.name, value))
        except ConfigError as e:
            raise ConfigError(f"--space {item!r}: {e}") from None


def parse_space(items: list[str], base: dict | None = None) -> tuple[SearchDim, ...]:
    """Parse `FIELD=LO:HI[:log]` items into search dimensions; raises ConfigError naming the item."""
    if not items:
        raise ConfigError("--space: give at least one FIELD=LO:HI[:log], e.g. --space reward.h_disc=0.5:5:log")
    base = {} if base is None else base
    searchable, known = searchable_fields(), config_fields()
    dims: list[SearchDim] = []
    for item in items:
        if "=" not in item:
            raise ConfigError(f"--space {item!r} must look like FIELD=LO:HI or FIELD=LO:HI:log")
        name, raw = (part.strip() for part in item.split("=", 1))
        if name not in searchable:
            if name in known or name == "reward.scheme":
                why = _unsearchable_reason(name) or (
                    "it is not a traced number, so members with different values cannot share one program"
                )
                raise ConfigError(f"--space {name}: cannot be searched: {why}; searchable: {', '.join(searchable)}")
            close = difflib.get_close_matches(name, known, n=1)
            hint = f" (did you mean {close[0]!r}?)" if close else ""
            raise ConfigError(f"--space {name}: unknown config key{hint}; searchable: {', '.join(searchable)}")
        if any(d.name == name for d in dims):
            raise ConfigError(f"--space {name} is given twice")
        parts = raw.split(":")
        if len(parts) not in (2, 3) or (len(parts) == 3 and parts[2].strip() != "log"):
            raise ConfigError(f"--space {item!r}: expected LO:HI or LO:HI:log")
        low, high = _bound(parts[0], item, "lower"), _bound(parts[1], item, "upper")
        if low >= high:
            raise ConfigError(f"--space {item!r}: the lower bound must be below the upper one ({low:g} >= {high:g})")
        log = len(parts) == 3
        if log and low <= 0.0:
            raise ConfigError(f"--space {item!r}: a log range needs a positive lower bound (got {low:g})")
        dim = SearchDim(name, low, high, log)
        _check_in_config(dim, item, base)
        dims.append(dim)
    return tuple(dims)


def draw_values(dims: tuple[SearchDim, ...], count: int, seed: int) -> np.ndarray:
    """(count, D) float32 values drawn uniformly within each dimension's bounds (log-uniformly on a log scale) from
    `seed`: a tune's starting members, and a random search's points (the same seed gives the same draws)."""
    u = np.random.default_rng(seed).uniform(size=(count, len(dims)))
    values = np.empty_like(u)
    for j, d in enumerate(dims):
        if d.log:
            values[:, j] = np.exp(np.log(d.low) + u[:, j] * (np.log(d.high) - np.log(d.low)))
        else:
            values[:, j] = d.low + u[:, j] * (d.high - d.low)
    return values.astype(np.float32)
