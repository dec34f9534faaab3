"""Reward functions: the transformable Gaussian reward function (TGRF) and the reward schemes built on it.

Everything here is pure `jnp` and differentiable in the reward parameters, so the same code serves the
environment, `jax.grad` sensitivity studies in notebooks, and `jax.vmap` over reward grids.

Every scheme is a value of one `RewardParams` pytree: the shape of r_disc is a numeric blend of a Gaussian
(TGRF) term and a linear (CrowdNav++) term, so gridding over schemes or over h/sigma is a plain vmap.
"""

from __future__ import annotations

import jax.numpy as jnp
from flax import struct

SCHEMES = ("tgrf", "crowdnav_pp", "dsrnn", "tgrf_circle")


def tgrf(x, h, sigma, mu=0.0):
    """TGRF(x; h, sigma, mu) = h * N(x; mu, sigma^2) / max N  (eq. 1 of Kim et al. 2024).

    Dividing by the peak density leaves h * exp(-(x - mu)^2 / (2 sigma^2)): h is the peak value whatever
    sigma is, and sigma alone sets the width (sigma -> inf: constant h; sigma -> 0: an impulse at mu).
    """
    x, h, sigma, mu = (jnp.asarray(v, jnp.float32) for v in (x, h, sigma, mu))
    return h * jnp.exp(-jnp.square(x - mu) / (2.0 * jnp.square(sigma)))


@struct.dataclass
class RewardParams:
    """Numeric reward parameters (all traced; vmap over any of them).

    r_disc(d) = -tgrf(d, h_disc, sigma_disc) + disc_slope * (d - d_disc)   for d < d_disc
    r_pot     = tgrf(0, pot_factor * delta_d, sigma_pot) = pot_factor * delta_d
    r_pred    = min_{i,k} 1[robot within pred_radius of human i's prediction at t+k] * pred_penalty / 2^(k + pred_c)
    """

    r_goal: jnp.ndarray
    r_col: jnp.ndarray
    d_disc: jnp.ndarray
    h_disc: jnp.ndarray
    sigma_disc: jnp.ndarray
    disc_slope: jnp.ndarray
    pot_factor: jnp.ndarray
    sigma_pot: jnp.ndarray
    pred_penalty: jnp.ndarray
    pred_c: jnp.ndarray
    pred_radius: jnp.ndarray
    spin_coef: jnp.ndarray
    back_coef: jnp.ndarray


# Scheme defaults. `tgrf` is the paper's eq. 5 as the authors' code runs it (h_disc is the absolute peak:
# 0.25 x |r_col| = 2.5); `crowdnav_pp` is the CrowdNav++ reward (the paper's "without TGRF" baseline);
# `dsrnn` is CrowdNav++ without the prediction term; `tgrf_circle` is what the TGRF authors' code runs with its
# Gaussian turned off (danger_zone_type 'circle'): CrowdNav++'s linear r_disc, but with TGRF's r_col -10,
# d_disc 0.5 and 1.5 x progress. The paper does not say which of the two its "without TGRF" rows used.
# The reference's reward parameters (paper Secs. 3.2-3.3; docs/reference.md).
SCHEME_DEFAULTS: dict[str, dict[str, float]] = {
    "tgrf": dict(
        r_goal=10.0,
        r_col=-10.0,
        d_disc=0.5,
        h_disc=2.5,
        sigma_disc=0.2,
        disc_slope=0.0,
        pot_factor=1.5,
        sigma_pot=1000.0,
        pred_penalty=-10.0,
        pred_c=1.0,
        pred_radius=0.6,
        spin_coef=4.5,
        back_coef=2.0,
    ),
    "crowdnav_pp": dict(
        r_goal=10.0,
        r_col=-20.0,
        d_disc=0.25,
        h_disc=0.0,
        sigma_disc=0.2,
        disc_slope=2.5,
        pot_factor=2.0,
        sigma_pot=1000.0,
        pred_penalty=-20.0,
        pred_c=1.0,
        pred_radius=0.6,
        spin_coef=4.5,
        back_coef=2.0,
    ),
    "dsrnn": dict(
        r_goal=10.0,
        r_col=-20.0,
        d_disc=0.25,
        h_disc=0.0,
        sigma_disc=0.2,
        disc_slope=2.5,
        pot_factor=2.0,
        sigma_pot=1000.0,
        pred_penalty=0.0,
        pred_c=1.0,
        pred_radius=0.6,
        spin_coef=4.5,
        back_coef=2.0,
    ),
    "tgrf_circle": dict(
        r_goal=10.0,
        r_col=-10.0,
        d_disc=0.5,
        h_disc=0.0,
        sigma_disc=0.2,
        disc_slope=2.5,
        pot_factor=1.5,
        sigma_pot=1000.0,
        pred_penalty=-10.0,
        pred_c=1.0,
        pred_radius=0.6,
        spin_coef=4.5,
        back_coef=2.0,
    ),
}


