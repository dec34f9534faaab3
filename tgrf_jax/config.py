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
import numbers
import re
from collections.abc import Mapping
from typing import Any

import numpy as np
import yaml

from tgrf_jax import reward as reward_lib
from tgrf_jax.fields import (  # ConfigError, apply_overrides, load_yaml: re-exported with the config classes
    ConfigError,
    _coerce,
    _unknown_key_error,
    apply_overrides,
    check_fields,
    check_traced,
    concrete,
    first_where,
    from_dict,
    load_yaml,
    spec,
    traced,
    traced_names,
)

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

_REWARD_FIELDS = tuple(reward_lib.SCHEME_DEFAULTS["tgrf"])


@dataclasses.dataclass(frozen=True)
class RewardConfig:
    """A reward scheme plus per-field overrides; see `tgrf_jax.reward` for the formulas.

    Fields left at None take the scheme's default, so `{scheme: crowdnav_pp}` alone is the full CrowdNav++
    reward, and `{scheme: tgrf, h_disc: 1.0}` changes only the TGRF peak.
    """

    scheme: str = spec("tgrf", choices=reward_lib.SCHEMES)
    r_goal: float | None = traced(None, low=0.0, doc="reward for reaching the goal")
    r_col: float | None = traced(None, high=0.0, doc="reward (penalty) for a collision")
    d_disc: float | None = traced(None, low=0.0, doc="danger-zone radius, edge-to-edge metres")
    h_disc: float | None = traced(None, low=0.0, doc="TGRF peak of the danger penalty (absolute)")
    sigma_disc: float | None = traced(None, low=0.0, low_inclusive=False, doc="TGRF width of the danger penalty")
    disc_slope: float | None = traced(None, low=0.0, doc="linear danger penalty slope (CrowdNav++: 2.5)")
    pot_factor: float | None = traced(None, low=0.0, doc="progress reward per metre towards the goal")
    sigma_pot: float | None = traced(None, low=0.0, low_inclusive=False, doc="TGRF width of r_pot")
    pred_penalty: float | None = traced(None, high=0.0, doc="r_col used by r_pred (0 disables r_pred)")
    pred_c: float | None = traced(None, low=0.0, doc="r_pred exponent offset: penalty / 2^(k + c)")
    pred_radius: float | None = traced(None, low=0.0, doc="centre distance counted as inside a prediction")
    spin_coef: float | None = traced(None, low=0.0, doc="unicycle: penalty per rad^2 of heading change")
    back_coef: float | None = traced(None, low=0.0, doc="unicycle: penalty per m/s of backwards speed")

    def __post_init__(self):
        if self.scheme not in reward_lib.SCHEMES:
            raise ConfigError(
                f"reward.scheme = {self.scheme!r} is not allowed; allowed: {', '.join(map(repr, reward_lib.SCHEMES))}"
            )
        for f in dataclasses.fields(self):
            if f.name == "scheme":
                continue
            value = getattr(self, f.name)
            if value is None:
                continue
            value = _coerce(value, 0.0, f"reward.{f.name}")
            object.__setattr__(self, f.name, value)
        check_fields(_ResolvedReward(**self.resolved()), "reward")

    def resolved(self) -> dict[str, float]:
        values = dict(reward_lib.SCHEME_DEFAULTS[self.scheme])
        for name in _REWARD_FIELDS:
            if getattr(self, name) is not None:
                values[name] = getattr(self, name)
        return values

    def params(self) -> reward_lib.RewardParams:
        return reward_lib.reward_params(self.scheme, **self.resolved())


def _resolved_reward_class():
    base = {f.name: f for f in dataclasses.fields(RewardConfig) if f.name != "scheme"}
    return dataclasses.make_dataclass(
        "_ResolvedReward",
        [(n, float, dataclasses.field(default=0.0, metadata=f.metadata)) for n, f in base.items()],
        frozen=True,
    )


