"""Exported policies and the navigator runtime (tgrf_jax.deploy, tgrf-export).

The references are real env episodes played by the env-side policy (`LearnedPolicy.act` on `CrowdNavEnv`
observations): the exported files must give its actions and recurrent states on its observations, and
`Navigator`, fed only what a robot would know (poses, velocities, radii of the humans), must give its actions.
"""

from __future__ import annotations

import json
import pathlib

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
            steps.append(dict(
                robot=np.array([r.pos[0], r.pos[1], r.heading, r.vel[0], r.vel[1]]), goal=np.asarray(r.goal),
                humans=np.concatenate([h.pos, h.vel, h.radius[:, None]], axis=1),
                obs=(o.robot_node, o.robot_vel, o.humans, o.human_mask.astype(np.float32)),
                state=step_info.state_from_carry(carry), new_state=step_info.state_from_carry(new_carry),
                action=np.asarray(action[0])))
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
    assert files == ["config.yaml", "interface.json", "meta.json", "params.npz", "policy.onnx", "policy.stablehlo"]
    assert not list(exported.parent.glob(".policy.*"))  # no temporary directory left beside it
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
            d = nav.act(s["robot"], s["goal"], s["humans"], ids=ids)
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

    bad = [Detection((1.0, 0.5), (0.0, 0.0), 0.3), Detection((np.nan, 1.0), (0.0, 0.0)),
           Detection((1.0, 1.0), (np.inf, 0.0)), {"position": (2.0, 0.0), "velocity": (0.0, 0.0), "radius": np.nan}]
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
        (dict(humans=[Detection((1, 1), (0, 0), -0.3)]), r"humans\[0\] radius = -0.3"),
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
