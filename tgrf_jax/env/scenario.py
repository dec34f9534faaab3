"""Circle-crossing scenario: robot start/goal sampling, human spawning, goal changes and respawns (SPEC B 1.2).

Rejection sampling is bounded: each draw proposes `tries` candidates at once and takes the first valid one;
when none is valid (a very crowded scene), it takes the candidate with the most clearance, so shapes and run
time never depend on luck.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from tgrf_jax.env.types import EnvParams, Humans, Robot


def pick_first_valid(valid, score):
    """Index of the first True in `valid` (tries,), else the index of the highest `score`."""
    first = jnp.argmax(valid)
    return jnp.where(jnp.any(valid), first, jnp.argmax(score))


def sample_robot(key, params: EnvParams, tries: int) -> Robot:
    """Start and goal ~ U(-a, a)^2 each, at least `min_start_goal_dist` apart."""
    pts = jax.random.uniform(key, (tries, 2, 2), minval=-params.arena_size, maxval=params.arena_size)
    dist = jnp.linalg.norm(pts[:, 0] - pts[:, 1], axis=-1)
    idx = pick_first_valid(dist >= params.min_start_goal_dist, dist)
    zero = jnp.zeros((), jnp.float32)
    return Robot(
        pos=pts[idx, 0], vel=jnp.zeros(2), goal=pts[idx, 1], heading=zero + jnp.pi / 2, speed=zero
    )


def sample_attributes(key, params: EnvParams, shape=()):
    """Radius and preferred speed of newly spawned humans."""
    k_r, k_v = jax.random.split(key)
    radius = jax.random.uniform(k_r, shape, minval=params.human_radius_min, maxval=params.human_radius_max)
    v_pref = jax.random.uniform(k_v, shape, minval=params.human_v_pref_min, maxval=params.human_v_pref_max)
    return radius, v_pref


def circle_candidates(key, params: EnvParams, shape):
    """Spawn points on the crossing circle with one-sided noise in [0, noise) per axis, as the reference."""
    k_a, k_n = jax.random.split(key)
    angle = jax.random.uniform(k_a, shape, maxval=2 * jnp.pi)
    noise = jax.random.uniform(k_n, shape + (2,)) * params.spawn_noise
    return params.circle_radius * jnp.stack([jnp.cos(angle), jnp.sin(angle)], -1) + noise


def goal_candidates(key, params: EnvParams, v_pref, shape):
    """New goals on the circle with symmetric noise (U - 0.5) * v_pref per axis (goal changes)."""
    k_a, k_n = jax.random.split(key)
    angle = jax.random.uniform(k_a, shape, maxval=2 * jnp.pi)
    noise = (jax.random.uniform(k_n, shape + (2,)) - 0.5) * v_pref[..., None, None]
    return params.circle_radius * jnp.stack([jnp.cos(angle), jnp.sin(angle)], -1) + noise


def clearance(candidates, own_radius, others_pos, others_goal, others_radius, others_valid, gap):
    """Smallest margin between candidate points (..., T, 2) and other agents' positions and goals.

    A candidate is acceptable where the margin is >= 0, i.e. it keeps r_self + r_other + gap from every other
    agent's position and goal (the reference's spawn rule). `others_*` have shape (..., M, ...).
    """
    need = own_radius[..., None, None] + others_radius[..., None, :] + gap  # (..., 1, M)
    d_pos = jnp.linalg.norm(candidates[..., :, None, :] - others_pos[..., None, :, :], axis=-1)
    d_goal = jnp.linalg.norm(candidates[..., :, None, :] - others_goal[..., None, :, :], axis=-1)
    margin = jnp.minimum(d_pos, d_goal) - need
    margin = jnp.where(others_valid[..., None, :], margin, jnp.inf)
    return jnp.min(margin, axis=-1, initial=jnp.inf)


def spawn_humans(key, params: EnvParams, robot: Robot, num_humans: int, tries: int) -> Humans:
    """Place humans one at a time on the circle, each clear of the robot and every human placed before."""
    k_attr, k_cand = jax.random.split(key)
    radius, v_pref = sample_attributes(k_attr, params, (num_humans,))
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
        pos = candidates[i, pick_first_valid(margin >= 0, margin)]
        carry = (others_pos.at[i + 1].set(pos), others_goal.at[i + 1].set(-pos), placed.at[i + 1].set(True))
        return carry, None

    (others_pos, others_goal, _), _ = jax.lax.scan(
        place, (others_pos, others_goal, placed), jnp.arange(num_humans)
    )
    return Humans(
        pos=others_pos[1:], vel=jnp.zeros((num_humans, 2)), goal=others_goal[1:], radius=radius, v_pref=v_pref
    )


def _others_excluding_self(humans: Humans, robot: Robot, params: EnvParams):
    """Per-human view of every other agent: arrays (N, N+1, ...) with the robot last and self masked out."""
    n = humans.pos.shape[0]
    pos = jnp.concatenate([humans.pos, robot.pos[None]], 0)
    goal = jnp.concatenate([humans.goal, robot.goal[None]], 0)
    radius = jnp.concatenate([humans.radius, params.robot_radius[None]], 0)
    valid = ~jnp.eye(n, n + 1, dtype=bool)
    tile = lambda x: jnp.broadcast_to(x, (n,) + x.shape)
    return tile(pos), tile(goal), tile(radius), valid


def change_goals(key, humans: Humans, robot: Robot, params: EnvParams, step_count, tries: int) -> Humans:
    """Every goal_change_interval seconds each human switches, with goal_change_prob, to a new circle goal."""
    n = humans.pos.shape[0]
    k_coin, k_cand = jax.random.split(key)
    due = (step_count % params.goal_change_period) == 0
    switch = due & jax.random.bernoulli(k_coin, params.goal_change_prob, (n,))
    candidates = goal_candidates(k_cand, params, humans.v_pref, (n, tries))
    margin = clearance(candidates, humans.radius, *_others_excluding_self(humans, robot, params), params.spawn_clearance)
    idx = jax.vmap(pick_first_valid)(margin >= 0, margin)
    new_goal = jnp.take_along_axis(candidates, idx[:, None, None], axis=1)[:, 0]
    return humans.replace(goal=jnp.where(switch[:, None], new_goal, humans.goal))


def respawn_arrived(key, humans: Humans, robot: Robot, params: EnvParams, tries: int) -> Humans:
    """Humans within their own radius of their goal are replaced by fresh circle-crossing humans."""
    n = humans.pos.shape[0]
    k_attr, k_cand = jax.random.split(key)
    arrived = jnp.linalg.norm(humans.pos - humans.goal, axis=-1) < humans.radius
    radius, v_pref = sample_attributes(k_attr, params, (n,))
    candidates = circle_candidates(k_cand, params, (n, tries))
    margin = clearance(candidates, radius, *_others_excluding_self(humans, robot, params), params.spawn_clearance)
    idx = jax.vmap(pick_first_valid)(margin >= 0, margin)
    pos = jnp.take_along_axis(candidates, idx[:, None, None], axis=1)[:, 0]
    fresh = Humans(pos=pos, vel=jnp.zeros_like(pos), goal=-pos, radius=radius, v_pref=v_pref)
    return jax.tree_util.tree_map(
        lambda new, old: jnp.where(arrived.reshape((n,) + (1,) * (old.ndim - 1)), new, old), fresh, humans
    )
