"""The crowd-navigation environment: pure `reset` / `step` in the gymnax 1.0 shape, jit- and vmap-able.

Step order (docs/reference.md; docs/differences.md lists where it departs from the reference): clip the robot's
action and move it; every human picks a velocity from the pre-step joint state and moves; collision (swept over
the step), goal and danger are judged on the state the action led to; then human goal changes and respawns; then
predictions and the new observation.
"""

from __future__ import annotations

import pathlib
from collections.abc import Mapping

import chex
import jax
import jax.numpy as jnp

from tgrf_jax import reward as reward_lib
from tgrf_jax.config import EnvConfig, RewardConfig, reward_config_from_dict
from tgrf_jax.env import detection, orca, prediction, routing, scenarios, sensing, stuck
from tgrf_jax.env import humans as humans_lib
from tgrf_jax.env import obstacles as obstacles_lib
from tgrf_jax.env import replay as replay_lib
from tgrf_jax.env.geometry import norm
from tgrf_jax.env.gst import history as gst_history
from tgrf_jax.env.gst import weights as gst_weights
from tgrf_jax.env.obstacles import Obstacles
from tgrf_jax.env.scenarios.sampling import sample_attributes
from tgrf_jax.env.types import (
    COLLISION,
    OBSTACLE_COLLISION,
    RUNNING,
    SUCCESS,
    TIMEOUT,
    EnvParams,
    EnvState,
    Info,
    Obs,
    Robot,
)

_START_CLEARANCE = 0.2  # metres kept between the robot and an obstacle at its start and goal
_RESET_CHUNK = 16  # fresh episodes computed together by step_batch (a step finishes a few per 512 envs)
# Largest perturbation (m/s) of a routed ORCA human's preferred velocity against exact symmetries (as in RVO2's
# examples): far below anything visible, enough to break a tie between two mirror-image humans.
_JITTER = 1e-4


def _as_env_config(config) -> EnvConfig:
    if config is None:
        return EnvConfig()
    if isinstance(config, EnvConfig):
        return config
    if isinstance(config, Mapping):
        return EnvConfig.from_dict(config)
    if isinstance(config, (str, pathlib.Path)):
        return EnvConfig.from_yaml(config)
    raise TypeError(f"env config must be an EnvConfig, a dict or a YAML path, not {type(config).__name__}")


def _as_reward_config(reward) -> RewardConfig:
    if isinstance(reward, RewardConfig):
        return reward
    if isinstance(reward, str):
        return RewardConfig(scheme=reward)
    if isinstance(reward, Mapping) or reward is None:
        return reward_config_from_dict(reward)
    raise TypeError(f"reward must be a RewardConfig, a scheme name or a dict, not {type(reward).__name__}")


def move_robot(robot: Robot, action, params: EnvParams, kinematics: str) -> tuple[Robot, jnp.ndarray]:
    """Apply an action; returns the moved robot and the heading change (for the unicycle spin penalty).

    Non-finite actions are sanitised first (NaN -> 0, +-inf -> the largest float), so no action can corrupt
    the state. Holonomic: action = (vx, vy), rescaled to norm <= v_max, keeping its direction however large
    it is. Unicycle: action = (dv, dtheta), each clipped to its per-step limit, speed clipped to [-v_max, v_max].
    """
    action = jnp.nan_to_num(jnp.asarray(action, jnp.float32), nan=0.0)
    if kinematics == "holonomic":
        speed = jnp.linalg.norm(action)
        vel = action * jnp.minimum(1.0, params.robot_v_max / jnp.maximum(speed, 1e-12))
        # The norm of (1e30, 1e30) overflows float32: such actions are scaled by their largest component first
        # (infinite components become the direction), so the robot still moves at v_max their way.
        # (Pre-scaled by 2^-64: XLA flushes 1 / 3e38, a subnormal, to zero.)
        shrunk = action * jnp.float32(2.0**-64)
        scale = jnp.max(jnp.abs(shrunk))
        unit = jnp.where(jnp.isinf(scale), jnp.sign(action) * jnp.isinf(action), shrunk / scale)
        huge = unit * (params.robot_v_max / jnp.linalg.norm(unit))
        vel = jnp.where(jnp.isfinite(speed), vel, huge)
        moved = robot.replace(pos=robot.pos + vel * params.dt, vel=vel)
        return moved, jnp.zeros(())
    dv = jnp.clip(action[0], params.unicycle_dv_min, params.unicycle_dv_max)
    dtheta = jnp.clip(action[1], -params.unicycle_dtheta_max, params.unicycle_dtheta_max)
    speed = jnp.clip(robot.speed + dv, -params.robot_v_max, params.robot_v_max)
    heading = robot.heading + dtheta
    vel = speed * jnp.stack([jnp.cos(heading), jnp.sin(heading)])
    moved = robot.replace(pos=robot.pos + vel * params.dt, vel=vel, heading=heading, speed=speed)
    return moved, dtheta


