"""The learner's formulas against numpy written from their definitions: the clipped PPO loss, the value-target
statistics, the learning-rate schedule, the Social Force step of the humans, and the whole run against its
chunked form."""

import distrax
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import tiny_config

from tgrf_jax.env import social_force
from tgrf_jax.train import Transition, hparams_from_config, make_trainer, ppo_loss
from tgrf_jax.train.ppo import METRIC_NAMES, SUMMED_METRICS, ReturnStats, learning_rate

# ------------------------------------------------------------------------------------------------- PPO loss

EPS, VF_COEF, ENT_COEF = 0.2, 0.5, 0.01

# One minibatch of T = 4 steps x b = 4 envs. The policy ratios straddle [1 - EPS, 1 + EPS] and meet advantages of
# both signs, so each of the four cases of the clipped objective occurs: below the range with A > 0 and above it
# with A < 0 keep the unclipped term, the other two are clipped.
RATIOS = np.array([[0.5, 0.5, 0.79, 0.81], [1.0, 1.0, 1.19, 1.21], [1.5, 1.5, 2.0, 0.3], [0.9, 1.1, 1.3, 0.7]])
ADVANTAGES = np.array([[1.0, -1.0, 2.0, -2.0], [0.5, -0.5, 1.5, 1.5], [1.0, -1.0, -3.0, 0.7], [-0.4, 0.6, 0.9, -1.2]])
# New values move from the rollout's by more than EPS in some entries (the clipped value then counts where it is
# the worse fit) and by less in others.
OLD_VALUES = np.array([[0.0, 1.0, 2.0, -1.0], [0.5, 0.5, -0.5, 3.0], [1.0, 2.0, 0.0, 0.0], [4.0, -2.0, 1.0, 0.3]])
VALUES = OLD_VALUES + np.array(
    [[0.5, -0.5, 0.1, -0.1], [0.25, -0.3, 0.05, 1.0], [-0.8, 0.15, 0.6, -0.19], [0.21, 0.0, -0.4, 0.3]]
)
RETURNS = np.array([[1.0, 0.0, 2.5, -2.0], [0.0, 1.5, -0.5, 5.0], [-1.0, 2.5, 1.0, -0.5], [3.0, -1.0, -0.2, 0.1]])


class FakeNet:
    """Stands in for the actor-critic in `ppo_loss`: its "parameters" are the policy's means and log-stds and the
    critic's values themselves, whatever the observations."""

    @staticmethod
    def apply_sequence(params, carry0, obs, resets):
        pi = distrax.MultivariateNormalDiag(params["mean"], jnp.exp(params["log_std"]))
        return carry0, pi, params["values"]


def _gaussian_log_prob(x, mean, log_std):
    return np.sum(-0.5 * np.square((x - mean) / np.exp(log_std)) - log_std - 0.5 * np.log(2 * np.pi), axis=-1)


def _loss_inputs(values, old_values):
    """Fake-net parameters and a minibatch whose stored log-probs make the policy ratios equal RATIOS."""
    rng = np.random.default_rng(0)
    mean = rng.normal(size=(4, 4, 2))
    log_std = rng.normal(scale=0.3, size=(4, 4, 2))
    action = mean + rng.normal(size=(4, 4, 2)) * np.exp(log_std)
    old_log_prob = _gaussian_log_prob(action, mean, log_std) - np.log(RATIOS)
    f32 = lambda x: jnp.asarray(x, jnp.float32)
    params = {"mean": f32(mean), "log_std": f32(log_std), "values": f32(values)}
    zeros = jnp.zeros((4, 4), jnp.float32)
    batch = Transition(
        obs=zeros,
        resets=zeros.astype(bool),
        action=f32(action),
        log_prob=f32(old_log_prob),
        value=f32(old_values),
        reward=zeros,
        done=zeros.astype(bool),
        truncated=zeros.astype(bool),
        final_value=zeros,
    )
    return params, batch, log_std


@pytest.fixture(scope="module")
def hparams():
    hp = hparams_from_config(tiny_config())
    return hp.replace(clip_eps=jnp.float32(EPS), vf_coef=jnp.float32(VF_COEF), ent_coef=jnp.float32(ENT_COEF))


