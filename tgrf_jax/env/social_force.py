"""Social Force humans (Helbing & Molnar 1995), as the CrowdNav++ reference runs them
(`crowd_nav/policy/social_force.py`; docs/reference.md).

    v_des = v_pref * (g - p) / |g - p|
    dv    = [ KI (v_des - v) + sum_j A exp((r_i + r_j - d_ij) / B) (p_i - p_j) / d_ij ] * dt
    v'    = v + dv, rescaled to speed v_pref if faster
"""

from __future__ import annotations

import jax.numpy as jnp

from tgrf_jax.env.geometry import safe_norm


def step(positions, velocities, goals, radii, v_pref, *, a, b, ki, dt, neighbor_mask=None):
    """New velocities of N agents (N, 2). `neighbor_mask` (N,) hides agents from everyone's repulsion sum."""
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

    new_vel = velocities + (ki * (v_des - velocities) + repulsion) * dt
    speed = safe_norm(new_vel)
    scale = jnp.where(speed > v_pref, v_pref / speed, 1.0)
    return new_vel * scale[:, None]
