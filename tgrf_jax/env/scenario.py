"""Scenarios: how the robot's start and goal and the humans' spawns, goals, goal changes and respawns are drawn.

`circle_crossing` is the paper's (the reference's `crowd_sim_pred_real_gst.py` and its parents;
docs/reference.md); the others follow the scenario names of Francis et al., "Principles and Guidelines for
Evaluating Social Robot Navigation Algorithms" (ACM THRI 2025), and CrowdNav's layouts (docs/scenarios.md).
Each scenario is a `Scenario` of pure candidate samplers; the shared machinery here picks among the candidates
(rejection sampling), so every scenario obeys the same spacing rules. With `env.scenario: mix` an episode's
scenario is drawn at reset, stored in the state, and its samplers are selected with `lax.switch`.

Rejection sampling is bounded: each draw proposes `tries` candidates at once and takes the first valid one;
when none is valid (a very crowded scene), it takes the candidate with the most clearance, so shapes and run
time never depend on luck.
"""

from __future__ import annotations

from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp

from tgrf_jax.config import SCENARIOS
from tgrf_jax.env.batching import cond_gathered
from tgrf_jax.env.geometry import norm
from tgrf_jax.env.types import EnvParams, Humans, Robot

def _mix32(x):
    """murmur3's 32-bit finaliser: a cheap bijective integer hash with full avalanche."""
    x = x ^ (x >> 16)
    x = x * jnp.uint32(0x85EBCA6B)
    x = x ^ (x >> 13)
    x = x * jnp.uint32(0xC2B2AE35)
    return x ^ (x >> 16)


def uniform(key, shape, minval=0.0, maxval=1.0):
    """Uniform floats in [minval, maxval) from one key, drawn by hashing a counter.

    Scene sampling needs thousands of numbers per step and XLA:CPU's threefry costs ~13 ns per number, more
    than the whole crowd simulation; here threefry draws only a 64-bit seed per call and a counter hash
    expands it. Still a pure function of the key, so runs stay reproducible.
    """
    seed = jax.random.bits(key, (2,), jnp.uint32)
    size = 1
    for d in shape:
        size *= d
    counter = jnp.arange(size, dtype=jnp.uint32).reshape(shape)
    bits = _mix32(_mix32(counter * jnp.uint32(0x9E3779B9) + seed[0]) ^ seed[1])
    unit = (bits >> 8).astype(jnp.float32) * jnp.float32(2.0**-24)
    return minval + unit * (maxval - minval)


def sample_robot(key, params: EnvParams, tries: int) -> Robot:
    """Start and goal ~ U(-a, a)^2 each, at least `min_start_goal_dist` apart."""
    pts = uniform(key, (tries, 2, 2), minval=-params.arena_size, maxval=params.arena_size)
    dist = norm(pts[:, 0] - pts[:, 1])
    start_goal = choose(pts.reshape(tries, 4), dist - params.min_start_goal_dist).reshape(2, 2)
    zero = jnp.zeros((), jnp.float32)
    return Robot(
        pos=start_goal[0], vel=jnp.zeros(2), goal=start_goal[1], heading=zero + jnp.pi / 2, speed=zero
    )


def sample_attributes(key, params: EnvParams, shape=()):
    """Radius and preferred speed of newly spawned humans."""
    k_r, k_v = jax.random.split(key)
    radius = uniform(k_r, shape, minval=params.human_radius_min, maxval=params.human_radius_max)
    v_pref = uniform(k_v, shape, minval=params.human_v_pref_min, maxval=params.human_v_pref_max)
    return radius, v_pref


def circle_candidates(key, params: EnvParams, shape):
    """Spawn points on the crossing circle with one-sided noise in [0, noise) per axis, as the reference."""
    k_a, k_n = jax.random.split(key)
    angle = uniform(k_a, shape, maxval=2 * jnp.pi)
    noise = uniform(k_n, shape + (2,)) * params.spawn_noise
    return params.circle_radius * jnp.stack([jnp.cos(angle), jnp.sin(angle)], -1) + noise


def goal_candidates(key, params: EnvParams, v_pref, shape):
    """New goals on the circle with symmetric noise (U - 0.5) * v_pref per axis (goal changes)."""
    k_a, k_n = jax.random.split(key)
    angle = uniform(k_a, shape, maxval=2 * jnp.pi)
    noise = (uniform(k_n, shape + (2,)) - 0.5) * v_pref[..., None, None]
    return params.circle_radius * jnp.stack([jnp.cos(angle), jnp.sin(angle)], -1) + noise