@pytest.mark.parametrize("clip_value", [False, True])
@pytest.mark.parametrize("norm_value", [False, True])
def test_ppo_loss_matches_the_clipped_objective(hparams, clip_value, norm_value):
    targets = np.linspace(-4.0, 14.0, 16)  # value targets of some earlier batch, far from mean 0 / std 1
    stats = ReturnStats.create().update(jnp.asarray(targets, jnp.float32)) if norm_value else None
    raw_returns, raw_old_values = RETURNS, OLD_VALUES
    if norm_value:
        # After one update the bias-corrected statistics are that batch's mean and (population) std. The critic
        # predicts standardised values, the rollout stored them in reward units, and the loss standardises the
        # stored values and the targets: in reward units they are RETURNS and OLD_VALUES destandardised.
        m, s = targets.mean(), targets.std()
        raw_returns, raw_old_values = RETURNS * s + m, OLD_VALUES * s + m
    params, batch, log_std = _loss_inputs(VALUES, raw_old_values)

    loss, aux = jax.jit(ppo_loss, static_argnums=(0, 7))(
        FakeNet(),
        params,
        None,
        batch,
        jnp.asarray(ADVANTAGES, jnp.float32),
        jnp.asarray(raw_returns, jnp.float32),
        hparams,
        clip_value,
        stats,
    )

    unclipped = RATIOS * ADVANTAGES
    clipped = np.clip(RATIOS, 1 - EPS, 1 + EPS) * ADVANTAGES
    pg = -np.mean(np.minimum(unclipped, clipped))
    assert np.any(clipped < unclipped) and np.any(unclipped < clipped)  # both terms win somewhere
    sq = np.square(VALUES - RETURNS)
    if clip_value:
        v_clipped = OLD_VALUES + np.clip(VALUES - OLD_VALUES, -EPS, EPS)
        sq_clipped = np.square(v_clipped - RETURNS)
        assert np.any(sq_clipped > sq) and np.any(sq_clipped < sq)
        sq = np.maximum(sq, sq_clipped)
    vf = 0.5 * np.mean(sq)
    entropy = np.mean(np.sum(0.5 * np.log(2 * np.pi * np.e) + log_std, axis=-1))
    expected = {
        "pg_loss": pg,
        "vf_loss": vf,
        "entropy": entropy,
        "approx_kl": np.mean(RATIOS - 1 - np.log(RATIOS)),
        "clip_frac": np.mean(np.abs(RATIOS - 1) > EPS),
    }
    for name, value in expected.items():
        np.testing.assert_allclose(float(aux[name]), value, rtol=2e-5, atol=1e-6, err_msg=name)
    np.testing.assert_allclose(float(loss), pg + VF_COEF * vf - ENT_COEF * entropy, rtol=2e-5, atol=1e-6)


# ---------------------------------------------------------------------------------------- value-target statistics


def test_return_stats_are_bias_corrected_moving_moments():
    """After n updates the statistics weigh batch k's moments by decay^(n - 1 - k), normalised to sum 1: the
    closed form of the exponential moving average with bias correction, written here as a weighted mean."""
    decay = 0.99
    rng = np.random.default_rng(1)
    batches = [rng.normal(loc=5.0 + k, scale=2.0 + 0.5 * k, size=64) for k in range(5)]

    stats = ReturnStats.create()
    mean, std = stats.moments()
    assert (float(mean), float(std)) == (0.0, 1.0)  # nothing seen yet: the identity standardisation

    update = jax.jit(ReturnStats.update)
    for n in range(1, len(batches) + 1):
        stats = update(stats, jnp.asarray(batches[n - 1], jnp.float32))
        w = decay ** np.arange(n - 1, -1, -1)
        w = w / w.sum()
        m1 = np.sum(w * [b.mean() for b in batches[:n]])
        m2 = np.sum(w * [np.mean(b**2) for b in batches[:n]])
        expected_std = np.sqrt(m2 - m1**2)
        mean, std = stats.moments()
        np.testing.assert_allclose([float(mean), float(std)], [m1, expected_std], rtol=1e-4)

    x = jnp.asarray([-3.0, 0.0, 7.5, 20.0])
    np.testing.assert_allclose(stats.normalize(x), (np.asarray(x) - m1) / expected_std, rtol=1e-4, atol=1e-5)
    np.testing.assert_allclose(stats.denormalize(x), np.asarray(x) * expected_std + m1, rtol=1e-4)
    np.testing.assert_allclose(stats.denormalize(stats.normalize(x)), x, rtol=1e-5, atol=1e-5)


