"""Exported policies and the navigator runtime (tgrf_jax.deploy, tgrf-export).

The references are real env episodes played by the env-side policy (`LearnedPolicy.act` on `CrowdNavEnv`
observations): the exported files must give its actions and recurrent states on its observations, and
`Navigator`, fed only what a robot would know (poses, velocities, radii of the humans), must give its actions.
"""

from __future__ import annotations

import json
import pathlib
import shutil

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from tgrf_jax.config import ConfigError, TrainConfig
from tgrf_jax.deploy import (
    Detection,
    Navigator,
    PolicySource,
    PolicyStep,
    load_source,
    make_runtime,
    read_interface,
)
from tgrf_jax.deploy.runtimes import OnnxRuntime, StableHloRuntime
from tgrf_jax.env import CrowdNavEnv
from tgrf_jax.policies import LearnedPolicy, make_network_for

pytest.importorskip("onnxruntime")
pytest.importorskip("jax2onnx")

PRETRAINED = "table1-const_vel-tgrf"


def record(source: PolicySource, episodes: int = 2, max_steps: int = 40, seed: int = 0) -> list[list[dict]]:
    """Play `episodes` env episodes (at most `max_steps` steps each) with the env-side deterministic policy and
    keep, per step, the true world state, the observation, the recurrent state before and after, and the action."""
    config = source.config
    env = CrowdNavEnv(config.env, config.reward)
    params = env.default_params
    policy = LearnedPolicy(make_network_for(config), jax.tree_util.tree_map(jnp.asarray, source.params))
    step_info = PolicyStep(config, source.params)
    reset = jax.jit(env.reset_env)
    step = jax.jit(env.step_env)
    act = jax.jit(policy.act)
    out = []
    for e in range(episodes):
        key = jax.random.PRNGKey(seed * 1000 + e)
        key, k = jax.random.split(key)
        obs, state = reset(k, params)
        carry = policy.initialize_carry(1)
        steps = []
        for _ in range(max_steps):
            batched = jax.tree_util.tree_map(lambda x: x[None], obs)
            new_carry, action = act(carry, batched, jnp.zeros(1, bool), k)
            r, h = jax.device_get(state.robot), jax.device_get(state.humans)
            o = jax.device_get(obs)
            lidar = (o.lidar,) if config.env.lidar_rays else ()
            steps.append(
                dict(
                    robot=np.array([r.pos[0], r.pos[1], r.heading, r.vel[0], r.vel[1]]),
                    goal=np.asarray(r.goal),
                    humans=np.concatenate([h.pos, h.vel, h.radius[:, None]], axis=1),
                    lidar=o.lidar,
                    obs=(o.robot_node, o.robot_vel, o.humans, o.human_mask.astype(np.float32), *lidar),
                    state=step_info.state_from_carry(carry),
                    new_state=step_info.state_from_carry(new_carry),
                    action=np.asarray(action[0]),
                )
            )
            key, k = jax.random.split(key)
            obs, state, _, terminated, truncated, _ = step(k, state, action[0], params)
            carry = new_carry
            if bool(terminated | truncated):
                break
        out.append(steps)
    return out


@pytest.fixture(scope="module")
def const_vel():
    return load_source(PRETRAINED)


@pytest.fixture(scope="module")
def const_vel_episodes(const_vel):
    return record(const_vel)


@pytest.fixture(scope="module")
def exported(tmp_path_factory, const_vel):
    from tgrf_jax.cli.export import main

    out = tmp_path_factory.mktemp("export") / "policy"
    assert main(["--pretrained", PRETRAINED, "--out", str(out)]) == 0
    return out


def test_episodes_see_humans(const_vel_episodes):
    # the parity checks below mean something only if the recorded observations hold humans in range
    seen = [s["obs"][3].sum() for ep in const_vel_episodes for s in ep]
    assert len(seen) >= 40 and max(seen) >= 3 and np.mean(seen) >= 1


@pytest.mark.parametrize("runtime", ["onnx", "stablehlo"])
def test_exported_step_matches_env_policy(exported, const_vel_episodes, runtime):
    run = OnnxRuntime(exported) if runtime == "onnx" else StableHloRuntime(exported)
    worst_action = worst_state = 0.0
    for ep in const_vel_episodes:
        for s in ep:
            action, new_state = run(*s["obs"], s["state"])
            assert action.shape == (2,) and action.dtype == np.float32
            worst_action = max(worst_action, float(np.max(np.abs(action - s["action"]))))
            worst_state = max(worst_state, float(np.max(np.abs(new_state - s["new_state"]))))
    assert worst_action <= 1e-5 and worst_state <= 1e-5, (worst_action, worst_state)


