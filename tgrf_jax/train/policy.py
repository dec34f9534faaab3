"""A trained actor-critic as a robot policy (the `tgrf_jax.policies` interface), for evaluation and rendering."""

from __future__ import annotations

import jax

from tgrf_jax.nets import ActorCritic


@jax.tree_util.register_pytree_node_class
class LearnedPolicy:
    """`act` returns the Gaussian mean (deterministic, as the reference's test) or a sample.

    A pytree whose leaves are the parameters (the network is static): `evaluate` traces the parameters, so every
    checkpoint of a run (periodic evaluations, tgrf-eval) runs the same compiled program and gets the same numbers.
    """

    def tree_flatten(self):
        return (self.params,), (self.net, self.deterministic)

    @classmethod
    def tree_unflatten(cls, static, leaves):
        return cls(static[0], leaves[0], deterministic=static[1])

    def __init__(self, net: ActorCritic, params, deterministic: bool = True):
        self.net = net
        self.params = params
        self.deterministic = deterministic

    def __repr__(self):
        return f"LearnedPolicy({self.net.name}/{self.net.size}, deterministic={self.deterministic})"

    def initialize_carry(self, batch_size: int):
        return self.net.initialize_carry(batch_size)

    def act(self, carry, obs, resets, key):
        carry, pi, _ = self.net.apply(self.params, carry, obs, resets)
        action = pi.mean() if self.deterministic else pi.sample(seed=key)
        return carry, action