def test_return_stats_std_has_a_floor():
    """Constant targets have variance 0 (or a rounding error below it): the std is floored at a small positive
    value, so standardising never divides by zero or takes the root of a negative number."""
    stats = ReturnStats.create().update(jnp.full(8, 3.0))
    mean, std = stats.moments()
    assert float(mean) == pytest.approx(3.0) and 0.0 < float(std) <= 0.1
    assert np.all(np.isfinite(np.asarray(stats.normalize(jnp.array([2.0, 4.0])))))


# ------------------------------------------------------------------------------------------ learning-rate schedule


@pytest.mark.parametrize("anneal", [True, False])
def test_learning_rate_schedule(anneal):
    """With ppo.anneal_lr the rate falls linearly from lr at update 0 to 0 at update num_updates, one past the
    last (and stays 0); without it the rate is lr throughout. lr and the update index are traced."""
    ppo = tiny_config(ppo={"anneal_lr": anneal}).ppo
    num_updates, lr = 10, 3e-4
    rates = jax.jit(jax.vmap(lambda u: learning_rate(ppo, jnp.float32(lr), u, num_updates)))(jnp.arange(13))
    expected = lr * np.clip(1.0 - np.arange(13) / num_updates, 0.0, 1.0) if anneal else np.full(13, lr)
    np.testing.assert_allclose(np.asarray(rates), expected, rtol=1e-6, atol=1e-12)


# ---------------------------------------------------------------------------------------------- Social Force


def reference_social_force(pos, vel, goal, radius, v_pref, a, b, ki, dt, visible=None):
    """New velocities by the Social Force rule of CrowdNav++ (`crowd_nav/policy/social_force.py`,
    `SOCIAL_FORCE.predict`), one agent at a time in float64: a relaxation towards the desired velocity
    v_pref * (unit vector to the goal) at rate KI, plus a push A * exp((r_i + r_j - d_ij) / B) away from every
    other agent j along (p_i - p_j) / d_ij; both are accelerations applied over one time step, and the result is
    rescaled to speed v_pref if it is faster."""
    n = len(pos)
    visible = np.ones(n, bool) if visible is None else visible
    out = np.zeros((n, 2))
    for i in range(n):
        to_goal = goal[i] - pos[i]
        desired = to_goal / np.linalg.norm(to_goal) * v_pref[i]
        accel = ki * (desired - vel[i])
        for j in range(n):
            if j == i or not visible[j]:
                continue
            away = pos[i] - pos[j]
            dist = np.linalg.norm(away)
            accel = accel + a * np.exp((radius[i] + radius[j] - dist) / b) * away / dist
        new = vel[i] + accel * dt
        speed = np.linalg.norm(new)
        out[i] = new / speed * v_pref[i] if speed > v_pref[i] else new
    return out


def _scene(seed, n=8):
    rng = np.random.default_rng(seed)
    pos = rng.uniform(-2.5, 2.5, (n, 2))  # a dense crowd: some pairs overlap, some are metres apart
    return dict(
        pos=pos,
        vel=rng.uniform(-1.0, 1.0, (n, 2)),
        goal=rng.uniform(-6.0, 6.0, (n, 2)),
        radius=rng.uniform(0.3, 0.5, n),
        v_pref=rng.uniform(0.5, 1.5, n),
    )


SF_STEP = jax.jit(social_force.step)


@pytest.mark.parametrize("a, b, ki", [(2.0, 1.0, 1.0), (1.5, 0.4, 2.5)])  # the reference's values; others
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_social_force_step_matches_the_reference_rule(seed, a, b, ki):
    s = _scene(seed)
    dt = 0.25
    expected = reference_social_force(s["pos"], s["vel"], s["goal"], s["radius"], s["v_pref"], a, b, ki, dt)
    got = SF_STEP(
        *(jnp.asarray(s[k], jnp.float32) for k in ("pos", "vel", "goal", "radius", "v_pref")), a=a, b=b, ki=ki, dt=dt
    )
    np.testing.assert_allclose(np.asarray(got), expected, rtol=1e-5, atol=1e-5)
    # the scene exercises both sides of the speed cap
    speeds = np.linalg.norm(expected, axis=-1)
    assert np.any(np.isclose(speeds, s["v_pref"])) and np.any(speeds < s["v_pref"] - 1e-3)


