"""The people sensor's errors (env.detection_noise, detection_dropout, false_detections, detection_latency,
sensor_fov, randomise_sensing): what the robot observes changes, the world and its rewards do not."""

import functools
import pathlib

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import hand_state, make_env

from tgrf_jax.config import ConfigError, EnvConfig, TrainConfig
from tgrf_jax.env import CrowdNavEnv, detection, sensing

REFERENCE = pathlib.Path(__file__).parent / "data" / "sensing_reference.npz"
# Envs whose default arrays `reference_arrays` wrote to REFERENCE, with the steps it rolled out.
REFERENCE_CASES = {
    "default": ({}, 60),
    "obstacles": (
        dict(
            num_humans=6,
            human_policy="social_force",
            obstacles=[[[-1.0, -1.0], [1.0, -1.0], [1.0, 1.0], [-1.0, 1.0]]],
            occlusion=True,
            lidar_rays=8,
            predictor="truth",
            kinematics="unicycle",
            human_routing=False,  # the reference predates routing; routing has tests of its own
        ),
        40,
    ),
    "gst": (dict(num_humans=5, predictor="gst"), 30),
}
ALL_ZERO = dict(
    detection_noise=0.0,
    detection_dropout=0.0,
    false_detections=0.0,
    detection_latency=0,
    sensor_fov=360.0,
    max_detection_latency=3,
    randomise_sensing=True,
)
# Every random error at once. (A field of view is no error: like the range, it decides who is visible at all.)
NOISY = dict(detection_noise=0.3, detection_dropout=0.3, false_detections=2.0, detection_latency=2)


def to_goal(obs):
    offset = obs.robot_node[3:5] - obs.robot_node[:2]
    return offset / jnp.maximum(jnp.linalg.norm(offset), 1e-6)


def reference_arrays(env, params, steps: int, seed: int = 0) -> dict:
    """{path: array} of the reset and of `steps` auto-reset steps towards the goal (the ORCA obstacle table, derived
    data, left out). REFERENCE holds these arrays as the env computed them before it had sensing errors."""

    def body(carry, k):
        obs, state = carry
        out = env.step(k, state, to_goal(obs), params)
        return (out[0], out[1]), out

    @jax.jit
    def run(key):
        k0, k1 = jax.random.split(key)
        obs, state = env.reset(k0, params)
        return (obs, state), jax.lax.scan(body, (obs, state), jax.random.split(k1, steps))[1]

    flat = jax.tree_util.tree_flatten_with_path(run(jax.random.key(seed)))[0]
    return {jax.tree_util.keystr(p): np.asarray(v) for p, v in flat if "obstacle_table" not in jax.tree_util.keystr(p)}


def assert_matches_reference(name: str, arrays: dict) -> None:
    # Other CPUs and XLA settings round floats differently; a changed random draw moves people by metres.
    reference = np.load(REFERENCE)
    keys = [k for k in reference.files if k.startswith(f"{name}:")]
    assert keys
    for key in keys:
        expected, actual = reference[key], arrays[key.split(":", 1)[1]]
        if expected.dtype.kind == "f":
            np.testing.assert_allclose(actual, expected, rtol=1e-4, atol=1e-3, err_msg=key)
        else:
            np.testing.assert_array_equal(actual, expected, err_msg=key)


# ------------------------------------------------------------------------------------------ defaults unchanged


@pytest.mark.parametrize("name", list(REFERENCE_CASES))
def test_defaults_give_the_arrays_of_the_env_without_sensing_errors(name):
    config, steps = REFERENCE_CASES[name]
    env = CrowdNavEnv(config)
    arrays = reference_arrays(env, env.default_params, steps)
    assert_matches_reference(name, arrays)
    assert not [k for k in arrays if ".sensor_errors" in k or ".detections" in k]  # no extra state by default


def test_errors_set_to_zero_with_a_delay_buffer_and_randomising_change_nothing():
    config, steps = REFERENCE_CASES["default"]
    env = CrowdNavEnv({**config, **ALL_ZERO})
    assert_matches_reference("default", reference_arrays(env, env.default_params, steps))


def test_the_observation_is_the_perfect_sensors_when_errors_are_zero():
    env = make_env(num_humans=4, human_policy="social_force")
    params = env.default_params
    state = jax.jit(env.reset)(jax.random.key(0), params)[1]
    obs, state, *_ = jax.jit(env.step_env)(jax.random.key(1), state, jnp.ones(2), params)
    predictions, _ = env._predict(state, params, env.visible(state, params))
    expected = sensing.observe(state, params, predictions, env.visible(state, params))
    for a, b in zip(jax.tree_util.tree_leaves(obs), jax.tree_util.tree_leaves(expected)):
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-6)


