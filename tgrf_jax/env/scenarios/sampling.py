"""Sampling primitives every scenario shares: the counter-hash `uniform`, bounded rejection sampling (`clearance`,
`choose`), the humans' attributes, the episode's active slots and the parking of the inactive ones.

Rejection sampling is bounded: each draw proposes `tries` candidates at once and takes the first valid one; when
none is valid (a very crowded scene), it takes the candidate with the most clearance, so shapes and run time never
depend on luck.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from tgrf_jax.env import obstacles as obstacles_lib
from tgrf_jax.env.obstacles import Obstacles
from tgrf_jax.env.types import EnvParams, Humans

# Inactive slots wait here, 10 m apart: far beyond any sensor range or arena, and at finite coordinates.
PARKING = 1.0e4


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


def box(key, shape, lo_x, hi_x, lo_y, hi_y):
    """Points uniform in a box, (*shape, 2); bounds broadcast against `shape`."""
    u = uniform(key, shape + (2,))
    return jnp.stack([lo_x + u[..., 0] * (hi_x - lo_x), lo_y + u[..., 1] * (hi_y - lo_y)], -1)


def sample_attributes(key, params: EnvParams, shape=()):
    """Radius and preferred speed of newly spawned humans."""
    k_r, k_v = jax.random.split(key)
    radius = uniform(k_r, shape, minval=params.human_radius_min, maxval=params.human_radius_max)
    v_pref = uniform(k_v, shape, minval=params.human_v_pref_min, maxval=params.human_v_pref_max)
    return radius, v_pref


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


def obstacle_margin(candidates, own_radius, layout: Obstacles | None, gap):
    """How far candidates (..., T, 2) of radius `own_radius` (...,) keep `gap` from every obstacle (negative:
    too close or inside one), or None without obstacle slots."""
    if layout is None or layout.num_vertices.shape[-1] == 0:
        return None
    return obstacles_lib.clearance(candidates, layout) - own_radius[..., None] - gap


# Below any agent-spacing margin a real scene produces (squared metres): ranks obstacle overlaps last.
_INSIDE_OBSTACLE = -1.0e6


def require_room(margin, room, gap):
    """An agent-spacing margin (squared metres) that also requires `room` (metres, `obstacle_margin` with `gap`)
    >= 0.

    In `choose`'s fallback (no candidate keeps every gap) a candidate whose body overlaps an obstacle ranks below
    every other: a start or goal a little close to a human or a wall sorts itself out as the crowd moves, one in
    a wall never does (its goal unreachable, or the human stuck in the wall)."""
    return jnp.where(room + gap >= 0.0, jnp.minimum(margin, room), _INSIDE_OBSTACLE + room)


def with_obstacles(margin, candidates, own_radius, layout, gap):
    """An agent-spacing margin also requiring room from the obstacles (`require_room`)."""
    room = obstacle_margin(candidates, own_radius, layout, gap)
    return margin if room is None else require_room(margin, room, gap)


def choose(candidates, margin):
    """Per row, the first candidate with margin >= 0 (else the widest margin): (..., T, D) -> (..., D)."""
    tries = margin.shape[-1]
    first = jnp.argmax(margin >= 0, axis=-1)
    idx = jnp.where(jnp.any(margin >= 0, axis=-1), first, jnp.argmax(margin, axis=-1))
    onehot = (jnp.arange(tries) == idx[..., None]).astype(candidates.dtype)
    return jnp.sum(onehot[..., None] * candidates, axis=-2)


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
    return humans.replace(
        pos=jnp.where(on, humans.pos, spot), goal=jnp.where(on, humans.goal, spot), vel=jnp.where(on, humans.vel, 0.0)
    )