def reward_params(scheme: str = "tgrf", **overrides) -> RewardParams:
    """RewardParams of a named scheme, with optional per-field overrides."""
    if scheme not in SCHEME_DEFAULTS:
        raise ValueError(f"reward.scheme = {scheme!r} is unknown; valid schemes: {', '.join(SCHEMES)}")
    values = dict(SCHEME_DEFAULTS[scheme])
    unknown = set(overrides) - set(values)
    if unknown:
        raise ValueError(f"unknown reward field(s) {sorted(unknown)}; valid fields: {', '.join(values)}")
    values.update(overrides)
    return RewardParams(**{k: jnp.asarray(v, jnp.float32) for k, v in values.items()})


@struct.dataclass
class RewardTerms:
    """The reward of one step split into its terms (they sum to `total`)."""

    goal: jnp.ndarray
    collision: jnp.ndarray
    disc: jnp.ndarray
    pot: jnp.ndarray
    pred: jnp.ndarray
    kinematic: jnp.ndarray

    @property
    def total(self):
        return self.goal + self.collision + self.disc + self.pot + self.pred + self.kinematic


def disc_reward(dmin, p: RewardParams):
    """Danger-zone penalty at nearest edge-to-edge distance `dmin` (applies only where dmin < d_disc)."""
    return -tgrf(dmin, p.h_disc, p.sigma_disc) + p.disc_slope * (dmin - p.d_disc)


def pot_reward(delta_d, p: RewardParams):
    """Progress reward for reducing the goal distance by `delta_d` (eq. 3; constant-shaped TGRF)."""
    return tgrf(0.0, p.pot_factor * delta_d, p.sigma_pot)


def pred_reward(pred_hits, p: RewardParams):
    """Prediction penalty (eq. 4) from `pred_hits` (..., n_humans, K): robot inside human i's prediction at t+k."""
    k = jnp.arange(1, pred_hits.shape[-1] + 1, dtype=jnp.float32)
    per_step = p.pred_penalty / jnp.power(2.0, k + p.pred_c)
    penalties = jnp.where(pred_hits, per_step, 0.0)
    return jnp.min(penalties, axis=(-2, -1), initial=0.0)


def step_reward(
    p: RewardParams, *, collided, reached, dmin, delta_d, pred_hits, delta_heading=0.0, speed=0.0
) -> RewardTerms:
    """Reward of one step, evaluated on the post-step state (as the reference does).

    Collision beats reaching the goal; inside d_disc the danger penalty replaces the progress reward.
    r_pred is added on every step, terminal ones included, as the reference code does.
    `delta_heading` and `speed` feed the unicycle penalties (zero for holonomic robots).
    """
    collided = jnp.asarray(collided)
    reached = jnp.asarray(reached) & ~collided
    running = ~(collided | reached)
    in_danger = dmin < p.d_disc
    zero = jnp.zeros((), jnp.float32)
    kinematic = -p.spin_coef * jnp.square(delta_heading) - p.back_coef * jnp.abs(jnp.minimum(speed, 0.0))
    return RewardTerms(
        goal=jnp.where(reached, p.r_goal, zero),
        collision=jnp.where(collided, p.r_col, zero),
        disc=jnp.where(running & in_danger, disc_reward(dmin, p), zero),
        pot=jnp.where(running & ~in_danger, pot_reward(delta_d, p), zero),
        pred=pred_reward(pred_hits, p),
        kinematic=jnp.where(running, kinematic, zero),
    )
