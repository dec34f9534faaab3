"""Variable crowds: `env.num_humans` is the capacity, `env.active_humans_min/max` the per-episode count."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import CompileCounter, hand_state, make_env, to_goal

from tgrf_jax.config import ConfigError, EnvConfig
from tgrf_jax.env import scenarios, stuck


def _padded(state, capacity):
    """`state` with its humans in the first slots of `capacity` slots, the rest inactive and parked."""
    h = state.humans
    extra = capacity - h.pos.shape[0]
    pad = lambda x, v=0.0: jnp.concatenate([x, jnp.full((extra,) + x.shape[1:], v, x.dtype)])  # noqa: E731
    humans = scenarios.park(
        h.replace(
            pos=pad(h.pos),
            vel=pad(h.vel),
            goal=pad(h.goal),
            radius=pad(h.radius, 0.4),
            v_pref=pad(h.v_pref, 1.0),
            active=pad(h.active, False),
        )
    )
    return state.replace(humans=humans, progress=stuck.fresh(humans))


def _crossing_state(n):
    """n humans on a 4 m circle heading for the far side (they arrive and respawn within the test)."""
    angle = np.linspace(0.0, 2 * np.pi, n, endpoint=False) + 0.1
    pos = 4.0 * np.stack([np.cos(angle), np.sin(angle)], -1)
    vel = -0.5 * pos / 4.0
    return hand_state([0.0, -5.0], [0.0, 5.0], pos, human_vel=vel, human_goal=-pos, v_pref=1.2)


def _run(env, state, steps=60):
    params = env.default_params

    def body(state, key):
        offset = state.robot.goal - state.robot.pos
        action = 0.6 * offset / jnp.maximum(jnp.linalg.norm(offset), 1e-6)
        obs, state, reward, term, trunc, info = env.step_env(key, state, action, params)
        return state, (obs, state, reward, info)

    return jax.jit(lambda s: jax.lax.scan(body, s, jax.random.split(jax.random.key(5), steps)))(state)[1]


@pytest.mark.parametrize("policy", ["orca", "social_force"])
def test_inactive_slots_change_nothing(policy):
    """10 humans in a capacity-30 env step exactly as the same 10 in a capacity-10 env: goal changes and
    respawns included (60 steps), robot, humans, rewards, observations and metrics."""
    small = make_env(num_humans=10, human_policy=policy, goal_change_prob=1.0)
    big = make_env(num_humans=30, human_policy=policy, goal_change_prob=1.0, active_humans_min=10, active_humans_max=10)
    state = _crossing_state(10)
    a_obs, a_state, a_rew, a_info = _run(small, state)
    b_obs, b_state, b_rew, b_info = _run(big, _padded(state, 30))
    assert np.asarray(a_info.num_visible).max() > 0
    assert not np.array_equal(a_state.humans.goal[-1], state.humans.goal)  # goals did change
    np.testing.assert_array_equal(a_rew, b_rew)
    for name in ("pos", "vel", "goal", "radius", "v_pref"):
        np.testing.assert_array_equal(getattr(a_state.humans, name), getattr(b_state.humans, name)[:, :10])
    np.testing.assert_array_equal(a_state.robot.pos, b_state.robot.pos)
    for x, y in zip(jax.tree_util.tree_leaves(a_info.reward_terms), jax.tree_util.tree_leaves(b_info.reward_terms)):
        np.testing.assert_array_equal(x, y)
    for f in ("outcome", "dmin", "intrusion_disc", "num_visible", "path_increment"):
        np.testing.assert_array_equal(getattr(a_info, f), getattr(b_info, f))
    np.testing.assert_array_equal(a_obs.humans, b_obs.humans[:, :10])
    np.testing.assert_array_equal(a_obs.human_mask, b_obs.human_mask[:, :10])
    assert not np.asarray(b_obs.human_mask[:, 10:]).any() and not np.asarray(b_obs.humans[:, 10:]).any()
    # The parked slots never moved.
    np.testing.assert_array_equal(
        b_state.humans.pos[:, 10:],
        np.broadcast_to(_padded(state, 30).humans.pos[10:], b_state.humans.pos[:, 10:].shape),
    )


def test_active_count_is_drawn_per_episode_in_range():
    env = make_env(num_humans=12, active_humans_min=3, active_humans_max=7)
    obs, state = jax.jit(jax.vmap(env.reset, in_axes=(0, None)))(
        jax.random.split(jax.random.key(0), 400), env.default_params
    )
    active = np.asarray(state.humans.active)
    counts = active.sum(1)
    assert set(counts.tolist()) == set(range(3, 8))
    # The active humans are the first slots; nobody inactive is seen or left near the arena.
    np.testing.assert_array_equal(active, np.arange(12)[None] < counts[:, None])
    assert np.all(np.asarray(obs.human_mask).sum(1) <= counts)
    assert np.all(np.abs(np.asarray(state.humans.pos)[~active]) > 1000)


def test_one_program_any_crowd_size_and_zero_humans():
    env = make_env(num_humans=30)
    params = env.default_params

    @jax.jit
    def play(params):
        obs, state = jax.vmap(env.reset, in_axes=(0, None))(jax.random.split(jax.random.key(1), 4), params)

        def body(carry, key):
            obs, state = carry
            obs, state, reward, term, trunc, info = jax.vmap(env.step, in_axes=(0, 0, 0, None))(
                jax.random.split(key, 4), state, jax.vmap(to_goal)(obs), params
            )
            return (obs, state), (reward, info.num_visible, state.humans.active.sum(-1))

        return jax.lax.scan(body, (obs, state), jax.random.split(jax.random.key(2), 30))[1]

    play(params.replace(active_humans_min=jnp.float32(0), active_humans_max=jnp.float32(0)))
    with CompileCounter() as counter:
        for n in (0, 5, 10, 20, 30):
            rew, visible, active = play(
                params.replace(active_humans_min=jnp.float32(n), active_humans_max=jnp.float32(n))
            )
            assert np.all(np.asarray(active) == n) and np.all(np.isfinite(np.asarray(rew)))
            assert np.asarray(visible).max() <= n
            if n == 0:
                assert np.asarray(visible).max() == 0
    assert counter.compiles == 0


@pytest.mark.parametrize(
    "fields, message",
    [
        ({"num_humans": 10, "active_humans_max": 11}, "env.active_humans_max = 11 must be <= env.num_humans = 10"),
        (
            {"num_humans": 10, "active_humans_min": 8, "active_humans_max": 5},
            "env.active_humans_min = 8 must be <= env.active_humans_max = 5",
        ),
        (
            {"num_humans": 10, "active_humans_min": 12},
            "env.active_humans_min = 12 must be <= env.active_humans_max = 10",
        ),
        ({"active_humans_min": 2.5}, "env.active_humans_min = 2.5 must be an integer"),
        ({"active_humans_max": -1}, "env.active_humans_max = -1 is out of range"),
    ],
)
def test_bad_crowd_bounds(fields, message):
    with pytest.raises(ConfigError, match=message.replace("[", r"\[")):
        EnvConfig.from_dict(fields)


def test_crowd_bounds_default_to_capacity():
    cfg = EnvConfig(num_humans=7)
    assert cfg.active_humans_min is None and cfg.resolved("active_humans_max") == 7
    params = make_env(num_humans=7).default_params
    assert float(params.active_humans_min) == 7 and float(params.active_humans_max) == 7


# ------------------------------------------------------------------------------------------------ scenarios

from tgrf_jax.config import CROWD_SCENARIOS, SCENARIOS  # noqa: E402


def _reset_many(env, n=128, seed=7, params=None):
    params = env.default_params if params is None else params
    return jax.jit(jax.vmap(env.reset, in_axes=(0, None)))(jax.random.split(jax.random.key(seed), n), params)


def test_circle_crossing_reset_is_todays():
    """The default scenario draws the episodes it drew before scenarios existed: on these keys the previous code
    gave a mean start-goal distance of 9.9406 m and 1021 humans visible over 256 resets."""
    obs, state = _reset_many(make_env(), n=256)
    dist = np.linalg.norm(np.asarray(state.robot.pos - state.robot.goal), axis=-1)
    assert dist.mean() == pytest.approx(9.940567, abs=1e-4)
    assert int(np.asarray(obs.human_mask).sum()) == 1021
    assert np.all(np.asarray(state.scenario) == 0)


@pytest.mark.parametrize("name", SCENARIOS)
def test_every_scenario_resets_and_steps(name):
    env = make_env(num_humans=6, scenario=name, goal_change_prob=1.0, goal_change_interval=1.0)
    params = env.default_params
    obs, state = _reset_many(env, n=16)
    h, r = state.humans, state.robot
    assert np.all(np.asarray(state.scenario) == 0)  # an index into env.config.drawn_scenarios: (name,)
    a, rad = float(params.arena_size), float(params.circle_radius)
    goal = np.asarray(h.goal)
    if name in ("parallel_traffic", "frontal_approach", "robot_overtaking"):
        assert np.allclose(np.abs(goal[..., 1]), rad)  # streams leave at the lane's ends
    if name == "parallel_traffic":
        np.testing.assert_array_equal(np.sign(goal[:, :, 1]), np.broadcast_to([1, -1, 1, -1, 1, -1], (16, 6)))
    if name == "perpendicular_traffic":
        assert np.allclose(goal[..., 0], rad) and np.all(np.abs(goal[..., 1]) <= a / 2)
    if name == "frontal_approach":
        assert np.all(goal[..., 1] < 0)
    if name == "robot_overtaking":
        assert np.all(goal[..., 1] > 0) and np.all(np.asarray(h.v_pref) <= 0.75)
    if name == "robot_crowding":
        assert np.all(np.abs(goal[..., 0]) <= 0.5) and np.all(np.abs(goal[..., 1]) <= a)
    if name in ("parallel_traffic", "perpendicular_traffic", "frontal_approach", "robot_overtaking", "robot_crowding"):
        np.testing.assert_allclose(np.asarray(r.pos[:, 1]), -a)
        np.testing.assert_allclose(np.asarray(r.goal[:, 1]), a)

    def body(carry, key):
        obs, state = carry
        obs, state, reward, term, trunc, info = jax.vmap(env.step, in_axes=(0, 0, 0, None))(
            jax.random.split(key, 16), state, jax.vmap(to_goal)(obs), params
        )
        return (obs, state), (reward, state.humans.goal, state.scenario, state.humans.pos, info.humans_unreachable)

    run = jax.jit(lambda c: jax.lax.scan(body, c, jax.random.split(jax.random.key(1), 40)))
    rew, goals, index, pos, unreachable = run((obs, state))[1]
    assert np.all(np.isfinite(np.asarray(rew))) and np.all(np.asarray(index) == 0)
    assert np.all(np.isfinite(np.asarray(pos)))
    assert int(np.asarray(unreachable).sum()) == 0  # among obstacles the humans route, and every goal has a path
    assert not np.array_equal(goals[-1], goal)  # goal changes and respawns happened
    if name == "perpendicular_traffic":
        assert np.allclose(np.asarray(goals)[..., 0], rad)  # the stream keeps its direction


def test_mix_draws_scenarios_by_weight_in_one_program():
    env = make_env(num_humans=4, scenario="mix")
    params = env.default_params
    reset = jax.jit(jax.vmap(env.reset, in_axes=(0, None)))
    keys = jax.random.split(jax.random.key(3), 800)
    counts = np.bincount(np.asarray(reset(keys, params)[1].scenario), minlength=len(CROWD_SCENARIOS))
    assert np.all(counts > 60)  # about 100 each
    weights = np.zeros(len(CROWD_SCENARIOS), np.float32)
    weights[[2, 5]] = [1.0, 3.0]
    weighted = params.replace(scenario_weights=jnp.asarray(weights))
    with CompileCounter() as counter:
        drawn = np.asarray(reset(keys, weighted)[1].scenario)
    assert counter.compiles == 0
    assert set(drawn.tolist()) == {2, 5} and 0.65 < np.mean(drawn == 5) < 0.85


def test_a_mix_in_any_order_gives_each_scenario_its_speed():
    """The speed factor is looked up by the episode's index into the mix (the old code used the index into
    config.SCENARIOS there, so this mix gave robot_overtaking full speed and circle_crossing half)."""
    env = make_env(num_humans=4, scenario="mix", mix_scenarios=["robot_overtaking", "circle_crossing"])
    state = _reset_many(env, n=64)[1]
    overtaking = np.asarray(state.scenario) == 0
    v_pref = np.asarray(state.humans.v_pref)
    assert 0 < overtaking.sum() < 64
    assert np.all(v_pref[overtaking] <= 0.75) and np.any(v_pref[~overtaking] > 0.75)


@pytest.mark.parametrize("name", ["circle_crossing", "parallel_traffic", "random"])
def test_mix_with_one_weight_plays_that_scenario(name):
    """A one-hot mix plays the scenario's own episodes (same keys, same draws; up to FMA contraction, which
    differently compiled programs apply to different products)."""
    weights = [0.0] * len(CROWD_SCENARIOS)
    weights[CROWD_SCENARIOS.index(name)] = 1.0
    plain = make_env(num_humans=5, scenario=name)
    mix = make_env(num_humans=5, scenario="mix", scenario_weights=weights)
    a = _reset_many(plain, n=8)[1]
    b = _reset_many(mix, n=8)[1]
    # the same scenario, each as an index into its env's scenarios
    assert {plain.config.drawn_scenarios[i] for i in np.asarray(a.scenario)} == {name}
    assert {mix.config.drawn_scenarios[i] for i in np.asarray(b.scenario)} == {name}
    a, b = a.replace(scenario=b.scenario), b
    for x, y in zip(jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b)):
        np.testing.assert_array_equal(x, y)
    from helpers import rollout

    ra = rollout(plain, jax.random.key(4), plain.default_params, 60, to_goal)
    rb = rollout(mix, jax.random.key(4), mix.default_params, 60, to_goal)
    np.testing.assert_allclose(ra[0].humans.pos, rb[0].humans.pos, atol=1e-3)
    np.testing.assert_array_equal(ra[4].outcome, rb[4].outcome)


@pytest.mark.parametrize(
    "fields, message",
    [
        (
            {"scenario": "hallway"},
            "env.scenario = 'hallway' is not allowed; allowed: one of 'circle_crossing', "
            "'square_crossing', 'parallel_traffic'",
        ),
        ({"scenario": "mix", "scenario_weights": [1, 1]}, "env.scenario_weights has 2 value"),
        ({"scenario": "mix", "scenario_weights": [1, 1, 1, -1, 1, 1, 1, 1]}, "has a negative or non-finite weight"),
        ({"scenario": "mix", "scenario_weights": [0] * 8}, r"are all zero \(in float32\); allowed: 8 finite, non-neg"),
        (
            {"scenario": "mix", "scenario_weights": "uniform"},
            "env.scenario_weights = 'uniform' must be a list of 8 numbers",
        ),
        (
            {"scenario": "mix", "scenario_weights": [1, "x", 1, 1, 1, 1, 1, 1]},
            r"env.scenario_weights\[1\] = 'x' must be a number",
        ),
        # weights the env would draw with as float32 inf or 0 (the config used to pass them on)
        (
            {"scenario": "mix", "mix_scenarios": ["circle_crossing", "random"], "scenario_weights": [1e39, 1]},
            r"env.scenario_weights = \[1e\+39, 1.0\] has a weight beyond float32's range \(inf\); allowed: 2 "
            r"finite, non-negative numbers, one per scenario of the mix \(circle_crossing, random\), at least one "
            r"of them positive \(>= 1.18e-38\) and their sum finite \(<= 3.4e\+38, float32\)",
        ),
        (
            {"scenario": "mix", "mix_scenarios": ["circle_crossing", "random"], "scenario_weights": [1e-46, 0]},
            r"env.scenario_weights = \[1e-46, 0.0\] are all zero \(in float32\); allowed: 2 finite",
        ),
        (
            {"scenario": "mix", "mix_scenarios": ["circle_crossing", "random"], "scenario_weights": [3e38, 3e38]},
            r"sum beyond float32's range; allowed: 2 finite",
        ),
        # mix settings with another scenario: refused, not ignored
        (
            {"scenario_weights": [1]},
            r"env.scenario_weights = \[1\] is given but env.scenario = 'circle_crossing' is not 'mix', which alone "
            r"reads it; allowed: null \(or env.scenario: mix\)",
        ),
        ({"scenario": "random", "mix_scenarios": ["random"]}, r"env.mix_scenarios = \['random'\] is given but"),
    ],
)
def test_bad_scenarios(fields, message):
    with pytest.raises(ConfigError, match=message):
        EnvConfig.from_dict(fields)


def test_bad_weights_in_params_are_caught_before_compiling():
    env = make_env(scenario="mix")
    with pytest.raises(ConfigError, match="are all zero"):
        env.default_params.replace(scenario_weights=jnp.zeros(len(CROWD_SCENARIOS))).validate()
    ones = jnp.ones(len(CROWD_SCENARIOS))
    with pytest.raises(ConfigError, match=r"has a negative or non-finite weight; allowed: 8 finite, non-negative"):
        env.default_params.replace(scenario_weights=ones.at[0].set(jnp.inf)).validate()
    with pytest.raises(ConfigError, match=r"sum beyond float32's range"):
        env.default_params.replace(scenario_weights=ones * 3e38).validate()
    with pytest.raises(ConfigError, match=r"are all zero \(in float32\)"):  # below float32's normal numbers
        env.default_params.replace(scenario_weights=ones * 1e-39).validate()
