"""env.scenario: replay: recorded pedestrians (small generated recordings) as the simulator's humans."""

import os
import pathlib

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from tgrf_jax import CrowdNavEnv
from tgrf_jax.config import ConfigError, EnvConfig, TrainConfig
from tgrf_jax.env.types import COLLISION
from tgrf_jax.pedestrians import load_file

ROOT = pathlib.Path(__file__).resolve().parents[1]
SPF = 0.25  # one frame per default env step: the recording's frames are the grid's steps


def person(pid, f0, f1, start, vel):
    return [(f, pid, start[0] + vel[0] * (f - f0) * SPF, start[1] + vel[1] * (f - f0) * SPF) for f in range(f0, f1 + 1)]


# Four people, at most three in view at once: 1 crosses the whole recording, 4 leaves early, 2 and 3 enter later.
PEOPLE = (
    person(1, 0, 40, (-6.0, 0.0), (1.2, 0.0))
    + person(2, 5, 35, (0.0, -4.0), (0.0, 1.0))
    + person(3, 20, 44, (6.0, 3.0), (-1.0, 0.0))
    + person(4, 0, 10, (-3.0, -3.0), (1.0, 0.5))
)


def write_four_column(path, rows):
    path.write_text("".join(f"{f:.1f}\t{p:.1f}\t{x:.10g}\t{y:.10g}\n" for f, p, x, y in sorted(rows)))
    return path


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    return write_four_column(tmp_path_factory.mktemp("rec") / "walk.txt", PEOPLE)


def replay_env(path, **overrides):
    config = {
        "scenario": "replay",
        "human_policy": "replay",
        "num_humans": 4,
        "min_start_goal_dist": 3.0,
        "replay_files": [{"path": str(path), "seconds_per_frame": SPF}],
        "replay_augment": False,
        **overrides,
    }
    return CrowdNavEnv(config)


def recorded_at(frame, rows=PEOPLE):
    """{person id: recorded position} at `frame`."""
    return {p: np.array([x, y]) for f, p, x, y in rows if f == frame}


def centre(path):
    return load_file(path, SPF).walked_positions().mean(axis=0)  # each scene is centred on its walked ground


def matches(world_pos, frame, path, atol=1e-4, rows=PEOPLE):
    """The recorded person each position stands on at `frame` (augmentation off: world = recorded - centre)."""
    people = recorded_at(frame, rows)
    out = []
    for p in world_pos:
        found = [pid for pid, q in people.items() if np.allclose(p + centre(path), q, atol=atol)]
        assert found, (p + centre(path), people)
        out.append(found[0])
    return out


def run(env, state, steps, params=None, action=None):
    params = env.default_params if params is None else params
    step = jax.jit(env.step_env)
    action = jnp.zeros(2) if action is None else action
    out = []
    for i in range(steps):
        obs, state, reward, terminated, truncated, info = step(jax.random.PRNGKey(100 + i), state, action, params)
        out.append((state, terminated, truncated, info))
        if terminated or truncated:
            break
    return out


def test_non_reactive_humans_follow_the_recording_exactly_entering_and_leaving(recording):
    env = replay_env(recording, time_limit=1000.0)
    params = env.default_params
    _, state = jax.jit(env.reset_env)(jax.random.PRNGKey(0), params)
    state = state.replace(robot=state.robot.replace(pos=jnp.array([50.0, 50.0]), goal=jnp.array([60.0, 50.0])))
    start = int(state.replay.start)
    slots = {}  # slot -> person: a person keeps their slot while in view
    previous = None
    for k, (s, terminated, truncated, _) in enumerate([(state, False, False, None)] + run(env, state, 60)):
        frame = start + k
        active = np.asarray(s.humans.active)
        assert active.sum() == len(recorded_at(frame)), frame  # everyone in view, nobody else
        pos = np.asarray(s.humans.pos)[active]
        for slot, pid in zip(np.flatnonzero(active), matches(pos, frame, recording)):
            if previous is not None and slot in previous:
                assert slots.get(slot) == pid  # still the same person
                np.testing.assert_allclose(
                    np.asarray(s.humans.vel)[slot], (np.asarray(s.humans.pos)[slot] - previous[slot]) / 0.25, atol=1e-3
                )
            slots[slot] = pid
        previous = {slot: np.asarray(s.humans.pos)[slot] for slot in np.flatnonzero(active)}
        assert not terminated  # the robot stands far away
        if truncated:
            break
    assert truncated and frame == 44  # the episode ends with the recording
    assert set(slots.values()) >= {1, 3} and {2, 3} <= set(recorded_at(25)) | set(slots.values())