def test_export_directory_and_interface(exported):
    files = sorted(p.name for p in exported.iterdir())
    assert files == [
        "config.yaml",
        "interface.json",
        "manifest.json",
        "meta.json",
        "params.npz",
        "policy.onnx",
        "policy.stablehlo",
    ]
    assert not list(exported.parent.glob(".policy.*"))  # no temporary directory left beside it
    manifest = json.loads((exported / "manifest.json").read_text())
    assert sorted(manifest["sha256"]) == [f for f in files if f != "manifest.json"]
    spec = read_interface(exported)
    import onnxruntime as ort

    session = ort.InferenceSession(str(exported / spec["files"]["onnx"]), providers=["CPUExecutionProvider"])
    onnx_inputs = {i.name: i.shape for i in session.get_inputs()}
    assert {i["name"]: i["shape"] for i in spec["inputs"]} == onnx_inputs
    assert {o["name"]: o["shape"] for o in spec["outputs"]} == {o.name: o.shape for o in session.get_outputs()}
    assert [i["name"] for i in spec["inputs"]] == ["robot_node", "robot_vel", "humans", "human_mask", "state"]
    humans = next(i for i in spec["inputs"] if i["name"] == "humans")
    assert humans["shape"] == [20, 12] and len(humans["layout"]) == 12 and "padding" in humans
    assert all(i["dtype"] == "float32" and i.get("units") for i in spec["inputs"])
    assert spec["robot"]["kinematics"] == "holonomic" and spec["dt_s"] == 0.25
    # the export is a pretrained-format directory too
    config, _, meta = __import__("tgrf_jax.pretrained", fromlist=["load"]).load(str(exported))
    assert config.env.predictor == "const_vel" and meta["pretrained"] == PRETRAINED


def test_export_refuses_bad_input(tmp_path, exported, capsys):
    from tgrf_jax.cli.export import main

    assert main(["--pretrained", PRETRAINED, "--out", str(exported)]) == 2
    assert "already exists" in capsys.readouterr().err
    assert main(["--pretrained", "no-such-policy", "--out", str(tmp_path / "a")]) == 2
    err = capsys.readouterr().err
    assert "no pretrained policy 'no-such-policy'" in err and PRETRAINED in err
    assert main(["--out", str(tmp_path / "b")]) == 2
    assert "exactly one of RUN_DIR and --pretrained" in capsys.readouterr().err

    # a run directory whose checkpoint is damaged: named, and nothing written
    run = tmp_path / "run"
    (run / "checkpoints" / "8").mkdir(parents=True)
    (run / "checkpoints" / "8" / "junk").write_text("not a checkpoint")
    (run / "config.yaml").write_text((pathlib.Path(exported) / "config.yaml").read_text())
    assert main([str(run), "--out", str(tmp_path / "c")]) == 2
    err = capsys.readouterr().err
    assert "tgrf-export: error:" in err and "checkpoint" in err
    assert not (tmp_path / "c").exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run"]

    with pytest.raises(ConfigError, match="unknown runtime 'tflite'"):
        Navigator(exported, runtime="tflite")
    with pytest.raises(ConfigError, match="not exported"):
        Navigator(PRETRAINED, runtime="onnx")


# ------------------------------------------------------------------------------------------------ navigator


def replay(nav: Navigator, episodes, with_ids: bool = True) -> float:
    """Largest |navigator action - env action| over recorded episodes, fed the true world state."""
    worst = 0.0
    for ep in episodes:
        nav.reset()
        for s in ep:
            ids = list(range(len(s["humans"]))) if with_ids else None
            d = nav.act(s["robot"], s["goal"], s["humans"], s["lidar"] if nav.lidar_rays else None, ids=ids)
            worst = max(worst, float(np.max(np.abs(d.action - s["action"]))))
    return worst


def test_navigator_replays_env_const_vel(const_vel, const_vel_episodes):
    assert replay(Navigator(const_vel), const_vel_episodes) <= 1e-5


def test_navigator_onnx_runtime_replays_env(exported, const_vel_episodes):
    assert replay(Navigator(exported, runtime="onnx"), const_vel_episodes) <= 1e-5


