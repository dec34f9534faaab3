import math

import jax
import numpy as np
import pytest
from helpers import make_env

from tgrf_jax.evaluate import evaluate, format_table
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


# Compiling an episode loop costs far more than running it, so the tests below share one env and one batch shape
# (evaluate() compiles one program per env, policy and batch size, kept for the whole module).
ENV = make_env(num_humans=10, predictor="none")
BATCH = 16


def test_episodes_are_distinct_and_rates_sum_to_one():
    import tgrf_jax.evaluate as ev

    params = ENV.default_params
    key = jax.random.key(1)
    # Batch 0 of evaluate() is run_episodes with fold_in(key, 0): the same program and episodes.
    stats = ev._run_episodes_jit(ENV, StraightPolicy(), jax.random.fold_in(key, 0), BATCH, params)
    outcome = np.asarray(stats.outcome)
    assert np.all(np.isin(outcome, [1, 2, 3]))
    result = evaluate(ENV, StraightPolicy(), key, BATCH)
    assert result.success_rate == pytest.approx(np.mean(outcome == 1))
    assert result.success_rate + result.collision_rate + result.timeout_rate == pytest.approx(1.0)
    # Different episodes start from different scenarios.
    k_reset, _ = jax.random.split(jax.random.fold_in(key, 0))
    _, state = jax.jit(jax.vmap(ENV.reset, in_axes=(0, None)))(jax.random.split(k_reset, BATCH), params)
    assert len(np.unique(np.round(np.asarray(state.robot.pos), 4), axis=0)) == BATCH


def test_orca_robot_collides_less_than_straight():
    key = jax.random.key(2)
    straight = evaluate(ENV, StraightPolicy(), key, 4 * BATCH, batch_size=BATCH)
    orca = evaluate(ENV, OrcaPolicy(), key, 4 * BATCH, batch_size=BATCH)
    assert straight.collision_rate > 0.3  # humans crossing a blind robot's path: it hits them
    assert orca.collision_rate < straight.collision_rate
    assert orca.itr_future >= 0.0 and straight.itr_future > 0.0
    table = format_table({"straight": straight, "orca": orca})
    assert table.count("\n") == 3 and f"| straight | {4 * BATCH} |" in table


def test_batched_evaluation_is_deterministic():
    a = evaluate(ENV, StraightPolicy(), jax.random.key(3), 2 * BATCH, batch_size=BATCH)
    b = evaluate(ENV, StraightPolicy(), jax.random.key(3), 2 * BATCH, batch_size=BATCH)
    assert a == b
    assert a != evaluate(ENV, StraightPolicy(), jax.random.key(4), 2 * BATCH, batch_size=BATCH)


def test_bad_arguments():
    with pytest.raises(ValueError, match="n_episodes = 0 is out of range; allowed: 1 .. 10,000,000"):
        evaluate(make_env(num_humans=1), StraightPolicy(), jax.random.key(0), 0)
    with pytest.raises(ValueError, match="valid: straight, orca"):
        baseline("dwa")


def test_episodes_run_in_bounded_batches_with_progress(monkeypatch):
    import tgrf_jax.evaluate as ev

    calls = []
    monkeypatch.setattr(ev, "MAX_BATCH", BATCH)
    batched = evaluate(ENV, StraightPolicy(), jax.random.key(3), 3 * BATCH, progress=lambda d, n: calls.append((d, n)))
    assert calls == [(BATCH, 3 * BATCH), (2 * BATCH, 3 * BATCH), (3 * BATCH, 3 * BATCH)]
    assert batched.n_episodes == 3 * BATCH
    explicit = evaluate(ENV, StraightPolicy(), jax.random.key(3), 3 * BATCH, batch_size=BATCH)
    assert batched == explicit
    with pytest.raises(ValueError, match="batch_size = 0 must be >= 1"):
        evaluate(ENV, StraightPolicy(), jax.random.key(3), 10, batch_size=0)