def test_robot_start_and_goal_lie_on_walked_positions_clear_of_people(recording):
    env = replay_env(recording)
    params = env.default_params
    _, states = jax.jit(jax.vmap(env.reset_env, in_axes=(0, None)))(jax.random.split(jax.random.PRNGKey(1), 32), params)
    walked = load_file(recording, SPF).walked_positions() - centre(recording)
    room = float(params.robot_radius + params.human_radius_max + params.spawn_clearance)
    for i in range(32):
        robot = states.robot
        for point in (robot.pos[i], robot.goal[i]):
            assert np.min(np.linalg.norm(walked - np.asarray(point), axis=1)) < 1e-4
        assert np.linalg.norm(robot.goal[i] - robot.pos[i]) >= 3.0
        active = np.asarray(states.humans.active[i])
        gaps = np.linalg.norm(np.asarray(states.humans.pos[i])[active] - np.asarray(robot.pos[i]), axis=1)
        assert np.all(gaps >= room - 1e-5)


def test_augmentation_off_is_deterministic_and_on_transforms_rigidly(recording):
    plain, augmented = replay_env(recording), replay_env(recording, replay_augment=True)
    keys = jax.random.split(jax.random.PRNGKey(2), 16)
    reset = lambda env: jax.jit(jax.vmap(env.reset_env, in_axes=(0, None)))(keys, env.default_params)[1]
    a, b, c = reset(plain), reset(plain), reset(augmented)
    jax.tree_util.tree_map(np.testing.assert_array_equal, a, b)
    np.testing.assert_array_equal(a.replay.rotation, np.broadcast_to(np.eye(2), (16, 2, 2)))
    np.testing.assert_array_equal(a.replay.offset, 0.0)
    dets = np.linalg.det(np.asarray(c.replay.rotation))
    np.testing.assert_allclose(np.abs(dets), 1.0, atol=1e-5)
    assert (dets < 0).any() and (dets > 0).any()  # reflections and rotations
    assert np.ptp(np.asarray(c.replay.offset), axis=0).min() > 0.5
    # the same scene and start either way, moved rigidly: the people keep their distances
    np.testing.assert_array_equal(a.replay.start, c.replay.start)
    np.testing.assert_array_equal(a.humans.active, c.humans.active)
    for i in range(16):
        act = np.asarray(a.humans.active[i])
        pa, pc = np.asarray(a.humans.pos[i])[act], np.asarray(c.humans.pos[i])[act]
        np.testing.assert_allclose(
            np.linalg.norm(pa[:, None] - pa[None], axis=-1), np.linalg.norm(pc[:, None] - pc[None], axis=-1), atol=1e-4
        )


def test_a_crowd_larger_than_the_slots_is_refused_naming_file_frame_and_count(recording):
    with pytest.raises(ConfigError, match=r"env\.replay_files\[0\]: .*walk\.txt: 3 people are in view at frame 5 "):
        replay_env(recording, num_humans=2)


def test_overflow_nearest_plays_the_people_nearest_the_robot(recording):
    env = replay_env(recording, num_humans=2, replay_overflow="nearest", time_limit=5.0)
    _, state = jax.jit(env.reset_env)(jax.random.PRNGKey(3), env.default_params)
    start = int(state.replay.start)
    for k, (s, *_rest) in enumerate([(state,)] + [r[:1] for r in run(env, state, 20)]):
        people = np.stack(list(recorded_at(start + k).values())) - centre(recording)
        dist = np.sort(np.linalg.norm(people - np.asarray(s.robot.pos), axis=1))[:2]
        active = np.asarray(s.humans.active)
        assert active.sum() == min(2, len(people))
        got = np.sort(np.linalg.norm(np.asarray(s.humans.pos)[active] - np.asarray(s.robot.pos), axis=1))
        np.testing.assert_allclose(got, dist, atol=1e-4)


