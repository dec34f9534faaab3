"""Reward functions: the transformable Gaussian reward function (TGRF) and the reward schemes built on it.

Everything here is pure `jnp` and differentiable in the reward parameters, so the same code serves the
environment, `jax.grad` sensitivity studies in notebooks, and `jax.vmap` over reward grids.

Every scheme is a value of one `RewardParams` pytree: the shape of r_disc is a numeric blend of a Gaussian
(TGRF) term and a linear (CrowdNav++) term, so gridding over schemes or over h/sigma is a plain vmap.
"""

from __future__ import annotations

import dataclasses

import jax.numpy as jnp
from flax import struct


def tgrf(x, h, sigma, mu=0.0):
    """TGRF(x; h, sigma, mu) = h * N(x; mu, sigma^2) / max N  (eq. 1 of Kim et al. 2024).

    Dividing by the peak density leaves h * exp(-(x - mu)^2 / (2 sigma^2)): h is the peak value whatever
    sigma is, and sigma alone sets the width (sigma -> inf: constant h; sigma -> 0: an impulse at mu).
    """
    x, h, sigma, mu = (jnp.asarray(v, jnp.float32) for v in (x, h, sigma, mu))
    return h * jnp.exp(-jnp.square(x - mu) / (2.0 * jnp.square(sigma)))


# The schemes, each a set of values of the fields below. `tgrf` is the paper's eq. 5 as the authors' code runs it
# (h_disc is the absolute peak: 0.25 x |r_col| = 2.5); `crowdnav_pp` is the CrowdNav++ reward (the paper's "without
# TGRF" baseline); `dsrnn` is CrowdNav++ without the prediction term; `tgrf_circle` is what the TGRF authors' code
# runs with its Gaussian turned off (danger_zone_type 'circle'): CrowdNav++'s linear r_disc, but with TGRF's r_col
# -10, d_disc 0.5 and 1.5 x progress. The paper does not say which of the two its "without TGRF" rows used.
# The reference's reward parameters (paper Secs. 3.2-3.3; docs/reference.md).
SCHEMES = ("tgrf", "crowdnav_pp", "dsrnn", "tgrf_circle")


def reward_field(tgrf, crowdnav_pp, dsrnn, tgrf_circle, *, doc, low=None, high=None, low_inclusive=True):
    """A field of `RewardParams`, declared once: its value under each scheme (in `SCHEMES`' order), its allowed
    range and its meaning. `config.RewardConfig` derives its per-field override (range and doc) from this."""
    defaults = dict(zip(SCHEMES, (tgrf, crowdnav_pp, dsrnn, tgrf_circle)))
    allowed = dict(low=low, high=high, low_inclusive=low_inclusive, high_inclusive=True)
    return struct.field(pytree_node=True, metadata=dict(scheme_defaults=defaults, doc=doc, **allowed))


