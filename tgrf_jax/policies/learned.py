"""A trained actor-critic as a robot policy (the `tgrf_jax.policies` interface), and the network a config asks for."""

from __future__ import annotations

import jax

from tgrf_jax.config import TrainConfig
from tgrf_jax.policies.nets import ActorCritic, make_network


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


def make_network_for(config: TrainConfig) -> ActorCritic:
    """The actor-critic of a training config: its network section, sized for its env's crowd and kinematics."""
    env_cfg, n = config.env, config.network
    # The scan is scaled by the sensor range (its largest value); a range of 0 gives all-zero scans, any scale will do.
    lidar_range = env_cfg.sensor_range if env_cfg.sensor_range > 0 else 1.0
    return make_network(
        n.name,
        n.size,
        env_cfg.obs_human_dim,
        env_cfg.num_humans,
        frame=n.frame,
        rotate_action=env_cfg.kinematics == "holonomic",
        init_log_std=n.init_log_std,
        lidar_rays=env_cfg.lidar_rays,
        lidar_range=lidar_range,
    )
