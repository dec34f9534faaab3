"""Feed-forward baseline policy (no memory).

Input, per batch element: robot_vel (2) ‖ robot_node (7) ‖ flatten(humans with invisible rows zeroed) (N x D)
‖ human_mask as 0/1 (N), and with a LiDAR the scan (R rays, in the policy's frame, clipped to the sensor range and
scaled to [0, 1]; R x hidden more weights in each of the actor's and critic's first layers). Rows arrive sorted by
distance with visible humans first, so the flattened layout is "nearest first". The actor and critic each get their
own 2-layer tanh MLP (orthogonal sqrt 2 init) on this input, then the same mean / value / log-std heads as the
recurrent policies.

Presets: ``paper`` 2 x 256 hidden units (270,597 params with D = 12, N = 20; 168,197 with D = 2), ``small`` 2 x 64
(43,077 / 17,477). The carry is a dummy zeros (B, 1) array (passed
through unchanged) so every policy has the same recurrent interface.
"""

from __future__ import annotations

import jax.numpy as jnp
from flax import linen as nn

from tgrf_jax.policies.nets.common import ActorCriticHeads, masked_humans, scale_scan

MLP_SIZES = {"paper": 256, "small": 64}


class MLPNet(nn.Module):
    hidden: int
    action_dim: int = 2
    lidar_range: float = 5.0  # metres that scale a scan's ranges to [0, 1] (the env's sensor range)

    def initialize_carry(self, batch_size: int):
        return {"dummy": jnp.zeros((batch_size, 1), jnp.float32)}

    def setup(self):
        self.heads = ActorCriticHeads((self.hidden, self.hidden), self.action_dim)

    def encode(self, obs):
        mask = obs.human_mask.astype(bool)
        humans = masked_humans(obs.humans.astype(jnp.float32), mask)
        batch = humans.shape[:-2]
        parts = [
            obs.robot_vel.astype(jnp.float32),
            obs.robot_node.astype(jnp.float32),
            humans.reshape(batch + (-1,)),
            mask.astype(jnp.float32),
        ]
        if obs.lidar.shape[-1]:
            parts.append(scale_scan(obs.lidar, self.lidar_range))
        return jnp.concatenate(parts, axis=-1)

    def recur(self, carry, x):
        return carry, x  # no memory

    def decode(self, x):
        return self.heads(x)

    def __call__(self, carry, obs):
        carry, x = self.recur(carry, self.encode(obs))
        return carry, self.decode(x)
