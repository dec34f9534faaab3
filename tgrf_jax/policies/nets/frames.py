"""Observation frames: the reference's world frame, or a robot-centred frame whose x axis points at the goal.

In the goal frame the same observation is re-expressed so that the robot sits at the origin and its goal at
(d_goal, 0): every relative position, prediction and velocity is rotated, and the robot's heading becomes its
angle to the goal direction. The navigation task is symmetric under rotations and translations of the plane, so
a policy in this frame never has to learn the same manoeuvre once per goal direction (the state rotation used by
CADRL / SARL in the original CrowdNav). A holonomic action (a velocity) is produced in the goal frame and
rotated back to the world frame inside the network, so the environment and the PPO loss see world-frame actions.
"""

from __future__ import annotations

import jax.numpy as jnp

from tgrf_jax.config import FRAMES  # noqa: F401  (re-exported: the valid frame names)
from tgrf_jax.env.types import Obs


def goal_axes(obs: Obs):
    """Unit vectors (ex, ey) of the goal frame in world coordinates, each (..., 2), and the goal distance (...,).

    At the goal itself (distance 0) the frame falls back to the world axes instead of dividing by zero."""
    to_goal = obs.robot_node[..., 3:5] - obs.robot_node[..., 0:2]
    dist = jnp.sqrt(jnp.square(to_goal[..., 0]) + jnp.square(to_goal[..., 1]))
    safe = dist > 1e-6
    inv = jnp.where(safe, 1.0 / jnp.where(safe, dist, 1.0), 0.0)
    ex_x = jnp.where(safe, to_goal[..., 0] * inv, 1.0)
    ex_y = jnp.where(safe, to_goal[..., 1] * inv, 0.0)
    ex = jnp.stack([ex_x, ex_y], axis=-1)
    ey = jnp.stack([-ex_y, ex_x], axis=-1)
    return ex, ey, dist


def _to_local(v, ex, ey):
    """World vectors v (..., 2) -> goal-frame coordinates; ex/ey broadcast against v's leading axes."""
    return jnp.stack(
        [v[..., 0] * ex[..., 0] + v[..., 1] * ex[..., 1], v[..., 0] * ey[..., 0] + v[..., 1] * ey[..., 1]], axis=-1
    )


def to_goal_frame(obs: Obs) -> tuple[Obs, tuple]:
    """The observation in the goal frame (same shapes and layout), plus the axes for `action_to_world`."""
    ex, ey, dist = goal_axes(obs)
    zero = jnp.zeros_like(dist)
    heading = obs.robot_node[..., 6] - jnp.arctan2(ex[..., 1], ex[..., 0])
    heading = jnp.arctan2(jnp.sin(heading), jnp.cos(heading))
    robot_node = jnp.stack(
        [zero, zero, obs.robot_node[..., 2], dist, zero, obs.robot_node[..., 5], heading], axis=-1
    )
    humans = obs.humans
    pairs = humans.reshape(humans.shape[:-1] + (humans.shape[-1] // 2, 2))
    h_ex, h_ey = ex[..., None, None, :], ey[..., None, None, :]
    humans = _to_local(pairs, h_ex, h_ey).reshape(humans.shape)
    local = obs.replace(
        robot_node=robot_node,
        robot_vel=_to_local(obs.robot_vel, ex, ey),
        humans=humans,
        human_vel=_to_local(obs.human_vel, ex[..., None, :], ey[..., None, :]),
    )
    return local, (ex, ey)


def action_to_world(action_local, axes):
    """A goal-frame velocity (..., 2) back to world coordinates."""
    ex, ey = axes
    return action_local[..., 0:1] * ex + action_local[..., 1:2] * ey
