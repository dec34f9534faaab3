"""The scenario registry: the one list of scenario names, which config's choices follow, and a scenario defined in
this file that is registered and joins a mix (docs/design.md, "Scenarios": adding one)."""

import dataclasses
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from tgrf_jax import config as config_lib
from tgrf_jax import scenario_registry as registry
from tgrf_jax.config import SCENARIO_OBSTACLE_SLOTS, ConfigError, EnvConfig
from tgrf_jax.env import CrowdNavEnv
from tgrf_jax.env import scenarios as scenarios_lib
from tgrf_jax.env.scenarios import Scenario, obstacle_layouts, open_space, register
from tgrf_jax.env.scenarios.sampling import uniform

# ---------------------------------------------------------------------------------- a scenario of this file
# "queue": humans start on the line y = LINE_Y, anywhere in |x| <= 3, and walk straight down to its mirror line;
# a goal change keeps the goal, an arrived human re-enters on the start line.
LINE_Y = 7.25


def _line(key, shape):
    x = uniform(key, shape, -3.0, 3.0)
    return jnp.stack([x, jnp.full_like(x, LINE_Y)], -1)


def _spawn(key, params, layout, n, tries):
    start = _line(key, (n, tries))
    return start, start * jnp.array([1.0, -1.0])


def _new_goal(key, params, layout, humans, tries):
    return jnp.broadcast_to(humans.goal[:, None], (humans.pos.shape[0], tries, 2))


def _respawn(key, params, layout, pos, goal, t, tries):
    start = _line(key, (tries,))
    return start, start * jnp.array([1.0, -1.0])


QUEUE = Scenario(robot=open_space.lane_robot, spawn=_spawn, new_goal=_new_goal, respawn=_respawn, speed=0.75)


@pytest.fixture
def queue():
    """'queue' registered for one test (a crowd scenario: while registered, the default mix draws it too)."""
    register("queue", QUEUE, kind="crowd")
    yield "queue"
    registry.unregister("queue")


# ------------------------------------------------------------------------------------------------ the tests


def test_config_reads_its_scenario_lists_from_the_registry():
    assert config_lib.SCENARIOS == config_lib.CROWD_SCENARIOS + config_lib.OBSTACLE_SCENARIOS
    # the synthetic scenarios; replay plays recordings, which a suite of scenarios cannot assume
    assert registry.names() == config_lib.SCENARIOS + ("replay",) and registry.names("replay") == ("replay",)
    assert config_lib.CROWD_SCENARIOS[0] == "circle_crossing" and len(config_lib.CROWD_SCENARIOS) == 8
    assert config_lib.OBSTACLE_SCENARIOS == ("corridor", "doorway", "intersection", "random_obstacles")
    assert EnvConfig(scenario="mix").drawn_scenarios == config_lib.CROWD_SCENARIOS
    assert all(registry.get(name) is not None for name in config_lib.SCENARIOS)


def test_a_fresh_process_sees_the_built_in_scenarios_through_config():
    """`import tgrf_jax.config` runs `tgrf_jax/__init__`, which imports the env and so registers the built-ins."""
    code = "from tgrf_jax.config import SCENARIOS, EnvConfig; EnvConfig(scenario='doorway'); print(len(SCENARIOS))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0 and out.stdout.strip() == "12", out.stderr[-2000:]


def test_a_registered_scenario_is_a_choice_of_the_config(queue):
    assert queue in config_lib.SCENARIOS and queue in config_lib.CROWD_SCENARIOS
    assert EnvConfig(scenario=queue).drawn_scenarios == (queue,)
    assert EnvConfig(scenario="mix", mix_scenarios=[queue, "corridor"]).obstacle_slots == SCENARIO_OBSTACLE_SLOTS
    assert EnvConfig(scenario="mix", mix_scenarios=[queue]).obstacle_slots == 0
    assert queue in EnvConfig(scenario="mix").drawn_scenarios  # the default mix: every crowd scenario


def test_an_unregistered_name_is_refused():
    with pytest.raises(ConfigError, match="env.scenario = 'queue' is not allowed; allowed: one of 'circle_crossing'"):
        EnvConfig(scenario="queue")
    with pytest.raises(ConfigError, match=r"env.mix_scenarios\[1\] = 'queue' is not a scenario"):
        EnvConfig(scenario="mix", mix_scenarios=["random", "queue"])


