"""The field's metrics (docs/metrics.md), computed inside the compiled evaluation."""

import math

import jax
import jax.numpy as jnp
import pytest
from helpers import make_env

from tgrf_jax.evaluate import EXTRA_METRIC_LABELS, evaluate, format_table, time_to_collision
from tgrf_jax.policies import StraightPolicy


def test_straight_line_without_humans():
    """Straight to the goal at v_max: SPL 1, one start-up acceleration, no turning, never stalled."""
    env = make_env(num_humans=0, predictor="none")
    r = evaluate(env, StraightPolicy(), jax.random.key(0), 32)
    assert r.success_rate == 1.0 and r.spl == pytest.approx(1.0)
    assert r.speed_max == pytest.approx(1.0, abs=1e-5) and 0.9 < r.speed_mean <= 1.0
    assert r.path_irregularity == pytest.approx(0.0, abs=1e-2) and r.time_stalled == 0.0
    # 0 -> 1 m/s in the first 0.25 s step (4 m/s^2), then constant speed; the last step may slow down to land on
    # the goal. Averaged over the ~40 steps of an episode.
    assert 0.05 < r.accel_mean < 0.25 and r.jerk_mean > r.accel_mean
    assert math.isnan(r.min_dist_human) and math.isnan(r.min_ttc) and r.personal_space_compliance == 100.0
    assert r.mean_humans == 0.0 and r.collision_human_rate == 0.0


def test_metrics_with_humans_are_consistent():
    env = make_env(num_humans=10, predictor="none", active_humans_min=5, active_humans_max=10)
    r = evaluate(env, StraightPolicy(), jax.random.key(1), 32)
    assert 5.0 <= r.mean_humans <= 10.0
    assert r.collision_human_rate == r.collision_rate > 0  # the straight robot hits people
    assert 0.0 <= r.spl <= r.success_rate
    assert r.min_dist_human < 0.45 and 0 <= r.personal_space_compliance < 100
    assert 0.0 <= r.min_ttc < 10.0
    d = r.to_dict()
    for field, _, _ in EXTRA_METRIC_LABELS:
        assert field in d
    table = format_table({"straight": r}, all_metrics=True)
    assert "SPL" in table and "min TTC (s)" in table and "SPL" not in format_table({"straight": r})


def test_time_to_collision():
    robot_pos = jnp.zeros((1, 2))
    robot_vel = jnp.array([[1.0, 0.0]])
    human_pos = jnp.array([[[5.0, 0.0], [0.0, 3.0], [0.5, 0.0], [-5.0, 0.0]]])
    human_vel = jnp.zeros((1, 4, 2))
    radius = jnp.full((1, 4), 0.5)

    def ttc(active):
        return float(
            time_to_collision(robot_pos, robot_vel, 0.5, human_pos, human_vel, radius, jnp.asarray([active]))[0]
        )

    assert ttc([True, False, False, False]) == pytest.approx(4.0)  # gap 5 - 1 closed at 1 m/s
    assert ttc([False, True, False, True]) == math.inf  # beside and behind: never
    assert ttc([True, True, True, True]) == 0.0  # already touching
    assert ttc([False, False, False, False]) == math.inf