@pytest.mark.parametrize("name", ["table1-no_pred-tgrf", "table1-gst-tgrf", "table1-dsrnn-tgrf"])
def test_navigator_replays_env_other_predictors(name):
    source = load_source(name)
    episodes = record(source, episodes=2, max_steps=30, seed=1)
    assert replay(Navigator(source), episodes) <= 1e-5


def test_navigator_replays_env_unicycle():
    # No unicycle policy ships yet: an untrained network checks the unicycle observation (heading, velocity).
    config = TrainConfig.from_dict({"env": {"kinematics": "unicycle"}})
    net = make_network_for(config)
    params = jax.device_get(net.init(jax.random.PRNGKey(3)))
    source = PolicySource(config, params, {"test": "untrained"})
    episodes = record(source, episodes=1, max_steps=30)
    nav = Navigator(source)
    assert replay(nav, episodes) <= 1e-5
    # the command is (v, omega) within the unicycle limits
    env = config.env
    s = episodes[0][-1]
    d = nav.act(s["robot"], s["goal"], s["humans"])
    v, omega = d.command
    forward = s["robot"][3] * np.cos(s["robot"][2]) + s["robot"][4] * np.sin(s["robot"][2])
    assert env.unicycle_dv_min - 1e-6 <= v - forward <= env.unicycle_dv_max + 1e-6
    assert abs(omega) <= env.unicycle_dtheta_max / env.dt + 1e-6


def test_navigator_capacity_none_and_non_finite(const_vel):
    nav = Navigator(const_vel)
    robot, goal = (0.0, 0.0, 0.0, 0.3, 0.0), (6.0, 0.0)
    rng = np.random.default_rng(0)
    crowd = np.concatenate([rng.uniform(-3, 3, (30, 2)), rng.uniform(-1, 1, (30, 2)), np.full((30, 1), 0.3)], 1)
    obs, counts = nav.observation(robot, goal, crowd)
    dist = np.hypot(crowd[:, 0], crowd[:, 1])
    assert counts == (30, 0, 30, 20)  # all in range, the 20 nearest used
    nearest = np.sort(dist)[:20]
    np.testing.assert_allclose(np.hypot(obs[2][:, 0], obs[2][:, 1]), nearest, rtol=1e-6)
    # the same decision as with only the 20 nearest detected
    nav.reset()
    many = nav.act(robot, goal, crowd)
    nav.reset()
    few = nav.act(robot, goal, crowd[np.argsort(dist)[:20]])
    np.testing.assert_array_equal(many.action, few.action)

    nav.reset()
    empty = nav.act(robot, goal, [])
    assert (empty.num_detected, empty.num_used) == (0, 0) and np.all(np.isfinite(empty.command))
    assert np.linalg.norm(empty.command) <= 1.0 + 1e-6
    nav.reset()
    assert np.array_equal(nav.act(robot, goal, None).action, empty.action)

    bad = [
        Detection((1.0, 0.5), (0.0, 0.0), 0.3),
        Detection((np.nan, 1.0), (0.0, 0.0)),
        Detection((1.0, 1.0), (np.inf, 0.0)),
        {"position": (2.0, 0.0), "velocity": (0.0, 0.0), "radius": np.nan},
    ]
    nav.reset()
    d = nav.act(robot, goal, bad)
    assert (d.num_detected, d.num_dropped, d.num_used) == (4, 3, 1)
    nav.reset()
    assert np.array_equal(d.action, nav.act(robot, goal, bad[:1]).action)
    assert nav.dropped_total == 3


def test_navigator_refuses_bad_input(const_vel):
    nav = Navigator(const_vel)
    robot, goal = (0.0, 0.0, 0.0, 0.0, 0.0), (5.0, 0.0)
    cases = [
        (dict(robot_state={"pose": (0, 0, 0, 1), "velocity": (0, 0)}), r"robot_state pose must be 3 numbers"),
        (dict(robot_state=(0, 0, 0, 0)), r"robot_state must be 5 numbers"),
        (dict(goal=(np.nan, 1.0)), r"goal must be finite"),
        (dict(goal=(1.0, 2.0, 3.0)), r"goal must be 2 numbers"),
        (dict(humans=np.zeros((3, 3))), r"humans as an array must be \(M, 4\)"),
        (dict(humans=[{"pos": (1, 1)}]), r"humans\[0\] needs 'position'"),
        (dict(robot_state=(0, 0, 0, 40.0, 0)), r"velocities are in m/s"),
        (dict(lidar=np.ones(360)), r"lidar: this policy has no scan input"),
    ]
    for change, message in cases:
        args = dict(robot_state=robot, goal=goal, humans=[], lidar=None) | change
        with pytest.raises(ValueError, match=message):
            nav.act(**args)
    with pytest.raises(ConfigError, match="ground-truth predictions"):
        Navigator("table1-truth-tgrf")
    gst = Navigator("table1-gst-tgrf")
    with pytest.raises(ValueError, match="give every detection an id"):
        gst.act(robot, goal, [Detection((1, 1), (0, 0))])