@pytest.mark.parametrize(
    "content, message",
    [
        ("0 1 0.0\n", r"walk\.txt:1: 3 columns"),
        ("0 1 0.0 1.0\n1 1 abc 1.0\n", r"walk\.txt:2: non-numeric cell 'abc'"),
        ("0 1 0.0 1.0\n0 1 0.3 1.0\n", r"walk\.txt:2: duplicated row: frame 0, id 1"),
    ],
)
def test_bad_files_are_refused_before_compiling(tmp_path, content, message):
    path = tmp_path / "walk.txt"
    path.write_text(content)
    with pytest.raises(ConfigError, match=r"env\.replay_files\[0\]: .*" + message):
        replay_env(path)


def test_bad_replay_configs(tmp_path, recording):
    with pytest.raises(ConfigError, match=r"env\.replay_files\[0\]: .*nope\.txt: no such file"):
        replay_env(tmp_path / "nope.txt")
    base = {"scenario": "replay", "human_policy": "replay"}
    with pytest.raises(ConfigError, match="env.replay_files is required"):
        EnvConfig.from_dict(base)
    with pytest.raises(ConfigError, match=r"env\.replay_files\[0\]: .*exactly one of seconds_per_frame and fps"):
        EnvConfig.from_dict({**base, "replay_files": [{"path": str(recording)}]})
    with pytest.raises(ConfigError, match=r"env\.replay_files\[0\] .*unknown key 'spf'"):
        EnvConfig.from_dict({**base, "replay_files": [{"path": str(recording), "spf": 0.4}]})
    with pytest.raises(ConfigError, match=r"env\.replay_files\[0\] = 'zara9' is not a catalogue name"):
        EnvConfig.from_dict({**base, "replay_files": ["zara9"]})
    with pytest.raises(ConfigError, match="env.replay_files is given but env.scenario = 'circle_crossing'"):
        EnvConfig.from_dict({"replay_files": ["eth-ucy"]})
    with pytest.raises(ConfigError, match="env.human_policy = 'replay' moves humans along recordings"):
        EnvConfig.from_dict({"human_policy": "replay"})
    # a config with recordings writes and reads back as it was
    config = TrainConfig.from_dict(
        {"env": {**base, "replay_files": ["zara1", {"path": str(recording), "fps": 4}], "replay_overflow": "nearest"}}
    )
    assert TrainConfig.from_dict(__import__("yaml").safe_load(config.to_yaml())) == config
    assert "replay" not in EnvConfig(scenario="mix").drawn_scenarios  # the default mix needs no recordings
    # params stepping another dt would play the recordings (resampled onto the config's) at the wrong speed
    env = replay_env(recording)
    with pytest.raises(ConfigError, match="env.dt = 0.1 must equal the config's env.dt = 0.25"):
        env.default_params.replace(dt=jnp.float32(0.1)).validate(env.config)
    env.default_params.validate(env.config)


