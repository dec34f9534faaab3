"""The configuration of a run: environment, reward, PPO, network and run sections, each a validated dataclass.

Every parameter is declared once, as a field here: its default, its allowed values and whether it is *traced*
(`traced(...)`: a numeric leaf of the `EnvParams` / `HParams` pytrees, vmappable and griddable) or *static*
(`spec(...)`: shapes and code paths, fixed at compilation). `EnvParams`, `HParams` and `griddable_fields` are
derived from these declarations, so adding a parameter is one line. An invalid value is reported with the
field's dotted name and the allowed range before anything is traced or compiled (`tgrf_jax.fields`).
"""

from __future__ import annotations

import dataclasses
import math
import re
from collections.abc import Mapping
from typing import Any

import yaml

from tgrf_jax import reward as reward_lib
from tgrf_jax import scenario_registry as registry
from tgrf_jax.env_rules import (
    check_detection_latency,
    check_env_relations,
    check_scenario_weights,
    check_weights,
    scenario_list,
)
from tgrf_jax.fields import (  # ConfigError, apply_overrides, load_yaml: re-exported with the config classes
    ConfigError,
    _coerce,
    _show,
    _unknown_key_error,
    apply_overrides,
    check_fields,
    from_dict,
    load_yaml,
    spec,
    traced,
    traced_names,
)
from tgrf_jax.polygons import check_polygons, narrow_gaps

__all__ = [
    "ConfigError",
    "EnvConfig",
    "NetworkConfig",
    "PPOConfig",
    "RewardConfig",
    "RunConfig",
    "TrainConfig",
    "apply_overrides",
    "config_fields",
    "griddable_fields",
    "load_yaml",
    "reward_config_from_dict",
]

# --------------------------------------------------------------------------------------------------
# Reward and environment configuration
# --------------------------------------------------------------------------------------------------

_REWARD_FIELDS = tuple(f.name for f in dataclasses.fields(reward_lib.RewardParams))


class _RewardConfigMethods:
    def __post_init__(self):
        if self.scheme not in reward_lib.SCHEMES:
            raise ConfigError(
                f"reward.scheme = {self.scheme!r} is not allowed; allowed: {', '.join(map(repr, reward_lib.SCHEMES))}"
            )
        for name in _REWARD_FIELDS:
            value = getattr(self, name)
            if value is not None:
                object.__setattr__(self, name, _coerce(value, 0.0, f"reward.{name}"))
        check_fields(_ResolvedReward(**self.resolved()), "reward")

    def resolved(self) -> dict[str, float]:
        """Every reward field's value: the override where one is given, else the scheme's."""
        values = dict(reward_lib.SCHEME_DEFAULTS[self.scheme])
        for name in _REWARD_FIELDS:
            if getattr(self, name) is not None:
                values[name] = getattr(self, name)
        return values

    def params(self) -> reward_lib.RewardParams:
        return reward_lib.reward_params(self.scheme, **self.resolved())


def _reward_override(field: dataclasses.Field):
    """RewardConfig's override of a `reward.RewardParams` field: None (the scheme's value) or a number in the range
    the field declares, with its doc."""
    allowed = {k: field.metadata[k] for k in ("low", "high", "low_inclusive", "high_inclusive", "doc")}
    return traced(None, **allowed)


# The reward section: a scheme plus one optional override per field of `reward.RewardParams`, where each field is
# declared once (its value in each scheme, its range and doc); the fields here follow from those declarations.
RewardConfig = dataclasses.make_dataclass(
    "RewardConfig",
    [("scheme", "str", spec("tgrf", choices=reward_lib.SCHEMES))]
    + [(f.name, "float | None", _reward_override(f)) for f in dataclasses.fields(reward_lib.RewardParams)],
    bases=(_RewardConfigMethods,),
    frozen=True,
    namespace={
        "__module__": __name__,
        "__doc__": """A reward scheme plus per-field overrides; see `tgrf_jax.reward` for the formulas and the fields.

    Fields left at None take the scheme's default, so `{scheme: crowdnav_pp}` alone is the full CrowdNav++
    reward, and `{scheme: tgrf, h_disc: 1.0}` changes only the TGRF peak.""",
    },
)


def _resolved_reward_class():
    base = {f.name: f for f in dataclasses.fields(RewardConfig) if f.name != "scheme"}
    return dataclasses.make_dataclass(
        "_ResolvedReward",
        [(n, float, dataclasses.field(default=0.0, metadata=f.metadata)) for n, f in base.items()],
        frozen=True,
    )


_ResolvedReward = _resolved_reward_class()

# The scenarios are registered in `tgrf_jax.scenario_registry` (the built-ins by `tgrf_jax.env.scenarios`), the only
# list of their names: `env.scenario`'s and `env.mix_scenarios`' choices and the default mix are read from it when a
# config is checked, so a scenario registered later is a valid choice too. CROWD_SCENARIOS, OBSTACLE_SCENARIOS and
# SCENARIOS (all of them), each in registration order, are module attributes read from it on access (`__getattr__`
# at the end of this module).
_SCENARIO_LISTS = {"CROWD_SCENARIOS": "crowd", "OBSTACLE_SCENARIOS": "obstacle", "SCENARIOS": None}
# Obstacle slots the scenarios draw into (random_obstacles: up to 8 boxes) and their vertex capacity.
SCENARIO_OBSTACLE_SLOTS = 8
SCENARIO_OBSTACLE_VERTICES = 4
MAX_LIDAR_RAYS = 1440  # a quarter of a degree: finer than any 2-D laser scanner a mobile robot carries

