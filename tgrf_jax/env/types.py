"""Pytrees of the crowd environment: traced parameters, state, observation and step info."""

from __future__ import annotations

from typing import Any

import jax.numpy as jnp
import numpy as np
from flax import struct

from tgrf_jax.config import EnvConfig, RewardConfig
from tgrf_jax.env.obstacles import Obstacles
from tgrf_jax.env_rules import check_detection_latency, check_env_relations, check_scenario_weights, check_weights
from tgrf_jax.fields import ConfigError, check_traced, concrete, first_where, traced_names, traced_pytree, traced_values
from tgrf_jax.reward import RewardParams, RewardTerms

# Episode outcome codes carried in `Info.outcome`: COLLISION is with a human, OBSTACLE_COLLISION with a static
# obstacle (both end the episode with the collision penalty).
RUNNING, SUCCESS, COLLISION, TIMEOUT, OBSTACLE_COLLISION = 0, 1, 2, 3, 4
OUTCOME_NAMES = ("running", "success", "collision", "timeout", "obstacle_collision")


class _EnvParamsMethods:
    @property
    def max_steps(self):
        return jnp.round(self.time_limit / self.dt).astype(jnp.int32)

    @property
    def goal_change_period(self):
        return jnp.maximum(jnp.round(self.goal_change_interval / self.dt), 1.0).astype(jnp.int32)

    @classmethod
    def from_config(cls, config: EnvConfig, reward: RewardParams) -> EnvParams:
        return cls(**traced_values(config), reward=reward)

    def validate(self, config: EnvConfig | None = None) -> EnvParams:
        """Check the concrete values (on the host; batched params element by element) against the ranges and
        relations declared in `EnvConfig` and `RewardConfig`, as a config is checked, and with the env's `config`
        against its static capacities too. Raises ConfigError (a ValueError) naming the field and what is allowed;
        returns the params."""
        # the weights first: their rule is more than a range (check_traced would only say they must be finite)
        check_scenario_weights(concrete(self.scenario_weights, "env.scenario_weights"))
        check_weights(
            concrete(self.replay_weights, "env.replay_weights"),
            "env.replay_weights",
            "entry of env.replay_files",
            None if config is None or config.replay_files is None else config.replay_entry_names,
        )
        check_traced(self, EnvConfig, "env")
        check_env_relations({n: concrete(getattr(self, n), f"env.{n}") for n in traced_names(EnvConfig)})
        if config is not None:
            check_detection_latency(
                concrete(self.detection_latency, "env.detection_latency"), config.max_detection_latency
            )
            if "replay" in config.drawn_scenarios:
                dt = concrete(self.dt, "env.dt")
                hit = first_where(~np.isclose(dt, config.dt), dt)
                if hit:
                    raise ConfigError(
                        f"env.dt = {hit[0]!s} must equal the config's env.dt = {config.dt:g} in an env with the "
                        "replay scenario: the recordings are resampled onto it when the env is built"
                    )
        check_traced(self.reward, RewardConfig, "reward")
        return self


EnvParams = traced_pytree(
    "EnvParams",
    EnvConfig,
    last=(("reward", RewardParams), ("predictor", Any, None)),
    base=_EnvParamsMethods,
    module=__name__,
    doc="""Every numeric setting of the environment (traced: vmap over any field for grids or randomisation).

    One float32 leaf per traced field of `EnvConfig` (where each is declared and documented), plus the reward
    parameters and, with `env.predictor: gst`, the learned predictor's weights (`predictor`, else None);
    `CrowdNavEnv.default_params` builds it from a config.""",
)


@struct.dataclass
class Humans:
    """True state of the N human slots (world frame).

    Only the slots where `active` holds are people in the scene; the others are parked far away, stand still
    and are masked out of every interaction, observation and metric. In the synthetic scenarios the active ones
    fill the first slots and stay active for the episode; replayed recordings (`tgrf_jax.env.replay`) activate a
    slot while its recorded person is in view, in any slot.
    """

    pos: jnp.ndarray  # (N, 2)
    vel: jnp.ndarray  # (N, 2) velocity applied during the last step
    goal: jnp.ndarray  # (N, 2)
    radius: jnp.ndarray  # (N,)
    v_pref: jnp.ndarray  # (N,)
    active: jnp.ndarray  # (N,) bool (fixed for the episode, except in replayed recordings)


@struct.dataclass
class Robot:
    pos: jnp.ndarray  # (2,)
    vel: jnp.ndarray  # (2,) velocity applied during the last step
    goal: jnp.ndarray  # (2,)
    heading: jnp.ndarray  # () rad; stays pi/2 for holonomic robots, as in the reference
    speed: jnp.ndarray  # () signed forward speed (unicycle)