def test_replay_weights_choose_the_entries_played(tmp_path, recording):
    # two entries: the module's recording, and a copy twice as long (its people walk on for another 44 frames)
    longer = write_four_column(tmp_path / "long.txt", PEOPLE + [(f + 45, p + 10, x, y) for f, p, x, y in PEOPLE])
    files = [{"path": str(recording), "seconds_per_frame": SPF}, {"path": str(longer), "seconds_per_frame": SPF}]
    reset = lambda env, params: (
        jax.jit(jax.vmap(env.reset_env, in_axes=(0, None)))(jax.random.split(jax.random.PRNGKey(3), 400), params)[
            1
        ].replay.scene
    )
    env = replay_env(recording, replay_files=files)
    lengths = env.replay.lengths - 1
    np.testing.assert_allclose(env.default_params.replay_weights, lengths)  # None: every recorded moment alike
    share = float(np.mean(np.asarray(reset(env, env.default_params)) == 1))
    assert abs(share - lengths[1] / lengths.sum()) < 0.08, share
    for weights, played in (((0.0, 1.0), {1}), ((1.0, 0.0), {0})):
        chosen = replay_env(recording, replay_files=files, replay_weights=list(weights))
        assert set(np.asarray(reset(chosen, chosen.default_params)).tolist()) == played
        # the weights are traced: the first env's program plays the same entries with them as params
        params = env.default_params.replace(replay_weights=jnp.asarray(weights, jnp.float32))
        assert set(np.asarray(reset(env, params)).tolist()) == played
    base = {"scenario": "replay", "human_policy": "replay", "replay_files": files}
    for bad, message in (
        ([1.0], r"env\.replay_weights has 1 value\(s\); allowed: 2 .* one per entry of env\.replay_files"),
        ([1.0, -1.0], "env.replay_weights = .* has a negative or non-finite weight"),
        ([0.0, 0.0], "env.replay_weights = .* are all zero"),
        (["many", 1.0], r"env\.replay_weights\[0\]"),
        (3.0, "env.replay_weights = 3.0 must be a list of 2 numbers"),
    ):
        with pytest.raises(ConfigError, match=message):
            EnvConfig.from_dict({**base, "replay_weights": bad})
    with pytest.raises(ConfigError, match="env.replay_weights = .* is given but no env.replay_files"):
        EnvConfig.from_dict({"replay_weights": [1.0]})
    with pytest.raises(ConfigError, match=r"env\.replay_weights has 3 value\(s\); allowed: 2"):
        env.default_params.replace(replay_weights=jnp.ones(3)).validate(env.config)
    config = TrainConfig.from_dict({"env": {**base, "replay_weights": [1, 2]}})
    assert TrainConfig.from_dict(__import__("yaml").safe_load(config.to_yaml())) == config


def test_envs_share_recordings_until_a_file_changes(tmp_path):
    path = write_four_column(tmp_path / "walk.txt", PEOPLE)
    a, b = replay_env(path), replay_env(path)
    assert a == b and hash(a) == hash(b) and a.replay is b.replay  # read once, one compiled program
    rows = [(f, p, x + 1.0, y) for f, p, x, y in PEOPLE]
    write_four_column(path, rows)
    os.utime(path, ns=(0, 1))  # a new modification time, however coarse the file system's clock
    c = replay_env(path)
    assert c != a and c.replay is not a.replay


def test_truth_predicts_the_recorded_future(recording):
    env = replay_env(recording, predictor="truth", pred_horizon=4, track_future_intrusion=True)
    params = env.default_params
    _, state = jax.jit(env.reset_env)(jax.random.PRNGKey(4), params)
    predicted = np.asarray(env._true_future(state, params, 4))
    later = [r[0] for r in run(env, state, 4)]
    for k in range(len(later)):
        same = np.asarray(state.humans.active & later[k].humans.active)
        # the people who stay in view are where the prediction put them
        np.testing.assert_allclose(predicted[same, k], np.asarray(later[k].humans.pos)[same], atol=1e-4)


def test_vmapped_batch_with_auto_reset(recording):
    env = replay_env(recording, human_policy="orca", replay_augment=True, time_limit=2.0)
    params = env.default_params
    keys = jax.random.split(jax.random.PRNGKey(5), 4)
    obs, state = jax.vmap(env.reset, in_axes=(0, None))(keys, params)
    step = jax.jit(jax.vmap(env.step, in_axes=(0, 0, 0, None)))
    for i in range(10):
        obs, state, reward, terminated, truncated, info = step(keys + i, state, jnp.ones((4, 2)) * 0.3, params)
    assert truncated.any() or int(state.step_count.min()) < 10  # episodes of 8 steps ended and restarted
    assert np.isfinite(np.asarray(reward)).all() and np.isfinite(np.asarray(obs.humans)).all()
    assert state.replay.slot.shape == (4, 4)