def test_social_force_neighbor_mask_hides_agents_from_the_push():
    s = _scene(3)
    visible = np.array([True, False, True, True, False, True, True, True])
    expected = reference_social_force(
        s["pos"], s["vel"], s["goal"], s["radius"], s["v_pref"], 2.0, 1.0, 1.0, 0.25, visible
    )
    got = SF_STEP(
        *(jnp.asarray(s[k], jnp.float32) for k in ("pos", "vel", "goal", "radius", "v_pref")),
        a=2.0,
        b=1.0,
        ki=1.0,
        dt=0.25,
        neighbor_mask=jnp.asarray(visible),
    )
    np.testing.assert_allclose(np.asarray(got), expected, rtol=1e-5, atol=1e-5)


def test_social_force_is_finite_where_the_reference_divides_by_zero():
    """The reference gives NaN for an agent standing on its goal or on another agent; here the first desires zero
    velocity and the coincident pair pushes along no direction, while the others still push as usual."""
    pos = np.array([[0.0, 0.0], [0.0, 0.0], [1.0, 0.0]])
    goal = np.array([[5.0, 0.0], [0.0, 5.0], [1.0, 0.0]])  # agent 2 is on its goal
    vel = np.array([[0.2, 0.0], [0.0, 0.2], [0.1, 0.1]])
    radius, v_pref = np.full(3, 0.3), np.full(3, 1.0)
    got = np.asarray(
        SF_STEP(*(jnp.asarray(x, jnp.float32) for x in (pos, vel, goal, radius, v_pref)), a=2.0, b=1.0, ki=1.0, dt=0.25)
    )
    assert np.all(np.isfinite(got))
    # agent 2: no pull, pushed away (+x) by agents 0 and 1 at distance 1
    push = 2 * 2.0 * np.exp(0.6 - 1.0) * np.array([1.0, 0.0])
    np.testing.assert_allclose(got[2], vel[2] + (-vel[2] + push) * 0.25, rtol=1e-5)


# ---------------------------------------------------------------------------------------------- whole run


def test_train_equals_one_chunk_of_all_its_updates():
    """`Trainer.train(key, hparams)` (init, then every update in a lax.scan) against init + `run_chunk` of all
    updates (a fori_loop with a traced count): per-update metrics of shape (num_updates,), and the same final state.

    The two are different XLA programs around the same update. On XLA:CPU, the suite's platform, they agree bit
    for bit (checked at both of the suite's XLA optimisation levels); elsewhere the comparison allows float32
    rounding (rtol 1e-5), as a different compiler may order the loop bodies' arithmetic differently."""
    t = make_trainer(tiny_config(ppo={"anneal_lr": True}))
    key, hp, n = jax.random.PRNGKey(5), t.default_hparams, t.num_updates
    final, per_update = jax.jit(t.train)(key, hp)
    assert set(per_update) == set(METRIC_NAMES)
    for name, v in per_update.items():
        assert v.shape == (n,), name
    np.testing.assert_allclose(per_update["lr"], float(hp.lr) * (1 - np.arange(n) / n), rtol=1e-6)

    chunked, chunk_metrics = t.jit_run_chunk(t.jit_init(key, hp), n)
    exact = jax.default_backend() == "cpu"
    assert int(final.update) == int(chunked.update) == n
    for a, b in zip(jax.tree_util.tree_leaves(final), jax.tree_util.tree_leaves(chunked)):
        a, b = np.asarray(a), np.asarray(b)
        if exact or a.dtype.kind != "f":
            np.testing.assert_array_equal(a, b)
        else:
            np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-7)
    initial = t.jit_init(key, hp).params
    moved = max(
        float(jnp.abs(x - y).max())
        for x, y in zip(jax.tree_util.tree_leaves(final.params), jax.tree_util.tree_leaves(initial))
    )
    assert moved > 1e-4  # training moved the parameters, so the comparison means something
    for name in METRIC_NAMES:  # a chunk reports sums of episode counts and means of the rest
        reduce = np.sum if name in SUMMED_METRICS else np.mean
        np.testing.assert_allclose(
            float(chunk_metrics[name]), reduce(np.asarray(per_update[name])), rtol=1e-6, atol=1e-7, err_msg=name
        )
