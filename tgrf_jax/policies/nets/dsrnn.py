"""DS-RNN policy torso: the reference's `SRNN` (CrowdNav++ `rl/networks/srnn_model.py`).

One step, per batch element:

    temporal edge:  h_t = GRU(64 -> He)(ReLU(Linear(2, Ee)(robot_vel)))
    spatial edges:  h_s[i] = GRU(Ee -> He)(ReLU(Linear(2, Ee)(p_i)))   one GRU with weights shared over humans;
                    p_i = current relative position of human i (first 2 features of obs.humans, as the
                    reference: predicted positions are ignored)
    attention:      score_i = <Linear(He, a)(h_t), Linear(He, a)(h_s[i])> * (N / sqrt(a)); masked softmax over
                    visible humans; attn = sum_i w_i h_s[i]                                  (He)
    node:           r = Linear(7, 3)(robot_node) (orthogonal sqrt 2); enc = ReLU(Linear(3, e)(r));
                    edge = ReLU(Linear(2 He, e)(h_t ‖ attn)); h_n = GRU(2e -> G)(enc ‖ edge); x = Linear(G, O)(h_n)
    heads:          as HH Attn (actor / critic 2 x (Linear(O, O) + tanh), mean, value, log-std)

With a 2-D LiDAR (lidar_rays = R > 0; not in the reference) the scan is encoded as in HH Attn (`LidarEncoder`: two
circular 1-D convolutions of width 5 and stride 2, then a dense layer to L = e features; HEIGHT's obstacle branch)
and the embedding joins the node RNN's input: h_n = GRU(2e + L -> G)(enc ‖ edge ‖ lidar). There rather than before
the heads because the node RNN is where the robot's own features enter and its memory: a scan read through it
is integrated over time like the edge features (walls drifting by, returns moving), while a scan added after
the GRU would be seen one frame at a time. (The edge RNNs are per human and per robot velocity: no place for a
view of the whole scene.) With R = 0 nothing is built and the network is exactly the reference's. Parameters:
small 92,221 -> 101,077 with 36 rays, 121,813 with 360; paper 957,021 -> 992,269 / 1,075,213.

Carry: {"node": (B, G), "temporal": (B, He), "spatial": (B, N, He)}. Spatial edge states are indexed by row, i.e. by
distance rank (the observation sorts humans by distance), as in the reference.

Differences from the reference, all deliberate:
* the attention uses the padding mask (the reference attends to the padded fake humans at (15, 15)); with no visible
  human its output is zeros. Invisible rows are zeroed on input, so they influence neither the outputs nor the
  carry.
* the reference builds three unused layers (`human_node_final_linear` Linear(256, 2), `spatial_linear`
  Linear(D, 2), `HumanNodeRNN.edge_embed` Linear(256, 64): 16,968 parameters with D = 2) that are not built here:
  the paper preset has 957,021 parameters (973,989 with the reference's unused layers, its "≈ 0.97 M").

Presets (`DSRNN_SIZES`):
* ``paper``: Ee = e = a = 64, He = 256, G = 128, O = head hidden = 256 (reference `arguments.py`). 957,021 params.
* ``small``: Ee = e = a = 32, He = 64, G = 64, O = head hidden = 64. The 256-wide edge GRUs run once per human per
  step and dominate the cost (20 x 3 x 256 x (64 + 256) MACs); 64 wide cuts that ~16x, matching HH Attn ``small``'s
  64-unit GRU/heads. 92,221 params (any D).
"""

from __future__ import annotations

import dataclasses
import math

import jax.numpy as jnp
from flax import linen as nn

from tgrf_jax.policies.nets.common import (
    ActorCriticHeads,
    LidarEncoder,
    LidarEncoderSize,
    TorchGRUCell,
    masked_humans,
    orthogonal_dense,
    robot_human_attention,
    torch_dense,
)


