"""Trajectory predictions of the humans the robot sees: constant velocity, or the ground truth of the human
model rolled forward. The learned predictor's (GST) predictions come from `tgrf_jax.env.gst.history`."""

from __future__ import annotations

import jax
import jax.numpy as jnp

from tgrf_jax.config import EnvConfig
from tgrf_jax.env import routing as routing_lib
from tgrf_jax.env.humans import Steering, body_radius, human_velocities
from tgrf_jax.env.types import EnvParams, Humans


def predict(
    humans: Humans,
    params: EnvParams,
    config: EnvConfig,
    neighbor_dist,
    obstacles=None,
    obstacle_table=None,
    routing=None,
):
    """Predicted world positions (N, K, 2) at t+1..t+K, or None for predictor 'none'.

    const_vel extrapolates the last applied velocity; truth rolls the human model itself forward K steps from
    the true joint state (among the episode's `obstacles`) with goals frozen and the robot left out (as the
    reference does). `obstacle_table`: the obstacles processed for ORCA (`EnvState.obstacle_table`) or None;
    `routing`: the humans' routing among the obstacles (`EnvState.routing`) or None.
    """
    k = config.pred_horizon
    if config.predictor == "none":
        return None
    if config.predictor == "const_vel":
        return constant_velocity(humans.pos, humans.vel, params.dt, k)
    return true_future(humans, params, config, k, neighbor_dist, obstacles, obstacle_table, routing)


def constant_velocity(pos, vel, dt, k: int):
    """Positions (N, k, 2) at t+1..t+k of people keeping velocities `vel` (N, 2) from `pos` (N, 2)."""
    steps = jnp.arange(1, k + 1, dtype=jnp.float32)[None, :, None] * dt
    return pos[:, None, :] + steps * vel[:, None, :]


def true_future(
    humans: Humans,
    params: EnvParams,
    config: EnvConfig,
    k: int,
    neighbor_dist,
    obstacles=None,
    obstacle_table=None,
    routing=None,
):
    """Ground-truth future positions (N, k, 2) of the humans' own policy, goals frozen, robot invisible (routed
    among the obstacles as they walk, without the symmetry-breaking jitter)."""

    def advance(h: Humans, _):
        steering = None
        if routing is not None:
            radii = body_radius(h.radius, params, config)
            target, at_goal, _ = routing_lib.targets(routing, h.pos, h.goal, radii, obstacles)
            steering = Steering(target, at_goal, jnp.zeros_like(target))
        vel = human_velocities(h, None, params, config, neighbor_dist, obstacles, obstacle_table, steering)
        h = h.replace(pos=h.pos + vel * params.dt, vel=vel)
        return h, h.pos

    _, future = jax.lax.scan(advance, humans, None, length=k)
    return jnp.swapaxes(future, 0, 1)
