"""What an episode draws from its env's scenarios: the scenario itself (a mix), the robot, the obstacle layout,
the crowd's spawns, and during the episode the humans' goal changes and respawns.

`ScenarioTable` is an env's scenarios, built once per env from the registry (`CrowdNavEnv.__init__`). An episode's
scenario is an index into the table, drawn once at reset (`env.scenario: mix`; a fixed scenario: 0), kept in
`EnvState.scenario` and handed as it is to every sampler call, which selects the scenario's sampler with
`lax.switch` (a fixed scenario calls its own directly). Every scenario's candidates go through the same rejection
sampling (`sampling.choose`), so every scenario obeys the same spacing rules.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from tgrf_jax import scenario_registry as registry
from tgrf_jax.env import obstacles as obstacles_lib
from tgrf_jax.env.batching import cond_gathered
from tgrf_jax.env.obstacles import Obstacles
from tgrf_jax.env.scenarios import open_space
from tgrf_jax.env.scenarios.obstacle_layouts import slots
from tgrf_jax.env.scenarios.sampling import (
    choose,
    clearance,
    obstacle_margin,
    park,
    require_room,
    sample_attributes,
    uniform,
    with_obstacles,
)
from tgrf_jax.env.types import EnvParams, Humans, Robot
from tgrf_jax.scenario_registry import Scenario


class ScenarioTable(NamedTuple):
    """The scenarios of one configured env, in the order of `config.drawn_scenarios` (a fixed scenario: itself;
    a mix: `env.mix_scenarios` in the order of `env.scenario_weights`); an episode's scenario is an index into it."""

    names: tuple[str, ...]
    scenarios: tuple[Scenario, ...]

    @classmethod
    def of(cls, config) -> ScenarioTable:
        """The table of an `EnvConfig`, from the registry."""
        names = config.drawn_scenarios
        return cls(names, tuple(registry.get(name) for name in names))

    def draw(self, key, weights):
        """The episode's scenario: an index ~ Categorical(weights / sum(weights)) into the table (zero-weight
        scenarios are never drawn); a table of one scenario needs no draw."""
        if len(self.scenarios) == 1:
            return jnp.zeros((), jnp.int32)
        edges = jnp.cumsum(weights)
        u = uniform(key, ()) * edges[-1]
        return jnp.minimum(jnp.sum(edges <= u), weights.shape[0] - 1).astype(jnp.int32)

    def _call(self, field, index, *args, static=()):
        """Scenario `field`'s sampler on `args` plus the trailing `static` Python values (shapes: bound, not
        passed through the switch, which would trace them)."""
        fns = [getattr(s, field) for s in self.scenarios]
        if len(fns) == 1:
            return fns[0](*args, *static)
        return jax.lax.switch(index, [lambda *a, f=f: f(*a, *static) for f in fns], *args)

    def robot(self, key, params: EnvParams, index, tries: int) -> Robot:
        """The robot's start and goal."""
        return self._call("robot", index, key, params, static=(tries,))

    @property
    def draws_obstacles(self) -> bool:
        return any(s.layout is not None for s in self.scenarios)

    def layout(self, key, params: EnvParams, robot: Robot, index, tries: int):
        """The scenario's obstacle slots (vertices (S, V, 2), num_vertices (S,)); open spaces leave them empty."""
        empty = lambda key, params, robot, tries: slots()  # noqa: E731
        fns = [s.layout or empty for s in self.scenarios]
        if len(fns) == 1:
            return fns[0](key, params, robot, tries)
        return jax.lax.switch(index, [lambda *a, f=f: f(*a, tries) for f in fns], key, params, robot)

    def scale_speed(self, v_pref, index):
        """Preferred speeds times the scenario's speed factor."""
        speeds = [s.speed for s in self.scenarios]
        if speeds == [1.0]:
            return v_pref
        if len(speeds) == 1:
            return v_pref * speeds[0]
        return v_pref * jnp.asarray(speeds, jnp.float32)[index]


_CIRCLE_CROSSING = ScenarioTable(("circle_crossing",), (open_space.CIRCLE_CROSSING,))