@dataclasses.dataclass(frozen=True)
class DSRNNSize:
    edge_embed: int  # Ee
    edge_rnn: int  # He
    attn: int  # a
    node_input: int  # robot_node -> this many features (3 in the reference)
    node_embed: int  # e
    node_rnn: int  # G
    output: int  # O
    head_hidden: int
    lidar: LidarEncoderSize = LidarEncoderSize()  # the scan encoder (built only with lidar_rays > 0)


DSRNN_SIZES = {
    "paper": DSRNNSize(
        edge_embed=64,
        edge_rnn=256,
        attn=64,
        node_input=3,
        node_embed=64,
        node_rnn=128,
        output=256,
        head_hidden=256,
        lidar=LidarEncoderSize(channels=(16, 16), embed=64),
    ),
    "small": DSRNNSize(
        edge_embed=32,
        edge_rnn=64,
        attn=32,
        node_input=3,
        node_embed=32,
        node_rnn=64,
        output=64,
        head_hidden=64,
        lidar=LidarEncoderSize(channels=(8, 8), embed=32),
    ),
}


class DSRNNNet(nn.Module):
    """One step of the DS-RNN policy."""

    size: DSRNNSize
    num_humans: int
    action_dim: int = 2
    lidar_rays: int = 0  # R, rays of the scan (0: no scan, no encoder: the reference network)
    lidar_range: float = 5.0  # metres that scale the ranges to [0, 1] (the env's sensor range)

    def initialize_carry(self, batch_size: int):
        s = self.size
        return {
            "node": jnp.zeros((batch_size, s.node_rnn), jnp.float32),
            "temporal": jnp.zeros((batch_size, s.edge_rnn), jnp.float32),
            "spatial": jnp.zeros((batch_size, self.num_humans, s.edge_rnn), jnp.float32),
        }

    @nn.compact
    def __call__(self, carry, obs):
        s = self.size
        mask = obs.human_mask.astype(bool)
        num_humans = obs.humans.shape[-2]
        pos = masked_humans(obs.humans[..., :2].astype(jnp.float32), mask)  # current relative positions only

        # temporal edge RNN (robot velocity)
        t_in = nn.relu(torch_dense(s.edge_embed, 2, name="temporal_encoder")(obs.robot_vel.astype(jnp.float32)))
        h_t = TorchGRUCell(s.edge_rnn, name="temporal_gru")(carry["temporal"], t_in)

        # spatial edge RNNs (weights shared over humans)
        s_in = nn.relu(torch_dense(s.edge_embed, 2, name="spatial_encoder")(pos))
        h_s = TorchGRUCell(s.edge_rnn, name="spatial_gru")(carry["spatial"], s_in)

        # attention of the temporal edge over the spatial edges (score x N / sqrt(a): reference quirk), masked
        tq = torch_dense(s.attn, s.edge_rnn, name="attn_temporal")(h_t)
        sk = torch_dense(s.attn, s.edge_rnn, name="attn_spatial")(h_s)
        attn = robot_human_attention(tq, sk, h_s, mask, scale=num_humans / math.sqrt(s.attn))

        # node RNN
        r = orthogonal_dense(s.node_input, name="robot_linear")(obs.robot_node.astype(jnp.float32))
        enc = nn.relu(torch_dense(s.node_embed, s.node_input, name="node_encoder")(r))
        edge = nn.relu(
            torch_dense(s.node_embed, 2 * s.edge_rnn, name="node_edge_embed")(jnp.concatenate([h_t, attn], -1))
        )
        node_in = [enc, edge]
        if self.lidar_rays > 0:
            node_in.append(LidarEncoder(s.lidar, self.lidar_range, name="lidar_encoder")(obs.lidar))
        h_n = TorchGRUCell(s.node_rnn, name="node_gru")(carry["node"], jnp.concatenate(node_in, axis=-1))
        x = torch_dense(s.output, s.node_rnn, name="node_output")(h_n)

        mean, log_std, value = ActorCriticHeads((s.head_hidden, s.head_hidden), self.action_dim, name="heads")(x)
        return {"node": h_n, "temporal": h_t, "spatial": h_s}, (mean, log_std, value)
