import jax
import jax.numpy as jnp
import numpy as np
import pytest

from tgrf_jax import reward as R


@pytest.mark.parametrize(
    "dmin, expected",
    [(0.0, -2.500), (0.1, -2.206), (0.2, -1.516), (0.3, -0.812), (0.4, -0.338), (0.4999, -0.110)],
)
def test_tgrf_disc_values_match_reference(dmin, expected):
    # r_disc = -2.5 exp(-d^2 / (2 * 0.2^2)) in the TGRF scheme (paper §3.3, eq. 2; docs/reference.md, Rewards).
    p = R.reward_params("tgrf")
    assert float(R.disc_reward(jnp.float32(dmin), p)) == pytest.approx(expected, abs=1e-3)


def test_tgrf_peak_is_h_for_any_sigma_and_limits():
    for sigma in (0.01, 0.2, 5.0, 5000.0):
        assert float(R.tgrf(0.0, 2.0, sigma)) == pytest.approx(2.0)
    # sigma -> inf: constant; sigma -> 0: impulse.
    assert float(R.tgrf(3.0, 1.0, 5000.0)) == pytest.approx(1.0, abs=1e-6)
    assert float(R.tgrf(0.05, 1.0, 1e-3)) == pytest.approx(0.0, abs=1e-6)
    assert float(R.tgrf(1.0, 1.0, 1.0, mu=1.0)) == pytest.approx(1.0)


def test_crowdnav_pp_linear_disc_and_potential():
    p = R.reward_params("crowdnav_pp")
    # (dmin - 0.25) * 10 * 0.25
    assert float(R.disc_reward(jnp.float32(0.1), p)) == pytest.approx(-0.375, abs=1e-6)
    assert float(R.pot_reward(0.25, p)) == pytest.approx(0.5)
    assert float(R.pot_reward(0.25, R.reward_params("tgrf"))) == pytest.approx(0.375)


def test_tgrf_circle_is_the_tgrf_code_with_its_gaussian_off():
    # r_disc = 10 * (dmin - 0.5) * dt with d_disc 0.5, r_col -10 and 1.5 x progress (the TGRF code with its
    # Gaussian off: docs/reference.md, Rewards)
    p = R.reward_params("tgrf_circle")
    assert float(R.disc_reward(jnp.float32(0.1), p)) == pytest.approx(-1.0, abs=1e-6)
    assert float(R.pot_reward(0.25, p)) == pytest.approx(0.375)
    terms = R.step_reward(p, collided=True, reached=False, dmin=-0.1, delta_d=0.0, pred_hits=jnp.zeros((1, 5), bool))
    assert float(terms.total) == pytest.approx(-10.0)


@pytest.mark.parametrize(
    "scheme, k, expected",
    [("tgrf", 1, -2.5), ("tgrf", 5, -0.15625), ("crowdnav_pp", 1, -5.0), ("dsrnn", 1, 0.0), ("tgrf_circle", 1, -2.5)],
)
def test_pred_reward_per_step(scheme, k, expected):
    hits = jnp.zeros((3, 5), bool).at[1, k - 1].set(True)
    assert float(R.pred_reward(hits, R.reward_params(scheme))) == pytest.approx(expected)


def test_pred_reward_takes_the_worst_hit_and_paper_offset():
    hits = jnp.zeros((2, 5), bool).at[0, 3].set(True).at[1, 1].set(True)
    assert float(R.pred_reward(hits, R.reward_params("tgrf"))) == pytest.approx(-10 / 2**3)
    # The paper prints 2^k (c = 0): twice the code's penalty.
    assert float(R.pred_reward(hits, R.reward_params("tgrf", pred_c=0.0))) == pytest.approx(-10 / 2**2)
    assert float(R.pred_reward(jnp.zeros((0, 5), bool), R.reward_params("tgrf"))) == 0.0


def test_gradients_match_finite_differences():
    x = jnp.float32(0.27)

    def f(h, sigma):
        return R.tgrf(x, h, sigma)

    h0, s0 = 2.5, 0.2
    gh, gs = jax.grad(f, argnums=(0, 1))(h0, s0)
    eps = 1e-3
    fd_h = (f(h0 + eps, s0) - f(h0 - eps, s0)) / (2 * eps)
    fd_s = (f(h0, s0 + eps) - f(h0, s0 - eps)) / (2 * eps)
    np.testing.assert_allclose(gh, fd_h, rtol=2e-3)
    np.testing.assert_allclose(gs, fd_s, rtol=2e-3)
    # Analytic check too: d/dh = exp(.), d/dsigma = h exp(.) x^2 / sigma^3
    e = np.exp(-(0.27**2) / (2 * 0.2**2))
    np.testing.assert_allclose(gh, e, rtol=1e-5)
    np.testing.assert_allclose(gs, 2.5 * e * 0.27**2 / 0.2**3, rtol=1e-5)