def test_a_registered_scenario_joins_a_mix_and_its_samplers_are_used(queue):
    env = CrowdNavEnv(
        dict(
            scenario="mix",
            mix_scenarios=["circle_crossing", queue],
            num_humans=4,
            human_policy="social_force",
            predictor="none",
            goal_change_interval=1.0,
        )
    )
    params = env.default_params
    assert env.scenario_table.names == ("circle_crossing", queue)
    reset = jax.jit(jax.vmap(env.reset, in_axes=(0, None)))
    _, state = reset(jax.random.split(jax.random.key(0), 64), params)
    drawn = np.asarray(state.scenario)
    assert set(drawn.tolist()) == {0, 1}  # both drawn, in one program
    pos, goal, v_pref = (np.asarray(x) for x in (state.humans.pos, state.humans.goal, state.humans.v_pref))
    queued = drawn == 1
    np.testing.assert_array_equal(pos[queued][..., 1], LINE_Y)  # the queue's own spawn placed them ...
    np.testing.assert_array_equal(goal[queued][..., 1], -LINE_Y)  # ... with its goals
    assert np.all(np.abs(pos[queued][..., 0]) <= 3.0)
    assert np.all(v_pref[queued] <= 0.75 * 1.5) and np.any(v_pref[~queued] > 0.75 * 1.5)  # its speed factor
    assert not np.any(pos[~queued][..., 1] == LINE_Y)
    # only the queue's episodes: every one of them plays it, and stepping runs its goal changes and respawns
    only = params.replace(scenario_weights=jnp.array([0.0, 1.0]))
    obs, state = reset(jax.random.split(jax.random.key(1), 8), only)
    assert np.all(np.asarray(state.scenario) == 1)

    def body(carry, key):
        obs, state = carry
        out = jax.vmap(env.step, in_axes=(0, 0, 0, None))(jax.random.split(key, 8), state, jnp.zeros((8, 2)), only)
        return out[:2], (out[1].scenario, out[1].humans.goal)

    _, (index, goals) = jax.jit(lambda c: jax.lax.scan(body, c, jax.random.split(jax.random.key(2), 30)))((obs, state))
    assert np.all(np.asarray(index) == 1)
    np.testing.assert_array_equal(np.asarray(goals)[..., 1], -LINE_Y)  # goals only ever on the queue's end line


def test_the_table_of_samplers_is_built_once_per_env(monkeypatch):
    env = CrowdNavEnv(dict(scenario="mix", num_humans=3, human_policy="social_force", predictor="none"))

    def rebuilt(config):
        raise AssertionError("ScenarioTable.of called after the env was built")

    monkeypatch.setattr(scenarios_lib.ScenarioTable, "of", rebuilt)
    params = env.default_params
    obs, state = jax.eval_shape(env.reset, jax.random.key(0), params)
    jax.eval_shape(env.step, jax.random.key(1), state, jnp.zeros(2), params)


@pytest.mark.parametrize(
    "name, scenario, kind, message",
    [
        ("circle_crossing", QUEUE, "crowd", "already registered"),
        ("Queue", QUEUE, "crowd", "must be lower-case letters"),
        ("mix", QUEUE, "crowd", "and not 'mix'"),
        ("queue", QUEUE, "obstacle", "kind 'obstacle' is a scenario with a layout"),
        ("queue", dataclasses.replace(QUEUE, layout=obstacle_layouts.CORRIDOR.layout), "crowd", "'crowd' one without"),
        ("queue", QUEUE, "open", "kind 'open' is not one of 'crowd', 'obstacle'"),
        ("queue", open_space.crowd, "crowd", "must be a Scenario record"),
    ],
)
def test_register_refuses_what_it_cannot_hold(name, scenario, kind, message):
    with pytest.raises(ValueError, match=message):
        register(name, scenario, kind=kind)
    assert "queue" not in registry.names()


def test_an_obstacle_scenario_carries_the_obstacle_slots():
    walled = dataclasses.replace(QUEUE, layout=obstacle_layouts.CORRIDOR.layout)
    register("walled_queue", walled, kind="obstacle")
    try:
        assert config_lib.OBSTACLE_SCENARIOS[-1] == "walled_queue"
        assert EnvConfig(scenario="walled_queue").obstacle_slots == SCENARIO_OBSTACLE_SLOTS
    finally:
        registry.unregister("walled_queue")


def _clock_respawn(key, params, layout, pos, goal, t, tries):
    # the fresh human starts at x = the episode time it was respawned at, so the test can read the time back
    start = jnp.broadcast_to(jnp.stack([t, LINE_Y]), (tries, 2))
    return start, start * jnp.array([1.0, -1.0])


def test_a_respawn_reads_the_episodes_time():
    clock = dataclasses.replace(QUEUE, respawn=_clock_respawn)
    register("clock", clock, kind="crowd")
    try:
        env = CrowdNavEnv(dict(scenario="clock", num_humans=2, human_policy="social_force", predictor="none"))
        params = env.default_params
        _, state = env.reset(jax.random.key(0), params)
        # human 0 stands on its goal at step 9: the step to step 10 (t = 2.5 s) respawns it
        humans = state.humans.replace(pos=state.humans.pos.at[0].set(state.humans.goal[0]))
        state = state.replace(humans=humans, step_count=jnp.asarray(9, state.step_count.dtype))
        _, after, *_ = env.step(jax.random.key(1), state, jnp.zeros(2), params)
        np.testing.assert_allclose(np.asarray(after.humans.pos[0]), [10 * float(params.dt), LINE_Y], atol=1e-5)
    finally:
        registry.unregister("clock")
