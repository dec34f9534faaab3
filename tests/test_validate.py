"""`EnvParams.validate()`: hand-built parameters checked on the host against the declarations in tgrf_jax.config (the
same ranges and relations as a config), and checked wherever concrete parameters enter: evaluate, record_episodes,
a trainer's init and a sweep's runs."""

import pathlib

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import CompileCounter, make_env

from tgrf_jax.config import ConfigError, TrainConfig
from tgrf_jax.evaluate import evaluate
from tgrf_jax.policies import StraightPolicy
from tgrf_jax.render import record_episodes

ROOT = pathlib.Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def params():
    return make_env(num_humans=2, predictor="none").default_params


@pytest.mark.parametrize(
    "change, message",
    [
        (dict(dt=0.0), "env.dt = 0.0 is out of range; allowed: >= 0.01 and <= 1.0"),
        (dict(dt=-0.25), "env.dt = -0.25 is out of range; allowed: >= 0.01 and <= 1.0"),
        (dict(dt=np.nan), "env.dt = nan must be finite; allowed: >= 0.01 and <= 1.0"),
        (dict(robot_radius=-0.3), "env.robot_radius = -0.3 is out of range; allowed: > 0.0"),
        (dict(human_radius_min=-0.3), "env.human_radius_min = -0.3 is out of range; allowed: > 0.0"),
        (dict(time_limit=1e9), r"env.time_limit = 1e\+09 is out of range; allowed: > 0.0 and <= 1000.0"),
        (dict(human_radius_min=0.6), "env.human_radius_min = 0.6 must be <= env.human_radius_max = 0.5"),
        (dict(time_limit=0.1), "env.time_limit = 0.1 must be >= env.dt = 0.25"),
        (dict(dt=jnp.array([0.25, 0.0, 0.1])), r"env.dt\[1\] = 0.0 is out of range"),  # batched: the element named
    ],
)
def test_hand_built_env_params_name_the_field_and_the_allowed_range(params, change, message):
    bad = params.replace(**{k: jnp.asarray(v, jnp.float32) for k, v in change.items()})
    with pytest.raises(ValueError, match=message):
        bad.validate()


@pytest.mark.parametrize(
    "value, kind",
    [
        ("0.1", "str"),
        (None, "NoneType"),
        (True, "bool"),
        (1 + 2j, "complex"),
        ([0.1, [0.2]], "list"),
        (["0.1", "0.2"], "array of <U3"),
        ("9" * 5000, "str"),
    ],
)
def test_a_leaf_that_is_no_number_is_named_with_what_is_allowed(params, value, kind):
    # replace() takes anything: numpy's comparisons would fail on a string without naming the field, and a bool
    # would pass as 0 or 1
    with pytest.raises(ConfigError) as e:
        params.replace(dt=value).validate()
    message = str(e.value)
    assert message.startswith("env.dt = ") and f"({kind}) must be a number, or an array of numbers" in message
    assert len(message) < 200  # a huge value is cut short, not echoed


def test_reward_params_and_valid_params(params):
    with pytest.raises(ConfigError, match=r"reward.sigma_disc = -0.2 is out of range; allowed: > 0.0"):
        params.replace(reward=params.reward.replace(sigma_disc=jnp.float32(-0.2))).validate()
    assert params.validate() is params
    # a config's boundary values pass as float32 leaves (0.01 is not exactly representable)
    assert make_env(num_humans=1, dt=0.01, goal_change_prob=1.0).default_params.validate()
    batched = jax.tree_util.tree_map(lambda x: jnp.stack([x, x]), params)
    assert batched.validate() is batched


def test_traced_params_cannot_be_checked(params):
    # the first traced field in declaration order is named
    with pytest.raises(TypeError, match=r"env\.\w+ is traced: parameters are checked on concrete values"):
        jax.jit(lambda p: p.validate().dt)(params)


def test_evaluate_and_record_check_their_params_before_compiling(params):
    env = make_env(num_humans=2, predictor="none")
    key, zero_dt, negative_radius = (
        jax.random.key(0),
        params.replace(dt=np.float32(0.0)),
        params.replace(robot_radius=np.float32(-0.3)),
    )
    with CompileCounter() as counter:
        with pytest.raises(ConfigError, match="env.dt = 0.0 is out of range"):  # dt 0 never ends an episode
            evaluate(env, StraightPolicy(), key, 4, params=zero_dt)
        with pytest.raises(ConfigError, match="env.robot_radius = -0.3 is out of range"):
            record_episodes(env, StraightPolicy(), key, 1, params=negative_radius)
    assert counter.compiles == 0


def test_a_trainer_checks_hand_built_hyper_parameters():
    from tgrf_jax.train.ppo import make_trainer

    t = make_trainer(TrainConfig.from_yaml(ROOT / "configs" / "tiny.yaml"))
    hp, key = t.default_hparams, jax.random.PRNGKey(0)
    negative_lr, zero_dt = hp.replace(lr=np.float32(-1e-3)), hp.replace(env=hp.env.replace(dt=np.float32(0.0)))
    with CompileCounter() as counter:
        with pytest.raises(ConfigError, match=r"ppo.lr = -0.001 is out of range; allowed: > 0.0 and <= 1.0"):
            t.jit_init(key, negative_lr)
        with pytest.raises(ConfigError, match=r"env.dt = 0.0 is out of range"):
            t.jit_init(key, zero_dt)
    assert counter.compiles == 0


def test_a_sweep_checks_every_run_s_hyper_parameters(monkeypatch):
    from tgrf_jax.sweep import SweepSpec
    from tgrf_jax.sweep.program import BatchedProgram
    from tgrf_jax.train import ppo

    runs = SweepSpec.create(str(ROOT / "configs" / "tiny.yaml"), ["reward.h_disc=1,2"], "1", []).runs()
    real = ppo.hparams_from_config

    def second_run_with_zero_dt(config):  # what a bug between the config and the program could hand over
        hp = real(config)
        return hp.replace(env=hp.env.replace(dt=np.float32(0.0))) if config.reward.h_disc == 2 else hp

    monkeypatch.setattr(ppo, "hparams_from_config", second_run_with_zero_dt)
    with CompileCounter() as counter:
        with pytest.raises(ConfigError, match=r"env.dt\[1\] = 0.0 is out of range"):
            BatchedProgram(runs, jax.local_devices()[:1])
    assert counter.compiles == 0
