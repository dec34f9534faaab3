"""Building blocks shared by the policy networks.

Initialisers follow the reference (CrowdNav++ / TGRF, PyTorch):

* layers the reference wraps in its `init_` helper (robot embedding, post-attention linear, actor / critic MLPs,
  value head) are orthogonal with gain sqrt(2) and zero bias; the action-mean layer is orthogonal with gain 1;
* every other `nn.Linear` keeps PyTorch's default, U(-1/sqrt(fan_in), 1/sqrt(fan_in)) for weight and bias
  (`torch_dense` below);
* GRUs are PyTorch-style (separate input and hidden biases, 6H bias parameters) with orthogonal weights and zero
  biases, as `RNNBase.__init__` sets them;
* `nn.MultiheadAttention` uses a Xavier-uniform packed input projection with zero bias and a default-initialised
  output projection with zero bias.

`LidarEncoder` (the scan branch of HH Attn and DS-RNN, no counterpart in the reference) uses PyTorch's defaults too:
`nn.Conv1d` and `nn.Linear` draw weight and bias from U(-1/sqrt(fan_in), 1/sqrt(fan_in)).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Sequence

import jax
import jax.numpy as jnp
from flax import linen as nn

SQRT2 = math.sqrt(2.0)


# ----------------------------------------------------------------------------------------------------------- init


def orthogonal_dense(features: int, gain: float = SQRT2, name: str | None = None) -> nn.Dense:
    """Dense layer with orthogonal weights (given gain) and zero bias (the reference's `init_`)."""
    return nn.Dense(features, kernel_init=nn.initializers.orthogonal(gain), bias_init=nn.initializers.zeros, name=name)


def _uniform(bound: float) -> Callable:
    def init(key, shape, dtype=jnp.float32):
        return jax.random.uniform(key, shape, dtype, -bound, bound)

    return init


def torch_linear_init(fan_in: int) -> Callable:
    """PyTorch's default `nn.Linear` initialiser, for weight and bias alike: U(-1/sqrt(fan_in), +)."""
    return _uniform(1.0 / math.sqrt(fan_in) if fan_in > 0 else 0.0)


def torch_dense(features: int, fan_in: int, name: str | None = None) -> nn.Dense:
    """Dense layer with PyTorch's default `nn.Linear` initialisation."""
    init = torch_linear_init(fan_in)
    return nn.Dense(features, kernel_init=init, bias_init=init, name=name)


# ------------------------------------------------------------------------------------------------------------ GRU


class TorchGRUCell(nn.Module):
    """GRU cell with PyTorch's parameterisation (gate order r, z, n; input and hidden biases).

    r = sigmoid(x W_ir + b_ir + h W_hr + b_hr);  z = sigmoid(x W_iz + b_iz + h W_hz + b_hz)
    n = tanh(x W_in + b_in + r * (h W_hn + b_hn));  h' = (1 - z) * n + z * h

    Weights orthogonal (over the packed 3H matrix, as `nn.init.orthogonal_` on `weight_ih_l0`), biases zero.
    Works on any leading batch shape (e.g. (B, N, H) for per-human edge GRUs with shared weights).
    Parameters: 3H (in + H) + 6H.
    """

    hidden: int

    @nn.compact
    def __call__(self, h: jnp.ndarray, x: jnp.ndarray) -> jnp.ndarray:
        H = self.hidden
        ortho = nn.initializers.orthogonal(1.0)
        w_i = self.param("w_i", ortho, (x.shape[-1], 3 * H))
        w_h = self.param("w_h", ortho, (H, 3 * H))
        b_i = self.param("b_i", nn.initializers.zeros, (3 * H,))
        b_h = self.param("b_h", nn.initializers.zeros, (3 * H,))
        gi = x @ w_i + b_i
        gh = h @ w_h + b_h
        i_r, i_z, i_n = jnp.split(gi, 3, axis=-1)
        h_r, h_z, h_n = jnp.split(gh, 3, axis=-1)
        r = jax.nn.sigmoid(i_r + h_r)
        z = jax.nn.sigmoid(i_z + h_z)
        n = jnp.tanh(i_n + r * h_n)
        return (1.0 - z) * n + z * h


# ------------------------------------------------------------------------------------------------------ attention


def masked_softmax(scores: jnp.ndarray, mask: jnp.ndarray, axis: int = -1) -> jnp.ndarray:
    """Softmax over `axis` restricted to `mask`; masked entries get weight exactly 0.

    An all-False mask (or an empty axis) gives all-zero weights, never NaN, and finite gradients.
    """
    mask = jnp.broadcast_to(mask, scores.shape)
    fill = jnp.finfo(scores.dtype).min
    masked = jnp.where(mask, scores, fill)
    s_max = jnp.max(masked, axis=axis, keepdims=True, initial=fill)
    s_max = jax.lax.stop_gradient(s_max)
    e = jnp.where(mask, jnp.exp(jnp.where(mask, masked - s_max, 0.0)), 0.0)
    denom = jnp.sum(e, axis=axis, keepdims=True)
    return e / jnp.where(denom > 0, denom, 1.0)


class MultiHeadAttention(nn.Module):
    """`torch.nn.MultiheadAttention(embed, heads)` with a key padding mask (keys where `key_mask` is False are
    ignored). Own packed input projection (3E x E + 3E) and output projection (E x E + E), as PyTorch.

    q, k, v: (..., L, E); key_mask: (..., L) bool. Returns (..., L, E). A query whose keys are all masked gets a
    zero attention vector (PyTorch would give NaN), so its output is the output-projection bias.

    Two departures from PyTorch, off by default, for networks that pay per row (HH Attn `small`):
    `qk_head_dim` makes queries and keys narrower than the values (scores only need a rank-`qk_head_dim` bilinear
    form per head, while the values carry the content), and `out_projection=False` returns the concatenated heads
    unprojected, for a caller whose next layer is linear anyway (two linear maps in a row are one).
    """

    embed: int
    heads: int
    qk_head_dim: int = 0  # 0: embed // heads, as PyTorch
    out_projection: bool = True

    @nn.compact
    def __call__(self, q: jnp.ndarray, k: jnp.ndarray, v: jnp.ndarray, key_mask: jnp.ndarray) -> jnp.ndarray:
        E, nh = self.embed, self.heads
        if E % nh:
            raise ValueError(f"embed ({E}) must be divisible by heads ({nh})")
        hd = E // nh
        qkd = self.qk_head_dim or hd
        width = 2 * nh * qkd + E
        # xavier-uniform over the packed (width, E) matrix: fan_in E, fan_out width (3E when qk_head_dim is unset)
        bound = math.sqrt(6.0 / (E + width))
        w_in = self.param("in_proj_kernel", _uniform(bound), (E, width))
        b_in = self.param("in_proj_bias", nn.initializers.zeros, (width,))
        if q is k and k is v:  # self-attention on one input: one matmul for all three projections
            qkv = q @ w_in + b_in
            qp, kp, vp = jnp.split(qkv, [nh * qkd, 2 * nh * qkd], axis=-1)
        else:
            wq, wk, wv = jnp.split(w_in, [nh * qkd, 2 * nh * qkd], axis=-1)
            bq, bk, bv = jnp.split(b_in, [nh * qkd, 2 * nh * qkd])
            qp, kp, vp = q @ wq + bq, k @ wk + bk, v @ wv + bv
        qp = qp.reshape(q.shape[:-1] + (nh, qkd))
        kp = kp.reshape(k.shape[:-1] + (nh, qkd))
        vp = vp.reshape(v.shape[:-1] + (nh, hd))
        scores = jnp.einsum("...qhd,...khd->...hqk", qp, kp) / math.sqrt(qkd)
        weights = masked_softmax(scores, key_mask[..., None, None, :])
        out = jnp.einsum("...hqk,...khd->...qhd", weights, vp).reshape(q.shape[:-1] + (E,))
        if not self.out_projection:
            return out
        out_bound = 1.0 / math.sqrt(E)
        return nn.Dense(E, kernel_init=_uniform(out_bound), bias_init=nn.initializers.zeros, name="out_proj")(out)


def robot_human_attention(
    query: jnp.ndarray, keys: jnp.ndarray, values: jnp.ndarray, mask: jnp.ndarray, scale: float
) -> jnp.ndarray:
    """Single-head dot-product attention of one robot query over N humans (the reference's `EdgeAttention(_M)`).

    query (B, A), keys (B, N, A), values (B, N, F), mask (B, N) -> (B, F). `scale` multiplies the scores. Masked
    humans have weight exactly 0 and their values are zeroed first, so they cannot influence the result; with no
    visible human (or N = 0) the output is zeros.
    """
    scores = jnp.sum(query[..., None, :] * keys, axis=-1) * scale
    w = masked_softmax(scores, mask)
    values = jnp.where(mask[..., None], values, 0.0)
    return jnp.sum(w[..., None] * values, axis=-2)


# ---------------------------------------------------------------------------------------------------------- LiDAR


def scale_scan(ranges: jnp.ndarray, max_range: float) -> jnp.ndarray:
    """LiDAR ranges in metres -> [0, 1] (0: contact, 1: nothing within `max_range`). Values beyond the range (a
    sensor reporting further than the env's) are clipped to 1, negative ones to 0."""
    return jnp.clip(ranges.astype(jnp.float32) / max_range, 0.0, 1.0)


@dataclasses.dataclass(frozen=True)
class LidarEncoderSize:
    """Scan encoder: 1-D convolutions (`channels[i]` filters of width `kernel`, stride `stride`, circular padding,
    ReLU) over the R rays, then one dense layer (ReLU) to `embed` features."""

    channels: tuple = (8, 8)
    kernel: int = 5
    stride: int = 2
    embed: int = 32

    def conv_length(self, rays: int) -> int:
        """Rays left after the convolutions (each keeps ceil(L / stride) of L)."""
        for _ in self.channels:
            rays = -(-rays // self.stride)
        return rays

    def num_params(self, rays: int) -> int:
        n, c_in = 0, 1
        for c in self.channels:
            n += c_in * self.kernel * c + c
            c_in = c
        return n + (self.conv_length(rays) * c_in + 1) * self.embed


class LidarEncoder(nn.Module):
    """A 2-D LiDAR scan (..., R) in metres -> an embedding (..., embed), as the obstacle branch of HEIGHT (Liu et
    al. 2024) beside its human attention.

    The ranges are scaled to [0, 1] by `max_range` (`scale_scan`), then `size.channels` 1-D convolutions with
    circular padding (the scan is a ring: ray R-1 neighbours ray 0, so no seam at ray 0) and stride `size.stride`
    (each halves the angular resolution and doubles the channels' field of view: two layers of width 5 see 13
    neighbouring rays), ReLU, and a dense layer over the flattened feature map (it keeps each sector's direction,
    which a pooling would lose), ReLU. The scan arrives in the policy's frame (`frames.py`: world or goal frame),
    so the direction of a feature means the same in every situation. Parameters grow with R only in the dense
    layer: ceil(R / stride^layers) x channels[-1] x embed.
    """

    size: LidarEncoderSize
    max_range: float

    @nn.compact
    def __call__(self, ranges: jnp.ndarray) -> jnp.ndarray:
        s = self.size
        x = scale_scan(ranges, self.max_range)[..., None]  # (..., R, 1)
        c_in = 1
        for i, c in enumerate(s.channels):
            init = torch_linear_init(c_in * s.kernel)
            x = nn.relu(
                nn.Conv(
                    c,
                    (s.kernel,),
                    strides=(s.stride,),
                    padding="CIRCULAR",
                    kernel_init=init,
                    bias_init=init,
                    name=f"conv_{i}",
                )(x)
            )
            c_in = c
        x = x.reshape(x.shape[:-2] + (x.shape[-2] * x.shape[-1],))
        return nn.relu(torch_dense(s.embed, x.shape[-1], name="embed")(x))


# ---------------------------------------------------------------------------------------------------------- heads


class TanhMLP(nn.Module):
    """Stack of orthogonal(sqrt 2) Dense + tanh layers (the reference's actor / critic trunks)."""

    hidden: Sequence[int]

    @nn.compact
    def __call__(self, x):
        for h in self.hidden:
            x = jnp.tanh(orthogonal_dense(h)(x))
        return x


class ActorCriticHeads(nn.Module):
    """Actor and critic trunks (separate), mean layer (orthogonal gain 1) and value layer (orthogonal sqrt 2), plus a
    state-independent log-std parameter initialised to 0 (the reference's `DiagGaussian`)."""

    hidden: Sequence[int]
    action_dim: int

    @nn.compact
    def __call__(self, x):
        actor = TanhMLP(tuple(self.hidden), name="actor")(x)
        critic = TanhMLP(tuple(self.hidden), name="critic")(x)
        mean = orthogonal_dense(self.action_dim, gain=1.0, name="action_mean")(actor)
        value = orthogonal_dense(1, gain=SQRT2, name="value")(critic)[..., 0]
        log_std = self.param("log_std", nn.initializers.zeros, (self.action_dim,))
        return mean, log_std, value


# ---------------------------------------------------------------------------------------------------------- utils


def reset_carry(carry, resets: jnp.ndarray):
    """Zero every carry leaf (leading batch axis) where `resets` (B,) is True."""

    def _reset(leaf):
        r = resets.reshape(resets.shape + (1,) * (leaf.ndim - resets.ndim))
        return jnp.where(r, jnp.zeros_like(leaf), leaf)

    return jax.tree_util.tree_map(_reset, carry)


def masked_humans(humans: jnp.ndarray, mask: jnp.ndarray) -> jnp.ndarray:
    """Zero the feature rows of invisible humans (so padded rows can never influence anything)."""
    return jnp.where(mask[..., None], humans, 0.0)


def count_params(params) -> int:
    """Total number of scalar parameters in a pytree (arrays or `jax.ShapeDtypeStruct`s, e.g. from
    `jax.eval_shape(net.init, key)`)."""
    return int(sum(math.prod(x.shape) for x in jax.tree_util.tree_leaves(params)))