def test_reactive_replay_steps_around_the_robot(recording):
    """A robot standing on person 1's path: the recording walks through it; with ORCA and a visible robot the
    person leaves their path to pass it, then heads back along the recording."""
    outcomes = {}
    for policy in ("replay", "orca"):
        env = replay_env(recording, human_policy=policy, robot_visible=True, time_limit=1000.0)
        _, state = jax.jit(env.reset_env)(jax.random.PRNGKey(0), env.default_params)
        slot = int(np.flatnonzero(np.asarray(state.humans.active))[0])
        ahead = state.humans.pos[slot] + 1.5 * state.humans.vel[slot]  # where they will be in 1.5 s
        state = state.replace(robot=state.robot.replace(pos=ahead, goal=ahead + jnp.array([0.0, 20.0])))
        steps = run(env, state, 12)
        outcomes[policy] = [int(info.outcome) for *_x, info in steps]
        gaps = [float(np.linalg.norm(s.humans.pos[slot] - s.robot.pos)) for s, *_y in steps]
        if policy == "orca":
            assert COLLISION not in outcomes[policy] and min(gaps) > 0.6
    assert COLLISION in outcomes["replay"]


@pytest.mark.parametrize("policy", ["orca", "social_force"])
def test_reactive_replay_keeps_to_the_recording_when_unhindered(tmp_path, policy):
    """People on paths that do not meet, the robot far away: they walk their recordings (Social Force pushes a
    little at any distance)."""
    rows = person(1, 0, 30, (-6.0, -4.0), (1.2, 0.0)) + person(2, 0, 30, (6.0, 4.0), (-1.1, 0.1))
    recording = write_four_column(tmp_path / "apart.txt", rows)
    env = replay_env(recording, human_policy=policy, time_limit=3.0, num_humans=4)
    _, state = jax.jit(env.reset_env)(jax.random.PRNGKey(0), env.default_params)
    state = state.replace(robot=state.robot.replace(pos=jnp.array([50.0, 50.0]), goal=jnp.array([60.0, 50.0])))
    start = int(state.replay.start)
    for k, (s, *_r) in enumerate(run(env, state, 12), start=1):
        act = np.asarray(s.humans.active)
        assert act.sum() == 2
        matches(np.asarray(s.humans.pos)[act], start + k, recording, atol=1e-4 if policy == "orca" else 0.02, rows=rows)


def test_replay_in_a_mix(recording):
    env = CrowdNavEnv(
        {
            "scenario": "mix",
            "mix_scenarios": ["circle_crossing", "replay"],
            "num_humans": 4,
            "min_start_goal_dist": 3.0,
            "replay_files": [{"path": str(recording), "seconds_per_frame": SPF}],
            "replay_augment": False,
            "predictor": "truth",
        }
    )
    params = env.default_params
    keys = jax.random.split(jax.random.PRNGKey(6), 16)
    _, states = jax.jit(jax.vmap(env.reset_env, in_axes=(0, None)))(keys, params)
    scenario = np.asarray(states.scenario)
    assert set(scenario) == {0, 1}
    for b in np.flatnonzero(scenario == 1):  # the replay episodes start on their recordings
        act = np.asarray(states.humans.active[b])
        assert act.sum() == len(recorded_at(int(states.replay.start[b])))
        matches(np.asarray(states.humans.pos[b])[act], int(states.replay.start[b]), recording)
    step = jax.jit(jax.vmap(env.step_env, in_axes=(0, 0, 0, None)))
    for i in range(3):
        _, states, reward, *_ = step(keys + i, states, jnp.zeros((16, 2)), params)
    assert np.isfinite(np.asarray(reward)).all()
    # circle crossing's humans stay active; replay's walk on along their recording (reactively, with ORCA)
    assert np.asarray(states.humans.active)[scenario == 0].all()
    assert (np.asarray(states.step_count) == 3).all()
    for b in np.flatnonzero(scenario == 1):
        act = np.asarray(states.humans.active[b])
        assert act.sum() == len(recorded_at(int(states.replay.start[b]) + 3))
        matches(np.asarray(states.humans.pos[b])[act], int(states.replay.start[b]) + 3, recording, atol=0.5)