def _pair_sq_dist(a, b):
    """Squared distances between points a (..., T, 2) and b (..., M, 2) -> (..., T, M).

    x and y are handled as separate arrays: a reduction over a trailing axis of size 2 vectorises badly on CPU.
    """
    dx = a[..., :, None, 0] - b[..., None, :, 0]
    dy = a[..., :, None, 1] - b[..., None, :, 1]
    return dx * dx + dy * dy


def clearance(candidates, own_radius, others_pos, others_goal, others_radius, others_valid, gap):
    """Smallest squared-distance margin between candidates (..., T, 2) and other agents' positions and goals.

    A candidate is acceptable where the margin is >= 0, i.e. it keeps r_self + r_other + gap from every other
    agent's position and goal (the reference's spawn rule); larger margins mean more room. `others_*` have
    shape (..., M, ...). Squares avoid a square root per pair in this hot loop.
    """
    need = own_radius[..., None, None] + others_radius[..., None, :] + gap  # (..., 1, M)
    sq = jnp.minimum(_pair_sq_dist(candidates, others_pos), _pair_sq_dist(candidates, others_goal))
    margin = jnp.where(others_valid[..., None, :], sq - need * need, jnp.inf)
    return jnp.min(margin, axis=-1, initial=jnp.inf)


# Inactive slots wait here, 10 m apart: far beyond any sensor range or arena, and at finite coordinates.
PARKING = 1.0e4


def active_slots(key, params: EnvParams, num_humans: int):
    """The episode's active mask (N,): the first k slots, k ~ U{active_humans_min..active_humans_max}.

    Bounds are rounded and clipped to the capacity, so gridded or hand-built params cannot ask for more humans
    than there are slots. With min = max = N (the default) every slot is active whatever the key.
    """
    lo = jnp.clip(jnp.round(params.active_humans_min), 0, num_humans)
    hi = jnp.clip(jnp.round(params.active_humans_max), lo, num_humans)
    count = jnp.minimum(lo + jnp.floor(uniform(key, ()) * (hi - lo + 1.0)), hi)
    return jnp.arange(num_humans) < count


def park(humans: Humans) -> Humans:
    """Move the inactive slots to their parking spots, at rest, with their goals where they stand."""
    n = humans.pos.shape[0]
    spot = jnp.stack([PARKING + 10.0 * jnp.arange(n, dtype=jnp.float32), jnp.full((n,), PARKING)], -1)
    on = humans.active[:, None]
    return humans.replace(pos=jnp.where(on, humans.pos, spot), goal=jnp.where(on, humans.goal, spot),
                          vel=jnp.where(on, humans.vel, 0.0))


# ------------------------------------------------------------------------------------------------ the scenarios
#
# Geometry follows the arena's traced parameters: a = arena_size (the robot's start and goal region), R =
# circle_radius (where humans enter and leave), lanes of half-width a / 2 (traffic) or a / 4 (head-on and
# overtaking lanes). The robot of the lane scenarios walks up the y axis from (x0, -a) to (x1, a).


class Scenario(NamedTuple):
    """One scenario's samplers (pure functions of a key and the traced params).

    robot(key, params, tries) -> Robot
    spawn(key, params, n, tries) -> (pos, goal) candidates, each (n, tries, 2): human i of an episode
    new_goal(key, params, humans, tries) -> goal candidates (N, tries, 2) for a goal change
    respawn(key, params, pos, goal, tries) -> (pos, goal) candidates (tries, 2) replacing an arrived human
    speed: factor on the humans' preferred speeds
    """

    robot: Callable
    spawn: Callable
    new_goal: Callable
    respawn: Callable
    speed: float = 1.0


def _box(key, shape, lo_x, hi_x, lo_y, hi_y):
    """Points uniform in a box; bounds broadcast against `shape`."""
    u = uniform(key, shape + (2,))
    return jnp.stack([lo_x + u[..., 0] * (hi_x - lo_x), lo_y + u[..., 1] * (hi_y - lo_y)], -1)


