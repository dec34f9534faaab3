"""HH Attn policy torso: the reference's `selfAttn_merge_SRNN` (CrowdNav++ `rl/networks/selfAttn_srnn_temp_node.py`,
paper Sec. 4.1).

One step, per batch element:

    robot   = robot_vel (2) ‖ robot_node (7)                       9 features, world frame, unnormalised
                                                                    (the reference concatenates temporal_edges first)
    r_emb   = ReLU(Linear(9, R))                                    orthogonal sqrt 2
    h_emb   = ReLU(Linear(D, Eh)) -> ReLU(Linear(Eh, A))            HH self-attention embedding (PyTorch default init)
    q, k, v = Linear(A, A) each, then MultiheadAttention(A, heads) with key_padding_mask = ~human_mask
    hum     = ReLU(Linear(A, F))                                    orthogonal sqrt 2
    attn    = RH attention: q = Linear(R, a)(r_emb), k = Linear(F, a)(hum),
              score = <q, k> * (N / sqrt(a)), masked softmax over visible humans, output sum_i w_i hum_i  (F)
    x       = ReLU(Linear(R, e))(r_emb) ‖ ReLU(Linear(F, e))(attn)  -> GRU(2e, G) -> Linear(G, O)
    heads   = actor / critic: 2 x (Linear(O, O) + tanh); mean Linear(O, 2); value Linear(O, 1)

With a 2-D LiDAR (lidar_rays = R > 0; not in the reference) a scan branch runs beside the human attention, as
the obstacle branch of HEIGHT (Liu et al. 2024):

    scan    = lidar (R) in the policy's frame (ray 0 along world +x, or at the goal: `frames.rotate_scan`),
              clipped to the sensor range and scaled to [0, 1]
    c1      = ReLU(Conv1d(1 -> C1, width 5, stride 2, circular padding))          ceil(R / 2) x C1
    c2      = ReLU(Conv1d(C1 -> C2, width 5, stride 2, circular padding))         ceil(R / 4) x C2
    lid     = ReLU(Linear(ceil(R / 4) C2, L)(flatten(c2)))
    x       = ReLU(Linear(R, e))(r_emb) ‖ ReLU(Linear(F, e))(attn) ‖ lid  -> GRU(2e + L, G) -> ...

C1 = C2 = 8, L = e = 32 (small); C1 = C2 = 16, L = e = 64 (paper). The embedding joins the GRU's input, beside the
robot and the attended humans, so the robot's memory integrates the scan over time (it sees walls drift by and
scan returns move) and the encoder stays in `encode`, run once over a whole sequence. With R = 0 the branch
does not exist: parameters and outputs are exactly the reference network's. Parameters added: the encoder
(48 + 328 + (8 ceil(R / 4) + 1) 32 small; 96 + 1296 + (16 ceil(R / 4) + 1) 64 paper) and 3 G L in the GRU's
input weights: hh_attn small 69,925 -> 78,781 with 36 rays, 99,517 with 360; paper 2,502,021 -> 2,537,269 /
2,620,213 (D = 12, N = 20).

Quirk kept from the reference: the robot–human attention score is *multiplied* by num_humans / sqrt(a)
(`temperature = num_edges / np.sqrt(attention_size)`, then `attn * temperature`), i.e. x 2.5 at 20 humans and
a = 64, instead of divided by sqrt(a). It sharpens the softmax as the (padded) number of humans grows.

Differences from the reference, all deliberate:
* padded (invisible) humans are masked in both attentions with a boolean mask; with no visible human the
  attention output is zeros (the reference instead keeps a "dummy" first human so its masks are never empty, and
  PyTorch's MultiheadAttention would return NaN for an all-masked query). Invisible rows are zeroed on input.
* the robot-human key layer Linear(F, a) is applied to the robot's query instead of to every human
  (`KeyIntoQuery`): the same attention weights, one product per robot instead of one per human.
* the reference builds an unused `human_node_final_linear = Linear(256, 2)` (514 parameters); it is not built here,
  so the paper preset has 2,502,021 parameters with D = 12 and 20 humans, against 2,502,535 when it is counted.

Presets (`HH_ATTN_SIZES`):
* ``paper``: R = F = O = head hidden = 256, self-attention A = 512 wide with 8 heads (Eh = 128),
  a = e = 64, GRU 128 — exactly the reference; 2,502,021 params (D = 12, N = 20), 2,500,741 with D = 2.
* ``small``: R = F = O = head hidden = 64, self-attention A = 64 wide with 2 heads (Eh = 32; queries and keys
  16 wide per head, values 32), a = 32, e = 32, GRU 64. Reasoning: the paper net spends 1.9 M of its 2.5 M
  parameters and almost all of its FLOPs in the 512-wide self-attention (four 512x512 projections per human per
  step); shrinking it to 64 wide makes a step about 37x cheaper on a CPU, so many parallel envs can be stepped
  on 2 CPU cores, while keeping every architectural element (both attentions, masks, GRU memory, separate
  actor / critic trunks). 64 hidden units and a 64-unit GRU are the usual sizes for small continuous-control PPO
  policies. Since PPO's epochs dominate training time on a CPU and almost
  all of their arithmetic is per human row, `small` trims that path: it feeds the embedding straight into the
  attention's own in-projection and the heads straight into `spatial_linear` (`qkv_pre_projection`,
  `hh_out_projection`: linear maps in a row, no function lost), uses 16-wide queries and keys (`hh_qk_head_dim`)
  and a 32-wide first embedding layer, and attends to the 16 nearest visible humans (`max_humans`): on average 8
  of the 20 are visible and more than 16 in under 3% of the steps (sensor range 5 m). One gradient slice of
  the PPO loss (16 envs x 15 steps) costs 429 MFLOP, against 728 with 64-wide layers throughout
  (docs/benchmarks.md). 69,925 params (D = 12, N = 20), 69,605 with D = 2.
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
    MultiHeadAttention,
    TorchGRUCell,
    masked_humans,
    orthogonal_dense,
    robot_human_attention,
    torch_dense,
    torch_linear_init,
)


@dataclasses.dataclass(frozen=True)
class HHAttnSize:
    robot_embed: int  # R
    hh_embed_hidden: int  # Eh, first layer of the per-human embedding
    hh_attn: int  # A, self-attention width
    hh_heads: int
    human_embed: int  # F
    rh_attn: int  # a, robot-human attention key size
    node_embed: int  # e
    gru: int  # G
    output: int  # O
    head_hidden: int
    # The reference projects the embedding with Linear(A, A) for q, k and v and then again with the attention's
    # packed in-projection; two linear maps in a row are one linear map, so `small` skips the first (same function
    # class, a third fewer attention FLOPs).
    qkv_pre_projection: bool = True
    # Attend to at most this many humans, the nearest visible ones (observation rows are sorted visible first by
    # distance); 0: all N rows.
    max_humans: int = 0
    # Width of each self-attention head's queries and keys (0: A / heads, as the reference); values keep A / heads.
    hh_qk_head_dim: int = 0
    # The reference follows the attention's output projection with `spatial_linear`, again two linear maps in a
    # row; False drops the first.
    hh_out_projection: bool = True
    # The scan encoder, built only for a policy with a LiDAR (lidar_rays > 0).
    lidar: LidarEncoderSize = LidarEncoderSize()


HH_ATTN_SIZES = {
    "paper": HHAttnSize(
        robot_embed=256,
        hh_embed_hidden=128,
        hh_attn=512,
        hh_heads=8,
        human_embed=256,
        rh_attn=64,
        node_embed=64,
        gru=128,
        output=256,
        head_hidden=256,
        lidar=LidarEncoderSize(channels=(16, 16), embed=64),
    ),
    "small": HHAttnSize(
        robot_embed=64,
        hh_embed_hidden=32,
        hh_attn=64,
        hh_heads=2,
        human_embed=64,
        rh_attn=32,
        node_embed=32,
        gru=64,
        output=64,
        head_hidden=64,
        qkv_pre_projection=False,
        max_humans=16,
        hh_qk_head_dim=16,
        hh_out_projection=False,
        lidar=LidarEncoderSize(channels=(8, 8), embed=32),
    ),
}


class KeyIntoQuery(nn.Module):
    """The robot-human attention's key layer, Linear(F, a), applied to the query instead of to every human.

    score_i = q . (W^T hum_i + b) = (W q) . hum_i + q . b: the robot's query is projected once into the humans'
    F-dim space rather than every human into the a-dim key space (a F x a product per human saved), and q . b,
    the same for every human, cancels in the softmax. The bias is kept as a parameter (same names, shapes and
    initial values as the reference's `nn.Linear`, so parameter counts and checkpoints match) although no output
    depends on it; its gradient is exactly zero.
    """

    features: int  # a
    fan_in: int  # F

    @nn.compact
    def __call__(self, query: jnp.ndarray) -> jnp.ndarray:
        init = torch_linear_init(self.fan_in)
        kernel = self.param("kernel", init, (self.fan_in, self.features))
        self.param("bias", init, (self.features,))
        return query @ kernel.T


class HHAttnNet(nn.Module):
    """One step of the HH Attn policy. Carry: {"node": (B, G)}.

    Split into `encode` (everything that depends only on the observation: both attentions and the GRU input
    embeddings), `recur` (the GRU) and `decode` (output layer and heads). The encoder does not read the recurrent
    state, so `ActorCritic.apply_sequence` runs it once over a whole (T, B) sequence and scans only the GRU: on CPU
    that turns T small per-step attention evaluations into one large batched one.
    """

    size: HHAttnSize
    obs_human_dim: int
    action_dim: int = 2
    lidar_rays: int = 0  # R, rays of the scan (0: no scan, no encoder: the reference network)
    lidar_range: float = 5.0  # metres that scale the ranges to [0, 1] (the env's sensor range)

    def initialize_carry(self, batch_size: int):
        return {"node": jnp.zeros((batch_size, self.size.gru), jnp.float32)}

    def setup(self):
        s = self.size
        self.robot_linear = orthogonal_dense(s.robot_embed)
        self.hh_embed_0 = torch_dense(s.hh_embed_hidden, self.obs_human_dim)
        self.hh_embed_1 = torch_dense(s.hh_attn, s.hh_embed_hidden)
        if s.qkv_pre_projection:
            self.hh_q = torch_dense(s.hh_attn, s.hh_attn)
            self.hh_k = torch_dense(s.hh_attn, s.hh_attn)
            self.hh_v = torch_dense(s.hh_attn, s.hh_attn)
        self.hh_mha = MultiHeadAttention(
            s.hh_attn, s.hh_heads, qk_head_dim=s.hh_qk_head_dim, out_projection=s.hh_out_projection
        )
        self.spatial_linear = orthogonal_dense(s.human_embed)
        self.rh_query = torch_dense(s.rh_attn, s.robot_embed)
        self.rh_key = KeyIntoQuery(s.rh_attn, s.human_embed)
        self.node_encoder = torch_dense(s.node_embed, s.robot_embed)
        self.node_attn_embed = torch_dense(s.node_embed, s.human_embed)
        if self.lidar_rays > 0:
            self.lidar_encoder = LidarEncoder(s.lidar, self.lidar_range)
        self.node_gru = TorchGRUCell(s.gru)
        self.node_output = torch_dense(s.output, s.gru)
        self.heads = ActorCriticHeads((s.head_hidden, s.head_hidden), self.action_dim)

    def encode(self, obs):
        """Observation (any leading shape) -> GRU input (..., 2e), (..., 2e + L) with a scan."""
        s = self.size
        mask = obs.human_mask.astype(bool)
        num_humans = obs.humans.shape[-2]  # the attention temperature keeps the env's N (reference quirk)
        humans = masked_humans(obs.humans.astype(jnp.float32), mask)
        if 0 < s.max_humans < num_humans:
            mask, humans = mask[..., : s.max_humans], humans[..., : s.max_humans, :]

        robot = jnp.concatenate([obs.robot_vel, obs.robot_node], axis=-1).astype(jnp.float32)
        r_emb = nn.relu(self.robot_linear(robot))

        # human-human multi-head self-attention
        e = nn.relu(self.hh_embed_1(nn.relu(self.hh_embed_0(humans))))
        if s.qkv_pre_projection:
            q, k, v = self.hh_q(e), self.hh_k(e), self.hh_v(e)
        else:
            q = k = v = e
        z = self.hh_mha(q, k, v, mask)
        hum = nn.relu(self.spatial_linear(z))

        # robot-human attention (score multiplied by N / sqrt(a): reference quirk, see module docstring)
        attn = robot_human_attention(
            self.rh_key(self.rh_query(r_emb)), hum, hum, mask, scale=num_humans / math.sqrt(s.rh_attn)
        )
        enc = nn.relu(self.node_encoder(r_emb))
        att_emb = nn.relu(self.node_attn_embed(attn))
        if self.lidar_rays == 0:
            return jnp.concatenate([enc, att_emb], axis=-1)
        return jnp.concatenate([enc, att_emb, self.lidar_encoder(obs.lidar)], axis=-1)

    def recur(self, carry, x):
        """(carry, GRU input) -> (new carry, decoder input)."""
        h = self.node_gru(carry["node"], x)
        return {"node": h}, h

    def decode(self, h):
        """GRU output (any leading shape) -> (mean, log_std, value)."""
        return self.heads(self.node_output(h))

    def __call__(self, carry, obs):
        carry, h = self.recur(carry, self.encode(obs))
        return carry, self.decode(h)