def test_envs_without_replay_step_exactly_as_before():
    """reset + 20 steps of the default env (5 humans) equal a rollout recorded before replay existed."""
    env = CrowdNavEnv({"num_humans": 5})
    params = env.default_params
    obs, state = jax.jit(env.reset)(jax.random.PRNGKey(7), params)
    assert state.replay is None and env.replay is None
    step = jax.jit(env.step)
    robot, humans, rewards = [], [], []
    for i in range(20):
        action = jnp.array([0.6 * np.cos(i * 0.3), 0.6 * np.sin(i * 0.2)], jnp.float32)
        obs, state, r, *_ = step(jax.random.fold_in(jax.random.PRNGKey(8), i), state, action, params)
        robot.append(np.asarray(state.robot.pos))
        humans.append(np.asarray(state.humans.pos))
        rewards.append(float(r))
    want = np.load(ROOT / "tests" / "data" / "default_rollout.npz")
    # Other CPUs and XLA settings round floats differently (the last bit); a changed random draw or step moves
    # people by metres
    for got, key in ((robot, "robot"), (humans, "humans"), (rewards, "reward"), (obs.humans, "obs")):
        np.testing.assert_allclose(np.asarray(got, np.float32), want[key], rtol=1e-4, atol=1e-3, err_msg=key)


def test_evaluate_and_render_a_replay_episode(recording):
    """Metrics and rendering take replay episodes as they are (evaluation plays them without augmentation)."""
    import matplotlib

    matplotlib.use("Agg")
    from tgrf_jax import render
    from tgrf_jax.evaluate import evaluate
    from tgrf_jax.policies.baselines import OrcaPolicy

    env = replay_env(recording, human_policy="orca", replay_augment=True, time_limit=4.0, predictor="const_vel")
    result = evaluate(env, OrcaPolicy(), jax.random.PRNGKey(0), 4)
    assert 0.0 <= result.success_rate <= 1.0
    (ep,) = render.record_episodes(env, OrcaPolicy(), render.eval_key(0), 1, label="orca")
    # every slot kept, NaN where empty: drawing and distances skip them, the view holds only the scene
    assert ep.active.shape == ep.human_pos.shape[:2] and ep.num_humans == 4
    assert np.isnan(ep.human_pos[~ep.active]).all() and np.isfinite(ep.human_pos[ep.active]).all()
    assert np.isfinite(ep.dmin()).all()
    x0, x1, y0, y1 = render.view_limits(ep)
    assert x1 - x0 < 40
    for t in (0, ep.steps):
        assert render.plot_frame(ep, t) is not None


def test_reactive_replay_keeps_out_of_an_obstacle_on_the_recorded_path(recording):
    """A box on person 1's recorded path: the recording walks through it; ORCA people keep out of it."""
    from tgrf_jax.env import obstacles as obstacles_lib

    x, y = np.array([3.0, 0.0]) - centre(recording)  # person 1 passes here at frame 30
    box = [[x - 0.3, y - 0.3], [x + 0.3, y - 0.3], [x + 0.3, y + 0.3], [x - 0.3, y + 0.3]]
    inside = {}
    for policy in ("replay", "orca"):
        env = replay_env(recording, human_policy=policy, obstacles=[box], time_limit=1000.0)
        _, state = jax.jit(env.reset_env)(jax.random.PRNGKey(0), env.default_params)
        assert int(state.obstacles_dropped) == 0 and int(state.replay.start) < 25
        state = state.replace(robot=state.robot.replace(pos=jnp.array([50.0, 50.0]), goal=jnp.array([60.0, 50.0])))
        room = []
        for s, *_r in run(env, state, 40):
            act = np.asarray(s.humans.active)
            gap = np.asarray(obstacles_lib.clearance(s.humans.pos, s.obstacles)) - np.asarray(s.humans.radius)
            room.append(gap[act].min(initial=np.inf))
        inside[policy] = min(room)
    assert inside["replay"] < -0.2  # through the box
    assert inside["orca"] > -1e-3  # around it