def _lane_robot(key, params: EnvParams, tries: int) -> Robot:
    """Start near (0, -a), goal near (0, a), each shifted sideways by up to 0.5 m."""
    x = uniform(key, (2,), -0.5, 0.5)
    a = params.arena_size
    zero = jnp.zeros((), jnp.float32)
    return Robot(pos=jnp.stack([x[0], -a]), vel=jnp.zeros(2), goal=jnp.stack([x[1], a]),
                 heading=zero + jnp.pi / 2, speed=zero)


# circle_crossing (Francis et al.: circular crossing): spawn on a circle, walk to the antipode; goal changes
# pick a new point of the circle.
def _circle_spawn(key, params, n, tries):
    pos = circle_candidates(key, params, (n, tries))
    return pos, -pos


def _circle_new_goal(key, params, humans, tries):
    return goal_candidates(key, params, humans.v_pref, (humans.pos.shape[0], tries))


def _circle_respawn(key, params, pos, goal, tries):
    new = circle_candidates(key, params, (tries,))
    return new, -new


# square_crossing (CrowdNav): start on one side of a square of half-width R, goal anywhere on the other side.
def _square_pair(key, params, shape):
    k_side, k_start, k_goal = jax.random.split(key, 3)
    side = jnp.where(uniform(k_side, shape) < 0.5, -1.0, 1.0)[..., None]
    r = params.circle_radius
    start = _box(k_start, shape, 0.0, r, -r, r) * jnp.stack([side[..., 0], jnp.ones(shape)], -1)
    goal = _box(k_goal, shape, 0.0, r, -r, r) * jnp.stack([-side[..., 0], jnp.ones(shape)], -1)
    return start, goal


def _square_spawn(key, params, n, tries):
    return _square_pair(key, params, (n, tries))


def _square_new_goal(key, params, humans, tries):
    side = jnp.where(humans.pos[:, 0] < 0, -1.0, 1.0)[:, None]  # the far side of where the human is
    r = params.circle_radius
    goal = _box(key, (humans.pos.shape[0], tries), 0.0, r, -r, r)
    return goal * jnp.stack([-side * jnp.ones_like(goal[..., 0]), jnp.ones_like(goal[..., 0])], -1)


def _square_respawn(key, params, pos, goal, tries):
    return _square_pair(key, params, (tries,))


# parallel_traffic (Francis et al.: parallel traffic): two opposing streams in a lane of half-width a/2 along the
# robot's way; even slots walk with the robot, odd slots against it. Arrived humans re-enter at their stream's start.
def _stream_goal(key, params, direction, shape, half_width):
    return _box(key, shape, -half_width, half_width, 0.0, 0.0) + jnp.stack(
        [jnp.zeros(shape), direction * params.circle_radius * jnp.ones(shape)], -1)


def _parallel_spawn(key, params, n, tries):
    k_pos, k_goal = jax.random.split(key)
    c, r = 0.5 * params.arena_size, params.circle_radius
    direction = jnp.where(jnp.arange(n) % 2 == 0, 1.0, -1.0)[:, None]
    pos = _box(k_pos, (n, tries), -c, c, -r, r)
    return pos, _stream_goal(k_goal, params, direction, (n, tries), c)


def _lane_new_goal(half_width_factor):
    def new_goal(key, params, humans, tries):
        direction = jnp.sign(humans.goal[:, 1:2])  # keep walking the stream's way
        return _stream_goal(key, params, direction, (humans.pos.shape[0], tries), half_width_factor * params.arena_size)
    return new_goal


def _lane_respawn(half_width_factor):
    def respawn(key, params, pos, goal, tries):
        k_pos, k_goal = jax.random.split(key)
        direction = jnp.sign(goal[1])
        c = half_width_factor * params.arena_size
        return (_stream_goal(k_pos, params, -direction, (tries,), c),
                _stream_goal(k_goal, params, direction, (tries,), c))
    return respawn


# perpendicular_traffic (Francis et al.: perpendicular traffic): one stream crossing the robot's way from left
# to right, in a band of half-width a/2 about the middle of its path.
def _cross_goal(key, params, shape, x):
    c = 0.5 * params.arena_size
    return _box(key, shape, x, x, -c, c)


def _perpendicular_spawn(key, params, n, tries):
    k_pos, k_goal = jax.random.split(key)
    c, r = 0.5 * params.arena_size, params.circle_radius
    return _box(k_pos, (n, tries), -r, r, -c, c), _cross_goal(k_goal, params, (n, tries), r)