def test_interface_json_is_self_contained(exported):
    # Someone without tgrf-jax: build the inputs from the JSON alone and run ONNX Runtime.
    import onnxruntime as ort

    spec = json.loads((exported / "interface.json").read_text())
    session = ort.InferenceSession(str(exported / spec["files"]["onnx"]), providers=["CPUExecutionProvider"])
    feeds = {i["name"]: np.zeros(i["shape"], np.float32) for i in spec["inputs"]}
    feeds["robot_node"][:] = [0, 0, spec["robot"]["radius_m"], 4, 0, spec["robot"]["v_max_m_s"], np.pi / 2]
    action, new_state = session.run(None, feeds)
    assert action.shape == (2,) and new_state.shape == tuple(spec["outputs"][1]["shape"])
    assert action[0] > 0  # an empty world: head for the goal


# -------------------------------------------------------------------------------------------- a policy with a LiDAR

RAYS = 16


@pytest.fixture(scope="module")
def lidar_source():
    # An untrained small HH Attn (its scan encoder included) in the corridor, whose walls the scan sees.
    config = TrainConfig.from_dict(
        {
            "env": {
                "scenario": "corridor",
                "lidar_rays": RAYS,
                "num_humans": 3,
                "human_policy": "social_force",
                "predictor": "none",
            }
        }
    )
    params = jax.device_get(jax.jit(make_network_for(config).init)(jax.random.PRNGKey(5)))
    return PolicySource(config, params, {"test": "untrained lidar"})


@pytest.fixture(scope="module")
def lidar_episodes(lidar_source):
    return record(lidar_source, episodes=1, max_steps=8)


@pytest.fixture(scope="module")
def lidar_exported(tmp_path_factory, lidar_source):
    from tgrf_jax.deploy import export

    return export(lidar_source, tmp_path_factory.mktemp("export") / "lidar", say=lambda m: None)


def test_lidar_export_matches_env_policy(lidar_exported, lidar_episodes):
    scans = np.array([s["lidar"] for s in lidar_episodes[0]])
    assert scans.shape == (8, RAYS) and scans.min() < 5.0 and scans.max() == 5.0  # walls seen and open rays
    spec = read_interface(lidar_exported)
    names = [i["name"] for i in spec["inputs"]]
    assert names == ["robot_node", "robot_vel", "humans", "human_mask", "lidar", "state"]
    lidar = spec["inputs"][4]
    assert lidar["shape"] == [RAYS] and lidar["units"] == "m" and lidar["values"]["max_range_m"] == 5.0
    assert "heading" in lidar["frame"] and "pi/2" in lidar["frame"]  # holonomic: the heading the policy expects
    assert spec["network"]["lidar_rays"] == RAYS and spec["robot"]["lidar_rays"] == RAYS
    import onnxruntime as ort

    session = ort.InferenceSession(str(lidar_exported / spec["files"]["onnx"]), providers=["CPUExecutionProvider"])
    assert [i.name for i in session.get_inputs()] == names
    assert [i.shape for i in session.get_inputs()] == [i["shape"] for i in spec["inputs"]]
    for run in (OnnxRuntime(lidar_exported), StableHloRuntime(lidar_exported)):
        worst = 0.0
        for s in lidar_episodes[0]:
            action, new_state = run(*s["obs"], s["state"])
            worst = max(
                worst, float(np.max(np.abs(action - s["action"]))), float(np.max(np.abs(new_state - s["new_state"])))
            )
        assert worst <= 1e-5, (type(run).__name__, worst)
        # beyond the range reads as the range, NaN as no return (the range)
        s = lidar_episodes[0][-1]
        far = s["obs"][:4] + (np.where(s["lidar"] >= 5.0, np.float32(np.nan), s["lidar"]).astype(np.float32),)
        far2 = s["obs"][:4] + (np.where(s["lidar"] >= 5.0, np.float32(40.0), s["lidar"]).astype(np.float32),)
        np.testing.assert_allclose(run(*far, s["state"])[0], s["action"], atol=1e-5)
        np.testing.assert_allclose(run(*far2, s["state"])[0], s["action"], atol=1e-5)
    with pytest.raises(ValueError, match="takes 6 inputs"):
        OnnxRuntime(lidar_exported)(*lidar_episodes[0][0]["obs"][:4], lidar_episodes[0][0]["state"])


