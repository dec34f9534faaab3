"""Observation frames: the reference's world frame, or a robot-centred frame whose x axis points at the goal.

In the goal frame the same observation is re-expressed so that the robot sits at the origin and its goal at
(d_goal, 0): every relative position, prediction and velocity is rotated, and the robot's heading becomes its
angle to the goal direction. The navigation task is symmetric under rotations and translations of the plane, so
a policy in this frame never has to learn the same manoeuvre once per goal direction (the state rotation used by
CADRL / SARL in the original CrowdNav). A holonomic action (a velocity) is produced in the goal frame and
rotated back to the world frame inside the network, so the environment and the PPO loss see world-frame actions.

The LiDAR scan (`Obs.lidar`, R rays) arrives in the robot's body frame: ray k at angle heading + 2 pi k / R. A
scan is rotated into another frame by `rotate_scan`: a circular shift by the angle between the frames in ray
steps, with linear interpolation between the two neighbouring rays for the fractional part (cheap, differentiable,
exact for whole ray steps). In the goal frame ray 0 points at the goal (the scan is shifted by the goal's angle
from the heading); in the world frame (`to_world_frame`, the reference's frame, which has no other
body-frame input) ray 0 points along world +x (shifted by -heading). Either way the policy sees every input in
one frame. Without a scan (R = 0) neither function touches the observation.
"""

from __future__ import annotations

import math

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


# A shift within this many ray steps of a whole number is taken as that whole number, so a rotation by whole ray
# steps is an exact circular shift despite float32 rounding of angle * R / (2 pi) (an error of at most 1e-3 of
# the difference between neighbouring rays; headings are stored as float32, 1e-3 ray steps of 1440 rays is 4e-6 rad).
_WHOLE_STEP_TOLERANCE = 1e-3


def rotate_scan(scan, angle):
    """A scan (..., R) re-expressed in a frame turned by `angle` (...,) rad counter-clockwise from the scan's own.

    Ray j of the result points where ray j + angle / (2 pi / R) of the input pointed: out[j] = (1 - f) scan[i]
    + f scan[i + 1] (indices modulo R) with i + f = j + angle R / (2 pi), i whole and 0 <= f < 1. Cheap (two
    gathers), differentiable in the ranges and in the angle, exact for whole ray steps, and the identity for
    angle 0. R = 0: the scan unchanged."""
    r = scan.shape[-1]
    if r == 0:
        return scan
    shift = jnp.mod(jnp.asarray(angle, jnp.float32) * jnp.float32(r / (2.0 * math.pi)), jnp.float32(r))
    whole = jnp.round(shift)
    shift = jnp.where(jnp.abs(shift - whole) < _WHOLE_STEP_TOLERANCE, whole, shift)
    base = jnp.floor(shift)
    frac = (shift - base)[..., None]
    idx = (jnp.arange(r, dtype=jnp.int32) + base.astype(jnp.int32)[..., None]) % r
    idx = jnp.broadcast_to(idx, scan.shape)
    lo = jnp.take_along_axis(scan, idx, axis=-1)
    hi = jnp.take_along_axis(scan, (idx + 1) % r, axis=-1)
    return lo + frac * (hi - lo)


def to_world_frame(obs: Obs) -> Obs:
    """The reference's world-frame observation, with the body-frame scan turned so that ray 0 points along world
    +x (every other input is already in world axes). Without a scan: `obs` itself."""
    if obs.lidar.shape[-1] == 0:
        return obs
    return obs.replace(lidar=rotate_scan(obs.lidar, -obs.robot_node[..., 6]))


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
    robot_node = jnp.stack([zero, zero, obs.robot_node[..., 2], dist, zero, obs.robot_node[..., 5], heading], axis=-1)
    humans = obs.humans
    pairs = humans.reshape(humans.shape[:-1] + (humans.shape[-1] // 2, 2))
    h_ex, h_ey = ex[..., None, None, :], ey[..., None, None, :]
    humans = _to_local(pairs, h_ex, h_ey).reshape(humans.shape)
    local = obs.replace(
        robot_node=robot_node,
        robot_vel=_to_local(obs.robot_vel, ex, ey),
        humans=humans,
        human_vel=_to_local(obs.human_vel, ex[..., None, :], ey[..., None, :]),
        # the goal direction lies at -heading from the robot's heading: there ray 0 of the goal-frame scan points
        lidar=rotate_scan(obs.lidar, -heading),
    )
    return local, (ex, ey)


def action_to_world(action_local, axes):
    """A goal-frame velocity (..., 2) back to world coordinates."""
    ex, ey = axes
    return action_local[..., 0:1] * ex + action_local[..., 1:2] * ey
