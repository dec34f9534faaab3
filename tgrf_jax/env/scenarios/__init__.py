"""Scenarios: how the robot's start and goal, the obstacles, and the humans' spawns, goals, goal changes and
respawns are drawn (docs/scenarios.md; docs/design.md, "Scenarios", for adding one).

* `sampling`: the primitives every scenario shares (the counter-hash `uniform`, bounded rejection sampling,
  the active slots and the parking of the inactive ones);
* `open_space`: the crowd scenarios (no obstacles); `obstacle_layouts`: the scenarios with static obstacles
  (their layouts and the crowd samplers that read them);
* `episodes`: an env's `ScenarioTable` (built once per env) and the draws of an episode from it;
* the registry (`tgrf_jax.scenario_registry`, re-exported here: `Scenario`, `register`): the built-in
  scenarios are registered below, in this order, one line each; config's choices and every env read it.
"""

from tgrf_jax.env.scenarios import obstacle_layouts, open_space
from tgrf_jax.env.scenarios.episodes import (
    ScenarioTable,
    change_goals,
    reassign_goals,
    respawn_arrived,
    spawn_humans,
)
from tgrf_jax.env.scenarios.sampling import PARKING, active_slots, park, uniform
from tgrf_jax.scenario_registry import Scenario, register

# The built-in scenarios: open spaces with a crowd, then layouts with static obstacles (this order is
# config.SCENARIOS', the default mix's and the benchmark suite's).
register("circle_crossing", open_space.CIRCLE_CROSSING, kind="crowd")
register("square_crossing", open_space.SQUARE_CROSSING, kind="crowd")
register("parallel_traffic", open_space.PARALLEL_TRAFFIC, kind="crowd")
register("perpendicular_traffic", open_space.PERPENDICULAR_TRAFFIC, kind="crowd")
register("frontal_approach", open_space.FRONTAL_APPROACH, kind="crowd")
register("robot_overtaking", open_space.ROBOT_OVERTAKING, kind="crowd")
register("robot_crowding", open_space.ROBOT_CROWDING, kind="crowd")
register("random", open_space.RANDOM, kind="crowd")
register("corridor", obstacle_layouts.CORRIDOR, kind="obstacle")
register("doorway", obstacle_layouts.DOORWAY, kind="obstacle")
register("intersection", obstacle_layouts.INTERSECTION, kind="obstacle")
register("random_obstacles", obstacle_layouts.RANDOM_OBSTACLES, kind="obstacle")
# Recorded pedestrians (tgrf_jax.env.replay draws its episodes; circle crossing's samplers only fill its row of a
# mix's table, and what they draw is replaced).
register("replay", open_space.REPLAY_STAND_IN, kind="replay")

__all__ = [
    "PARKING",
    "Scenario",
    "ScenarioTable",
    "active_slots",
    "change_goals",
    "park",
    "reassign_goals",
    "register",
    "respawn_arrived",
    "spawn_humans",
    "uniform",
]