@struct.dataclass
class EnvState:
    robot: Robot
    humans: Humans
    goal_dist_ref: jnp.ndarray  # () goal distance at the last step outside the danger zone (for r_pot)
    step_count: jnp.ndarray  # () int32 steps taken in this episode
    orca_neighbor_dist: jnp.ndarray  # () the humans' ORCA neighbour distance, drawn once per episode
    scenario: jnp.ndarray  # () int32 the episode's scenario: its index in config.drawn_scenarios (fixed scenario: 0)
    obstacles: Obstacles  # the episode's static obstacles (env.obstacle_slots slots; none: 0 slots)
    obstacles_dropped: jnp.ndarray  # () int32 obstacle slots removed at reset for lying on the robot's start or goal
    progress: Any  # tgrf_jax.env.stuck.Progress: the humans' still spells (the stuck measure)
    history: Any = None  # learned predictor's observed frames (tgrf_jax.env.gst.history), else None
    # `obstacles` processed once for the ORCA humans (orca.process_obstacles, at reset), else None (then every
    # solve processes them itself, with the same results); derived data: replacing `obstacles` needs a new one
    obstacle_table: Any = None
    # the humans' routing among the obstacles (tgrf_jax.env.routing.Routing), None without obstacle slots
    routing: Any = None
    # sensing (tgrf_jax.env.detection): the episode's `SensorErrors` with env.randomise_sensing, else None (then
    # the params' values hold); the last env.max_detection_latency `Detections` frames, newest first, else None
    sensor_errors: Any = None
    detections: Any = None
    # the recording an episode plays (tgrf_jax.env.replay.ReplayState) in an env with the replay scenario, else None
    replay: Any = None


@struct.dataclass
class SensorErrors:
    """How the people sensor errs in an episode: the env's params, or with env.randomise_sensing a draw per episode."""

    noise: jnp.ndarray  # () std of each position (m) and velocity (m/s) component
    dropout: jnp.ndarray  # () probability that a visible person is missed on a step
    false_rate: jnp.ndarray  # () mean phantom detections per step
    latency: jnp.ndarray  # () int32 steps by which detections are late
    fov: jnp.ndarray  # () degrees, centred on the robot's heading


@struct.dataclass
class Detections:
    """One frame of what the people sensor reports, in human-slot order, world frame: a slot holds a detected
    person (true identity, perceived position and velocity), a phantom, or nothing (`seen` false)."""

    pos: jnp.ndarray  # (N, 2)
    vel: jnp.ndarray  # (N, 2)
    radius: jnp.ndarray  # (N,)
    seen: jnp.ndarray  # (N,) bool
    pred: Any = None  # (N, K, 2) predicted world positions, or None without predictions


@struct.dataclass
class Obs:
    """What the robot perceives. Human rows are sorted by distance, visible ones first.

    robot_node:  (7,)  [px, py, radius, gx, gy, v_max, heading], world frame (as the reference's robot_node)
    robot_vel:   (2,)  last applied robot velocity
    humans:      (N, D) per human: position relative to the robot, then K predicted positions relative to the
                 robot's current position (D = 2 (K + 1), or 2 without predictions); zero where not visible
    human_mask:  (N,)  bool, True for humans within sensor range (a mask, never a magic coordinate)
    human_vel:   (N, 2) velocities of visible humans (used by the ORCA-robot baseline; zero where masked)
    human_radius:(N,)  radii of visible humans (zero where masked)
    lidar:       (R,)  2-D LiDAR ranges in metres (R = env.lidar_rays, 0: none), ray k at heading + 2 pi k / R
                 counter-clockwise (the robot's body frame), hits on obstacles and humans' discs, env.sensor_range
                 where nothing is hit
    obstacles:   the episode's static obstacles, world frame (the map; used by the ORCA-robot baseline, not by
                 the networks)
    """

    robot_node: jnp.ndarray
    robot_vel: jnp.ndarray
    humans: jnp.ndarray
    human_mask: jnp.ndarray
    human_vel: jnp.ndarray
    human_radius: jnp.ndarray
    lidar: jnp.ndarray
    obstacles: Obstacles


@struct.dataclass
class Info:
    """Everything metrics need about one step (values refer to the step's post-step state, before auto-reset)."""

    outcome: jnp.ndarray  # () int32: RUNNING, SUCCESS, COLLISION or TIMEOUT
    time: jnp.ndarray  # () seconds elapsed in the episode after this step
    dmin: jnp.ndarray  # () nearest edge-to-edge robot-human distance (inf without humans)
    intrusion_disc: jnp.ndarray  # () bool, dmin < d_disc
    intrusion_future: jnp.ndarray  # () bool, robot within intrusion_radius of a visible human's true future
    future_dist: jnp.ndarray  # () smallest such centre distance (inf when not tracked / no intrusion)
    path_increment: jnp.ndarray  # () distance the robot moved this step
    num_visible: jnp.ndarray  # () int32
    obstacle_dist: jnp.ndarray  # () robot's edge distance to the nearest obstacle (inf without obstacles)
    obstacles_dropped: jnp.ndarray  # () int32, the episode's EnvState.obstacles_dropped
    humans_active: jnp.ndarray  # () int32 humans present after the step
    humans_stuck: jnp.ndarray  # () int32 of them stuck (tgrf_jax.env.stuck)
    goals_reassigned: jnp.ndarray  # () int32 humans given a new goal this step for staying stuck (env.unstuck_after)
    humans_unreachable: jnp.ndarray  # () int32 humans whose goal no path reaches (routing among obstacles)
    reward_terms: RewardTerms
    final_obs: Obs  # observation of the post-step state before any auto-reset (for bootstrapping)