# Capacities: they are shapes, and they set how long an env compiles (docs/scenarios.md, "Capacities", has the
# measurements). Human slots: the reference scenario uses 20; jit(env.step) compiles in about 25 s of CPU with 100
# human slots and several minutes with 200, and a 6*sqrt(2) m circle cannot seat many more without overlaps anyway.
MAX_HUMANS = 100
# Obstacles: an env's obstacle slots (the scenario's SCENARIO_OBSTACLE_SLOTS, when it draws obstacles, plus one per
# polygon of env.obstacles) each hold as many vertices as the longest polygon, and the obstacle code is unrolled
# over those edge slots: compilation grows by about 0.6 s of CPU per edge slot (128: about 1.5 minutes; a
# 500-vertex polygon: over 5 minutes).
MAX_OBSTACLE_SLOTS = 32
MAX_POLYGON_VERTICES = 32
MAX_OBSTACLE_EDGES = 128  # obstacle slots x vertices per slot
# ORCA humans keep r + this pad + env.orca_safety_space from everything (CrowdNav's ORCA radius).
ORCA_RADIUS_PAD = 0.01
# Time: steps of at least 10 ms and episodes of at most 1000 s keep an episode within 100,000 steps (int32 step
# counters, evaluation loops and recordings that end).
MIN_DT = 0.01
MAX_EPISODE_SECONDS = 1000.0
# bodies and the goal tolerance in metres: a 2 m radius is already no pedestrian or robot of the paper's arena
MAX_BODY_RADIUS = 2.0
MAX_SENSOR_RANGE = 100.0  # edge-to-edge metres: far beyond any arena the scenarios draw
MAX_NAME_LENGTH = 200  # with room for a sweep's run suffix within a file name's 255 bytes
_NAME = re.compile(r"[A-Za-z0-9_.=+-]+")
# Episodes of one evaluation: their per-episode statistics stay on the host (about 40 bytes each).
MAX_EPISODES = 10_000_000
# Sensing errors: the delay buffer holds this many past detection frames at most (every one a copy of the humans'
# positions, velocities and predictions in the episode state), and a detection off by more than 10 m is no detection.
MAX_DETECTION_LATENCY = 20
MAX_DETECTION_NOISE = 10.0


_REPLAY_KEYS = ("path", "seconds_per_frame", "fps", "format")


def replay_file_list(files) -> tuple:
    """env.replay_files as a hashable tuple: catalogue names as strings, files as tuples of (key, value) pairs in
    `_REPLAY_KEYS` order (each a valid `RecordingSpec`; the file itself is read when an env is built)."""
    from tgrf_jax.pedestrians import RecordingError, RecordingSpec
    from tgrf_jax.pedestrians import catalogue as catalogue_lib

    known = [*catalogue_lib.DATASETS, *catalogue_lib.FOLDS, *(e.name for e in catalogue_lib.ETH_UCY)]
    if isinstance(files, (str, bytes, Mapping)) or not hasattr(files, "__iter__"):
        files = [files]  # one entry on its own
    out = []
    for i, item in enumerate(files):
        name = f"env.replay_files[{i}]"
        if isinstance(item, str):
            if item not in known:
                raise ConfigError(
                    f"{name} = {item!r} is not a catalogue name; allowed: {', '.join(known)}, or a mapping "
                    "{path, seconds_per_frame or fps, format}"
                )
            out.append(item)
            continue
        if not isinstance(item, Mapping) and isinstance(item, tuple) and all(len(p) == 2 for p in item):
            item = dict(item)  # the normalised form, as a config built from a normalised one holds it
        if not isinstance(item, Mapping):
            raise ConfigError(f"{name} = {_show(item)} must be a catalogue name or a mapping {{path, ...}}")
        unknown = [k for k in item if k not in _REPLAY_KEYS]
        if unknown or "path" not in item:
            raise ConfigError(
                f"{name} = {_show(dict(item))}: {'unknown key ' + repr(unknown[0]) if unknown else 'no path'}; "
                f"allowed keys: {', '.join(_REPLAY_KEYS)} (path and one of seconds_per_frame and fps required)"
            )
        values = {k: item.get(k) for k in _REPLAY_KEYS}
        values["path"] = str(values["path"])
        for key in ("seconds_per_frame", "fps"):
            if values[key] is not None and not isinstance(values[key], bool):
                try:
                    values[key] = float(values[key])
                except (TypeError, ValueError):
                    pass  # RecordingSpec names it below
        try:
            RecordingSpec(**values)
        except RecordingError as e:
            raise ConfigError(f"{name}: {e}") from None
        out.append(tuple(values.items()))
    if not out:
        raise ConfigError("env.replay_files is empty; allowed: at least one recording")
    return tuple(out)