def _perpendicular_new_goal(key, params, humans, tries):
    return _cross_goal(key, params, (humans.pos.shape[0], tries), params.circle_radius)


def _perpendicular_respawn(key, params, pos, goal, tries):
    k_pos, k_goal = jax.random.split(key)
    r = params.circle_radius
    return _cross_goal(k_pos, params, (tries,), -r), _cross_goal(k_goal, params, (tries,), r)


# frontal_approach (Francis et al.: frontal approach): humans come head-on down the robot's lane (half-width
# a/4), from ahead of the robot's start to behind it.
def _frontal_spawn(key, params, n, tries):
    k_pos, k_goal = jax.random.split(key)
    c, a, r = 0.25 * params.arena_size, params.arena_size, params.circle_radius
    return _box(k_pos, (n, tries), -c, c, -0.5 * a, r), _stream_goal(k_goal, params, -1.0, (n, tries), c)


# robot_overtaking (Francis et al.: robot overtaking): humans at half their usual speed walk the robot's way in its
# lane, so the robot has to pass them.
def _overtaking_spawn(key, params, n, tries):
    k_pos, k_goal = jax.random.split(key)
    c, a, r = 0.25 * params.arena_size, params.arena_size, params.circle_radius
    return _box(k_pos, (n, tries), -c, c, -0.5 * a, r), _stream_goal(k_goal, params, 1.0, (n, tries), c)


# robot_crowding (Francis et al.: robot crowding): humans enter on the circle and head for points on the robot's
# path, converging on it; goal changes pick other points of the path.
def _path_points(key, params, shape):
    a = params.arena_size
    return _box(key, shape, -0.5, 0.5, -a, a)


def _crowding_spawn(key, params, n, tries):
    k_pos, k_goal = jax.random.split(key)
    return circle_candidates(k_pos, params, (n, tries)), _path_points(k_goal, params, (n, tries))


def _crowding_new_goal(key, params, humans, tries):
    return _path_points(key, params, (humans.pos.shape[0], tries))


def _crowding_respawn(key, params, pos, goal, tries):
    k_pos, k_goal = jax.random.split(key)
    return circle_candidates(k_pos, params, (tries,)), _path_points(k_goal, params, (tries,))


# random (CrowdNav's random goals): start and goal uniform in the square of half-width R; an arrived human stays
# where it is and walks on to a new random goal.
def _square_points(key, params, shape):
    r = params.circle_radius
    return _box(key, shape, -r, r, -r, r)


def _random_spawn(key, params, n, tries):
    k_pos, k_goal = jax.random.split(key)
    return _square_points(k_pos, params, (n, tries)), _square_points(k_goal, params, (n, tries))


def _random_new_goal(key, params, humans, tries):
    return _square_points(key, params, (humans.pos.shape[0], tries))


def _random_respawn(key, params, pos, goal, tries):
    return jnp.broadcast_to(pos, (tries, 2)), _square_points(key, params, (tries,))


SCENARIO_TABLE = {
    "circle_crossing": Scenario(sample_robot, _circle_spawn, _circle_new_goal, _circle_respawn),
    "square_crossing": Scenario(sample_robot, _square_spawn, _square_new_goal, _square_respawn),
    "parallel_traffic": Scenario(_lane_robot, _parallel_spawn, _lane_new_goal(0.5), _lane_respawn(0.5)),
    "perpendicular_traffic": Scenario(_lane_robot, _perpendicular_spawn, _perpendicular_new_goal,
                                      _perpendicular_respawn),
    "frontal_approach": Scenario(_lane_robot, _frontal_spawn, _lane_new_goal(0.25), _lane_respawn(0.25)),
    "robot_overtaking": Scenario(_lane_robot, _overtaking_spawn, _lane_new_goal(0.25), _lane_respawn(0.25), 0.5),
    "robot_crowding": Scenario(_lane_robot, _crowding_spawn, _crowding_new_goal, _crowding_respawn),
    "random": Scenario(sample_robot, _random_spawn, _random_new_goal, _random_respawn),
}
assert tuple(SCENARIO_TABLE) == SCENARIOS, "config.SCENARIOS lists the scenarios in this order"


