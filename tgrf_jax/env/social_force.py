"""Social Force humans (Helbing & Molnar 1995), as the CrowdNav++ reference runs them
(`crowd_nav/policy/social_force.py`; docs/reference.md).

    v_des = v_pref * (g - p) / |g - p|
    dv    = [ KI (v_des - v) + sum_j A exp((r_i + r_j - d_ij) / B) (p_i - p_j) / d_ij ] * dt
    v'    = v + dv, rescaled to speed v_pref if faster

With static obstacles (`obstacles`), the bracket of dv also gets the wall term of Helbing, Farkas & Vicsek
(Nature 407, 2000, eq. 2, without the body and friction forces), with the same A and B, summed over the
obstacle polygons W (`obstacles.wall_force`):

    dv    = [ ... + sum_W A exp((r_i - d_iW) / B) n_iW ] * dt

where d_iW is the distance from p_i to the nearest point of W and n_iW the unit vector from that point to p_i.
Without obstacles the computation is exactly the one above.
"""

from __future__ import annotations

import jax.numpy as jnp

from tgrf_jax.env.geometry import safe_norm
from tgrf_jax.env.obstacles import wall_force


def step(positions, velocities, goals, radii, v_pref, *, a, b, ki, dt, neighbor_mask=None, obstacles=None):
    """New velocities of N agents (N, 2). `neighbor_mask` (N,) hides agents from everyone's repulsion sum;
    `obstacles` (an `obstacles.Obstacles`) adds their wall force on every agent."""
    n = positions.shape[0]
    to_goal = goals - positions
    dist_goal = safe_norm(to_goal)
    # At the goal the desired velocity is zero instead of a 0/0 direction.
    v_des = jnp.where((dist_goal > 1e-6)[:, None], v_pref[:, None] * to_goal / dist_goal[:, None], 0.0)

    diff = positions[:, None, :] - positions[None, :, :]  # (N, N, 2): p_i - p_j
    dist = safe_norm(diff)
    others = ~jnp.eye(n, dtype=bool)
    if neighbor_mask is not None:
        others = others & neighbor_mask[None, :]
    # The exponent is capped so that tiny B or deep overlaps give a huge, not an infinite, push.
    magnitude = a * jnp.exp(jnp.minimum((radii[:, None] + radii[None, :] - dist) / b, 30.0))
    # Coincident agents push along no direction (diff = 0) rather than producing NaN.
    repulsion = jnp.where(others[..., None], magnitude[..., None] * diff / dist[..., None], 0.0).sum(axis=1)
    # Decided on static shapes, so no obstacles (None, or no slots) leaves today's program untouched.
    if obstacles is not None and obstacles.vertices.shape[-3] > 0:
        repulsion = repulsion + wall_force(positions, radii, obstacles, a=a, b=b)

    new_vel = velocities + (ki * (v_des - velocities) + repulsion) * dt
    speed = safe_norm(new_vel)
    scale = jnp.where(speed > v_pref, v_pref / speed, 1.0)
    return new_vel * scale[:, None]
