"""cond_gathered (a conditional that stays one under vmap) and the counting sort used by the observation."""

import jax
import jax.numpy as jnp
import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from tgrf_jax.env import scenarios
from tgrf_jax.env.batching import cond_gathered
from tgrf_jax.env.sensing import sort_order


def _bump(x, y):
    return {"x": x * 2.0 + y, "n": jnp.int32(1)}


def _keep(x, y):
    return {"x": x, "n": jnp.int32(0)}


def test_cond_gathered_equals_lax_cond_unbatched_and_batched():
    x = jnp.arange(6.0)
    y = jnp.float32(0.5)
    for pred in (True, False):
        got = cond_gathered(jnp.asarray(pred), _bump, _keep, x, y)
        want = jax.lax.cond(pred, _bump, _keep, x, y)
        for a, b in zip(jax.tree_util.tree_leaves(got), jax.tree_util.tree_leaves(want)):
            np.testing.assert_array_equal(a, b)

    xs = jnp.arange(12.0).reshape(4, 3)
    ys = jnp.asarray([0.0, 1.0, 2.0, 3.0])
    for preds in ([True, False, True, False], [False] * 4, [True] * 4):
        preds = jnp.asarray(preds)
        got = jax.jit(jax.vmap(lambda p, a, b: cond_gathered(p, _bump, _keep, a, b)))(preds, xs, ys)
        want = jax.vmap(lambda p, a, b: jax.lax.cond(p, _bump, _keep, a, b))(preds, xs, ys)
        np.testing.assert_array_equal(got["x"], want["x"])
        np.testing.assert_array_equal(got["n"], want["n"])
    # an unbatched operand and a nested vmap (the outer level falls back to a select)
    got = jax.vmap(jax.vmap(lambda p, a: cond_gathered(p, _bump, _keep, a, y)))(
        jnp.asarray([[True, False], [False, False]]), jnp.ones((2, 2, 3))
    )
    np.testing.assert_array_equal(got["n"], [[1, 0], [0, 0]])
    np.testing.assert_array_equal(got["x"][0, 0], np.full(3, 2.5))
    np.testing.assert_array_equal(got["x"][1, 1], np.ones(3))


def test_cond_gathered_runs_the_true_branch_only_for_the_elements_that_need_it():
    rows_seen = []

    def true_fn(x):
        jax.debug.callback(lambda x: rows_seen.append(np.asarray(x).copy()), x)
        return x + 1.0

    f = jax.jit(jax.vmap(lambda p, x: cond_gathered(p, true_fn, lambda x: x, x, chunk=2)))
    xs = jnp.arange(8.0)
    jax.block_until_ready(f(jnp.zeros(8, bool), xs))
    assert rows_seen == []  # nothing due: the true branch never runs
    pred = jnp.isin(jnp.arange(8), jnp.asarray([1, 4, 6]))
    out = f(pred, xs)
    jax.block_until_ready(out)
    np.testing.assert_array_equal(out, np.where(pred, xs + 1.0, xs))
    # (the callback runs once per element) three elements in chunks of two: two chunks, the second padded
    # with the last row, whose result is dropped; the other elements never reach the true branch
    assert sorted(float(r) for r in rows_seen) == [1.0, 4.0, 6.0, 7.0]


def test_goal_changes_only_when_due():
    from helpers import make_env

    env = make_env(num_humans=6)
    params = env.default_params
    _, state = env.reset(jax.random.key(0), params)
    period = int(params.goal_change_period)
    steps = jnp.asarray([period - 1, period, 2 * period, 2 * period + 1])
    keys = jax.random.split(jax.random.key(1), 4)
    change = jax.vmap(lambda k, s: scenarios.change_goals(k, state.humans, state.robot, params, s, 4))
    goals = np.asarray(change(keys, steps).goal)
    old = np.asarray(state.humans.goal)
    assert np.array_equal(goals[0], old) and np.array_equal(goals[3], old)
    assert not np.array_equal(goals[1], old) and not np.array_equal(goals[2], old)  # prob 0.5 x 6 humans


@settings(max_examples=50, deadline=None)
@given(st.lists(st.sampled_from([0.0, 1.0, 2.5, 2.5, 3.0, float("inf")]), min_size=1, max_size=24))
def test_sort_order_equals_stable_argsort(values):
    keys = jnp.asarray(values, jnp.float32)
    np.testing.assert_array_equal(sort_order(keys), jnp.argsort(keys, stable=True))
