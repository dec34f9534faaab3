"""Human motion: one velocity update for all humans, by ORCA or Social Force."""

from __future__ import annotations

from typing import Any

import jax.numpy as jnp
from flax import struct

from tgrf_jax.config import ORCA_RADIUS_PAD, EnvConfig
from tgrf_jax.env import orca, social_force
from tgrf_jax.env.geometry import safe_norm
from tgrf_jax.env.obstacles import Obstacles
from tgrf_jax.env.types import EnvParams, Humans, Robot


def preferred_velocity(pos, goal):
    """Unit vector towards the goal, or the raw offset within 1 m of it (RVO2/CrowdNav convention)."""
    offset = goal - pos
    dist = safe_norm(offset)
    return jnp.where((dist > 1.0)[..., None], offset / dist[..., None], offset)


@struct.dataclass
class Steering:
    """Where the humans head when it is not straight at their goals (routing among obstacles).

    target (N, 2): the point each human heads for; at_goal (N,) bool: the target is the goal itself (ORCA then
    slows within 1 m of it as usual, while an intermediate target is approached at full preferred speed);
    jitter (N, 2): added to ORCA's preferred velocity, a tiny perturbation that breaks exact symmetries (as
    RVO2's examples do), zeros for none. velocity (N, 2) or None: a preferred velocity given outright, in place of
    the unit vector towards the target (replayed recordings: the velocity that follows the recording); ORCA takes
    it as it is, Social Force pulls towards the target at its speed (at most the human's v_pref).
    """

    target: jnp.ndarray
    at_goal: jnp.ndarray
    jitter: jnp.ndarray
    velocity: Any = None


def steered_preference(pos, goal, steering: Steering):
    """ORCA's preferred velocities (N, 2) towards the steering targets."""
    if steering.velocity is not None:
        return steering.velocity + steering.jitter
    offset = steering.target - pos
    dist = safe_norm(offset)
    toward = offset / jnp.maximum(dist, 1e-9)[..., None]
    return jnp.where(steering.at_goal[..., None], preferred_velocity(pos, goal), toward) + steering.jitter


def body_radius(radius, params: EnvParams, config: EnvConfig):
    """The room a human of `radius` keeps from walls and others: ORCA adds its pad and safety space."""
    if config.human_policy == "orca":
        return radius + ORCA_RADIUS_PAD + params.orca_safety_space
    return radius


def human_velocities(
    humans: Humans,
    robot: Robot | None,
    params: EnvParams,
    config: EnvConfig,
    neighbor_dist,
    obstacles: Obstacles | None = None,
    obstacle_table: orca.ObstacleTable | None = None,
    steering: Steering | None = None,
):
    """New velocities (N, 2) of all humans from the current joint state.

    `robot` is None when humans do not see the robot (the default); otherwise it joins the solve as an extra
    agent whose own result is discarded. `neighbor_dist` is the episode's ORCA neighbour distance
    (`EnvState.orca_neighbor_dist`). `obstacles`: the episode's static obstacles (ORCA: RVO2's obstacle lines;
    Social Force: the wall force), None or no slots for an open space. `obstacle_table`: optionally the same
    obstacles processed for ORCA (`orca.process_obstacles`, `EnvState.obstacle_table`): the same velocities,
    without processing the obstacles again. `steering`: where the humans head instead of their goals (None:
    straight at their goals).
    """
    if obstacles is not None and obstacles.num_vertices.shape[-1] == 0:
        obstacles = None
    n = humans.pos.shape[0]
    if n == 0:
        return jnp.zeros((0, 2))
    pos, vel, goal, radius, v_pref = humans.pos, humans.vel, humans.goal, humans.radius, humans.v_pref
    if config.human_policy == "orca":
        pref = preferred_velocity(pos, goal) if steering is None else steered_preference(pos, goal, steering)
    elif steering is not None:
        goal = steering.target  # Social Force pulls towards its goal at full speed: the target takes its place
        if steering.velocity is not None:  # ... or at the speed given
            v_pref = jnp.minimum(v_pref, jnp.linalg.norm(steering.velocity, axis=-1))
    present = humans.active
    if robot is not None:
        present = jnp.concatenate([present, jnp.ones((1,), bool)])
        pos = jnp.concatenate([pos, robot.pos[None]])
        vel = jnp.concatenate([vel, robot.vel[None]])
        goal = jnp.concatenate([goal, robot.goal[None]])
        radius = jnp.concatenate([radius, params.robot_radius[None]])
        v_pref = jnp.concatenate([v_pref, params.robot_v_max[None]])
    if config.human_policy == "orca":
        if robot is not None:
            pref = jnp.concatenate([pref, robot.vel[None]])  # the robot's "preference" is what it is doing
        new_vel = orca.solve(
            pos,
            vel,
            body_radius(radius, params, config),
            pref,
            v_pref,
            time_horizon=params.orca_time_horizon,
            dt=params.dt,
            neighbor_dist=neighbor_dist,
            max_neighbors=config.max_neighbors,
            neighbor_mask=present,
            **(
                {}
                if obstacles is None
                else dict(
                    obstacles=(obstacles.vertices, obstacles.num_vertices)
                    if obstacle_table is None
                    else obstacle_table,
                    time_horizon_obst=params.orca_time_horizon_obst,
                )
            ),
        )
    else:
        new_vel = social_force.step(
            pos,
            vel,
            goal,
            radius,
            v_pref,
            a=params.sf_a,
            b=params.sf_b,
            ki=params.sf_ki,
            dt=params.dt,
            neighbor_mask=present,
            obstacles=obstacles,
        )
    # Inactive slots stay where they are parked.
    return jnp.where(humans.active[:, None], new_vel[:n], 0.0)