class Sampler(NamedTuple):
    """The samplers of one configured scenario: `scenarios` is one `Scenario` (a fixed scenario: called
    directly) or all of them (mix: each call selects the episode's by `lax.switch` on its index)."""

    scenarios: tuple

    def _call(self, field, index, *args, static=()):
        """Scenario `field`'s sampler on `args` plus the trailing `static` Python values (shapes: bound, not
        passed through the switch, which would trace them)."""
        fns = [getattr(s, field) for s in self.scenarios]
        if len(fns) == 1:
            return fns[0](*args, *static)
        return jax.lax.switch(index, [lambda *a, f=f: f(*a, *static) for f in fns], *args)

    def scale_speed(self, v_pref, index):
        """Preferred speeds times the scenario's speed factor."""
        speeds = [s.speed for s in self.scenarios]
        if speeds == [1.0]:
            return v_pref
        if len(speeds) == 1:
            return v_pref * speeds[0]
        return v_pref * jnp.asarray(speeds, jnp.float32)[index]


def sampler(name: str) -> Sampler:
    """The samplers of `env.scenario` (a scenario name or 'mix')."""
    if name == "mix":
        return Sampler(tuple(SCENARIO_TABLE.values()))
    return Sampler((SCENARIO_TABLE[name],))


def scenario_index(name: str) -> int:
    """The index of a scenario in `SCENARIOS` (the order of `env.scenario_weights`)."""
    return SCENARIOS.index(name)


def draw_scenario(key, weights):
    """An index ~ Categorical(weights / sum(weights)); zero-weight scenarios are never drawn."""
    edges = jnp.cumsum(weights)
    u = uniform(key, ()) * edges[-1]
    return jnp.minimum(jnp.sum(edges <= u), weights.shape[0] - 1).astype(jnp.int32)


def robot_start(key, params: EnvParams, sampler: Sampler, index, tries: int) -> Robot:
    return sampler._call("robot", index, key, params, static=(tries,))


def spawn_humans(key, params: EnvParams, robot: Robot, num_humans: int, tries: int, active=None,
                 sampler: Sampler | None = None, index=0) -> Humans:
    """Place the active humans one at a time at the scenario's spawn candidates, each clear of the robot and
    every human placed before (positions and goals); the inactive slots are parked. `active` (N,) bool
    defaults to all slots, `sampler` to circle crossing."""
    sampler = sampler or Sampler((SCENARIO_TABLE["circle_crossing"],))
    k_attr, k_cand = jax.random.split(key)
    radius, v_pref = sample_attributes(k_attr, params, (num_humans,))
    v_pref = sampler.scale_speed(v_pref, index)
    active = jnp.ones((num_humans,), bool) if active is None else active
    if num_humans == 0:
        empty = jnp.zeros((0, 2))
        return Humans(pos=empty, vel=empty, goal=empty, radius=radius, v_pref=v_pref, active=active)
    start, goal = sampler._call("spawn", index, k_cand, params, static=(num_humans, tries))
    candidates = jnp.concatenate([start, goal], -1)  # (N, tries, 4): a start is chosen with its goal

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
        pick = choose(candidates[i], margin)
        carry = (others_pos.at[i + 1].set(pick[:2]), others_goal.at[i + 1].set(pick[2:]),
                 placed.at[i + 1].set(active[i]))
        return carry, None

    (others_pos, others_goal, _), _ = jax.lax.scan(
        place, (others_pos, others_goal, placed), jnp.arange(num_humans)
    )
    return park(Humans(
        pos=others_pos[1:], vel=jnp.zeros((num_humans, 2)), goal=others_goal[1:], radius=radius, v_pref=v_pref,
        active=active,
    ))


def _others_excluding_self(humans: Humans, robot: Robot, params: EnvParams):
    """Every agent (humans, then the robot) with a (N, N+1) mask hiding each human from itself and the inactive
    slots from everyone."""
    n = humans.pos.shape[0]
    pos = jnp.concatenate([humans.pos, robot.pos[None]], 0)
    goal = jnp.concatenate([humans.goal, robot.goal[None]], 0)
    radius = jnp.concatenate([humans.radius, params.robot_radius[None]], 0)
    present = jnp.concatenate([humans.active, jnp.ones((1,), bool)])
    return pos, goal, radius, ~jnp.eye(n, n + 1, dtype=bool) & present[None, :]