# ------------------------------------------------------------------------------------------ the world is untouched


@functools.cache
def _world_rollout_fn(env, steps=25):
    """A jitted rollout (key, params) of a fixed action sequence (independent of the observation), so the world
    may depend only on the keys."""

    @jax.jit
    def run(key, params):
        k0, k1 = jax.random.split(key)
        obs, state = env.reset(k0, params)
        actions = jnp.stack([jnp.cos(jnp.arange(steps) * 0.3), jnp.ones(steps)], axis=-1)

        def body(state, xs):
            k, a = xs
            obs, state, reward, term, trunc, info = env.step(k, state, a, params)
            return state, (obs, state, reward, term, trunc, info)

        return jax.lax.scan(body, state, (jax.random.split(k1, steps), actions))[1]

    return run


def _world_rollout(env, params):
    return _world_rollout_fn(env)(jax.random.key(5), params)


def test_sensing_errors_never_change_the_world_rewards_or_metrics():
    env = make_env(num_humans=6, human_policy="social_force", max_detection_latency=2)
    clean = _world_rollout(env, env.default_params)
    noisy = _world_rollout(env, env.default_params.replace(**{k: jnp.float32(v) for k, v in NOISY.items()}))
    obs_clean, obs_noisy = clean[0], noisy[0]
    assert not np.allclose(obs_clean.humans, obs_noisy.humans)
    world = lambda out: (
        out[1].robot,
        out[1].humans,
        out[1].goal_dist_ref,
        out[1].step_count,
        out[2],
        out[3],
        out[4],
        out[5].replace(final_obs=None, num_visible=None),
    )
    for a, b in zip(jax.tree_util.tree_leaves(world(clean)), jax.tree_util.tree_leaves(world(noisy))):
        np.testing.assert_array_equal(a, b)


def test_same_key_same_observation_and_other_keys_differ():
    env = make_env(num_humans=6, human_policy="social_force", max_detection_latency=2)
    params = env.default_params.replace(**{k: jnp.float32(v) for k, v in NOISY.items()}, sensor_fov=jnp.float32(180))
    a, b = _world_rollout(env, params), _world_rollout(env, params)
    for x, y in zip(jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b)):
        np.testing.assert_array_equal(x, y)
    params = params.replace(detection_latency=jnp.float32(0))  # the step's own frame, drawn with its key
    state = jax.jit(env.reset)(jax.random.key(9), params)[1]
    step = jax.jit(env.step_env)
    first = step(jax.random.key(1), state, jnp.zeros(2), params)[0]
    other = step(jax.random.key(2), state, jnp.zeros(2), params)[0]
    assert not np.array_equal(first.humans, other.humans)


# ------------------------------------------------------------------------------------------ each error


def _many_steps(env, params, state, n=4000):
    """One step from `state` with n different keys: (obs, next states)."""
    step = jax.jit(jax.vmap(env.step_env, in_axes=(0, None, None, None)))
    obs, nxt, *_ = step(jax.random.split(jax.random.key(0), n), state, jnp.zeros(2), params)
    return obs, nxt


SIGHT = dict(num_humans=2, human_policy="social_force", predictor="const_vel")
# one person 2 m ahead of the robot, one far out of range
SIGHT_STATE = dict(robot_pos=[0.0, 0.0], robot_goal=[0.0, 9.0], human_pos=[[0.0, 2.0], [30.0, 0.0]])


def test_noise_has_the_configured_spread_and_predictions_extrapolate_the_detection():
    env = make_env(**SIGHT)
    params = env.default_params.replace(detection_noise=jnp.float32(0.2))
    obs, nxt = _many_steps(env, params, hand_state(**SIGHT_STATE, human_vel=[[0.5, 0.0], [0.0, 0.0]]))
    assert np.all(np.asarray(obs.human_mask[:, 0])) and not np.any(np.asarray(obs.human_mask[:, 1]))
    rel = np.asarray(obs.humans[:, 0, :2])
    pos_error = rel + np.asarray(nxt.robot.pos) - np.asarray(nxt.humans.pos[:, 0])
    vel_error = np.asarray(obs.human_vel[:, 0]) - np.asarray(nxt.humans.vel[:, 0])
    for error in (pos_error, vel_error):
        np.testing.assert_allclose(error.std(axis=0), [0.2, 0.2], rtol=0.06)
        np.testing.assert_allclose(error.mean(axis=0), [0.0, 0.0], atol=0.015)
    steps = np.arange(1, 6)[None, :, None] * 0.25
    expected = rel[:, None, :] + steps * np.asarray(obs.human_vel[:, 0])[:, None, :]
    np.testing.assert_allclose(np.asarray(obs.humans[:, 0, 2:]).reshape(-1, 5, 2), expected, atol=1e-5)