def test_navigator_with_lidar(lidar_source, lidar_exported, lidar_episodes):
    nav = Navigator(lidar_source)
    assert nav.lidar_rays == RAYS and "lidar_rays=16" in repr(nav)
    assert replay(nav, lidar_episodes) <= 1e-5
    assert replay(Navigator(lidar_exported, runtime="onnx"), lidar_episodes) <= 1e-5

    s = lidar_episodes[0][3]
    nav.reset()
    ref = nav.act(s["robot"], s["goal"], s["humans"], s["lidar"])
    assert ref.num_lidar_invalid == 0
    # a holonomic robot facing +x (the env keeps heading pi/2): its scan is the env's turned by a quarter turn
    facing_x = s["robot"].copy()
    facing_x[2] = 0.0
    nav.reset()
    turned = nav.act(facing_x, s["goal"], s["humans"], np.roll(s["lidar"], RAYS // 4))
    np.testing.assert_array_equal(turned.action, ref.action)
    # non-finite rays read as the sensor range, counted like dropped detections
    open_rays = np.flatnonzero(s["lidar"] >= 5.0)
    assert len(open_rays) >= 2
    scan = s["lidar"].astype(np.float64).copy()
    scan[open_rays[0]], scan[open_rays[1]] = np.nan, np.inf
    nav.reset()
    fixed = nav.act(s["robot"], s["goal"], s["humans"], scan)
    assert fixed.num_lidar_invalid == 2 and nav.lidar_invalid_total == 2
    np.testing.assert_array_equal(fixed.action, ref.action)
    nav.reset()
    far = np.where(s["lidar"] >= 5.0, 30.0, s["lidar"])  # beyond the range: clipped to it
    np.testing.assert_array_equal(nav.act(s["robot"], s["goal"], s["humans"], far).action, ref.action)
    nav.reset()
    nearer = s["lidar"].copy()
    nearer[open_rays[0]] = 0.5
    assert not np.allclose(nav.act(s["robot"], s["goal"], s["humans"], nearer).action, ref.action)

    cases = [
        (None, r"lidar: this policy reads a 16-ray 2-D LiDAR scan.*ray 0 along the robot's heading"),
        (np.ones(360), r"lidar has 360 rays but this policy was trained on 16 rays"),
        (np.ones((2, 16)), r"lidar has shape \(2, 16\) but this policy was trained on 16 rays"),
        (np.r_[np.ones(15), -1.0], r"lidar\[15\] = -1.0: a range must be >= 0 m"),
    ]
    for lidar, message in cases:
        with pytest.raises(ValueError, match=message):
            nav.act(s["robot"], s["goal"], s["humans"], lidar)


# ------------------------------------------------------------------------------------- every policy tgrf-jax trains

# Each network with and without the LiDAR encoder, both kinematics, every predictor, recurrent (HH Attn, DS-RNN) or
# not (MLP), both frames: tiny crowds, untrained weights (the export does not care what the weights learnt).
POLICIES = {
    "mlp-none-world": dict(network="mlp", kinematics="holonomic", predictor="none", lidar_rays=0, frame="world"),
    "mlp-truth-lidar": dict(network="mlp", kinematics="holonomic", predictor="truth", lidar_rays=8, frame="goal"),
    "hh_attn-const_vel": dict(network="hh_attn", kinematics="holonomic", predictor="const_vel", lidar_rays=0),
    "hh_attn-unicycle-gst-lidar": dict(network="hh_attn", kinematics="unicycle", predictor="gst", lidar_rays=8),
    "dsrnn-gst": dict(network="dsrnn", kinematics="holonomic", predictor="gst", lidar_rays=0),
    "dsrnn-unicycle-lidar": dict(
        network="dsrnn", kinematics="unicycle", predictor="const_vel", lidar_rays=8, frame="world"
    ),
}


def tiny_source(network, kinematics, predictor, lidar_rays, frame="goal", seed=0) -> PolicySource:
    config = TrainConfig.from_dict(
        {
            "env": {
                "num_humans": 3,
                "kinematics": kinematics,
                "predictor": predictor,
                "lidar_rays": lidar_rays,
                "human_policy": "social_force",
            },
            "network": {"name": network, "size": "small", "frame": frame},
        }
    )
    params = jax.device_get(jax.jit(make_network_for(config).init)(jax.random.PRNGKey(seed)))
    return PolicySource(config, params, {"test": f"untrained {network}"})


def random_inputs(step: PolicyStep, rng: np.random.Generator) -> list[np.ndarray]:
    """A plausible observation: robot and goal in the arena, humans around the robot, a mask, a scan."""
    f32 = np.float32
    robot_node = np.array([*rng.uniform(-5, 5, 2), 0.3, *rng.uniform(-5, 5, 2), 1.0, rng.uniform(-3, 3)], f32)
    humans = rng.uniform(-4, 4, (step.num_humans, step.obs_human_dim)).astype(f32)
    mask = (rng.uniform(size=step.num_humans) < 0.7).astype(f32)
    humans[mask == 0] = 0.0
    scan = [rng.uniform(0.2, 6.0, step.lidar_rays).astype(f32)] if step.lidar_rays else []
    return [robot_node, rng.uniform(-1, 1, 2).astype(f32), humans, mask, *scan]


def assert_runtimes_agree(directory, source: PolicySource, steps: int = 4) -> None:
    """ONNX and StableHLO against the JAX policy over a few chained decisions (the state carried over)."""
    step = PolicyStep(source.config, source.params)
    reference = make_runtime(source, "jax")
    loaded = load_source(directory)  # the manifest and interface.json are checked on the way
    rng = np.random.default_rng(0)
    inputs = [random_inputs(step, rng) for _ in range(steps)]
    for name in ("onnx", "stablehlo"):
        run = make_runtime(loaded, name)
        state = ref_state = np.zeros(step.state_size, np.float32)
        for obs in inputs:
            action, state = run(*obs, state)
            ref_action, ref_state = reference(*obs, ref_state)
            np.testing.assert_allclose(action, ref_action, atol=1e-5, err_msg=name)
            np.testing.assert_allclose(state, ref_state, atol=1e-5, err_msg=name)
        if step.state_size and source.config.network.name != "mlp":
            assert np.abs(state).max() > 0  # a recurrent network's state moved, so it was carried and compared


def assert_onnx_loads_quietly(path, capfd) -> None:
    """ONNX Runtime at its default log level (warnings shown) says nothing when it loads the file."""
    import onnxruntime as ort

    capfd.readouterr()
    ort.InferenceSession(str(path), ort.SessionOptions(), providers=["CPUExecutionProvider"])
    err = capfd.readouterr().err
    assert "[W:" not in err and "[E:" not in err, err[:500]


@pytest.mark.parametrize("name", list(POLICIES))
def test_every_policy_exports_and_runs_alike(name, tmp_path, capfd):
    from tgrf_jax.deploy import export

    source = tiny_source(**POLICIES[name])
    out = export(source, tmp_path / "policy", say=lambda m: None)
    assert_runtimes_agree(out, source)
    assert_onnx_loads_quietly(out / "policy.onnx", capfd)
    spec = read_interface(out)
    assert spec["robot"]["kinematics"] == source.config.env.kinematics
    assert spec["predictions"]["predictor"] == source.config.env.predictor


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory):
    from tgrf_jax.train.run_dir import train_run

    run = tmp_path_factory.mktemp("tiny") / "run"
    tiny = pathlib.Path(__file__).resolve().parents[1] / "configs" / "tiny.yaml"
    train_run(TrainConfig.from_yaml(tiny, ["run.eval_episodes=0"]), run, log=lambda m: None)
    return run


def test_export_of_a_trained_run(tiny_run, tmp_path, capfd):
    from tgrf_jax.cli.export import main

    cases = {
        "latest": ([str(tiny_run)], 12),
        "step": ([str(tiny_run), "--step", "8"], 8),
        "pretrained": (["--pretrained", str(tiny_run)], 12),
    }
    for name, (args, update) in cases.items():
        assert main([*args, "--out", str(tmp_path / name)]) == 0, name
        source = load_source(tiny_run, step=update)
        assert json.loads((tmp_path / name / "meta.json").read_text())["update"] == update
        assert_runtimes_agree(tmp_path / name, source, steps=2)
    assert_onnx_loads_quietly(tmp_path / "latest" / "policy.onnx", capfd)


def test_export_removes_what_a_killed_export_left(tmp_path, const_vel):
    import os
    import signal
    import subprocess
    import sys
    import time

    from tgrf_jax.deploy import export
    from tgrf_jax.pretrained.directory import PARTIAL_SUFFIX, _lock

    command = [sys.executable, "-m", "tgrf_jax.cli.export", "--pretrained", PRETRAINED, "--out"]
    proc = subprocess.Popen([*command, str(tmp_path / "killed")], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    deadline = time.monotonic() + 300
    while not list(tmp_path.glob(f".killed.*{PARTIAL_SUFFIX}")) and proc.poll() is None:
        assert time.monotonic() < deadline, "the export never started writing"
        time.sleep(0.05)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    assert proc.returncode == -signal.SIGKILL, proc.stderr.read().decode()[-2000:]
    left = list(tmp_path.glob(f".killed.*{PARTIAL_SUFFIX}"))
    assert left and not (tmp_path / "killed").exists()
    # a writer still at work (its lock held) keeps its directory
    busy = tmp_path / f".busy.x{PARTIAL_SUFFIX}"
    busy.mkdir()
    fd = _lock(busy, wait=True)
    try:
        export(const_vel, tmp_path / "next", ["stablehlo"], say=lambda m: None)
        assert busy.is_dir()
    finally:
        os.close(fd)
    assert not [p for p in left if p.exists()]
    assert sorted(p.name for p in tmp_path.iterdir()) == [busy.name, "next"]


# ------------------------------------------------------------------------------------- a directory verified whole


def _flip_byte(path: pathlib.Path, offset: int) -> None:
    data = bytearray(path.read_bytes())
    data[offset] ^= 0x01
    path.write_bytes(bytes(data))


def _rewrite_params(directory: pathlib.Path, change) -> None:
    with np.load(directory / "params.npz") as data:
        flat = {k: data[k] for k in data.files}
    change(flat)
    np.savez(directory / "params.npz", **flat)


def _first_kernel(flat: dict) -> str:
    return sorted(k for k in flat if k.endswith("kernel"))[0]


def _set(value):
    def change(flat):
        key = _first_kernel(flat)
        flat[key] = flat[key].copy()
        flat[key].flat[3] = value

    return change


# Each case: what is done to a copy of an exported directory, whether the manifest is then written anew (to reach
# the checks behind it, as a hand-edited directory would), and the error.
TAMPERING = {
    "interface edited": (
        lambda d: (d / "interface.json").write_text(
            (d / "interface.json").read_text().replace('"dt_s": 0.25', '"dt_s": 0.5')
        ),
        False,
        r"interface.json' does not match manifest.json",
    ),
    "interface edited, manifest rewritten": (
        lambda d: (d / "interface.json").write_text(
            (d / "interface.json").read_text().replace('"dt_s": 0.25', '"dt_s": 0.5')
        ),
        True,
        r"interface.json' does not match the policy it describes: dt_s is 0.5 there, 0.25 from config.yaml",
    ),
    "interface deleted": (
        lambda d: (d / "interface.json").unlink(),
        False,
        r"interface.json' is listed in manifest.json but is missing",
    ),
    "params header byte flipped": (
        lambda d: _flip_byte(d / "params.npz", 40),
        False,
        r"params.npz' does not match manifest.json",
    ),
    "NaN weight": (lambda d: _rewrite_params(d, _set(np.nan)), True, r"params.npz': .*kernel holds 1 non-finite"),
    "inf weight": (lambda d: _rewrite_params(d, _set(np.inf)), True, r"params.npz': .*kernel holds 1 non-finite"),
    "float64 weights": (
        lambda d: _rewrite_params(d, lambda f: f.update({k: v.astype(np.float64) for k, v in f.items()})),
        True,
        r"params.npz': .* is float64, the config's network expects float32",
    ),
    "params truncated": (
        lambda d: (d / "params.npz").write_bytes((d / "params.npz").read_bytes()[:5000]),
        True,
        r"params.npz': cannot read the parameters \(BadZipFile: ",
    ),
    "manifest deleted": (lambda d: (d / "manifest.json").unlink(), False, r"manifest.json' missing"),
    "file added": (lambda d: (d / "notes.txt").write_text("hi"), False, r"notes.txt' is not listed in manifest.json"),
}


@pytest.mark.parametrize("case", list(TAMPERING))
def test_exported_directory_is_verified_whole(case, exported, tmp_path):
    from tgrf_jax.pretrained import write_manifest

    tamper, reseal, message = TAMPERING[case]
    broken = tmp_path / "broken"
    shutil.copytree(exported, broken)
    tamper(broken)
    if reseal:
        write_manifest(broken)
    with pytest.raises(ConfigError, match=message) as caught:
        load_source(broken)
    assert "\n" not in str(caught.value) and str(broken) in str(caught.value)


@pytest.fixture(scope="module")
def nan_weights(exported, tmp_path_factory):
    from tgrf_jax.pretrained import write_manifest

    broken = tmp_path_factory.mktemp("nan") / "policy"
    shutil.copytree(exported, broken)
    _rewrite_params(broken, _set(np.nan))
    write_manifest(broken)
    return broken


@pytest.mark.parametrize("runtime", ["jax", "onnx", "stablehlo"])
def test_navigator_refuses_nan_weights_in_every_runtime(nan_weights, runtime):
    with pytest.raises(ConfigError, match=r"params.npz': .* non-finite"):
        Navigator(nan_weights, runtime=runtime)


def test_navigator_refuses_nan_weights_built_in_memory(const_vel):
    params = jax.tree_util.tree_map(np.array, const_vel.params)
    params["params"]["robot_linear"]["kernel"][0, 0] = np.nan
    with pytest.raises(ConfigError, match=r"the policy's parameters: params/robot_linear/kernel holds 1 non-finite"):
        Navigator(PolicySource(const_vel.config, params, {"test": "nan"}))


def test_tools_refuse_a_damaged_directory(nan_weights, exported, tmp_path, capsys):
    from tgrf_jax.cli import eval_main
    from tgrf_jax.cli.export import main as export_main

    assert eval_main(["--pretrained", str(nan_weights), "--episodes", "2"]) == 2
    err = capsys.readouterr().err
    assert "params.npz" in err and "non-finite" in err and "Traceback" not in err
    assert export_main(["--pretrained", str(nan_weights), "--out", str(tmp_path / "a")]) == 2
    assert "non-finite" in capsys.readouterr().err and not (tmp_path / "a").exists()

    flipped = tmp_path / "flipped"
    shutil.copytree(exported, flipped)
    _flip_byte(flipped / "policy.onnx", 100)
    assert export_main(["--pretrained", str(flipped), "--out", str(tmp_path / "b")]) == 2
    assert "policy.onnx' does not match manifest.json" in capsys.readouterr().err
    with pytest.raises(ConfigError, match="policy.onnx' does not match manifest.json"):
        Navigator(flipped, runtime="onnx")


def test_install_hints_name_an_extra_that_installs_what_is_missing(monkeypatch, tmp_path, capsys):
    import re
    import sys

    tomllib = pytest.importorskip("tomllib")
    from tgrf_jax.cli.export import main as export_main

    root = pathlib.Path(__file__).resolve().parents[1]
    extras = tomllib.loads((root / "pyproject.toml").read_text())["project"]["optional-dependencies"]

    def installs(extra: str) -> set[str]:
        return {re.split(r"[<>=!~\[; ]", req, maxsplit=1)[0].lower() for req in extras[extra]}

    assert {"jax2onnx", "onnxruntime", "onnx"} <= installs("deploy")
    assert "gymnasium" in installs("gym")
    # every hint in the package names one of these extras
    hints = set()
    for path in [*root.joinpath("tgrf_jax").rglob("*.py")]:
        hints |= set(re.findall(r"pip install '(tgrf-jax\[[a-z,]+\])'", path.read_text()))
    assert hints and hints <= {"tgrf-jax[deploy]", "tgrf-jax[gym]"}, hints

    monkeypatch.setitem(sys.modules, "jax2onnx", None)  # as if not installed
    assert export_main(["--pretrained", PRETRAINED, "--out", str(tmp_path / "x")]) == 2
    assert "pip install 'tgrf-jax[deploy]'" in capsys.readouterr().err
    monkeypatch.setitem(sys.modules, "onnxruntime", None)
    with pytest.raises(ConfigError, match=r"pip install 'tgrf-jax\[deploy\]'"):
        OnnxRuntime(tmp_path)