def choose(candidates, margin):
    """Per row, the first candidate with margin >= 0 (else the widest margin): (..., T, D) -> (..., D)."""
    tries = margin.shape[-1]
    first = jnp.argmax(margin >= 0, axis=-1)
    idx = jnp.where(jnp.any(margin >= 0, axis=-1), first, jnp.argmax(margin, axis=-1))
    onehot = (jnp.arange(tries) == idx[..., None]).astype(candidates.dtype)
    return jnp.sum(onehot[..., None] * candidates, axis=-2)


def change_goals(key, humans: Humans, robot: Robot, params: EnvParams, step_count, tries: int,
                 sampler: Sampler | None = None, index=0) -> Humans:
    """Every goal_change_interval seconds each active human switches, with goal_change_prob, to a new goal
    drawn by the scenario.

    The candidates are drawn only on the steps where changes fall due (one in 20 by default), also in a
    vmapped batch of environments, where only the environments that are due do the work (see `cond_gathered`).
    """
    sampler = sampler or Sampler((SCENARIO_TABLE["circle_crossing"],))
    due = (step_count % params.goal_change_period) == 0
    return cond_gathered(due, lambda *args: _switch_goals(*args, tries, sampler), _unchanged,
                         key, humans, robot, params, jnp.asarray(index, jnp.int32))


def _unchanged(key, humans: Humans, robot: Robot, params: EnvParams, index) -> Humans:
    return humans


def _switch_goals(key, humans: Humans, robot: Robot, params: EnvParams, index, tries: int, sampler) -> Humans:
    """Each human switches, with goal_change_prob, to a new goal clear of the others."""
    n = humans.pos.shape[0]
    k_coin, k_cand = jax.random.split(key)
    switch = (uniform(k_coin, (n,)) < params.goal_change_prob) & humans.active
    candidates = sampler._call("new_goal", index, k_cand, params, humans, static=(tries,))
    margin = clearance(candidates, humans.radius, *_others_excluding_self(humans, robot, params), params.spawn_clearance)
    return humans.replace(goal=jnp.where(switch[:, None], choose(candidates, margin), humans.goal))


def respawn_arrived(key, humans: Humans, robot: Robot, params: EnvParams, tries: int,
                    sampler: Sampler | None = None, index=0) -> Humans:
    """A human within its own radius of its goal is replaced by a fresh one of the scenario (`random` keeps it
    where it is with a new goal).

    One arrival is served per step (the lowest index); another human arriving in the same step waits at its
    goal until the next one. Serving one instead of all N cuts the rejection-sampling work N-fold, and
    simultaneous arrivals are rare. In a vmapped batch only the environments with an arrival do the work
    (see `cond_gathered`).
    """
    sampler = sampler or Sampler((SCENARIO_TABLE["circle_crossing"],))
    return cond_gathered(jnp.any(_arrived(humans)), lambda *args: _respawn_first(*args, tries, sampler),
                         _unchanged, key, humans, robot, params, jnp.asarray(index, jnp.int32))


def _arrived(humans: Humans):
    offset = humans.pos - humans.goal
    return (jnp.square(offset[:, 0]) + jnp.square(offset[:, 1]) < jnp.square(humans.radius)) & humans.active


def _respawn_first(key, humans: Humans, robot: Robot, params: EnvParams, index, tries: int, sampler) -> Humans:
    """Replace the lowest-indexed arrived human (if any) by a fresh one."""
    n = humans.pos.shape[0]
    k_attr, k_cand = jax.random.split(key)
    arrived = _arrived(humans)
    who = jnp.argmax(arrived)
    radius, v_pref = sample_attributes(k_attr, params)
    v_pref = sampler.scale_speed(v_pref, index)
    start, goal = sampler._call("respawn", index, k_cand, params, humans.pos[who], humans.goal[who],
                                static=(tries,))
    pos, goals, radii, valid = _others_excluding_self(humans, robot, params)
    margin = clearance(start, radius, pos, goals, radii, valid[who], params.spawn_clearance)
    pick = choose(jnp.concatenate([start, goal], -1), margin)
    replace = arrived & (jnp.arange(n) == who)
    put = lambda new, old: jnp.where(replace.reshape((n,) + (1,) * (old.ndim - 1)), new, old)
    return Humans(
        pos=put(pick[:2], humans.pos), vel=put(jnp.zeros(2), humans.vel), goal=put(pick[2:], humans.goal),
        radius=put(radius, humans.radius), v_pref=put(v_pref, humans.v_pref), active=humans.active,
    )