def test_truth_and_gst_predictions_move_with_the_detected_position():
    humans = hand_state([0.0, 0.0], [0.0, 9.0], [[0.0, 2.0], [1.0, 1.0]]).humans
    predictions = jnp.arange(20.0).reshape(2, 5, 2)
    params = make_env(**SIGHT).default_params
    errors = detection.configured_errors(params.replace(detection_noise=jnp.float32(0.5)), 0)
    robot = hand_state([0.0, 0.0], [0.0, 9.0], [[0.0, 2.0]]).robot
    for predictor in ("truth", "gst"):
        frame = detection.perceive(
            jax.random.key(0), robot, humans, jnp.ones(2, bool), predictions, params, errors, predictor
        )
        assert not np.allclose(frame.pos, humans.pos)
        np.testing.assert_allclose(
            frame.pred - frame.pos[:, None], predictions - humans.pos[:, None], atol=1e-5, err_msg=predictor
        )


def test_dropout_misses_a_visible_person_at_the_configured_rate():
    env = make_env(**SIGHT)
    obs, _ = _many_steps(env, env.default_params.replace(detection_dropout=jnp.float32(0.3)), hand_state(**SIGHT_STATE))
    seen = np.asarray(obs.human_mask).sum(axis=1)
    assert set(np.unique(seen)) == {0, 1}
    assert abs(1.0 - seen.mean() - 0.3) < 0.025
    missed = seen == 0
    np.testing.assert_array_equal(np.asarray(obs.humans)[missed], 0.0)  # a missed person leaves a zero, masked row


def test_false_detections_count_place_and_look_like_people():
    env = make_env(num_humans=5, human_policy="social_force", predictor="const_vel", kinematics="unicycle")
    params = env.default_params.replace(false_detections=jnp.float32(1.5), sensor_fov=jnp.float32(90.0))
    # everybody far away: five free slots
    state = hand_state([0.0, 0.0], [0.0, 9.0], [[30.0, 0.0], [31.0, 0.0], [32.0, 0.0], [33.0, 0.0], [34.0, 0.0]])
    obs, nxt = _many_steps(env, params, state)
    count = np.asarray(obs.human_mask).sum(axis=1)
    pmf = np.array([np.exp(-1.5) * 1.5**k / np.prod(np.arange(1, k + 1)) for k in range(5)])
    pmf = np.append(pmf, 1.0 - pmf.sum())  # Poisson(1.5) capped at the 5 free slots
    mean = (pmf * np.arange(6)).sum()
    assert abs(count.mean() - mean) < 0.05
    assert abs(count.var() - (pmf * np.square(np.arange(6) - mean)).sum()) < 0.15
    mask = np.asarray(obs.human_mask)
    rel = np.asarray(obs.humans[..., :2])[mask]
    radius = np.asarray(obs.human_radius)[mask]
    edge = np.linalg.norm(rel, axis=-1) - 0.3 - radius
    assert np.all((edge >= -1e-5) & (edge <= 5.0 + 1e-5))  # within range, clear of the robot
    assert np.all((radius >= 0.3) & (radius <= 0.5))
    bearing = np.degrees(np.arctan2(rel[:, 1], rel[:, 0])) - 90.0  # the robot faces +y
    assert np.all(np.abs(bearing) <= 45.0 + 1e-3)
    speed = np.linalg.norm(np.asarray(obs.human_vel)[mask], axis=-1)
    assert np.all(speed <= 1.5 + 1e-5) and speed.std() > 0.2
    steps = np.arange(1, 6)[None, :, None] * 0.25
    pred = np.asarray(obs.humans[..., 2:])[mask].reshape(-1, 5, 2)
    np.testing.assert_allclose(pred, rel[:, None] + steps * np.asarray(obs.human_vel)[mask][:, None], atol=1e-5)
    assert int(np.asarray(nxt.step_count).max()) == 1
    # the true crowd did not see them: nobody is in range
    np.testing.assert_array_equal(np.asarray(jax.vmap(env.visible, in_axes=(0, None))(nxt, params)), False)


