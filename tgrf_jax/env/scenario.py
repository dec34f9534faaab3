"""Circle-crossing scenario: robot start/goal sampling, human spawning, goal changes and respawns
(the reference's `crowd_sim_pred_real_gst.py` and its parents; docs/reference.md).

Rejection sampling is bounded: each draw proposes `tries` candidates at once and takes the first valid one;
when none is valid (a very crowded scene), it takes the candidate with the most clearance, so shapes and run
time never depend on luck.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

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


def spawn_humans(key, params: EnvParams, robot: Robot, num_humans: int, tries: int) -> Humans:
    """Place humans one at a time on the circle, each clear of the robot and every human placed before."""
    k_attr, k_cand = jax.random.split(key)
    radius, v_pref = sample_attributes(k_attr, params, (num_humans,))
    if num_humans == 0:
        empty = jnp.zeros((0, 2))
        return Humans(pos=empty, vel=empty, goal=empty, radius=radius, v_pref=v_pref)
    candidates = circle_candidates(k_cand, params, (num_humans, tries))

    # Slot 0 of the "others" arrays is the robot; slots 1..N fill up with placed humans.
    others_pos = jnp.zeros((num_humans + 1, 2)).at[0].set(robot.pos)
    others_goal = jnp.zeros((num_humans + 1, 2)).at[0].set(robot.goal)
    others_radius = jnp.zeros(num_humans + 1).at[0].set(params.robot_radius).at[1:].set(radius)
    placed = jnp.zeros(num_humans + 1, bool).at[0].set(True)

    def place(carry, i):
        others_pos, others_goal, placed = carry
        margin = clearance(
            candidates[i], radius[i], others_pos, others_goal, others_radius, placed, params.spawn_clearance
        )
        pos = choose(candidates[i], margin)
        carry = (others_pos.at[i + 1].set(pos), others_goal.at[i + 1].set(-pos), placed.at[i + 1].set(True))
        return carry, None

    (others_pos, others_goal, _), _ = jax.lax.scan(
        place, (others_pos, others_goal, placed), jnp.arange(num_humans)
    )
    return Humans(
        pos=others_pos[1:], vel=jnp.zeros((num_humans, 2)), goal=others_goal[1:], radius=radius, v_pref=v_pref
    )


def _others_excluding_self(humans: Humans, robot: Robot, params: EnvParams):
    """Every agent (humans, then the robot) with a (N, N+1) mask hiding each human from itself."""
    n = humans.pos.shape[0]
    pos = jnp.concatenate([humans.pos, robot.pos[None]], 0)
    goal = jnp.concatenate([humans.goal, robot.goal[None]], 0)
    radius = jnp.concatenate([humans.radius, params.robot_radius[None]], 0)
    return pos, goal, radius, ~jnp.eye(n, n + 1, dtype=bool)


def choose(candidates, margin):
    """Per row, the first candidate with margin >= 0 (else the widest margin): (..., T, 2) -> (..., 2)."""
    tries = margin.shape[-1]
    first = jnp.argmax(margin >= 0, axis=-1)
    idx = jnp.where(jnp.any(margin >= 0, axis=-1), first, jnp.argmax(margin, axis=-1))
    onehot = (jnp.arange(tries) == idx[..., None]).astype(candidates.dtype)
    return jnp.sum(onehot[..., None] * candidates, axis=-2)


def change_goals(key, humans: Humans, robot: Robot, params: EnvParams, step_count, tries: int) -> Humans:
    """Every goal_change_interval seconds each human switches, with goal_change_prob, to a new circle goal.

    The candidates are drawn only on the steps where changes fall due (one in 20 by default), also in a
    vmapped batch of environments, where only the environments that are due do the work (see `cond_gathered`).
    """
    due = (step_count % params.goal_change_period) == 0
    return cond_gathered(due, lambda *args: _switch_goals(*args, tries), _unchanged, key, humans, robot, params)


def _unchanged(key, humans: Humans, robot: Robot, params: EnvParams) -> Humans:
    return humans


def _switch_goals(key, humans: Humans, robot: Robot, params: EnvParams, tries: int) -> Humans:
    """Each human switches, with goal_change_prob, to a new goal on the circle clear of the others."""
    n = humans.pos.shape[0]
    k_coin, k_cand = jax.random.split(key)
    switch = uniform(k_coin, (n,)) < params.goal_change_prob
    candidates = goal_candidates(k_cand, params, humans.v_pref, (n, tries))
    margin = clearance(candidates, humans.radius, *_others_excluding_self(humans, robot, params), params.spawn_clearance)
    return humans.replace(goal=jnp.where(switch[:, None], choose(candidates, margin), humans.goal))


def respawn_arrived(key, humans: Humans, robot: Robot, params: EnvParams, tries: int) -> Humans:
    """A human within its own radius of its goal is replaced by a fresh circle-crossing human.

    One arrival is served per step (the lowest index); another human arriving in the same step waits at its
    goal until the next one. Serving one instead of all N cuts the rejection-sampling work N-fold, and
    simultaneous arrivals are rare. In a vmapped batch only the environments with an arrival do the work
    (see `cond_gathered`).
    """
    return cond_gathered(jnp.any(_arrived(humans)), lambda *args: _respawn_first(*args, tries), _unchanged,
                         key, humans, robot, params)


def _arrived(humans: Humans):
    offset = humans.pos - humans.goal
    return jnp.square(offset[:, 0]) + jnp.square(offset[:, 1]) < jnp.square(humans.radius)


def _respawn_first(key, humans: Humans, robot: Robot, params: EnvParams, tries: int) -> Humans:
    """Replace the lowest-indexed arrived human (if any) by a fresh one on the circle."""
    n = humans.pos.shape[0]
    k_attr, k_cand = jax.random.split(key)
    arrived = _arrived(humans)
    who = jnp.argmax(arrived)
    radius, v_pref = sample_attributes(k_attr, params)
    candidates = circle_candidates(k_cand, params, (tries,))
    pos, goal, radii, valid = _others_excluding_self(humans, robot, params)
    margin = clearance(candidates, radius, pos, goal, radii, valid[who], params.spawn_clearance)
    new_pos = choose(candidates, margin)
    replace = arrived & (jnp.arange(n) == who)
    put = lambda new, old: jnp.where(replace.reshape((n,) + (1,) * (old.ndim - 1)), new, old)
    return Humans(
        pos=put(new_pos, humans.pos), vel=put(jnp.zeros(2), humans.vel), goal=put(-new_pos, humans.goal),
        radius=put(radius, humans.radius), v_pref=put(v_pref, humans.v_pref),
    )