@dataclasses.dataclass(frozen=True)
class EnvConfig:
    """Crowd-navigation environment configuration.

    Static fields (shapes and code paths) are fixed at construction; every numeric field becomes part of the
    traced `EnvParams` (see `CrowdNavEnv.default_params`) and can be vmapped over.
    Defaults are the paper scenario (docs/reference.md, "Scenario").
    """

    # --- static: shapes and code paths -------------------------------------------------------------
    num_humans: int = spec(20, low=0, high=MAX_HUMANS, doc="human slots (the capacity; see active_humans_*)")
    scenario: str = spec(
        "circle_crossing",
        choices=registry.Names("mix"),  # the registered scenarios, read when checked
        doc="how starts, goals, goal changes, respawns and obstacles are drawn (docs/scenarios.md); "
        "mix: a scenario of env.mix_scenarios drawn per episode by env.scenario_weights",
    )
    mix_scenarios: tuple | None = spec(
        None,
        doc="mix: the scenarios it draws from, in the order of env.scenario_weights (None: every crowd scenario, "
        "in the order of config.CROWD_SCENARIOS)",
    )
    obstacles: tuple | None = spec(
        None,
        doc="a fixed layout in every episode, beside the scenario's own obstacles: a list of polygons, each "
        f"a list of [x, y] vertices counter-clockwise (2 vertices: a wall segment), at most {MAX_POLYGON_VERTICES} "
        f"vertices each, {MAX_OBSTACLE_SLOTS} obstacle slots in all (the scenario's included) and "
        f"{MAX_OBSTACLE_EDGES} edge slots (slots x the longest polygon's vertices)",
    )
    lidar_rays: int = spec(
        0,
        low=0,
        high=MAX_LIDAR_RAYS,
        doc="rays of the robot's 360-degree 2-D LiDAR over env.sensor_range (0: no LiDAR)",
    )
    occlusion: bool = spec(False, doc="humans hidden behind an obstacle are not observed")
    human_routing: bool = spec(
        True,
        doc="among obstacles, humans route around them and a human that stays stuck gets a new goal "
        "(docs/walls.md); false: straight at their goals with local avoidance only",
    )
    human_policy: str = spec(
        "orca",
        choices=("orca", "social_force", "replay"),
        doc="how humans move: ORCA or Social Force (with env.scenario: replay, following their recordings while "
        "avoiding each other); replay: exactly along their recordings (env.scenario: replay only)",
    )
    predictor: str = spec("const_vel", choices=("none", "const_vel", "truth", "gst"))
    predictor_params: str = spec(
        "auto",
        choices=("auto", "orca", "social_force"),
        doc="gst: shipped parameters to use (auto: those of env.human_policy's crowd)",
    )
    pred_horizon: int = spec(5, low=1, high=50, doc="K, prediction steps")
    kinematics: str = spec("holonomic", choices=("holonomic", "unicycle"))
    robot_visible: bool = spec(False, doc="humans see and avoid the robot")
    track_future_intrusion: bool = spec(
        False, doc="compute itr_future (ground-truth human rollout every step; evaluation turns it on)"
    )
    spawn_tries: int = spec(16, low=1, high=1024, doc="rejection-sampling candidates per spawn or respawn")
    goal_tries: int = spec(4, low=1, high=1024, doc="rejection-sampling candidates per goal change")
    orca_max_neighbors: int = spec(-1, low=-1, high=MAX_HUMANS, doc="-1: all other humans")

    replay_files: tuple | None = spec(
        None,
        doc="env.scenario replay (or a mix with it): the recordings it plays, a list of entries, each a catalogue "
        "name resolved in the user data directory ('eth-ucy': all, a fold such as 'zara1', or a file such as "
        "'ucy/crowds_zara03.txt') or a mapping {path, seconds_per_frame or fps, format (optional: eth_ucy or "
        "obsmat)}; read once when the env is built (docs/pedestrians.md)",
    )
    replay_augment: bool = spec(
        True,
        doc="replay: each episode rotates, reflects and shifts (by up to env.arena_size / 2) the recorded scene at "
        "random; evaluation turns it off for reproducible episodes",
    )
    replay_overflow: str = spec(
        "error",
        choices=("error", "nearest"),
        doc="replay: a recording with more people in view at once than env.num_humans is an error, or (nearest) "
        "the human slots play the people nearest the robot",
    )

    # --- numeric (traced) --------------------------------------------------------------------------
    active_humans_min: int | None = traced(
        None,
        whole=True,
        low=0,
        high=MAX_HUMANS,
        doc="fewest humans present in an episode: the count is drawn per episode ~ U{min..max} out of the "
        "env.num_humans slots (None: env.num_humans)",
    )
    active_humans_max: int | None = traced(
        None, whole=True, low=0, high=MAX_HUMANS, doc="most humans present in an episode (None: env.num_humans)"
    )
    scenario_weights: tuple | None = traced(
        None,
        doc="mix: relative frequency of each scenario of env.mix_scenarios, in its order (None: equal); finite, "
        "non-negative, at least one positive and a finite sum, in float32",
    )
    replay_weights: tuple | None = traced(
        None,
        doc="replay: relative frequency of each entry of env.replay_files, in its order, an entry's files drawn in "
        "proportion to their recorded length (None: every entry in proportion to its recorded length, so every "
        "recorded moment is equally likely); rules as env.scenario_weights",
    )
    dt: float = traced(0.25, low=MIN_DT, high=1.0, doc="seconds per step")
    time_limit: float = traced(
        50.0, low=0.0, high=MAX_EPISODE_SECONDS, low_inclusive=False, doc="seconds; reaching it truncates"
    )
    arena_size: float = traced(6.0, low=0.0, low_inclusive=False, doc="robot start/goal ~ U(-a, a)^2")
    min_start_goal_dist: float = traced(8.0, low=0.0)
    circle_radius: float = traced(6.0 * math.sqrt(2.0), low=0.0, low_inclusive=False)
    spawn_noise: float = traced(2.0, low=0.0, doc="one-sided U(0, noise) added to spawn coordinates")
    spawn_clearance: float = traced(0.5, low=0.0, doc="extra gap between spawned agents")
    robot_radius: float = traced(0.3, low=0.0, high=MAX_BODY_RADIUS, low_inclusive=False)
    robot_v_max: float = traced(1.0, low=0.0, low_inclusive=False)
    goal_tolerance: float = traced(
        0.3, low=0.0, high=MAX_BODY_RADIUS, low_inclusive=False, doc="goal reached within this distance"
    )
    human_radius_min: float = traced(0.3, low=0.0, high=MAX_BODY_RADIUS, low_inclusive=False)
    human_radius_max: float = traced(0.5, low=0.0, high=MAX_BODY_RADIUS, low_inclusive=False)
    human_v_pref_min: float = traced(0.5, low=0.0, low_inclusive=False)
    human_v_pref_max: float = traced(1.5, low=0.0, low_inclusive=False)
    sensor_range: float = traced(5.0, low=0.0, high=MAX_SENSOR_RANGE, doc="edge-to-edge metres")
    goal_change_interval: float = traced(5.0, low=0.0, high=MAX_EPISODE_SECONDS, low_inclusive=False, doc="seconds")
    goal_change_prob: float = traced(0.5, low=0.0, high=1.0)
    intrusion_radius: float = traced(0.6, low=0.0, doc="itr_future: centre distance to a true future position")
    orca_time_horizon: float = traced(5.0, low=0.0, low_inclusive=False)
    orca_neighbor_dist_min: float = traced(
        5.0, low=0.0, low_inclusive=False, doc="humans' ORCA neighbour distance ~ U(min, max), drawn per episode"
    )
    orca_neighbor_dist_max: float = traced(10.0, low=0.0, low_inclusive=False, doc="min = max: a fixed distance")
    orca_safety_space: float = traced(0.15, low=0.0)
    orca_time_horizon_obst: float = traced(
        5.0, low=0.0, low_inclusive=False, doc="seconds of safety from static obstacles (RVO2's timeHorizonObst)"
    )
    route_margin: float = traced(
        0.3,
        low=0.0,
        high=2.0,
        doc="routing among obstacles: the humans' roadmap points lie the largest human's body radius + this many "
        "metres from every obstacle (docs/walls.md)",
    )
    unstuck_after: float = traced(
        10.0,
        low=0.0,
        high=MAX_EPISODE_SECONDS,
        doc="among obstacles: a human that has stayed within 0.5 m of one point this many seconds, away from its "
        "goal, gets a new goal from its scenario (0: never)",
    )
    sf_a: float = traced(2.0, low=0.0)
    sf_b: float = traced(1.0, low=0.0, low_inclusive=False)
    sf_ki: float = traced(1.0, low=0.0)
    unicycle_dv_min: float = traced(-0.1, high=0.0)
    unicycle_dv_max: float = traced(0.087, low=0.0)
    unicycle_dtheta_max: float = traced(0.06, low=0.0)

    # --- sensing errors (docs/sensing.md): the observation only; rewards and metrics read the true state ------
    max_detection_latency: int = spec(
        0,
        low=0,
        high=MAX_DETECTION_LATENCY,
        doc="static: steps of detection delay the episode state can hold, the bound of env.detection_latency "
        "(0: no delay buffer)",
    )
    randomise_sensing: bool = spec(
        False,
        doc="static: each episode draws its own sensor errors, each uniformly between perfect sensing and the "
        "configured value (noise, dropout, false detections and latency from 0, the field of view from 360 degrees)",
    )
    detection_noise: float = traced(
        0.0,
        low=0.0,
        high=MAX_DETECTION_NOISE,
        doc="standard deviation of the Gaussian error of each detected position (m) and velocity (m/s) component",
    )
    detection_dropout: float = traced(
        0.0, low=0.0, high=1.0, doc="probability that a person the sensor could see is missed on a step"
    )
    false_detections: float = traced(
        0.0,
        low=0.0,
        high=MAX_HUMANS,
        doc="mean number of phantom people detected per step within range (Poisson), filling free human slots",
    )
    detection_latency: int = traced(
        0,
        whole=True,
        low=0,
        high=MAX_DETECTION_LATENCY,
        doc="steps by which detections are late (whole steps, at most env.max_detection_latency)",
    )
    sensor_fov: float = traced(
        360.0,
        low=0.0,
        high=360.0,
        low_inclusive=False,
        doc="degrees of the people sensor's field of view, centred on the robot's heading (a holonomic robot's "
        "stays pi/2)",
    )

    def __post_init__(self):
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            if f.metadata.get("whole") and value is not None:
                object.__setattr__(self, f.name, _coerce(value, 0, f"env.{f.name}"))
        check_fields(self, "env", names=("scenario",))  # first: the checks below read the scenario
        if self.scenario != "mix":
            for name in ("mix_scenarios", "scenario_weights"):
                if getattr(self, name) is not None:
                    raise ConfigError(
                        f"env.{name} = {_show(getattr(self, name))} is given but env.scenario = "
                        f"{self.scenario!r} is not 'mix', which alone reads it; allowed: null (or env.scenario: mix)"
                    )
        if self.mix_scenarios is not None:
            object.__setattr__(self, "mix_scenarios", scenario_list(self.mix_scenarios))
        self._check_replay()
        if self.obstacles is not None:
            room = MAX_OBSTACLE_SLOTS - self.scenario_obstacle_slots
            polygons = check_polygons(
                self.obstacles,
                "env.obstacles",
                max_polygons=room,
                max_vertices=MAX_POLYGON_VERTICES,
                why=f"{MAX_OBSTACLE_SLOTS} obstacle slots in all, of which the scenario draws into "
                f"{self.scenario_obstacle_slots}",
            )
            object.__setattr__(self, "obstacles", polygons)
            edges = self.obstacle_slots * self.obstacle_vertices
            if edges > MAX_OBSTACLE_EDGES:
                raise ConfigError(
                    f"env.obstacles makes {self.obstacle_slots} obstacle slots of {self.obstacle_vertices} vertices "
                    f"(each slot holds as many as the longest polygon), {edges} edge slots; allowed: at most "
                    f"{MAX_OBSTACLE_EDGES} (compilation grows with them): fewer or shorter polygons"
                )
        if self.scenario_weights is not None:
            weights, names = self.scenario_weights, self.drawn_scenarios
            if isinstance(weights, (str, bytes)) or not hasattr(weights, "__iter__"):
                raise ConfigError(
                    f"env.scenario_weights = {weights!r} must be a list of {len(names)} numbers "
                    f"(one per scenario of the mix: {', '.join(names)})"
                )
            object.__setattr__(
                self,
                "scenario_weights",
                tuple(_coerce(w, 0.0, f"env.scenario_weights[{i}]") for i, w in enumerate(weights)),
            )
        check_fields(self, "env")
        check_scenario_weights(self.resolved("scenario_weights"), self.drawn_scenarios)
        check_env_relations({n: self.resolved(n) for n in traced_names(EnvConfig)})
        check_detection_latency(self.detection_latency, self.max_detection_latency)
        hi = self.resolved("active_humans_max")
        if hi > self.num_humans:
            raise ConfigError(
                f"env.active_humans_max = {hi} must be <= env.num_humans = {self.num_humans} "
                "(the capacity: humans are drawn from its slots)"
            )
        if self.num_humans == 0 and self.predictor != "none":
            raise ConfigError(
                f"env.predictor = {self.predictor!r} needs humans to predict, but env.num_humans = 0; "
                "use predictor: none (or num_humans >= 1)"
            )
        if self.predictor == "gst" and self.pred_horizon != 5:
            raise ConfigError(
                f"env.pred_horizon = {self.pred_horizon} must be 5 with env.predictor = 'gst' "
                "(the learned model predicts 5 steps)"
            )

    def _check_replay(self) -> None:
        plays = "replay" in self.drawn_scenarios
        if self.human_policy == "replay" and self.drawn_scenarios != ("replay",):
            raise ConfigError(
                f"env.human_policy = 'replay' moves humans along recordings, but env.scenario = {self.scenario!r} "
                f"plays {', '.join(self.drawn_scenarios)}; allowed: env.scenario: replay, or human_policy orca or "
                "social_force (which also follow the recordings, reactively, in a mix)"
            )
        if self.replay_files is None:
            if self.replay_weights is not None:
                raise ConfigError(
                    f"env.replay_weights = {_show(self.replay_weights)} is given but no env.replay_files; allowed: "
                    "null (or one weight per entry of env.replay_files)"
                )
            if plays:
                raise ConfigError(
                    "env.replay_files is required with the replay scenario: a list of catalogue names (e.g. "
                    "[eth-ucy]) or of {path, seconds_per_frame or fps} mappings"
                )
            return
        if not plays:
            raise ConfigError(
                f"env.replay_files is given but env.scenario = {self.scenario!r} plays no recordings; allowed: null "
                "(or env.scenario: replay, or a mix with replay)"
            )
        object.__setattr__(self, "replay_files", replay_file_list(self.replay_files))
        if self.replay_weights is not None:
            weights, count = self.replay_weights, len(self.replay_files)
            if isinstance(weights, (str, bytes)) or not hasattr(weights, "__iter__"):
                raise ConfigError(
                    f"env.replay_weights = {_show(weights)} must be a list of {count} numbers (one per entry of "
                    "env.replay_files)"
                )
            weights = tuple(_coerce(w, 0.0, f"env.replay_weights[{i}]") for i, w in enumerate(weights))
            object.__setattr__(self, "replay_weights", weights)
            check_weights(weights, "env.replay_weights", "entry of env.replay_files", self.replay_entry_names)

    def resolved(self, name: str):
        """A traced field's value as `EnvParams` carries it (the active-human bounds default to the capacity)."""
        value = getattr(self, name)
        if value is None and name in ("active_humans_min", "active_humans_max"):
            return self.num_humans
        if value is None and name == "replay_weights":
            # placeholder: the env replaces it with the entries' recorded lengths, which it alone knows
            return (1.0,) * len(self.replay_files or ((),))
        if value is None and name == "scenario_weights":
            return (1.0,) * len(self.drawn_scenarios)
        return value

    @property
    def replay_entry_names(self) -> tuple[str, ...]:
        """The entries of env.replay_files as messages name them: a catalogue name or a file's path."""
        return tuple(f if isinstance(f, str) else dict(f)["path"] for f in self.replay_files or ())

    @property
    def drawn_scenarios(self) -> tuple[str, ...]:
        """The scenarios this env plays: env.scenario, or the mix's (the order of env.scenario_weights). An episode's
        scenario is an index into this tuple (`EnvState.scenario`)."""
        if self.scenario != "mix":
            return (self.scenario,)
        return registry.names("crowd") if self.mix_scenarios is None else self.mix_scenarios

    @property
    def scenario_obstacle_slots(self) -> int:
        """The obstacle slots the scenarios draw into: SCENARIO_OBSTACLE_SLOTS when one of them is an obstacle
        scenario, else none."""
        drawn = any(registry.kind_of(name) == "obstacle" for name in self.drawn_scenarios)
        return SCENARIO_OBSTACLE_SLOTS if drawn else 0

    @property
    def obstacle_slots(self) -> int:
        """Static obstacle capacity: the scenarios' slots (when one of them draws obstacles) plus the fixed layout."""
        return self.scenario_obstacle_slots + len(self.obstacles or ())

    @property
    def obstacle_vertices(self) -> int:
        """Static vertex capacity of an obstacle slot."""
        return max([SCENARIO_OBSTACLE_VERTICES] + [len(p) for p in self.obstacles or ()])

    @property
    def max_neighbors(self) -> int:
        others = max(self.num_humans - 1 + int(self.robot_visible), 0)
        return others if self.orca_max_neighbors < 0 else min(self.orca_max_neighbors, others)

    @property
    def obs_human_dim(self) -> int:
        """Per-human feature size: current relative position plus K predicted ones (if any)."""
        return 2 * (1 + (self.pred_horizon if self.predictor != "none" else 0))

    @property
    def uses_predictions(self) -> bool:
        return self.predictor != "none"

    @classmethod
    def from_dict(cls, data: Mapping[str, Any] | None) -> EnvConfig:
        return from_dict(cls, data, "env")

    @classmethod
    def from_yaml(cls, path) -> EnvConfig:
        data = load_yaml(path)
        return cls.from_dict(data.get("env", data))


