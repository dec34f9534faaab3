"""Robot policies with one interface, so evaluation, rendering and training treat baselines and learned
policies alike.

A policy has `initialize_carry(batch_size)` and `act(carry, obs, resets, key) -> (carry, action)` on a batch
of observations (leading axis B). `resets` (B,) marks episode starts, where a recurrent policy zeroes its
state; the baselines here are memoryless and keep a dummy carry.
"""

from __future__ import annotations

import dataclasses
from typing import Protocol

import jax
import jax.numpy as jnp

from tgrf_jax.env import orca, routing
from tgrf_jax.env.humans import ORCA_RADIUS_PAD, preferred_velocity
from tgrf_jax.env.types import Obs


class Policy(Protocol):
    def initialize_carry(self, batch_size: int): ...

    def act(self, carry, obs: Obs, resets, key): ...


def _dummy_carry(batch_size: int):
    return jnp.zeros((batch_size, 1), jnp.float32)


@dataclasses.dataclass(frozen=True)
class StraightPolicy:
    """Drive straight at the goal at full speed, ignoring everyone (the lower bound of every table)."""

    def initialize_carry(self, batch_size: int):
        return _dummy_carry(batch_size)

    def act(self, carry, obs: Obs, resets, key):
        return carry, jax.vmap(self.action)(obs)

    @staticmethod
    def action(obs: Obs):
        pos, goal, v_max = obs.robot_node[:2], obs.robot_node[3:5], obs.robot_node[5]
        offset = goal - pos
        dist = jnp.linalg.norm(offset)
        return offset / jnp.maximum(dist, 1e-6) * v_max


@dataclasses.dataclass(frozen=True)
class OrcaPolicy:
    """The robot solves ORCA against the humans it sees (their positions, velocities and radii).

    Settings follow the CrowdNav ORCA robot: 10 m neighbour distance, 5 s horizon, safety space 0.15, the
    preferred velocity points at the goal with speed v_max. Unseen humans are masked out of the solve.

    With static obstacles (`obs.obstacles` holds M > 0 slots: the map, not the LiDAR) the solve also keeps the
    robot off them, as RVO2's obstacle lines do, for `time_horizon_obst` seconds, and (`route`) the preferred
    velocity points at the farthest point of the robot's shortest path around them that it can see, over the
    map's visibility roadmap (`tgrf_jax.env.routing`, as the humans route; corners pushed out by the robot's
    radius, safety space and `route_margin`): a global plan with ORCA as its local planner, as a robot with a
    map would drive. Without obstacles (M = 0) the call is the obstacle-free one, unchanged.
    """

    time_horizon: float = 5.0
    # RVO2's timeHorizonObst for the robot: the same 5 s as its horizon for humans, as CrowdNav's ORCA robot sets
    # both (time_horizon_obst = time_horizon = 5).
    time_horizon_obst: float = 5.0
    neighbor_dist: float = 10.0
    safety_space: float = 0.15
    dt: float = 0.25
    route: bool = True
    route_margin: float = 0.2

    def initialize_carry(self, batch_size: int):
        return _dummy_carry(batch_size)

    def act(self, carry, obs: Obs, resets, key):
        return carry, jax.vmap(self.action)(obs)

    def action(self, obs: Obs):
        n = obs.human_mask.shape[0]
        robot_pos, radius, goal, v_max = obs.robot_node[:2], obs.robot_node[2], obs.robot_node[3:5], obs.robot_node[5]
        # Agent 0 is the robot at the origin of its own frame; humans are at their relative positions.
        pos = jnp.concatenate([jnp.zeros((1, 2)), obs.humans[:, :2]])
        vel = jnp.concatenate([obs.robot_vel[None], obs.human_vel])
        radii = jnp.concatenate([radius[None], obs.human_radius]) + ORCA_RADIUS_PAD + self.safety_space
        pref = preferred_velocity(robot_pos, goal) * v_max
        if self.route and obs.obstacles.num_vertices.shape[-1] > 0:
            pref = self._routed(obs.obstacles, robot_pos, radius, goal, v_max, pref)
        prefs = jnp.concatenate([pref[None], obs.human_vel])
        max_speeds = jnp.concatenate([v_max[None], jnp.full((n,), v_max)])
        seen = jnp.concatenate([jnp.ones((1,), bool), obs.human_mask])
        extra = {}
        if obs.obstacles.num_vertices.shape[-1] > 0:
            # the obstacles in the same robot-centred frame as the agents
            extra = dict(
                obstacles=(obs.obstacles.vertices - robot_pos, obs.obstacles.num_vertices),
                time_horizon_obst=self.time_horizon_obst,
            )
        new_vel = orca.solve(
            pos,
            vel,
            radii,
            prefs,
            max_speeds,
            time_horizon=self.time_horizon,
            dt=self.dt,
            neighbor_dist=self.neighbor_dist,
            max_neighbors=n,
            neighbor_mask=seen,
            **extra,
        )
        return new_vel[0]

    def _routed(self, obstacles, robot_pos, radius, goal, v_max, pref):
        """The preferred velocity towards the robot's route target: `pref` (straight at the goal) when the goal is
        in sight or cannot be reached, else full speed at the farthest visible point of the shortest path."""
        body = radius + ORCA_RADIUS_PAD + self.safety_space
        roadmap = routing.build_roadmap(obstacles, body + self.route_margin, body)
        to_goal = routing.goal_costs(roadmap, goal, obstacles, body)
        target, _ = routing.aim(roadmap, to_goal, robot_pos, goal, obstacles, body)
        offset = target - robot_pos
        toward = offset / jnp.maximum(jnp.linalg.norm(offset), 1e-6) * v_max
        return jnp.where(jnp.all(target == goal), pref, toward)


BASELINES = {"straight": StraightPolicy, "orca": OrcaPolicy}


def baseline(name: str) -> Policy:
    if name not in BASELINES:
        raise ValueError(f"unknown baseline policy {name!r}; valid: {', '.join(BASELINES)}")
    return BASELINES[name]()