def spawn_humans(
    key,
    params: EnvParams,
    robot: Robot,
    num_humans: int,
    tries: int,
    active=None,
    table: ScenarioTable | None = None,
    index=0,
    layout: Obstacles | None = None,
) -> Humans:
    """Place the active humans one at a time at the scenario's spawn candidates, each clear of the robot, of
    every human placed before (positions and goals) and of the obstacles; the inactive slots are parked.
    `active` (N,) bool defaults to all slots, `table` to circle crossing, `layout` to no obstacles."""
    table = table or _CIRCLE_CROSSING
    layout = obstacles_lib.empty() if layout is None else layout
    k_attr, k_cand = jax.random.split(key)
    radius, v_pref = sample_attributes(k_attr, params, (num_humans,))
    v_pref = table.scale_speed(v_pref, index)
    active = jnp.ones((num_humans,), bool) if active is None else active
    if num_humans == 0:
        empty = jnp.zeros((0, 2))
        return Humans(pos=empty, vel=empty, goal=empty, radius=radius, v_pref=v_pref, active=active)
    start, goal = table._call("spawn", index, k_cand, params, layout, static=(num_humans, tries))
    candidates = jnp.concatenate([start, goal], -1)  # (N, tries, 4): a start is chosen with its goal
    # room from the obstacles at both ends of each candidate's walk
    room = obstacle_margin(
        jnp.stack([start, goal]), jnp.broadcast_to(radius, (2, num_humans)), layout, params.spawn_clearance
    )
    room = None if room is None else jnp.min(room, axis=0)

    # Slot 0 of the "others" arrays is the robot; slots 1..N fill up with placed humans.
    others_pos = jnp.zeros((num_humans + 1, 2)).at[0].set(robot.pos)
    others_goal = jnp.zeros((num_humans + 1, 2)).at[0].set(robot.goal)
    others_radius = jnp.zeros(num_humans + 1).at[0].set(params.robot_radius).at[1:].set(radius)
    placed = jnp.zeros(num_humans + 1, bool).at[0].set(True)

    def place(carry, i):
        others_pos, others_goal, placed = carry
        margin = clearance(
            candidates[i, :, :2], radius[i], others_pos, others_goal, others_radius, placed, params.spawn_clearance
        )
        if room is not None:
            margin = require_room(margin, room[i], params.spawn_clearance)
        pick = choose(candidates[i], margin)
        carry = (
            others_pos.at[i + 1].set(pick[:2]),
            others_goal.at[i + 1].set(pick[2:]),
            placed.at[i + 1].set(active[i]),
        )
        return carry, None

    (others_pos, others_goal, _), _ = jax.lax.scan(place, (others_pos, others_goal, placed), jnp.arange(num_humans))
    return park(
        Humans(
            pos=others_pos[1:],
            vel=jnp.zeros((num_humans, 2)),
            goal=others_goal[1:],
            radius=radius,
            v_pref=v_pref,
            active=active,
        )
    )


def _others_excluding_self(humans: Humans, robot: Robot, params: EnvParams):
    """Every agent (humans, then the robot) with a (N, N+1) mask hiding each human from itself and the inactive
    slots from everyone."""
    n = humans.pos.shape[0]
    pos = jnp.concatenate([humans.pos, robot.pos[None]], 0)
    goal = jnp.concatenate([humans.goal, robot.goal[None]], 0)
    radius = jnp.concatenate([humans.radius, params.robot_radius[None]], 0)
    present = jnp.concatenate([humans.active, jnp.ones((1,), bool)])
    return pos, goal, radius, ~jnp.eye(n, n + 1, dtype=bool) & present[None, :]


def change_goals(
    key,
    humans: Humans,
    robot: Robot,
    params: EnvParams,
    step_count,
    tries: int,
    table: ScenarioTable | None = None,
    index=0,
    layout: Obstacles | None = None,
) -> Humans:
    """Every goal_change_interval seconds each active human switches, with goal_change_prob, to a new goal
    drawn by the scenario.

    The candidates are drawn only on the steps where changes fall due (one in 20 by default), also in a
    vmapped batch of environments, where only the environments that are due do the work (see `cond_gathered`).
    """
    table = table or _CIRCLE_CROSSING
    layout = obstacles_lib.empty() if layout is None else layout
    due = (step_count % params.goal_change_period) == 0
    return cond_gathered(
        due,
        lambda *args: _switch_goals(*args, tries, table),
        _unchanged,
        key,
        humans,
        robot,
        params,
        jnp.asarray(index, jnp.int32),
        layout,
    )


def _unchanged(key, humans: Humans, *rest) -> Humans:
    return humans


def _switch_goals(
    key, humans: Humans, robot: Robot, params: EnvParams, index, layout, tries: int, table: ScenarioTable
) -> Humans:
    """Each human switches, with goal_change_prob, to a new goal clear of the others and of the obstacles."""
    n = humans.pos.shape[0]
    k_coin, k_cand = jax.random.split(key)
    switch = (uniform(k_coin, (n,)) < params.goal_change_prob) & humans.active
    return _new_goals(k_cand, humans, robot, params, index, layout, switch, tries, table)