def reward_config_from_dict(data: Mapping[str, Any] | None) -> RewardConfig:
    return from_dict(RewardConfig, data, "reward")


# --------------------------------------------------------------------------------------------------
# Training configuration (PPO, network, run)
# --------------------------------------------------------------------------------------------------

NETWORK_NAMES = ("hh_attn", "dsrnn", "mlp")
# Env steps of a run: 10^10 is days of training on any hardware; the update counter is int32.
MAX_TOTAL_STEPS = 10**10
MAX_UPDATES = 2**31 - 1
NETWORK_SIZES = ("paper", "small")
FRAMES = ("world", "goal")


@dataclasses.dataclass(frozen=True)
class PPOConfig:
    """PPO settings. Shape-affecting fields (envs, steps, epochs, minibatches, total steps, switches) are static;
    the numeric ones (lr, coefficients, clip, gamma, lambda, grad norm) become the traced `HParams` pytree.

    Defaults are the fast wall-clock configuration; `configs/paper_*.yaml` restores the reference (docs/reference.md,
    "Training").
    """

    # --- static
    num_envs: int = spec(256, low=1, high=65536, doc="parallel environments")
    num_steps: int = spec(15, low=1, high=10000, doc="rollout length per update (= sequence length)")
    total_steps: int = spec(5_990_400, low=1, high=MAX_TOTAL_STEPS, doc="environment steps of the whole run")
    update_epochs: int = spec(2, low=1, high=1000, doc="epochs over each rollout (reference: 5)")
    num_minibatches: int = spec(8, low=1, high=65536, doc="minibatches per epoch (split over envs, not time)")
    num_shards: int = spec(
        2,
        low=1,
        high=1024,
        doc="the envs are split into this many equal shards, each rolled out and cut into "
        "minibatches on its own; every minibatch gradient is averaged over the shards. "
        "Shards run on separate devices where there are enough (tgrf-train gives the CPU "
        "one device per shard), else vmapped on one. 1: no sharding",
    )
    microbatch_envs: int = spec(
        16,
        low=0,
        high=65536,
        doc="envs per gradient slice: each minibatch's gradient is accumulated over equal "
        "slices of at most this many envs (the same update up to float rounding; small "
        "slices keep the learner's activations in cache); 0: the whole minibatch at once",
    )
    reset_ratio: int = spec(
        8,
        low=1,
        high=65536,
        doc="num_envs / reset_ratio fresh episodes are sampled per rollout step for the envs "
        "that finished in it (1: one per env, as env.step; see CrowdNavEnv.step_batch)",
    )
    anneal_lr: bool = spec(True, doc="linear learning-rate decay to 0 over the run (reference: off)")
    clip_value: bool = spec(True, doc="clip the value update like the policy ratio (reference: on)")
    norm_adv: bool = spec(True, doc="normalise advantages over the whole rollout batch")
    norm_value: bool = spec(True, doc="critic predicts returns standardised by running statistics (reference: off)")
    adam_eps: float = spec(1e-5, low=0.0, low_inclusive=False)
    # --- numeric (traced hyper-parameters)
    lr: float = traced(6e-4, low=0.0, low_inclusive=False, high=1.0)
    gamma: float = traced(0.99, low=0.0, high=1.0)
    gae_lambda: float = traced(0.95, low=0.0, high=1.0)
    clip_eps: float = traced(0.2, low=0.0, low_inclusive=False, high=10.0)
    vf_coef: float = traced(0.5, low=0.0)
    ent_coef: float = traced(0.0, low=0.0)
    max_grad_norm: float = traced(0.5, low=0.0, low_inclusive=False)

    def __post_init__(self):
        check_fields(self, "ppo")
        if self.num_envs % (self.num_shards * self.num_minibatches):
            raise ConfigError(
                f"ppo.num_envs = {self.num_envs} must be divisible by ppo.num_shards x ppo.num_minibatches = "
                f"{self.num_shards} x {self.num_minibatches} (each shard's minibatches keep whole env sequences)"
            )
        if self.total_steps < self.batch_size:
            raise ConfigError(
                f"ppo.total_steps = {self.total_steps} is less than one update "
                f"(ppo.num_envs x ppo.num_steps = {self.batch_size}); allowed: >= {self.batch_size}"
            )
        if self.num_updates > MAX_UPDATES:
            raise ConfigError(
                f"ppo.total_steps = {self.total_steps} is {self.num_updates:,} updates of ppo.num_envs x "
                f"ppo.num_steps = {self.batch_size} steps; allowed: <= {MAX_UPDATES * self.batch_size:,} "
                f"({MAX_UPDATES:,} updates)"
            )

    @property
    def batch_size(self) -> int:
        return self.num_envs * self.num_steps

    @property
    def shard_envs(self) -> int:
        """Envs per shard."""
        return self.num_envs // self.num_shards

    @property
    def num_microbatches(self) -> int:
        """Gradient slices per shard's minibatch: the fewest equal slices of at most `microbatch_envs` envs."""
        minibatch_envs = self.shard_envs // self.num_minibatches
        if self.microbatch_envs == 0:
            return 1
        return next(
            n
            for n in range(1, minibatch_envs + 1)
            if minibatch_envs % n == 0 and minibatch_envs // n <= self.microbatch_envs
        )

    @property
    def reset_slots(self) -> int:
        """Fresh episodes sampled per rollout step and shard (about 3% of envs finish per step in the paper
        scenario)."""
        return -(-self.shard_envs // self.reset_ratio)

    @property
    def num_updates(self) -> int:
        return self.total_steps // self.batch_size


@dataclasses.dataclass(frozen=True)
class NetworkConfig:
    name: str = spec("hh_attn", choices=NETWORK_NAMES)
    size: str = spec("small", choices=NETWORK_SIZES)
    frame: str = spec(
        "goal",
        choices=FRAMES,
        doc="'world': the reference's inputs; 'goal': robot-centred frame with x towards the goal",
    )
    init_log_std: float = spec(-0.5, low=-5.0, high=2.0, doc="initial log-std of the Gaussian policy (reference: 0)")

    def __post_init__(self):
        check_fields(self, "network")


@dataclasses.dataclass(frozen=True)
class RunConfig:
    """Outer-loop settings: seed, logging / checkpoint cadence, final evaluation."""

    name: str = spec("default", doc="run name (used in the default run directory)")
    seed: int = spec(0, low=0, high=2**31 - 1)
    log_every: int = spec(5, low=1, doc="updates per compiled chunk (one progress line / CSV row per chunk)")
    checkpoint_every: int = spec(50, low=1, doc="updates between checkpoints (rounded up to whole chunks)")
    keep_checkpoints: int = spec(3, low=1, doc="checkpoints kept on disk")
    eval_episodes: int = spec(500, low=0, high=MAX_EPISODES, doc="episodes of the final evaluation (0: skip)")
    eval_seed: int = spec(0, low=0, high=2**31 - 1)
    eval_every: int = spec(
        0,
        low=0,
        doc="updates between test evaluations during training (learning curves under "
        "test conditions, eval_curve.csv); 0: none",
    )
    curve_episodes: int = spec(100, low=1, high=100_000, doc="test episodes of each evaluation during training")

    def __post_init__(self):
        check_fields(self, "run")
        # the name becomes part of directory names (runs/<stamp>_<name>, a sweep's runs/<name>_p000_...)
        if not 1 <= len(self.name) <= MAX_NAME_LENGTH or not _NAME.fullmatch(self.name) or ".." in self.name:
            shown = (
                repr(self.name) if len(self.name) <= 60 else repr(self.name[:60]) + f"... ({len(self.name):,} chars)"
            )
            raise ConfigError(
                f"run.name = {shown} is not allowed; allowed: 1 to {MAX_NAME_LENGTH} letters, digits "
                "and '_', '-', '.', '=', '+', without '..' (no path separators)"
            )


@dataclasses.dataclass(frozen=True)
class TrainConfig:
    """Everything a training run needs: env, reward, ppo, network and run sections."""

    env: EnvConfig = dataclasses.field(
        default_factory=lambda: EnvConfig(num_humans=20, human_policy="orca", predictor="const_vel")
    )
    reward: RewardConfig = dataclasses.field(default_factory=lambda: RewardConfig(scheme="tgrf"))
    ppo: PPOConfig = dataclasses.field(default_factory=PPOConfig)
    network: NetworkConfig = dataclasses.field(default_factory=NetworkConfig)
    run: RunConfig = dataclasses.field(default_factory=RunConfig)

    @classmethod
    def from_dict(cls, data: Mapping[str, Any] | None) -> TrainConfig:
        data = dict(data or {})
        valid = [f.name for f in dataclasses.fields(cls)]
        for key, value in data.items():
            if key not in valid:
                raise _unknown_key_error(key, "", valid)
            if value is None:
                data[key] = {}
        return from_dict(cls, data, "")

    @classmethod
    def from_yaml(cls, path, overrides: list[str] | None = None) -> TrainConfig:
        return cls.from_dict(apply_overrides(load_yaml(path), overrides or []))

    def to_dict(self) -> dict:
        data = dataclasses.asdict(self)
        env = data["env"]
        for name in ("scenario_weights", "replay_weights", "mix_scenarios"):  # lists, as YAML writes and reads them
            if env[name] is not None:
                env[name] = list(env[name])
        if env["obstacles"] is not None:
            env["obstacles"] = [[list(v) for v in polygon] for polygon in env["obstacles"]]
        if env["replay_files"] is not None:
            env["replay_files"] = [f if isinstance(f, str) else dict(f) for f in env["replay_files"]]
        return data

    def to_yaml(self) -> str:
        """The config as YAML, with a comment line for each of its `notes`."""
        notes = "".join(f"# note: {note}\n" for note in self.notes())
        return notes + yaml.safe_dump(self.to_dict(), sort_keys=False)

    def notes(self) -> list[str]:
        """Settings that are allowed but do nothing in this config (said where the config is shown, not errors)."""
        found = []
        h_wall = self.reward.resolved()["h_wall"]
        if h_wall > 0 and self.env.obstacle_slots == 0:
            found.append(
                f"reward.h_wall = {h_wall:g} but the env has no obstacles (no env.obstacles and no obstacle "
                "scenario): the wall term stays 0"
            )
        found.extend(self._narrow_gap_notes())
        return found

    def _narrow_gap_notes(self) -> list[str]:
        """Gaps of env.obstacles that routed humans will not plan through (narrower than the roadmap's clearance
        on both sides; the roadmap drops the points there)."""
        env = self.env
        if not (env.obstacles and env.human_routing and env.num_humans > 0):
            return []
        body = env.human_radius_max + (ORCA_RADIUS_PAD + env.orca_safety_space if env.human_policy == "orca" else 0.0)
        width = 2.0 * (body + env.route_margin)
        return [
            f"env.obstacles: the gap between obstacles {i} and {j} is {gap:.2f} m, narrower than twice the routing "
            f"clearance ({width:.2f} m: 2 x (the largest human's body radius {body:.2f} m + env.route_margin "
            f"{env.route_margin:g} m)), so routed humans will not plan a path through it; lower env.route_margin "
            "or env.human_radius_max to open it"
            for i, j, gap in narrow_gaps(env.obstacles, width)
        ]


def config_fields() -> list[str]:
    """Every dotted field of a TrainConfig."""
    return [
        f"{f.name}.{g.name}"
        for f in dataclasses.fields(TrainConfig)
        for g in dataclasses.fields(type(f.default_factory()))
    ]


def config_field(dotted: str) -> dataclasses.Field:
    """The declaration of a dotted field of a TrainConfig (its metadata: range, doc, traced, whole)."""
    section, name = dotted.split(".", 1)
    cls = type(next(f for f in dataclasses.fields(TrainConfig) if f.name == section).default_factory())
    return next(f for f in dataclasses.fields(cls) if f.name == name)


def griddable_fields() -> list[str]:
    """Dotted fields that are traced (leaves of `HParams`), hence griddable: runs that differ only in these share
    one compiled program. reward.scheme is one too: a scheme is only a set of reward values."""
    return (
        [f"ppo.{n}" for n in traced_names(PPOConfig)]
        + [f"env.{n}" for n in traced_names(EnvConfig)]
        + ["reward.scheme"]
        + [f"reward.{n}" for n in traced_names(RewardConfig)]
    )


def __getattr__(name: str):
    """CROWD_SCENARIOS, OBSTACLE_SCENARIOS and SCENARIOS: the registry's names, read when accessed."""
    if name == "SCENARIOS":  # the synthetic ones: replay needs recordings, which no suite of scenarios assumes
        return tuple(n for n in registry.names() if registry.kind_of(n) != "replay")
    if name in _SCENARIO_LISTS:
        return registry.names(_SCENARIO_LISTS[name])
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
