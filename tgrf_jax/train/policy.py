"""A trained actor-critic as a robot policy (the `tgrf_jax.policies` interface), for evaluation and rendering."""

from __future__ import annotations

import jax

from tgrf_jax.nets import ActorCritic


class LearnedPolicy:
    """`act` returns the Gaussian mean (deterministic, as the reference's test) or a sample.

    Hashed by identity: `evaluate` jits with the policy as a static argument, so each instance (one set of
    parameters) compiles once and different parameters never share a stale cache entry.
    """

    def __init__(self, net: ActorCritic, params, deterministic: bool = True):
        self.net = net
        self.params = params
        self.deterministic = deterministic

    def __repr__(self):
        return f"LearnedPolicy({self.net.name}/{self.net.size}, deterministic={self.deterministic})"

    __hash__ = object.__hash__

    def __eq__(self, other):
        return self is other

    def initialize_carry(self, batch_size: int):
        return self.net.initialize_carry(batch_size)

    def act(self, carry, obs, resets, key):
        carry, pi, _ = self.net.apply(self.params, carry, obs, resets)
        action = pi.mean() if self.deterministic else pi.sample(seed=key)
        return carry, action