def _new_goals(key, humans: Humans, robot: Robot, params: EnvParams, index, layout, who, tries: int, table):
    """`humans` with the goals of `who` (N,) bool redrawn by the scenario, clear of the others and the obstacles."""
    candidates = table._call("new_goal", index, key, params, layout, humans, static=(tries,))
    margin = clearance(
        candidates, humans.radius, *_others_excluding_self(humans, robot, params), params.spawn_clearance
    )
    margin = with_obstacles(margin, candidates, humans.radius, layout, params.spawn_clearance)
    return humans.replace(goal=jnp.where(who[:, None], choose(candidates, margin), humans.goal))


def reassign_goals(
    key,
    humans: Humans,
    robot: Robot,
    params: EnvParams,
    who,
    tries: int,
    table: ScenarioTable,
    index,
    layout: Obstacles,
) -> Humans:
    """New goals, drawn by the scenario as a goal change draws them, for the humans `who` (N,) bool (a human that
    stays stuck). In a vmapped batch only the environments with such a human do the work (see `cond_gathered`)."""

    def redraw(key, humans, robot, params, index, layout, who):
        return _new_goals(key, humans, robot, params, index, layout, who, tries, table)

    def keep(key, humans, robot, params, index, layout, who):
        return humans

    index = jnp.asarray(index, jnp.int32)
    return cond_gathered(jnp.any(who), redraw, keep, key, humans, robot, params, index, layout, who)


def respawn_arrived(
    key,
    humans: Humans,
    robot: Robot,
    params: EnvParams,
    tries: int,
    table: ScenarioTable | None = None,
    index=0,
    layout: Obstacles | None = None,
    t=0.0,
) -> Humans:
    """A human within its own radius of its goal is replaced by a fresh one of the scenario (`random` keeps it
    where it is with a new goal); `t` is the episode's time in seconds, which the scenario's sampler may read.

    One arrival is served per step (the lowest index); another human arriving in the same step waits at its
    goal until the next one. Serving one instead of all N cuts the rejection-sampling work N-fold, and
    simultaneous arrivals are rare. In a vmapped batch only the environments with an arrival do the work
    (see `cond_gathered`).
    """
    table = table or _CIRCLE_CROSSING
    layout = obstacles_lib.empty() if layout is None else layout
    return cond_gathered(
        jnp.any(_arrived(humans)),
        lambda *args: _respawn_first(*args, tries, table),
        _unchanged,
        key,
        humans,
        robot,
        params,
        jnp.asarray(index, jnp.int32),
        layout,
        jnp.asarray(t, jnp.float32),
    )


def _arrived(humans: Humans):
    offset = humans.pos - humans.goal
    return (jnp.square(offset[:, 0]) + jnp.square(offset[:, 1]) < jnp.square(humans.radius)) & humans.active


def _respawn_first(
    key, humans: Humans, robot: Robot, params: EnvParams, index, layout, t, tries: int, table: ScenarioTable
) -> Humans:
    """Replace the lowest-indexed arrived human (if any) by a fresh one."""
    n = humans.pos.shape[0]
    k_attr, k_cand = jax.random.split(key)
    arrived = _arrived(humans)
    who = jnp.argmax(arrived)
    radius, v_pref = sample_attributes(k_attr, params)
    v_pref = table.scale_speed(v_pref, index)
    start, goal = table._call(
        "respawn", index, k_cand, params, layout, humans.pos[who], humans.goal[who], t, static=(tries,)
    )
    pos, goals, radii, valid = _others_excluding_self(humans, robot, params)
    margin = clearance(start, radius, pos, goals, radii, valid[who], params.spawn_clearance)
    margin = with_obstacles(margin, start, radius, layout, params.spawn_clearance)
    margin = with_obstacles(margin, goal, radius, layout, params.spawn_clearance)
    pick = choose(jnp.concatenate([start, goal], -1), margin)
    replace = arrived & (jnp.arange(n) == who)

    def put(new, old):
        return jnp.where(replace.reshape((n,) + (1,) * (old.ndim - 1)), new, old)

    return Humans(
        pos=put(pick[:2], humans.pos),
        vel=put(jnp.zeros(2), humans.vel),
        goal=put(pick[2:], humans.goal),
        radius=put(radius, humans.radius),
        v_pref=put(v_pref, humans.v_pref),
        active=humans.active,
    )