def test_false_detections_fill_only_free_slots():
    params = make_env(**SIGHT).default_params
    robot = hand_state([0.0, 0.0], [0.0, 9.0], [[0.0, 2.0]]).robot
    seen = jnp.array([True, False, True, False])
    frame = detection.Detections(
        pos=jnp.ones((4, 2)), vel=jnp.zeros((4, 2)), radius=jnp.full(4, 0.4), seen=seen, pred=jnp.ones((4, 5, 2))
    )
    errors = detection.configured_errors(params.replace(false_detections=jnp.float32(50.0)), 0)
    out = detection.add_phantoms(jax.random.key(0), frame, robot, params, errors)
    np.testing.assert_array_equal(out.seen, True)  # a huge mean fills both free slots, no more
    np.testing.assert_array_equal(out.pos[jnp.array([0, 2])], 1.0)  # the people detected are kept
    assert np.all(np.asarray(out.pos[jnp.array([1, 3])]) != 1.0)
    counts = jax.vmap(lambda k: detection.capped_poisson(k, jnp.float32(0.0), 4))(
        jax.random.split(jax.random.key(1), 99)
    )
    np.testing.assert_array_equal(counts, 0)


def test_latency_shows_the_frame_of_l_steps_ago_and_starts_with_the_first():
    env = make_env(num_humans=1, human_policy="social_force", predictor="const_vel", max_detection_latency=3)
    params = env.default_params.replace(detection_latency=jnp.float32(2))
    state = hand_state([0.0, 0.0], [0.0, 9.0], [[0.0, 2.0]])
    frame = sensing.exact_detections(state.humans, env.visible(state, params), env._predict(state, params, None)[0])
    state = state.replace(detections=detection.fill_buffer(frame, 3))

    @jax.jit
    def run(state):
        def body(state, k):
            obs, state, *_ = env.step_env(k, state, jnp.zeros(2), params)
            return state, (obs, state.humans)

        return jax.lax.scan(body, state, jax.random.split(jax.random.key(0), 6))[1]

    obs, humans = run(state)
    pos = np.concatenate([np.asarray(state.humans.pos)[None], np.asarray(humans.pos)])[:, 0]  # p0 .. p6
    vel = np.concatenate([np.asarray(state.humans.vel)[None], np.asarray(humans.vel)])[:, 0]
    assert np.linalg.norm(pos[-1] - pos[0]) > 0.5  # the person walked
    for t in range(1, 7):
        seen = max(t - 2, 0)
        np.testing.assert_allclose(obs.humans[t - 1, 0, :2], pos[seen], atol=1e-6)  # the robot stays at 0
        np.testing.assert_allclose(obs.human_vel[t - 1, 0], vel[seen], atol=1e-6)
        expected = pos[seen] + np.arange(1, 6)[:, None] * 0.25 * vel[seen]
        np.testing.assert_allclose(np.asarray(obs.humans[t - 1, 0, 2:]).reshape(5, 2), expected, atol=1e-5)


def test_a_state_without_the_delay_buffer_is_refused():
    env = make_env(num_humans=1, human_policy="social_force", max_detection_latency=2)
    state = hand_state([0.0, 0.0], [0.0, 9.0], [[0.0, 2.0]])
    with pytest.raises(ValueError, match="env.max_detection_latency = 2 needs the delay buffer"):
        jax.eval_shape(env.step_env, jax.random.key(0), state, jnp.zeros(2), env.default_params)


@pytest.mark.parametrize("kinematics", ["unicycle", "holonomic"])
def test_field_of_view_hides_people_outside_it(kinematics):
    env = make_env(num_humans=4, human_policy="social_force", predictor="none", kinematics=kinematics)
    # ahead, behind, to the right, 30 degrees left of ahead; the robot faces +y (pi/2)
    people = [[0.0, 2.0], [0.0, -2.0], [2.0, 0.0], [2.0 * np.cos(2.0944), 2.0 * np.sin(2.0944)]]
    state = hand_state([0.0, 0.0], [0.0, 9.0], people)
    for fov, expected in ((90.0, [1, 0, 0, 1]), (200.0, [1, 0, 1, 1]), (360.0, [1, 1, 1, 1])):
        params = env.default_params.replace(sensor_fov=jnp.float32(fov))
        np.testing.assert_array_equal(env.visible(state, params), np.array(expected, bool), err_msg=str(fov))
    turned = state.replace(robot=state.robot.replace(heading=jnp.float32(-np.pi / 2)))
    params = env.default_params.replace(sensor_fov=jnp.float32(90.0))
    np.testing.assert_array_equal(env.visible(turned, params), [False, True, False, False])
    obs, nxt, reward, *_, info = jax.jit(env.step_env)(jax.random.key(0), state, jnp.zeros(2), params)
    assert int(obs.human_mask.sum()) == int(info.num_visible) == int(env.visible(nxt, params).sum()) == 2


# ------------------------------------------------------------------------------------------ traced and randomised


