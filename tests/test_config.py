import pathlib
import re

import pytest
from helpers import CompileCounter

from tgrf_jax import CrowdNavEnv
from tgrf_jax.config import (
    ConfigError,
    EnvConfig,
    RewardConfig,
    TrainConfig,
    apply_overrides,
    load_yaml,
    reward_config_from_dict,
)

CONFIGS = pathlib.Path(__file__).resolve().parents[1] / "configs"


@pytest.mark.parametrize(
    "data, pattern",
    [
        ({"num_human": 5}, r"unknown config key 'env.num_human' \(did you mean 'num_humans'\?\)"),
        ({"human_radius_min": -0.1}, r"env.human_radius_min = -0.1 is out of range; allowed: > 0.0"),
        ({"human_policy": "sfm"}, r"env.human_policy = 'sfm' is not allowed; allowed: one of 'orca', 'social_force'"),
        ({"pred_horizon": 0}, r"env.pred_horizon = 0 is out of range; allowed: >= 1 and <= 50"),
        ({"num_humans": 0}, r"env.predictor = 'const_vel' needs humans.*num_humans = 0"),
        ({"num_humans": 2.5}, r"env.num_humans = 2.5 must be an integer"),
        ({"dt": "fast"}, r"env.dt = 'fast' must be a number"),
        ({"goal_change_prob": 1.5}, r"env.goal_change_prob = 1.5 is out of range; allowed: >= 0.0 and <= 1.0"),
        ({"human_v_pref_min": 2.0}, r"env.human_v_pref_min = 2.0 must be <= env.human_v_pref_max = 1.5"),
        ({"min_start_goal_dist": 100.0}, r"env.min_start_goal_dist = 100.0 cannot be met"),
        ({"dt": float("nan")}, r"env.dt = nan must be finite"),
        ({"dt": "nan"}, r"env.dt = 'nan' must be a finite number"),  # YAML reads a bare nan as text
        ({"num_humans": "inf"}, r"env.num_humans = 'inf' must be an integer$"),
        ({"robot_visible": "maybe"}, r"env.robot_visible = 'maybe' must be a boolean"),
    ],
)
def test_bad_env_config_names_field_and_allowed_values(data, pattern):
    with pytest.raises(ConfigError, match=pattern):
        EnvConfig.from_dict(data)


def test_bad_reward_config():
    with pytest.raises(ConfigError, match=r"reward.sigma_disc = 0.0 is out of range; allowed: > 0.0"):
        reward_config_from_dict({"sigma_disc": 0})
    with pytest.raises(
        ConfigError,
        match=r"reward.scheme = 'scan' is not allowed; allowed: 'tgrf', 'crowdnav_pp', 'dsrnn', 'tgrf_circle'",
    ):
        reward_config_from_dict({"scheme": "scan"})
    with pytest.raises(ConfigError, match=r"unknown config key 'reward.hdisc' \(did you mean 'h_disc'\?\)"):
        reward_config_from_dict({"hdisc": 1.0})
    with pytest.raises(ConfigError, match=r"reward.r_col = 5.0 is out of range; allowed: <= 0.0"):
        RewardConfig(r_col=5.0)


def test_error_is_raised_before_any_tracing():
    # Constructing the environment validates; no jax computation is needed to see the error.
    with CompileCounter() as counter, pytest.raises(ConfigError, match="env.sensor_range"):
        CrowdNavEnv({"sensor_range": -1.0})
    assert counter.traces == counter.compiles == 0


def test_reward_config_scheme_defaults_and_overrides():
    cfg = reward_config_from_dict({"scheme": "crowdnav_pp", "h_disc": 1.0})
    resolved = cfg.resolved()
    assert resolved["r_col"] == -20.0 and resolved["h_disc"] == 1.0 and resolved["disc_slope"] == 2.5
    assert float(cfg.params().h_disc) == 1.0


def test_yaml_configs_load_and_build_envs():
    files = sorted(CONFIGS.glob("*.yaml"))
    assert files, "configs/ must ship example configs"
    for path in files:
        data = load_yaml(path)
        env = CrowdNavEnv(EnvConfig.from_dict(data.get("env")), reward_config_from_dict(data.get("reward")))
        assert env.num_humans >= 0


