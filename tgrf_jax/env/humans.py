"""Human motion: one velocity update for all humans (ORCA or Social Force) and K-step trajectory predictions."""

from __future__ import annotations

import jax
import jax.numpy as jnp

from tgrf_jax import orca, social_force
from tgrf_jax.geometry import safe_norm
from tgrf_jax.config import EnvConfig
from tgrf_jax.env.types import EnvParams, Humans, Robot


def preferred_velocity(pos, goal):
    """Unit vector towards the goal, or the raw offset within 1 m of it (RVO2/CrowdNav convention)."""
    offset = goal - pos
    dist = safe_norm(offset)
    return jnp.where((dist > 1.0)[..., None], offset / dist[..., None], offset)


# ORCA radius = r + 0.01 + safety_space in the reference (orca.py:85-88).
ORCA_RADIUS_PAD = 0.01


def human_velocities(humans: Humans, robot: Robot | None, params: EnvParams, config: EnvConfig, neighbor_dist):
    """New velocities (N, 2) of all humans from the current joint state.

    `robot` is None when humans do not see the robot (the default); otherwise it joins the solve as an extra
    agent whose own result is discarded. `neighbor_dist` is the episode's ORCA neighbour distance
    (`EnvState.orca_neighbor_dist`).
    """
    n = humans.pos.shape[0]
    if n == 0:
        return jnp.zeros((0, 2))
    pos, vel, goal, radius, v_pref = humans.pos, humans.vel, humans.goal, humans.radius, humans.v_pref
    if robot is not None:
        pos = jnp.concatenate([pos, robot.pos[None]])
        vel = jnp.concatenate([vel, robot.vel[None]])
        goal = jnp.concatenate([goal, robot.goal[None]])
        radius = jnp.concatenate([radius, params.robot_radius[None]])
        v_pref = jnp.concatenate([v_pref, params.robot_v_max[None]])
    if config.human_policy == "orca":
        pref = preferred_velocity(pos, goal)
        if robot is not None:
            pref = pref.at[-1].set(robot.vel)  # the robot's "preference" is what it is doing
        new_vel = orca.solve(
            pos, vel, radius + ORCA_RADIUS_PAD + params.orca_safety_space, pref, v_pref,
            time_horizon=params.orca_time_horizon, dt=params.dt,
            neighbor_dist=neighbor_dist, max_neighbors=config.max_neighbors,
        )
    else:
        new_vel = social_force.step(
            pos, vel, goal, radius, v_pref, a=params.sf_a, b=params.sf_b, ki=params.sf_ki, dt=params.dt
        )
    return new_vel[:n]


def predict(humans: Humans, params: EnvParams, config: EnvConfig, neighbor_dist):
    """Predicted world positions (N, K, 2) at t+1..t+K, or None for predictor 'none'.

    const_vel extrapolates the last applied velocity; truth rolls the human model itself forward K steps from
    the true joint state with goals frozen and the robot left out (as the reference does).
    """
    k = config.pred_horizon
    if config.predictor == "none":
        return None
    if config.predictor == "const_vel":
        steps = jnp.arange(1, k + 1, dtype=jnp.float32)[None, :, None] * params.dt
        return humans.pos[:, None, :] + steps * humans.vel[:, None, :]
    return true_future(humans, params, config, k, neighbor_dist)


def true_future(humans: Humans, params: EnvParams, config: EnvConfig, k: int, neighbor_dist):
    """Ground-truth future positions (N, k, 2) of the humans' own policy, goals frozen, robot invisible."""

    def advance(h: Humans, _):
        vel = human_velocities(h, None, params, config, neighbor_dist)
        h = h.replace(pos=h.pos + vel * params.dt, vel=vel)
        return h, h.pos

    _, future = jax.lax.scan(advance, humans, None, length=k)
    return jnp.swapaxes(future, 0, 1)
