"""The scenario registry: every scenario's name, kind and samplers, and the only list of scenario names.

A scenario is a `Scenario` record of pure samplers (how an episode's robot, humans and obstacles are drawn);
`register(name, scenario, kind=...)` adds one. The built-in scenarios are registered, in this order, by
`tgrf_jax.env.scenarios` (its `__init__`, one line each), which `import tgrf_jax` always runs; everything else
reads the registry: `tgrf_jax.config` takes the choices of `env.scenario` and `env.mix_scenarios` and the default
mix from `names(...)`, and an env builds its table of samplers from `get(name)`.

This module sits at the bottom of the import layers (pyproject's `[tool.importlinter]`), below `tgrf_jax.config`,
which must read the names but may not import the env; it is plain Python and imports nothing of the package at
run time (the env types below are annotations only).
The samplers it holds are the env's (`tgrf_jax.env.scenarios` explains their shapes and rules).
"""

from __future__ import annotations

import dataclasses
import re
from collections.abc import Callable, Iterator, Sequence
from typing import TYPE_CHECKING, Any, Literal

if TYPE_CHECKING:  # annotations only (pyproject: import-linter skips type-checking imports)
    from tgrf_jax.env.obstacles import Obstacles
    from tgrf_jax.env.types import EnvParams, Humans, Robot

Points = Any  # a float32 array of points (..., 2)

Kind = Literal["crowd", "obstacle", "replay"]
KINDS: tuple[str, ...] = ("crowd", "obstacle", "replay")
_NAME = re.compile(r"[a-z][a-z0-9_]*")


@dataclasses.dataclass(frozen=True)
class Scenario:
    """One scenario's samplers: pure functions of a key, the traced `EnvParams` and static Python ints (`n`,
    `tries`: shapes). Each human sampler proposes `tries` candidates; the env picks the first one that keeps
    every agent's and obstacle's clearance (rejection sampling, `tgrf_jax.env.scenarios.sampling.choose`).

    robot(key, params, tries) -> Robot: the robot's start and goal (heading pi/2, at rest).
    spawn(key, params, layout, n, tries) -> (pos, goal), each (n, tries, 2): human i's start and goal candidates.
    new_goal(key, params, layout, humans, tries) -> goals (N, tries, 2): a goal change of each human.
    respawn(key, params, layout, pos, goal, t, tries) -> (pos, goal), each (tries, 2): a fresh human in place of
        one that reached its goal (`pos`, `goal`: the arrived human's; `t`: the episode's time in seconds, for
        flows that change over an episode, such as the doorway's waves).
    layout(key, params, robot, tries) -> (vertices (S, V, 2), num_vertices (S,)), or None: an open space. The
        episode's obstacles in the scenario's S = config.SCENARIO_OBSTACLE_SLOTS slots of up to V =
        config.SCENARIO_OBSTACLE_VERTICES vertices (unused slots: 0 vertices).
    speed: factor on the humans' preferred speeds (robot_overtaking: 0.5).

    `layout` in the human samplers is the episode's `Obstacles` (the scenario's slots first, then env.obstacles):
    the obstacle scenarios read the geometry they drew (a corridor's width, a door's place) from it; open-space
    samplers ignore it (`tgrf_jax.env.scenarios.open_space.open_space` adapts a sampler without it).

    How a scenario supplies the humans' paths: a human's path is its destination, `Humans.goal`, which only
    `spawn`, `new_goal` and `respawn` set, and the point it heads for each step, the goal itself unless a
    `tgrf_jax.env.humans.Steering` says otherwise: routing around obstacles (`tgrf_jax.env.routing.aim`) and
    replayed recordings (kind 'replay', `tgrf_jax.env.replay`, which also draw their own episodes) do
    (docs/design.md, "Scenarios").
    """

    robot: Callable[[Any, EnvParams, int], Robot]
    spawn: Callable[[Any, EnvParams, Obstacles, int, int], tuple[Points, Points]]
    new_goal: Callable[[Any, EnvParams, Obstacles, Humans, int], Points]
    respawn: Callable[[Any, EnvParams, Obstacles, Points, Points, Any, int], tuple[Points, Points]]
    layout: Callable[[Any, EnvParams, Robot, int], tuple[Points, Any]] | None = None
    speed: float = 1.0


@dataclasses.dataclass(frozen=True)
class _Entry:
    scenario: Scenario
    kind: str


_REGISTRY: dict[str, _Entry] = {}


def register(name: str, scenario: Scenario, *, kind: Kind) -> Scenario:
    """Add a scenario under `name` (lower-case letters, digits and '_'); returns it.

    kind 'crowd': an open space (no `layout`); the default mix (`env.scenario: mix` without `env.mix_scenarios`)
    draws among every crowd scenario. kind 'obstacle': draws obstacles (a `layout`); an env playing one carries
    the scenario obstacle slots. kind 'replay': episodes played from recorded pedestrians (`env.scenario: replay`,
    `tgrf_jax.env.replay`), which the env draws itself from the recordings it loads; the record's samplers stand in
    for it only where a mix needs every scenario's (their draws are discarded), and the default mix leaves it
    out, as it needs recordings. Register at import time, before any env is built: an env's table of samplers is
    built once, from the registry as it is then. Raises ValueError for a taken or malformed name, a wrong record
    or a kind that does not match the record.
    """
    if not isinstance(name, str) or not _NAME.fullmatch(name) or name == "mix":
        raise ValueError(f"scenario name {name!r} must be lower-case letters, digits and '_' (and not 'mix')")
    if name in _REGISTRY:
        raise ValueError(f"scenario {name!r} is already registered")
    if not isinstance(scenario, Scenario):
        raise ValueError(f"scenario {name!r} must be a Scenario record, not {type(scenario).__name__}")
    if kind not in KINDS:
        raise ValueError(f"scenario {name!r}: kind {kind!r} is not one of {', '.join(map(repr, KINDS))}")
    if (kind == "obstacle") != (scenario.layout is not None):
        raise ValueError(f"scenario {name!r}: kind 'obstacle' is a scenario with a layout, 'crowd' one without")
    _REGISTRY[name] = _Entry(scenario, kind)
    return scenario


def unregister(name: str) -> None:
    """Remove a registered scenario (tests and notebooks that register their own)."""
    del _REGISTRY[name]


def get(name: str) -> Scenario:
    """The scenario registered under `name` (KeyError if none)."""
    return _REGISTRY[name].scenario


def kind_of(name: str) -> str:
    """The kind of a registered scenario: 'crowd', 'obstacle' or 'replay'."""
    return _REGISTRY[name].kind


def names(kind: str | None = None) -> tuple[str, ...]:
    """The registered scenario names (of one kind), in registration order."""
    return tuple(n for n, e in _REGISTRY.items() if kind is None or e.kind == kind)


class Names(Sequence):
    """A live view of `names()` plus fixed `extra` names, as a config field's `choices`: a scenario registered
    after the config module was imported is allowed too."""

    def __init__(self, *extra: str):
        self.extra = extra

    def _items(self) -> tuple[str, ...]:
        return names() + self.extra

    def __getitem__(self, i):
        return self._items()[i]

    def __len__(self) -> int:
        return len(self._items())

    def __iter__(self) -> Iterator[str]:
        return iter(self._items())

    def __contains__(self, value) -> bool:
        return value in self._items()

    def __repr__(self) -> str:
        return f"Names{self._items()!r}"
