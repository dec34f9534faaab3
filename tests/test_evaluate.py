import math

import jax
import numpy as np
import pytest

from helpers import make_env
from tgrf_jax.evaluate import evaluate, format_table, run_episodes
from tgrf_jax.policies import OrcaPolicy, StraightPolicy, baseline


def test_straight_policy_without_humans_always_succeeds():
    env = make_env(num_humans=0, predictor="none")
    result = evaluate(env, StraightPolicy(), jax.random.key(0), 64)
    assert result.n_episodes == 64
    assert result.success_rate == 1.0 and result.collision_rate == 0.0 and result.timeout_rate == 0.0
    # Straight at 1 m/s: NT ~ distance / v_max (start-goal >= 8 m), PL ~ NT * v_max, no intrusions.
    assert 8.0 <= result.path_length <= 17.0
    assert result.nav_time == pytest.approx(result.path_length, abs=0.3)
    assert result.itr_disc == 0.0 and result.itr_future == 0.0 and math.isnan(result.intrusion_dist_disc)


def test_episodes_are_distinct_and_rates_sum_to_one():
    env = make_env(num_humans=10, predictor="none")
    params = env.default_params
    stats = jax.jit(run_episodes, static_argnums=(0, 1, 3))(env, StraightPolicy(), jax.random.key(1), 32, params)
    outcome = np.asarray(stats.outcome)
    assert np.all(np.isin(outcome, [1, 2, 3]))
    result = evaluate(env, StraightPolicy(), jax.random.key(1), 32)
    assert result.success_rate + result.collision_rate + result.timeout_rate == pytest.approx(1.0)
    # Different episodes start from different scenarios.
    k_reset, _ = jax.random.split(jax.random.key(1))
    _, state = jax.vmap(env.reset, in_axes=(0, None))(jax.random.split(k_reset, 32), params)
    assert len(np.unique(np.round(np.asarray(state.robot.pos), 4), axis=0)) == 32


def test_orca_robot_collides_less_than_straight():
    env = make_env(num_humans=20, predictor="none")
    key = jax.random.key(2)
    straight = evaluate(env, StraightPolicy(), key, 64)
    orca = evaluate(env, OrcaPolicy(), key, 64)
    assert straight.collision_rate > 0.3  # 20 invisible-to-nobody humans crossing: a blind robot hits them
    assert orca.collision_rate < straight.collision_rate
    assert orca.itr_future >= 0.0 and straight.itr_future > 0.0
    table = format_table({"straight": straight, "orca": orca})
    assert table.count("\n") == 3 and "| straight | 64 |" in table


def test_batched_evaluation_is_deterministic():
    env = make_env(num_humans=5, predictor="none")
    a = evaluate(env, StraightPolicy(), jax.random.key(3), 20, batch_size=8)
    b = evaluate(env, StraightPolicy(), jax.random.key(3), 20, batch_size=8)
    assert a == b


def test_bad_arguments():
    with pytest.raises(ValueError, match="n_episodes = 0 is out of range; allowed: 1 .. 10,000,000"):
        evaluate(make_env(num_humans=1), StraightPolicy(), jax.random.key(0), 0)
    with pytest.raises(ValueError, match="valid: straight, orca"):
        baseline("dwa")


def test_episodes_run_in_bounded_batches_with_progress(monkeypatch):
    import tgrf_jax.evaluate as ev

    env = make_env(num_humans=2)
    calls = []
    monkeypatch.setattr(ev, "MAX_BATCH", 4)
    batched = evaluate(env, StraightPolicy(), jax.random.key(3), 10, progress=lambda d, n: calls.append((d, n)))
    assert calls == [(4, 10), (8, 10), (10, 10)] and batched.n_episodes == 10
    explicit = evaluate(env, StraightPolicy(), jax.random.key(3), 10, batch_size=4)
    assert batched == explicit
    with pytest.raises(ValueError, match="batch_size = 0 must be >= 1"):
        evaluate(env, StraightPolicy(), jax.random.key(3), 10, batch_size=0)