def test_grad_of_step_reward_wrt_reward_params():
    p = R.reward_params("tgrf")

    def total(p):
        return R.step_reward(
            p,
            collided=False,
            reached=False,
            dmin=jnp.float32(0.2),
            delta_d=jnp.float32(0.1),
            pred_hits=jnp.zeros((2, 5), bool),
        ).total

    g = jax.grad(total)(p)
    assert float(g.h_disc) == pytest.approx(-np.exp(-0.5), rel=1e-5)
    assert float(g.pot_factor) == 0.0  # inside the danger zone r_pot does not apply
    assert all(np.isfinite(np.asarray(v)) for v in jax.tree_util.tree_leaves(g))


def test_vmap_over_schemes_equals_individual():
    schemes = R.SCHEMES
    stacked = jax.tree_util.tree_map(lambda *xs: jnp.stack(xs), *[R.reward_params(s) for s in schemes])
    d = jnp.float32(0.15)
    batched = jax.vmap(lambda p: R.disc_reward(d, p))(stacked)
    for i, s in enumerate(schemes):
        assert float(batched[i]) == pytest.approx(float(R.disc_reward(d, R.reward_params(s))))


def test_step_reward_priorities():
    p = R.reward_params("tgrf")
    hits = jnp.zeros((1, 5), bool)
    both = R.step_reward(p, collided=True, reached=True, dmin=jnp.float32(-0.1), delta_d=0.2, pred_hits=hits)
    assert float(both.total) == -10.0 and float(both.goal) == 0.0
    goal = R.step_reward(p, collided=False, reached=True, dmin=jnp.float32(3.0), delta_d=0.2, pred_hits=hits)
    assert float(goal.total) == 10.0
    danger = R.step_reward(p, collided=False, reached=False, dmin=jnp.float32(0.2), delta_d=0.2, pred_hits=hits)
    assert float(danger.pot) == 0.0 and float(danger.disc) == pytest.approx(-1.516, abs=1e-3)
    free = R.step_reward(p, collided=False, reached=False, dmin=jnp.float32(0.6), delta_d=0.2, pred_hits=hits)
    assert float(free.total) == pytest.approx(0.3)


def test_unknown_scheme_and_field_are_rejected():
    with pytest.raises(ValueError, match="valid schemes: tgrf, crowdnav_pp, dsrnn, tgrf_circle"):
        R.reward_params("scan")
    with pytest.raises(ValueError, match="h_dsic"):
        R.reward_params("tgrf", h_dsic=1.0)


def test_the_reward_fields_are_declared_once():
    """RewardParams' fields carry their scheme values, ranges and docs; the scheme table and the config section's
    overrides follow from them (the fields in the same order, the same ranges)."""
    import dataclasses

    from tgrf_jax.config import RewardConfig, griddable_fields

    declared = dataclasses.fields(R.RewardParams)
    names = [f.name for f in declared]
    assert set(R.SCHEME_DEFAULTS) == set(R.SCHEMES)
    assert all(list(values) == names for values in R.SCHEME_DEFAULTS.values())
    overrides = [f for f in dataclasses.fields(RewardConfig) if f.name != "scheme"]
    assert [f.name for f in overrides] == names
    for param, override in zip(declared, overrides):
        assert override.default is None and override.metadata["traced"]
        for key in ("low", "high", "low_inclusive", "high_inclusive", "doc"):
            assert override.metadata[key] == param.metadata[key], (param.name, key)
    assert [n for n in griddable_fields() if n.startswith("reward.")] == ["reward.scheme"] + [
        f"reward.{n}" for n in names
    ]
    # the schemes' values, as the paper and the reference code set them (docs/reference.md, "Rewards")
    assert R.SCHEME_DEFAULTS["tgrf"]["h_disc"] == 2.5 and R.SCHEME_DEFAULTS["crowdnav_pp"]["r_col"] == -20.0
    assert R.SCHEME_DEFAULTS["dsrnn"]["pred_penalty"] == 0.0 and R.SCHEME_DEFAULTS["tgrf_circle"]["d_disc"] == 0.5