def swept_min_distance(rel_start, rel_motion):
    """Smallest |rel_start + s * rel_motion| over s in [0, 1], per row (N,)."""
    denom = jnp.square(rel_motion[:, 0]) + jnp.square(rel_motion[:, 1])
    s = jnp.clip(
        -(rel_start[:, 0] * rel_motion[:, 0] + rel_start[:, 1] * rel_motion[:, 1]) / jnp.maximum(denom, 1e-12), 0.0, 1.0
    )
    return norm(rel_start + s[:, None] * rel_motion)


class CrowdNavEnv:
    """Socially aware navigation among N humans (the CrowdNav++ scenario, docs/reference.md).

    `config` holds the static choices (shapes, code paths) and the defaults of every numeric parameter;
    `default_params` turns the numeric ones into a traced `EnvParams` pytree.
    """

    action_size = 2

    def __init__(self, config: EnvConfig | Mapping | str | pathlib.Path | None = None, reward="tgrf"):
        self.config = _as_env_config(config)
        self.reward_config = _as_reward_config(reward)
        # the env's scenarios (its env.scenario, or the mix's), from the registry; EnvState.scenario indexes it
        self.scenario_table = scenarios.ScenarioTable.of(self.config)
        # the recordings of the replay scenario, read and packed here, before anything compiles (else None)
        drawn = self.config.drawn_scenarios
        self.replay = replay_lib.load_data(self.config) if "replay" in drawn else None
        self._replay_index = drawn.index("replay") if "replay" in drawn else None

    def __repr__(self):
        c = self.config
        return (
            f"CrowdNavEnv(num_humans={c.num_humans}, human_policy={c.human_policy!r}, "
            f"predictor={c.predictor!r}, kinematics={c.kinematics!r}, reward={self.reward_config.scheme!r})"
        )

    # Environments with equal configs are interchangeable, so jit caches keyed on them are shared. Replayed
    # recordings are constants of the compiled program: envs share them (and a program) only while the files are
    # unchanged on disk (`replay.load_data` hands equal configs the same arrays until a file changes).
    def __eq__(self, other):
        return isinstance(other, CrowdNavEnv) and (self.config, self.reward_config, self.replay) == (
            other.config,
            other.reward_config,
            other.replay,
        )

    def __hash__(self):
        return hash((self.config, self.reward_config, self.replay))

    @property
    def default_params(self) -> EnvParams:
        params = EnvParams.from_config(self.config, self.reward_config.params())
        if self.replay is not None and self.config.replay_weights is None:
            params = params.replace(replay_weights=jnp.asarray(self.replay.entry_lengths))
        if self.config.predictor == "gst":
            params = params.replace(predictor=gst_weights.for_env(self.config))
        return params

    @property
    def num_humans(self) -> int:
        return self.config.num_humans

    @property
    def obs_human_dim(self) -> int:
        return self.config.obs_human_dim

    @property
    def replay_only(self) -> bool:
        """Every episode plays a recording (env.scenario: replay): the synthetic samplers are never called."""
        return self.replay is not None and len(self.scenario_table.names) == 1

    def _is_replay(self, index):
        """Whether an episode of scenario `index` plays a recording (a traced bool in a mix with replay)."""
        return True if self.replay_only else index == self._replay_index

    def _pick(self, is_replay, replayed, synthetic):
        """`replayed` in replay episodes, else `synthetic` (pytrees of equal structure)."""
        if self.replay_only:
            return replayed
        return jax.tree_util.tree_map(lambda a, b: jnp.where(is_replay, a, b), replayed, synthetic)

    # ------------------------------------------------------------------ public API (auto-reset)
    def reset(self, key, params: EnvParams | None = None) -> tuple[Obs, EnvState]:
        params = self.default_params if params is None else params
        return self.reset_env(key, params)

    def step(self, key, state: EnvState, action, params: EnvParams | None = None):
        """One step with automatic reset: returns (obs, state, reward, terminated, truncated, info).

        When the episode ends, `obs`/`state` already belong to a fresh episode and `info.final_obs` holds the
        observation of the state the action led to, so a learner can bootstrap through a time-limit
        truncation (which is not a termination).
        """
        params = self.default_params if params is None else params
        k_step, k_reset = jax.random.split(key)
        obs, next_state, reward, terminated, truncated, info = self.step_env(k_step, state, action, params)
        reset_obs, reset_state = self.reset_env(k_reset, params)
        done = terminated | truncated
        pick = lambda fresh, cont: jnp.where(done, fresh, cont)
        next_state = jax.tree_util.tree_map(pick, reset_state, next_state)
        obs = jax.tree_util.tree_map(pick, reset_obs, obs)
        return obs, next_state, reward, terminated, truncated, info

    def step_batch(self, key, state: EnvState, action, params: EnvParams, num_resets: int):
        """Step a batch of B environments (leading axis of `state` and `action`) with automatic reset, drawing
        only `num_resets` fresh episodes per call instead of one per environment.

        `step` pays for a reset in every environment on every step and keeps it only where an episode ended
        (a few percent of steps); here `num_resets` fresh episodes are sampled once and the k-th environment
        that finished in this call takes fresh episode k mod num_resets. With num_resets >= B every finished
        episode is replaced by its own fresh one; with fewer, two environments finishing in the same step
        beyond num_resets share a start state (they diverge from the next step on). Only the fresh episodes
        that are taken are computed. Same returns as `jax.vmap(step)`; `params` is shared by the batch.
        """
        num_envs = action.shape[0]
        num_resets = max(1, min(int(num_resets), num_envs))
        k_step, k_reset = jax.random.split(key)
        obs, next_state, reward, terminated, truncated, info = jax.vmap(self.step_env, in_axes=(0, 0, 0, None))(
            jax.random.split(k_step, num_envs), state, action, params
        )
        done = terminated | truncated
        reset_obs, reset_state = self._fresh_episodes(k_reset, params, num_resets, jnp.sum(done, dtype=jnp.int32))
        slot = (jnp.cumsum(done.astype(jnp.int32)) - 1) % num_resets

        def pick(fresh, cont):
            fresh = fresh[slot]
            return jnp.where(done.reshape(done.shape + (1,) * (cont.ndim - 1)), fresh, cont)

        next_state = jax.tree_util.tree_map(pick, reset_state, next_state)
        obs = jax.tree_util.tree_map(pick, reset_obs, obs)
        return obs, next_state, reward, terminated, truncated, info

    def _fresh_episodes(self, key, params: EnvParams, num_resets: int, num_done):
        """(obs, state) of fresh episodes 0..num_resets-1 (episode k from the k-th key of split(key,
        num_resets)), of which only the first min(num_done, num_resets) are computed, in chunks: only those
        are used, and a step finishes far fewer episodes than there are slots (the others stay zero)."""
        keys = jax.random.split(key, num_resets)
        chunk = min(_RESET_CHUNK, num_resets)
        reset_batch = jax.vmap(self.reset_env, in_axes=(0, None))
        fresh = jax.tree_util.tree_map(
            lambda s: jnp.zeros((num_resets,) + s.shape[1:], s.dtype), jax.eval_shape(reset_batch, keys[:chunk], params)
        )

        def run_chunk(c, fresh):
            start = jnp.minimum(c * chunk, num_resets - chunk)  # the last chunk overlaps: recomputed, identical
            part = reset_batch(jax.lax.dynamic_slice_in_dim(keys, start, chunk), params)
            return jax.tree_util.tree_map(lambda f, p: jax.lax.dynamic_update_slice_in_dim(f, p, start, 0), fresh, part)

        needed = jnp.minimum(num_done, num_resets)
        return jax.lax.fori_loop(0, (needed + chunk - 1) // chunk, run_chunk, fresh)

    # ------------------------------------------------------------------ dynamics
    def reset_env(self, key, params: EnvParams) -> tuple[Obs, EnvState]:
        k_robot, k_humans = jax.random.split(key)
        tries = self.config.spawn_tries
        table = self.scenario_table
        # Folded keys (not splits) keep the robot and crowd of a full-crowd circle-crossing episode what they were
        # before the neighbour distance, the crowd size and the scenario became random.
        index = table.draw(jax.random.fold_in(key, 3), params.scenario_weights)
        replay_state = None
        if self.replay is not None:
            is_replay = self._is_replay(index)
            radius, v_pref = sample_attributes(jax.random.fold_in(key, 9), params, (self.config.num_humans,))
            replay_state, r_robot, r_humans = replay_lib.reset(
                jax.random.fold_in(key, 8), self.replay, params, self.config, radius, v_pref
            )
        robot = r_robot if self.replay_only else table.robot(k_robot, params, index, tries)
        if self.replay is not None:
            robot = self._pick(is_replay, r_robot, robot)
        layout, dropped = self._layout(jax.random.fold_in(key, 4), params, robot, index)
        if self.replay_only:
            humans = r_humans
        else:
            active = scenarios.active_slots(jax.random.fold_in(key, 2), params, self.config.num_humans)
            humans = scenarios.spawn_humans(
                k_humans, params, robot, self.config.num_humans, tries, active, table, index, layout
            )
            if self.replay is not None:
                humans = self._pick(is_replay, r_humans, humans)
        neighbor_dist = scenarios.uniform(
            jax.random.fold_in(key, 1), (), params.orca_neighbor_dist_min, params.orca_neighbor_dist_max
        )
        state = EnvState(
            robot=robot,
            humans=humans,
            goal_dist_ref=jnp.linalg.norm(robot.pos - robot.goal),
            step_count=jnp.zeros((), jnp.int32),
            orca_neighbor_dist=neighbor_dist,
            scenario=index,
            obstacles=layout,
            obstacles_dropped=dropped,
            progress=stuck.fresh(humans),
            obstacle_table=self._obstacle_table(layout),
            routing=self._plan_routes(layout, humans, params),
            replay=replay_state,
        )
        if self.config.randomise_sensing:
            errors = detection.draw_errors(jax.random.fold_in(key, 5), params, self.config.max_detection_latency)
            state = state.replace(sensor_errors=errors)
        visible = self.visible(state, params)
        if self.config.predictor == "gst":
            state = state.replace(history=gst_history.fresh(robot.pos, humans.pos, visible))
            # Nobody is seen in two frames of a fresh history, so the model would predict nobody and every
            # human would hold its position: skipping it halves the model's cost in auto-resetting steps.
            predictions = gst_history.fresh_predictions(state.history)
        else:
            predictions, _ = self._predict(state, params, visible)
        frame = self._perceive(jax.random.fold_in(key, 6), state, params, predictions, visible)
        if self.config.max_detection_latency > 0:
            state = state.replace(detections=detection.fill_buffer(frame, self.config.max_detection_latency))
        return self._observe(state, params, frame), state

    def _layout(self, key, params: EnvParams, robot: Robot, index) -> tuple[Obstacles, jnp.ndarray]:
        """The episode's obstacles: the scenario's slots, then the fixed `env.obstacles`; a slot that would hold the
        robot's start or goal is removed (and counted), so the robot never starts in a wall nor has its goal in one."""
        cfg = self.config
        if cfg.obstacle_slots == 0:
            return obstacles_lib.empty(0, cfg.obstacle_vertices), jnp.zeros((), jnp.int32)
        parts = []
        if self.scenario_table.draws_obstacles:
            vertices, counts = self.scenario_table.layout(key, params, robot, index, cfg.spawn_tries)
            pad = cfg.obstacle_vertices - vertices.shape[1]
            parts.append(Obstacles(jnp.pad(vertices, ((0, 0), (0, pad), (0, 0))), counts))
        if cfg.obstacles:
            parts.append(obstacles_lib.from_polygons(cfg.obstacles, max_vertices=cfg.obstacle_vertices))
        layout = Obstacles(
            jnp.concatenate([p.vertices for p in parts]),
            jnp.concatenate([p.num_vertices for p in parts]).astype(jnp.int32),
        )
        # per slot: the robot's room at its start and goal from that slot alone
        single = jax.vmap(lambda v, n: Obstacles(v[None], n[None]))(layout.vertices, layout.num_vertices)
        room = jax.vmap(lambda one: obstacles_lib.clearance(jnp.stack([robot.pos, robot.goal]), one))(single)
        blocking = (layout.num_vertices > 0) & jnp.any(room < params.robot_radius + _START_CLEARANCE, axis=-1)
        layout = layout.replace(num_vertices=jnp.where(blocking, 0, layout.num_vertices))
        return layout, jnp.sum(blocking, dtype=jnp.int32)

    def _obstacle_table(self, layout: Obstacles):
        """The episode's obstacles processed for the ORCA humans (RVO2's obstacle tree, built once per episode
        instead of in every ORCA solve), or None (no obstacle slots, or Social Force humans)."""
        cfg = self.config
        if cfg.obstacle_slots == 0 or cfg.human_policy != "orca" or cfg.num_humans == 0:
            return None
        return orca.process_obstacles(layout.vertices, layout.num_vertices)

    @property
    def routes_humans(self) -> bool:
        """Whether the humans route around obstacles (env.human_routing, in an env with obstacle slots and humans)."""
        cfg = self.config
        # recorded people follow their recordings, never a route (a mix routes its synthetic episodes' humans)
        return cfg.human_routing and cfg.obstacle_slots > 0 and cfg.num_humans > 0 and not self.replay_only

    def _plan_routes(self, layout: Obstacles, humans, params: EnvParams):
        if not self.routes_humans:
            return None
        radius = humans_lib.body_radius(params.human_radius_max, params, self.config)
        return routing.plan(layout, humans.goal, radius, radius + params.route_margin)

    def _steering(self, key, state: EnvState, params: EnvParams):
        """Where the humans head this step (None: at their goals) and how many cannot reach their goal."""
        if state.routing is None:
            return None, jnp.zeros((), jnp.int32)
        h = state.humans
        radii = humans_lib.body_radius(h.radius, params, self.config)
        target, at_goal, reachable = routing.targets(state.routing, h.pos, h.goal, radii, state.obstacles)
        k_angle, k_size = jax.random.split(key)
        angle = jax.random.uniform(k_angle, h.radius.shape, maxval=2.0 * jnp.pi)
        size = jax.random.uniform(k_size, h.radius.shape, maxval=_JITTER)
        jitter = size[:, None] * jnp.stack([jnp.cos(angle), jnp.sin(angle)], -1)
        unreachable = jnp.sum(h.active & ~reachable, dtype=jnp.int32)
        return humans_lib.Steering(target, at_goal, jitter), unreachable

    def _unstick(self, key, humans, robot, params: EnvParams, progress, step_count, scenario, layout):
        """A new goal for each human that has stayed still, away from its goal, for env.unstuck_after seconds."""
        if not self.routes_humans:
            return humans, progress, jnp.zeros((), jnp.int32)
        still = stuck.still_seconds(progress, step_count, params.dt)
        stale = stuck.away_from_goal(humans) & (params.unstuck_after > 0) & (still >= params.unstuck_after)
        humans = scenarios.reassign_goals(
            key, humans, robot, params, stale, self.config.goal_tries, self.scenario_table, scenario, layout
        )
        return humans, stuck.restart(progress, stale, step_count), jnp.sum(stale, dtype=jnp.int32)

    def visible(self, state: EnvState, params: EnvParams):
        """Humans the robot could perceive: within sensor range and field of view and, with env.occlusion, in its
        line of sight (before the sensor's random errors: `_perceive`)."""
        fov = self.sensor_errors(state, params).fov
        visible = sensing.visible_mask(state, params)
        visible = visible & sensing.in_field_of_view(state.robot.pos, state.robot.heading, state.humans.pos, fov)
        if self.config.occlusion and self.config.obstacle_slots > 0:
            visible = visible & obstacles_lib.line_of_sight(state.robot.pos, state.humans.pos, state.obstacles)
        return visible

    def sensor_errors(self, state: EnvState, params: EnvParams):
        """The episode's `SensorErrors`: drawn at reset with env.randomise_sensing, else (or for a state built
        without them) the params'."""
        if state.sensor_errors is not None:
            return state.sensor_errors
        return detection.configured_errors(params, self.config.max_detection_latency)

    def _perceive(self, key, state: EnvState, params: EnvParams, predictions, visible):
        """This step's detection frame (`detection.perceive`) from the true state and predictions."""
        errors = self.sensor_errors(state, params)
        return detection.perceive(
            key, state.robot, state.humans, visible, predictions, params, errors, self.config.predictor
        )

    def _delay(self, state: EnvState, params: EnvParams, frame):
        """(the frame the robot sees now, the state with `frame` in its delay buffer): without a buffer, `frame`."""
        capacity = self.config.max_detection_latency
        if capacity == 0:
            return frame, state
        if state.detections is None:
            raise ValueError(
                f"env.max_detection_latency = {capacity} needs the delay buffer in EnvState.detections, but this "
                "state has none: start episodes with env.reset (or set it to detection.fill_buffer(frame, capacity))"
            )
        late, buffer = detection.delay(state.detections, frame, self.sensor_errors(state, params).latency)
        return late, state.replace(detections=buffer)

    def _observe(self, state: EnvState, params: EnvParams, frame) -> Obs:
        """The observation of detection `frame` (`_perceive`, or `sensing.exact_detections`) from `state`'s robot."""
        cfg = self.config
        if cfg.lidar_rays > 0:
            h = state.humans
            lidar = obstacles_lib.lidar_scan(
                state.robot.pos,
                state.robot.heading,
                state.obstacles,
                h.pos,
                h.radius,
                h.active,
                num_rays=cfg.lidar_rays,
                max_range=params.sensor_range,
            )
        else:
            lidar = jnp.zeros((0,), jnp.float32)
        return sensing.observe_detections(state, params, frame, lidar)

    def step_env(self, key, state: EnvState, action, params: EnvParams):
        """One step without auto-reset: (obs, state, reward, terminated, truncated, info)."""
        chex.assert_shape(action, (self.action_size,))
        cfg = self.config
        k_goal, k_respawn = jax.random.split(key)
        k_sense = jax.random.fold_in(key, 7)  # folded, so the split above draws what it drew before sensing errors
        robot0, humans0 = state.robot, state.humans

        robot, delta_heading = move_robot(robot0, action, params, cfg.kinematics)
        layout = state.obstacles
        step_count = state.step_count + 1
        is_replay = self._is_replay(state.scenario)
        if self.replay_only and cfg.human_policy == "replay":
            humans, unreachable = humans0, jnp.zeros((), jnp.int32)  # moved along the recording below
        else:
            # folded keys: the goal and respawn draws stay what they are without routing
            steering, unreachable = self._steering(jax.random.fold_in(key, 5), state, params)
            solver_humans = humans0
            if self.replay is not None:
                # reactive replay: heading along the recording, at the speeds that keep to it
                r_steering, r_humans = replay_lib.steering(self.replay, state.replay, humans0, params, state.step_count)
                if self.replay_only:
                    steering = r_steering
                else:
                    steering = self._pick(is_replay, r_steering, self._given_velocity(humans0, steering))
                    unreachable = jnp.where(is_replay, 0, unreachable)
                solver_humans = self._pick(is_replay, r_humans, humans0)
            human_vel = humans_lib.human_velocities(
                solver_humans,
                robot0 if cfg.robot_visible else None,
                params,
                cfg,
                state.orca_neighbor_dist,
                layout,
                state.obstacle_table,
                steering,
            )
            humans = humans0.replace(pos=humans0.pos + human_vel * params.dt, vel=human_vel)
        sweep_from = humans0.pos
        replay_state = state.replay
        if self.replay is not None:
            # the recording's people at the new step: those who walked on from their slot moved by the step's
            # velocities (reactive) or along the recording; those entering appear where recorded, those leaving go
            moved = None if cfg.human_policy == "replay" else humans
            r_next, r_state = replay_lib.advance(self.replay, state.replay, humans0, moved, robot, step_count)
            humans = self._pick(is_replay, r_next, humans)
            replay_state = self._pick(is_replay, r_state, state.replay)
            # a person's sweep starts where their velocity says they came from (not from a parking spot or another
            # slot's person)
            sweep_from = self._pick(is_replay, r_next.pos - r_next.vel * params.dt, sweep_from)
        human_vel = humans.vel

        # Outcome of the action, judged on the post-step state (collisions swept over the step).
        contact = params.robot_radius + humans.radius
        closest = swept_min_distance(sweep_from - robot0.pos, (human_vel - robot.vel) * params.dt)
        hit_human = jnp.any((closest < contact) & humans.active)
        if cfg.obstacle_slots > 0:
            hit_obstacle = obstacles_lib.swept_distance(robot0.pos, robot.pos, layout) < params.robot_radius
            obstacle_dist = obstacles_lib.clearance(robot.pos, layout) - params.robot_radius
        else:
            hit_obstacle, obstacle_dist = jnp.zeros((), bool), jnp.full((), jnp.inf)
        collided = hit_human | hit_obstacle
        dmin = jnp.min(
            jnp.where(
                humans.active,
                sensing.edge_distances(robot.pos, humans.pos, params.robot_radius, humans.radius),
                jnp.inf,
            ),
            initial=jnp.inf,
        )
        goal_dist = jnp.linalg.norm(robot.pos - robot.goal)
        reached = goal_dist < params.goal_tolerance

        replayed = humans
        if cfg.num_humans > 0 and not self.replay_only:
            humans = scenarios.change_goals(
                k_goal, humans, robot, params, step_count, cfg.goal_tries, self.scenario_table, state.scenario, layout
            )
            humans = scenarios.respawn_arrived(
                k_respawn,
                humans,
                robot,
                params,
                cfg.spawn_tries,
                self.scenario_table,
                state.scenario,
                layout,
                step_count * params.dt,
            )
        progress = stuck.update(state.progress, humans, step_count)
        stuck_now = stuck.stuck(progress, humans, step_count, params.dt)
        humans, progress, reassigned = self._unstick(
            jax.random.fold_in(key, 6), humans, robot, params, progress, step_count, state.scenario, layout
        )
        if self.replay is not None and not self.replay_only:
            # replay episodes of a mix: no goal changes, respawns nor new goals for the stuck
            humans = self._pick(is_replay, replayed, humans)
            reassigned = jnp.where(is_replay, 0, reassigned)
        next_state = state.replace(
            robot=robot, humans=humans, step_count=step_count, progress=progress, replay=replay_state
        )
        if state.routing is not None:
            changed = jnp.any(humans.goal != humans0.goal, axis=-1)
            next_state = next_state.replace(routing=routing.replan(state.routing, humans.goal, changed, layout))

        visible = self.visible(next_state, params)
        if cfg.predictor == "gst":
            next_state = next_state.replace(history=gst_history.push(state.history, robot.pos, humans.pos, visible))
        predictions, counted = self._predict(next_state, params, visible)
        if predictions is None:
            pred_hits = jnp.zeros((cfg.num_humans, 1), bool)
        else:
            pred_dist = norm(predictions - robot.pos)
            pred_hits = counted[:, None] & (pred_dist < params.reward.pred_radius)

        terms = reward_lib.step_reward(
            params.reward,
            collided=collided,
            reached=reached,
            dmin=dmin,
            delta_d=state.goal_dist_ref - goal_dist,
            pred_hits=pred_hits,
            delta_heading=delta_heading,
            speed=robot.speed,
            obstacle_dist=obstacle_dist,
        )
        # The progress reference only moves outside the danger zone, so the first r_pot after leaving it pays
        # for all the progress made inside (the reference's telescoping potential).
        in_danger = dmin < params.reward.d_disc
        next_state = next_state.replace(goal_dist_ref=jnp.where(in_danger, state.goal_dist_ref, goal_dist))

        terminated = collided | reached
        out_of_time = step_count >= params.max_steps
        if self.replay is not None:  # or out of recording
            out_of_time = out_of_time | (replay_lib.finished(self.replay, replay_state, step_count) & is_replay)
        truncated = out_of_time & ~terminated
        outcome = jnp.select(
            [hit_human, hit_obstacle, reached, truncated], [COLLISION, OBSTACLE_COLLISION, SUCCESS, TIMEOUT], RUNNING
        ).astype(jnp.int32)

        # The episode's last step never counts as an intrusion (it is counted in the ITR's denominator), as in
        # the reference, whose danger check comes after the goal, collision and timeout checks.
        future_hit, future_dist = self._future_intrusion(next_state, visible, predictions, params)
        future_hit = future_hit & ~(terminated | truncated)
        future_dist = jnp.where(future_hit, future_dist, jnp.inf)
        frame, next_state = self._delay(
            next_state, params, self._perceive(k_sense, next_state, params, predictions, visible)
        )
        obs = self._observe(next_state, params, frame)
        info = Info(
            outcome=outcome,
            time=step_count.astype(jnp.float32) * params.dt,
            dmin=dmin,
            intrusion_disc=in_danger,
            intrusion_future=future_hit,
            future_dist=future_dist,
            path_increment=jnp.linalg.norm(robot.pos - robot0.pos),
            num_visible=jnp.sum(visible).astype(jnp.int32),
            obstacle_dist=obstacle_dist,
            obstacles_dropped=state.obstacles_dropped,
            humans_active=jnp.sum(humans.active, dtype=jnp.int32),
            humans_stuck=jnp.sum(stuck_now, dtype=jnp.int32),
            goals_reassigned=reassigned,
            humans_unreachable=unreachable,
            reward_terms=terms,
            final_obs=obs,
        )
        return obs, next_state, terms.total, terminated, truncated, info

    def _predict(self, state: EnvState, params: EnvParams, visible):
        """World-frame predictions (N, K, 2) or None, and the humans whose predictions count for r_pred (visible,
        and for gst also predicted: seen in the last two frames)."""
        if self.config.predictor == "gst":
            pred = gst_history.predictions(params.predictor, state.history)
            return pred.means, visible & pred.out_mask
        if self.replay is not None and self.config.predictor == "truth":
            return self._true_future(state, params, self.config.pred_horizon), visible
        return prediction.predict(
            state.humans,
            params,
            self.config,
            state.orca_neighbor_dist,
            state.obstacles,
            state.obstacle_table,
            state.routing,
        ), visible

    def _future_intrusion(self, state: EnvState, visible, predictions, params):
        """itr_future: robot centre within intrusion_radius of a visible human's true position at t+1..t+K."""
        cfg = self.config
        if not cfg.track_future_intrusion or cfg.num_humans == 0:
            return jnp.zeros((), bool), jnp.full((), jnp.inf)
        if cfg.predictor == "truth":
            future = predictions
        else:
            future = self._true_future(state, params, cfg.pred_horizon)
        dist = norm(future - state.robot.pos)
        dist = jnp.where(visible[:, None], dist, jnp.inf)
        nearest = jnp.min(dist, initial=jnp.inf)
        hit = nearest < params.intrusion_radius
        return hit, jnp.where(hit, nearest, jnp.inf)

    def _true_future(self, state: EnvState, params: EnvParams, k: int):
        """The humans' true positions (N, k, 2) at the next k steps: the human model rolled forward, or in a
        replay episode the recording (exact for env.human_policy replay; the path the people follow, for
        reactive replay)."""
        cfg = self.config
        if self.replay is not None:
            recorded = replay_lib.future(self.replay, state.replay, state.humans, state.step_count, k)
            if self.replay_only:
                return recorded
        rolled = prediction.true_future(
            state.humans,
            params,
            cfg,
            k,
            state.orca_neighbor_dist,
            state.obstacles,
            state.obstacle_table,
            state.routing,
        )
        return rolled if self.replay is None else jnp.where(self._is_replay(state.scenario), recorded, rolled)

    def _given_velocity(self, humans, steering):
        """A synthetic episode's steering (None: straight at the goals) in the form replay's takes, a preferred
        velocity given outright, so a mix can select between the two: ORCA's preferred velocity itself; for Social
        Force the pull towards the target at the human's own speed."""
        n = humans.pos.shape[0]
        if steering is None:
            steering = humans_lib.Steering(humans.goal, jnp.ones((n,), bool), jnp.zeros((n, 2)))
        if self.config.human_policy == "orca":
            velocity = humans_lib.steered_preference(humans.pos, humans.goal, steering)
        else:
            offset = steering.target - humans.pos
            velocity = offset / jnp.maximum(norm(offset), 1e-9)[:, None] * humans.v_pref[:, None]
        return humans_lib.Steering(steering.target, steering.at_goal, jnp.zeros((n, 2)), velocity=velocity)