@struct.dataclass
class RewardParams:
    """Numeric reward parameters (all traced; vmap over any of them).

    r_disc(d) = -tgrf(d, h_disc, sigma_disc) + disc_slope * (d - d_disc)   for d < d_disc
    r_pot     = tgrf(0, pot_factor * delta_d, sigma_pot) = pot_factor * delta_d
    r_pred    = min_{i,k} 1[robot within pred_radius of human i's prediction at t+k] * pred_penalty / 2^(k + pred_c)
    r_wall(d) = -tgrf(d, h_wall, sigma_wall)                                for d < d_wall (d: edge distance to
                                                                            the nearest static obstacle)

    Each field is declared once, here: `reward_field(tgrf, crowdnav_pp, dsrnn, tgrf_circle, ...)` gives its value
    in each scheme, its allowed range and its doc.
    """

    # fmt: off
    #                        value in the scheme:  tgrf  crowdnav_pp    dsrnn  tgrf_circle   allowed
    r_goal:       jnp.ndarray = reward_field(   10.0,        10.0,    10.0,         10.0,  low=0.0,
        doc="reward for reaching the goal")
    r_col:        jnp.ndarray = reward_field(  -10.0,       -20.0,   -20.0,        -10.0,  high=0.0,
        doc="reward (penalty) for a collision")
    d_disc:       jnp.ndarray = reward_field(    0.5,        0.25,    0.25,          0.5,  low=0.0,
        doc="danger-zone radius, edge-to-edge metres")
    h_disc:       jnp.ndarray = reward_field(    2.5,         0.0,     0.0,          0.0,  low=0.0,
        doc="TGRF peak of the danger penalty (absolute)")
    sigma_disc:   jnp.ndarray = reward_field(    0.2,         0.2,     0.2,          0.2,  low=0.0, low_inclusive=False,
        doc="TGRF width of the danger penalty")
    disc_slope:   jnp.ndarray = reward_field(    0.0,         2.5,     2.5,          2.5,  low=0.0,
        doc="linear danger penalty slope (CrowdNav++: 2.5)")
    pot_factor:   jnp.ndarray = reward_field(    1.5,         2.0,     2.0,          1.5,  low=0.0,
        doc="progress reward per metre towards the goal")
    sigma_pot:    jnp.ndarray = reward_field( 1000.0,      1000.0,  1000.0,       1000.0,  low=0.0, low_inclusive=False,
        doc="TGRF width of r_pot")
    pred_penalty: jnp.ndarray = reward_field(  -10.0,       -20.0,     0.0,        -10.0,  high=0.0,
        doc="r_col used by r_pred (0 disables r_pred)")
    pred_c:       jnp.ndarray = reward_field(    1.0,         1.0,     1.0,          1.0,  low=0.0,
        doc="r_pred exponent offset: penalty / 2^(k + c)")
    pred_radius:  jnp.ndarray = reward_field(    0.6,         0.6,     0.6,          0.6,  low=0.0,
        doc="centre distance counted as inside a prediction")
    spin_coef:    jnp.ndarray = reward_field(    4.5,         4.5,     4.5,          4.5,  low=0.0,
        doc="unicycle: penalty per rad^2 of heading change")
    back_coef:    jnp.ndarray = reward_field(    2.0,         2.0,     2.0,          2.0,  low=0.0,
        doc="unicycle: penalty per m/s of backwards speed")
    h_wall:       jnp.ndarray = reward_field(    0.0,         0.0,     0.0,          0.0,  low=0.0,
        doc="TGRF peak of the wall penalty (0: no wall term)")
    sigma_wall:   jnp.ndarray = reward_field(    0.2,         0.2,     0.2,          0.2,  low=0.0, low_inclusive=False,
        doc="TGRF width of the wall penalty")
    d_wall:       jnp.ndarray = reward_field(    0.5,         0.5,     0.5,          0.5,  low=0.0,
        doc="wall zone: the robot's edge distance to an obstacle below which the wall penalty applies")
    # fmt: on


# Derived from the declarations above: {scheme: {field: value}}.
SCHEME_DEFAULTS: dict[str, dict[str, float]] = {
    scheme: {f.name: f.metadata["scheme_defaults"][scheme] for f in dataclasses.fields(RewardParams)}
    for scheme in SCHEMES
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
    wall: jnp.ndarray

    @property
    def total(self):
        return self.goal + self.collision + self.disc + self.pot + self.pred + self.kinematic + self.wall


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


def wall_reward(obstacle_dist, p: RewardParams):
    """Wall penalty at the robot's edge distance `obstacle_dist` to the nearest obstacle (applies only where
    obstacle_dist < d_wall): the danger zone's TGRF, centred on the wall, for the walls the paper's future work
    names. Without obstacles the distance is inf and the term 0."""
    return -tgrf(obstacle_dist, p.h_wall, p.sigma_wall)


def step_reward(
    p: RewardParams,
    *,
    collided,
    reached,
    dmin,
    delta_d,
    pred_hits,
    delta_heading=0.0,
    speed=0.0,
    obstacle_dist=jnp.inf,
) -> RewardTerms:
    """Reward of one step, evaluated on the post-step state (as the reference does).

    Collision beats reaching the goal; inside d_disc the danger penalty replaces the progress reward.
    r_pred is added on every step, terminal ones included, as the reference code does.
    `delta_heading` and `speed` feed the unicycle penalties (zero for holonomic robots); `obstacle_dist` the wall
    term (inf: no obstacle).
    """
    collided = jnp.asarray(collided)
    reached = jnp.asarray(reached) & ~collided
    running = ~(collided | reached)
    in_danger = dmin < p.d_disc
    in_wall_zone = obstacle_dist < p.d_wall
    zero = jnp.zeros((), jnp.float32)
    kinematic = -p.spin_coef * jnp.square(delta_heading) - p.back_coef * jnp.abs(jnp.minimum(speed, 0.0))
    return RewardTerms(
        goal=jnp.where(reached, p.r_goal, zero),
        collision=jnp.where(collided, p.r_col, zero),
        disc=jnp.where(running & in_danger, disc_reward(dmin, p), zero),
        pot=jnp.where(running & ~in_danger, pot_reward(delta_d, p), zero),
        pred=pred_reward(pred_hits, p),
        kinematic=jnp.where(running, kinematic, zero),
        # the safe distance keeps the gradient finite where the term does not apply (inf: no obstacle)
        wall=jnp.where(running & in_wall_zone, wall_reward(jnp.where(in_wall_zone, obstacle_dist, 0.0), p), zero),
    )