def test_missing_and_corrupt_yaml(tmp_path):
    with pytest.raises(ConfigError, match="does not exist"):
        load_yaml(tmp_path / "nope.yaml")
    bad = tmp_path / "bad.yaml"
    bad.write_text("env: [unclosed\n")
    with pytest.raises(ConfigError, match="not valid YAML"):
        load_yaml(bad)


def test_overrides_parse_yaml_scalars():
    data = apply_overrides({"env": {"num_humans": 20}}, ["env.num_humans=5", "reward.h_disc=2.0", "env.predictor=none"])
    assert data == {"env": {"num_humans": 5, "predictor": "none"}, "reward": {"h_disc": 2.0}}
    with pytest.raises(ConfigError, match="section.field=value"):
        apply_overrides({}, ["env.num_humans"])


@pytest.mark.parametrize(
    "text, message",
    [
        ("ppo:\n  lr: 1.0e-4\nppo:\n  num_envs: 8\n", "found duplicate key 'ppo' (first given on line 1)"),
        ("env:\n  dt: 0.25\n  dt: 0.1\n", "found duplicate key 'dt' (first given on line 2)"),
    ],
)
def test_duplicate_yaml_keys_are_rejected(tmp_path, text, message):
    path = tmp_path / "c.yaml"
    path.write_text(text)
    with pytest.raises(ConfigError, match=re.escape(message)):
        TrainConfig.from_yaml(path)


def test_non_utf8_and_directory_configs_are_named(tmp_path):
    path = tmp_path / "c.yaml"
    path.write_bytes(b"env:\n  dt: 0.25 \xff\xfe\n")
    with pytest.raises(ConfigError, match="is not UTF-8 text"):
        TrainConfig.from_yaml(path)
    with pytest.raises(ConfigError, match="is a directory, not a YAML file"):
        TrainConfig.from_yaml(tmp_path)


def test_eval_and_render_play_the_env_and_reward_of_a_train_config(tmp_path):
    from tgrf_jax.cli.common import load_playable

    train = TrainConfig.from_yaml(CONFIGS / "tiny.yaml")
    playable = load_playable(str(CONFIGS / "tiny.yaml"), ["env.num_humans=3"], "tgrf-eval")
    assert playable.env == EnvConfig.from_dict(dict(train.to_dict()["env"], num_humans=3))
    assert playable.reward == train.reward and not playable.has_policy
    typo = tmp_path / "typo.yaml"
    typo.write_text((CONFIGS / "tiny.yaml").read_text().replace("num_envs:", "num_env:"))
    with pytest.raises(ConfigError, match=r"unknown config key 'ppo.num_env'"):  # the other sections are checked too
        load_playable(str(typo), [], "tgrf-eval")


def test_notes_name_a_wall_term_without_walls_and_gaps_routing_cannot_use():
    assert TrainConfig().notes() == []
    lone_wall_term = TrainConfig.from_dict({"reward": {"h_wall": 1.0}})
    assert lone_wall_term.to_yaml().startswith("# note: reward.h_wall = 1 but the env has no obstacles")
    left, right = [[-2, -1], [-0.5, -1], [-0.5, 1], [-2, 1]], [[0.3, -1], [2, -1], [2, 1], [0.3, 1]]
    far = [[5, 5], [6, 6]]
    narrow = TrainConfig.from_dict({"env": {"obstacles": [left, right, far]}})
    (note,) = narrow.notes()  # ORCA humans keep 0.5 + 0.01 + 0.15 m; with the 0.3 m margin a gap needs 1.92 m
    assert "gap between obstacles 0 and 1 is 0.80 m" in note and "(1.92 m:" in note and "env.route_margin" in note
    assert TrainConfig.from_dict({"env": {"obstacles": [left, right], "human_routing": False}}).notes() == []
    social_force = {"obstacles": [left, right], "human_policy": "social_force", "route_margin": 0.0}
    assert TrainConfig.from_dict({"env": {**social_force, "human_radius_max": 0.35}}).notes() == []  # 0.7 < 0.8 m