_ResolvedReward = _resolved_reward_class()

# The concrete scenarios (tgrf_jax.env.scenario, docs/scenarios.md): open spaces with a crowd, then layouts with
# static obstacles. `env.scenario: mix` draws among `env.mix_scenarios` (default: the crowd scenarios).
CROWD_SCENARIOS = (
    "circle_crossing",
    "square_crossing",
    "parallel_traffic",
    "perpendicular_traffic",
    "frontal_approach",
    "robot_overtaking",
    "robot_crowding",
    "random",
)
OBSTACLE_SCENARIOS = ("corridor", "doorway", "intersection", "random_obstacles")
SCENARIOS = CROWD_SCENARIOS + OBSTACLE_SCENARIOS
# Obstacle slots the scenarios draw into (random_obstacles: up to 8 boxes) and their vertex capacity.
SCENARIO_OBSTACLE_SLOTS = 8
SCENARIO_OBSTACLE_VERTICES = 4
MAX_LIDAR_RAYS = 1440  # a quarter of a degree: finer than any 2-D laser scanner a mobile robot carries

# Allowed human counts: the reference scenario uses 20; spawning on a 6*sqrt(2) m circle cannot seat many more
# without overlaps.
MAX_HUMANS = 200
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
        choices=SCENARIOS + ("mix",),
        doc="how starts, goals, goal changes, respawns and obstacles are drawn (docs/scenarios.md); "
        "mix: a scenario of env.mix_scenarios drawn per episode by env.scenario_weights",
    )
    mix_scenarios: tuple | None = spec(
        None,
        doc="mix: the scenarios it draws from, in the order of env.scenario_weights (None: the crowd "
        f"scenarios, {', '.join(CROWD_SCENARIOS)})",
    )
    obstacles: tuple | None = spec(
        None,
        doc="a fixed layout in every episode, beside the scenario's own obstacles: a list of polygons, each "
        "a list of [x, y] vertices counter-clockwise (2 vertices: a wall segment)",
    )
    lidar_rays: int = spec(
        0,
        low=0,
        high=MAX_LIDAR_RAYS,
        doc="rays of the robot's 360-degree 2-D LiDAR over env.sensor_range (0: no LiDAR)",
    )
    occlusion: bool = spec(False, doc="humans hidden behind an obstacle are not observed")
    human_policy: str = spec("orca", choices=("orca", "social_force"))
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

    # --- numeric (traced) --------------------------------------------------------------------------
    active_humans_min: float | None = traced(
        None,
        low=0,
        high=MAX_HUMANS,
        doc="fewest humans present in an episode: the count is drawn per episode ~ U{min..max} out of the "
        "env.num_humans slots (None: env.num_humans)",
    )
    active_humans_max: float | None = traced(
        None, low=0, high=MAX_HUMANS, doc="most humans present in an episode (None: env.num_humans)"
    )
    scenario_weights: tuple | None = traced(
        None, doc="mix: relative frequency of each scenario of env.mix_scenarios, in its order (None: equal)"
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
    sf_a: float = traced(2.0, low=0.0)
    sf_b: float = traced(1.0, low=0.0, low_inclusive=False)
    sf_ki: float = traced(1.0, low=0.0)
    unicycle_dv_min: float = traced(-0.1, high=0.0)
    unicycle_dv_max: float = traced(0.087, low=0.0)
    unicycle_dtheta_max: float = traced(0.06, low=0.0)

    def __post_init__(self):
        for name in ("active_humans_min", "active_humans_max"):
            value = getattr(self, name)
            if value is not None:
                value = _coerce(value, 0, f"env.{name}")  # a count: whole numbers only
                object.__setattr__(self, name, value)
        if self.mix_scenarios is not None:
            object.__setattr__(self, "mix_scenarios", _scenario_list(self.mix_scenarios))
        if self.obstacles is not None:
            object.__setattr__(self, "obstacles", check_polygons(self.obstacles, "env.obstacles"))
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
        check_env_relations({n: self.resolved(n) for n in traced_names(EnvConfig)}, self.drawn_scenarios)
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

    def resolved(self, name: str):
        """A traced field's value as `EnvParams` carries it (the active-human bounds default to the capacity)."""
        value = getattr(self, name)
        if value is None and name in ("active_humans_min", "active_humans_max"):
            return self.num_humans
        if value is None and name == "scenario_weights":
            return (1.0,) * len(self.drawn_scenarios)
        return value

    @property
    def drawn_scenarios(self) -> tuple[str, ...]:
        """The scenarios this env plays: env.scenario, or the mix's (the order of env.scenario_weights)."""
        if self.scenario != "mix":
            return (self.scenario,)
        return CROWD_SCENARIOS if self.mix_scenarios is None else self.mix_scenarios

    @property
    def obstacle_slots(self) -> int:
        """Static obstacle capacity: the scenarios' slots (when one of them draws obstacles) plus the fixed layout."""
        drawn = SCENARIO_OBSTACLE_SLOTS if set(self.drawn_scenarios) & set(OBSTACLE_SCENARIOS) else 0
        return drawn + len(self.obstacles or ())

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


def _scenario_list(names) -> tuple[str, ...]:
    """env.mix_scenarios as a tuple of distinct known scenario names."""
    allowed = f"allowed: a non-empty list of distinct names among {', '.join(SCENARIOS)}"
    if isinstance(names, (str, bytes)) or not hasattr(names, "__iter__"):
        raise ConfigError(f"env.mix_scenarios = {names!r} must be a list of scenario names; {allowed}")
    names = tuple(names)
    for i, name in enumerate(names):
        if name not in SCENARIOS:
            raise ConfigError(f"env.mix_scenarios[{i}] = {name!r} is not a scenario; {allowed}")
    if not names or len(set(names)) != len(names):
        raise ConfigError(f"env.mix_scenarios = {list(names)!r} is empty or names a scenario twice; {allowed}")
    return names


def _describe(polygon) -> str:
    text = repr(polygon)
    return text if len(text) <= 80 else text[:77] + "..."


def _segments_intersect_np(a, b, c, d) -> np.ndarray:
    """Whether closed segments a-b and c-d intersect (touching included); arrays of shape (..., 2), float64."""

    def orient(p, q, r):
        return np.sign(
            (q[..., 0] - p[..., 0]) * (r[..., 1] - p[..., 1]) - (q[..., 1] - p[..., 1]) * (r[..., 0] - p[..., 0])
        )

    def on_segment(p, q, r):  # r collinear with p-q: within its bounding box
        return (
            (np.minimum(p[..., 0], q[..., 0]) <= r[..., 0])
            & (r[..., 0] <= np.maximum(p[..., 0], q[..., 0]))
            & (np.minimum(p[..., 1], q[..., 1]) <= r[..., 1])
            & (r[..., 1] <= np.maximum(p[..., 1], q[..., 1]))
        )

    o1, o2, o3, o4 = orient(a, b, c), orient(a, b, d), orient(c, d, a), orient(c, d, b)
    proper = (o1 * o2 < 0) & (o3 * o4 < 0)
    touch = (
        ((o1 == 0) & on_segment(a, b, c))
        | ((o2 == 0) & on_segment(a, b, d))
        | ((o3 == 0) & on_segment(c, d, a))
        | ((o4 == 0) & on_segment(c, d, b))
    )
    return proper | touch


def check_polygons(polygons, field: str) -> tuple:
    """Validate obstacle polygons on the host; returns them as tuples of (x, y) float pairs (hashable, as configs are).

    Raises ConfigError naming `field`, the polygon's index and what is allowed for: anything but a list of
    polygons, a polygon with fewer than 2 vertices, vertices that are not pairs of finite numbers, a clockwise
    polygon, zero-length edges (repeated consecutive vertices, the last and first included), a polygon of 3+
    vertices that encloses no area, and a self-intersecting polygon.
    """
    if polygons is None or isinstance(polygons, (str, bytes, dict)) or not hasattr(polygons, "__len__"):
        raise ConfigError(f"{field} = {_describe(polygons)} must be a list of polygons, each a list of [x, y] vertices")
    checked = []
    for i, polygon in enumerate(polygons):
        where = f"{field}[{i}] = {_describe(polygon)}"
        # Checked coordinate by coordinate: numpy would quietly parse strings such as "1.5" as numbers.
        try:
            rows = [list(vertex) for vertex in polygon]
        except TypeError:
            rows = None
        if (
            rows is None
            or isinstance(polygon, (str, bytes, dict))
            or not all(
                len(r) == 2 and all(isinstance(c, numbers.Real) and not isinstance(c, bool) for c in r) for r in rows
            )
        ):
            raise ConfigError(f"{where} must be a list of [x, y] vertices, each a pair of numbers")
        v = np.array(rows, dtype=np.float64).reshape(-1, 2)
        n = v.shape[0]
        if n < 2:
            raise ConfigError(f"{where} has {n} vertices; allowed: 2 (a wall segment) or more (a polygon)")
        if not np.all(np.isfinite(v)):
            raise ConfigError(f"{where} has non-finite coordinates; every coordinate must be a finite number")
        nxt = np.roll(v, -1, axis=0)
        edge_len = np.hypot(*(nxt - v).T)
        if np.any(edge_len[: n if n >= 3 else 1] == 0.0):
            raise ConfigError(
                f"{where} has a zero-length edge (repeated consecutive vertices, the last and the "
                "first included); give each vertex once"
            )
        if n >= 3:
            # Every pair of edges must meet only where they share a vertex. Adjacent edges share one; they
            # intersect elsewhere only by folding back over each other, caught by the collinear test below.
            j = np.arange(n)
            hit = _segments_intersect_np(v[:, None], nxt[:, None], v[None, :], nxt[None, :])
            adjacent = (
                (j[:, None] == j[None, :]) | ((j[:, None] + 1) % n == j[None, :]) | ((j[None, :] + 1) % n == j[:, None])
            )
            e, f = nxt - v, np.roll(nxt - v, -1, axis=0)  # edge k and edge k + 1, which share vertex k + 1
            folds = (e[:, 0] * f[:, 1] - e[:, 1] * f[:, 0] == 0) & (e[:, 0] * f[:, 0] + e[:, 1] * f[:, 1] < 0)
            if np.any(hit & ~adjacent) or np.any(folds):
                raise ConfigError(
                    f"{where} intersects itself; allowed: simple polygons (edges meet only at shared vertices)"
                )
            area = 0.5 * np.sum(v[:, 0] * nxt[:, 1] - nxt[:, 0] * v[:, 1])
            if area < 0:
                raise ConfigError(
                    f"{where} is clockwise (signed area {area:g}); give the vertices "
                    "counter-clockwise (interior on the left of each edge, as RVO2)"
                )
            if area == 0:
                raise ConfigError(f"{where} encloses no area (collinear vertices); use 2 vertices for a wall")
        checked.append(tuple((float(x), float(y)) for x, y in v))
    return tuple(checked)


def check_env_relations(values: Mapping[str, Any], drawn_scenarios=None) -> None:
    """The constraints between numeric env fields, on a config's values or on concrete `EnvParams` leaves (arrays:
    every element). `drawn_scenarios`: the env's scenarios (the length of scenario_weights; None: not checked)."""
    for lo, hi in (
        ("human_radius_min", "human_radius_max"),
        ("human_v_pref_min", "human_v_pref_max"),
        ("orca_neighbor_dist_min", "orca_neighbor_dist_max"),
        ("active_humans_min", "active_humans_max"),
    ):
        hit = first_where(np.asarray(values[lo]) > np.asarray(values[hi]), values[lo], values[hi])
        if hit:
            raise ConfigError(f"env.{lo} = {hit[0]!s} must be <= env.{hi} = {hit[1]!s}")
    diagonal = 2.0 * np.sqrt(2.0) * np.asarray(values["arena_size"])
    hit = first_where(
        np.asarray(values["min_start_goal_dist"]) >= diagonal,
        values["min_start_goal_dist"],
        values["arena_size"],
        diagonal,
    )
    if hit:
        raise ConfigError(
            f"env.min_start_goal_dist = {hit[0]!s} cannot be met in an arena of half-size {hit[1]!s}; "
            f"allowed: < {hit[2]:.3f}"
        )
    hit = first_where(np.asarray(values["time_limit"]) < np.asarray(values["dt"]), values["time_limit"], values["dt"])
    if hit:
        raise ConfigError(f"env.time_limit = {hit[0]!s} must be >= env.dt = {hit[1]!s}")
    check_scenario_weights(values["scenario_weights"], drawn_scenarios)


def check_scenario_weights(weights, drawn_scenarios=None) -> None:
    """One non-negative, finite weight per scenario of the mix (the last axis; leading axes: a batch), not all
    zero. `drawn_scenarios` None: any length."""
    w = np.asarray(weights, np.float64)
    names = drawn_scenarios or ()
    count = len(names) if drawn_scenarios is not None else (w.shape[-1] if w.ndim else 1)
    allowed = f"allowed: {count} non-negative numbers, not all zero, one per scenario of the mix" + (
        f" ({', '.join(names)})" if names else ""
    )
    if w.ndim == 0 or w.shape[-1] != count:
        raise ConfigError(f"env.scenario_weights has {1 if w.ndim == 0 else w.shape[-1]} value(s); {allowed}")
    if not np.all(np.isfinite(w)) or np.any(w < 0):
        raise ConfigError(
            f"env.scenario_weights = {np.round(w, 6).tolist()} has a negative or non-finite weight; {allowed}"
        )
    if np.any(w.sum(-1) <= 0):
        raise ConfigError(f"env.scenario_weights = {np.round(w, 6).tolist()} are all zero; {allowed}")


def check_env_params(params) -> None:
    """Concrete `EnvParams` (built by hand, batched or not) against the declarations of `EnvConfig` and
    `RewardConfig`: ranges and relations, as a config is checked. Raises ConfigError (a ValueError)."""
    check_traced(params, EnvConfig, "env")
    check_env_relations({n: concrete(getattr(params, n), f"env.{n}") for n in traced_names(EnvConfig)})
    check_traced(params.reward, RewardConfig, "reward")


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
        for name in ("scenario_weights", "mix_scenarios"):  # lists, as YAML writes and reads them
            if env[name] is not None:
                env[name] = list(env[name])
        if env["obstacles"] is not None:
            env["obstacles"] = [[list(v) for v in polygon] for polygon in env["obstacles"]]
        return data

    def to_yaml(self) -> str:
        return yaml.safe_dump(self.to_dict(), sort_keys=False)


def config_fields() -> list[str]:
    """Every dotted field of a TrainConfig."""
    return [
        f"{f.name}.{g.name}"
        for f in dataclasses.fields(TrainConfig)
        for g in dataclasses.fields(type(f.default_factory()))
    ]


def griddable_fields() -> list[str]:
    """Dotted fields that are traced (leaves of `HParams`), hence griddable: runs that differ only in these share
    one compiled program. reward.scheme is one too: a scheme is only a set of reward values."""
    return (
        [f"ppo.{n}" for n in traced_names(PPOConfig)]
        + [f"env.{n}" for n in traced_names(EnvConfig)]
        + ["reward.scheme"]
        + [f"reward.{n}" for n in traced_names(RewardConfig)]
    )