def test_a_sweep_can_vmap_over_noise_values():
    env = make_env(**SIGHT)
    params = env.default_params
    batch = jax.tree_util.tree_map(lambda x: jnp.stack([x, x]), params)
    batch = batch.replace(detection_noise=jnp.array([0.0, 0.3], jnp.float32))
    state = hand_state(**SIGHT_STATE)
    step = jax.jit(jax.vmap(env.step_env, in_axes=(None, None, None, 0)))
    obs = step(jax.random.key(3), state, jnp.zeros(2), batch)[0]
    single = jax.jit(env.step_env)(jax.random.key(3), state, jnp.zeros(2), params)[0]
    np.testing.assert_allclose(obs.humans[0], single.humans, atol=1e-6)
    assert np.abs(np.asarray(obs.humans[1] - obs.humans[0])).max() > 0.01


def test_randomised_errors_are_drawn_per_episode_within_the_configured_bounds():
    env = make_env(**SIGHT, randomise_sensing=True, max_detection_latency=4)
    top = dict(detection_noise=0.4, detection_dropout=0.5, false_detections=2.0, detection_latency=4, sensor_fov=120.0)
    params = env.default_params.replace(**{k: jnp.float32(v) for k, v in top.items()})
    obs, state = jax.jit(jax.vmap(env.reset, in_axes=(0, None)))(jax.random.split(jax.random.key(0), 2000), params)
    e = state.sensor_errors
    for value, lo, hi in ((e.noise, 0.0, 0.4), (e.dropout, 0.0, 0.5), (e.false_rate, 0.0, 2.0), (e.fov, 120.0, 360.0)):
        value = np.asarray(value)
        assert value.min() >= lo and value.max() <= hi
        assert abs(value.mean() - (lo + hi) / 2) < 0.05 * (hi - lo)
    latency = np.asarray(e.latency)
    assert latency.dtype == np.int32 and sorted(np.unique(latency)) == [0, 1, 2, 3, 4]
    assert np.all(np.abs(np.bincount(latency) / 2000 - 0.2) < 0.04)
    one = jax.tree_util.tree_map(lambda x: x[0], state)
    after = jax.jit(env.step_env)(jax.random.key(1), one, jnp.zeros(2), params)[1]
    for a, b in zip(jax.tree_util.tree_leaves(one.sensor_errors), jax.tree_util.tree_leaves(after.sensor_errors)):
        np.testing.assert_array_equal(a, b)  # fixed within the episode


# ------------------------------------------------------------------------------------------ bad input


@pytest.mark.parametrize(
    "field, value, message",
    [
        ("detection_noise", -0.1, r"env.detection_noise = -0.1 is out of range; allowed: >= 0.0 and <= 10.0"),
        ("detection_dropout", 1.5, r"env.detection_dropout = 1.5 is out of range; allowed: >= 0.0 and <= 1.0"),
        ("false_detections", -1.0, r"env.false_detections = -1.0 is out of range"),
        ("sensor_fov", 0.0, r"env.sensor_fov = 0.0 is out of range; allowed: > 0.0 and <= 360.0"),
        ("detection_latency", 1.5, r"env.detection_latency = 1.5 must be an integer"),
        ("detection_latency", 2, r"env.detection_latency = 2 must be <= env.max_detection_latency = 0"),
        ("max_detection_latency", 21, r"env.max_detection_latency = 21 is out of range; allowed: >= 0 and <= 20"),
    ],
)
def test_bad_sensing_settings_are_refused_naming_the_field(field, value, message):
    with pytest.raises(ConfigError, match=message):
        TrainConfig.from_dict({"env": {field: value}})
    with pytest.raises(ConfigError, match=message):
        EnvConfig(**{field: value})


def test_bad_sensing_params_are_refused_before_compiling():
    env = make_env(num_humans=1, human_policy="social_force", max_detection_latency=2)
    params = env.default_params
    with pytest.raises(ConfigError, match=r"env.detection_dropout = 2.0 is out of range"):
        params.replace(detection_dropout=jnp.float32(2.0)).validate()
    with pytest.raises(ConfigError, match=r"env.detection_noise\[1\] = -1.0 is out of range"):
        params.replace(detection_noise=jnp.array([0.1, -1.0])).validate()
    with pytest.raises(ConfigError, match=r"env.detection_latency = 0.5 must be a whole number of steps"):
        params.replace(detection_latency=jnp.float32(0.5)).validate()
    with pytest.raises(ConfigError, match=r"env.detection_latency = 3.0 must be <= env.max_detection_latency = 2"):
        params.replace(detection_latency=jnp.float32(3.0)).validate(env.config)
    params.replace(detection_latency=jnp.float32(2.0)).validate(env.config)
