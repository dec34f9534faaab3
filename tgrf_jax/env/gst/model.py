"""The Gumbel Social Transformer as CrowdNav++ runs it (0 edge heads, no ghost node: full connectivity), in flax.

One environment's N humans, 5 observed frames. The masking follows the released inference wrapper exactly,
including its quirks (they change numbers, and the released weights were tuned under them):

* a displacement's validity is `m[k-1] * m[last]`, not `m[k-1] * m[k]`, so a displacement into or out of an
  unseen frame counts as valid and the filler position held there enters the network;
* attention is a softmax over all keys, multiplied by the 0/1 mask and renormalised by (sum + 1e-10);
* the residual adds to the *normalised* input of the attention;
* the LSTM advances over all observed frames, fed zeros on invalid ones, then h, c are zeroed for humans
  without a prediction; decoding feeds the mean displacement back through the spatial block (no sampling).

Per-step outputs are bivariate Gaussians over the next displacement; `predict` accumulates them into
absolute positions the way the wrapper does.

One addition, off for the released weights: the parameter `cv_prior` (a frozen scalar, 0 or 1) adds the last
observed displacement to every predicted mean displacement, so the network predicts a correction to constant
velocity, and feeds each raw displacement to the LSTM beside its normalised embedding (a linear map, `speed`).
The released architecture reads displacements only through a LayerNorm of a 2-to-64 embedding, which keeps their
direction but all but erases their length: it cannot tell a fast walker from a slow one, nor "keep walking as
before" to centimetre precision, and on the simulator's crowds even the released weights predict worse than
constant velocity. With `cv_prior` = 0 the model is exactly the released one.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from flax import linen as nn
from flax import struct

OBS_LEN = 5
PRED_LEN = 5
D_MODEL = 64
NUM_HEADS = 8
D_FF = 128
DROPOUT = 0.1
LN_EPS = 1e-5
SPEED_SCALE = 4.0  # per-step displacement (dt = 0.25 s) -> velocity in m/s, O(1) like the other inputs


@struct.dataclass
class StepGaussians:
    """Per-step bivariate Gaussians over displacements: mu (N, K, 2), sigma (N, K, 2), corr (N, K)."""

    mu: jnp.ndarray
    sigma: jnp.ndarray
    corr: jnp.ndarray
    out_mask: jnp.ndarray  # (N,) bool, visible in the last two observed frames


@struct.dataclass
class Prediction:
    """Accumulated predictions: absolute means (N, K, 2), cumulative sigmas (N, K, 2) and correlations (N, K).

    Humans without a prediction (`out_mask` False) hold their last observed position in every step of
    `means`; their sigmas and correlations are the bias-only outputs (unmasked, as the reference returns them).
    """

    means: jnp.ndarray
    sigmas: jnp.ndarray
    rho: jnp.ndarray
    out_mask: jnp.ndarray


class SpatialBlock(nn.Module):
    """Node embedding + one encoder layer, applied to a (..., N, 2) batch of displacements with mask (..., N)."""

    dropout: float = DROPOUT

    @nn.compact
    def __call__(self, v, mask, deterministic: bool = True):
        drop = lambda x: nn.Dropout(self.dropout)(x, deterministic=deterministic)
        x = nn.Dense(D_MODEL, name="embed")(v)
        x = nn.LayerNorm(epsilon=LN_EPS, name="norm_attn")(x) * mask[..., None]
        qkv = nn.Dense(3 * D_MODEL, name="in_proj")(x)
        head_dim = D_MODEL // NUM_HEADS
        split = lambda t: t.reshape(t.shape[:-1] + (NUM_HEADS, head_dim))
        q, k, val = (split(t) for t in jnp.split(qkv, 3, axis=-1))
        logits = jnp.einsum("...qhd,...khd->...hqk", q * head_dim**-0.5, k)
        pair = (mask[..., :, None] * mask[..., None, :])[..., None, :, :]
        w = jax.nn.softmax(logits, axis=-1) * pair
        w = drop(w / (jnp.sum(w, axis=-1, keepdims=True) + 1e-10))
        attn = jnp.einsum("...hqk,...khd->...qhd", w, val).reshape(x.shape)
        x = x + drop(nn.Dense(D_MODEL, name="out_proj")(attn))
        y = nn.LayerNorm(epsilon=LN_EPS, name="norm_ff")(x)
        y = drop(nn.relu(nn.Dense(D_FF, name="ff1")(y)))
        return x + drop(nn.Dense(D_MODEL, name="ff2")(y))


class LSTMStep(nn.Module):
    """One LSTM step, gates (i, f, g, o) as PyTorch stacks them; one input and one recurrent matmul."""

    @nn.compact
    def __call__(self, x, h, c):
        gates = nn.Dense(4 * D_MODEL, name="ih")(x) + nn.Dense(4 * D_MODEL, use_bias=False, name="hh")(h)
        i, f, g, o = jnp.split(gates, 4, axis=-1)
        c = jax.nn.sigmoid(f) * c + jax.nn.sigmoid(i) * jnp.tanh(g)
        return jax.nn.sigmoid(o) * jnp.tanh(c), c


def displacement_masks(visible):
    """(m_rel (N, 5), m_final (N,)) as the released wrapper builds them from visibility (N, 5)."""
    m = visible.astype(jnp.float32)
    m_rel = jnp.concatenate([m[:, :1], m[:, :-1] * m[:, -1:]], axis=1)
    return m_rel, m_rel[:, -1]


class GST(nn.Module):
    """positions (N, 5, 2), visible (N, 5) -> StepGaussians over the next PRED_LEN displacements.

    `dropout` is the training-time rate; `detach_spreads` stops the gradient of the spreads and correlations
    at the LSTM state, so a loss on them trains only their rows of the output head (forward values unchanged)."""

    dropout: float = DROPOUT
    detach_spreads: bool = False

    @nn.compact
    def __call__(self, positions, visible, deterministic: bool = True):
        spatial = SpatialBlock(dropout=self.dropout, name="spatial")
        lstm = LSTMStep(name="lstm")
        head = nn.Dense(5, name="head")
        speed = nn.Dense(D_MODEL, use_bias=False, name="speed")
        # Frozen: the optimiser sees a zero gradient and leaves it where initialisation or import put it.
        prior = jax.lax.stop_gradient(self.param("cv_prior", nn.initializers.zeros, ()))
        m_rel, mf = displacement_masks(visible)
        v = jnp.concatenate([jnp.zeros_like(positions[:, :1]), positions[:, 1:] - positions[:, :-1]], axis=1)
        # Invalid displacements never reach a valid row (their rows are zeroed after the norm and masked out
        # of attention), so zero stands in for the reference's -999 without changing any output.
        v = v * m_rel[..., None]
        base = prior * v[:, -1]  # last displacement, valid wherever a prediction is made (mf)
        xs = spatial(jnp.swapaxes(v, 0, 1), m_rel.T, deterministic)  # (5, N, D)
        n = positions.shape[0]
        h = c = jnp.zeros((n, D_MODEL), positions.dtype)
        for t in range(OBS_LEN):
            h, c = lstm(xs[t] * m_rel[:, t, None] + prior * speed(v[:, t] * SPEED_SCALE), h, c)
        h, c = h * mf[:, None], c * mf[:, None]

        raws, mus = [], []
        for step in range(PRED_LEN):
            if step:
                x = spatial(mus[-1] * mf[:, None], mf, deterministic) + prior * speed(mus[-1] * SPEED_SCALE)
                x = x * mf[:, None]
                h_new, c_new = lstm(x, h, c)
                keep = mf[:, None] > 0
                h, c = jnp.where(keep, h_new, h), jnp.where(keep, c_new, c)
            raw = head(h)
            if self.detach_spreads:
                raw = jnp.concatenate([raw[:, :2], head(jax.lax.stop_gradient(h))[:, 2:]], axis=-1)
            raws.append(raw)
            mus.append(raw[:, :2] + base)
        raw = jnp.stack(raws, axis=1)  # (N, K, 5)
        return StepGaussians(
            mu=jnp.stack(mus, axis=1), sigma=jnp.exp(raw[..., 2:4]), corr=jnp.tanh(raw[..., 4]), out_mask=mf > 0
        )


MODEL = GST()


def init_params(key, num_humans: int = 20, cv_prior: bool = False):
    """Freshly initialised parameters (flax defaults: LeCun-normal kernels, zero biases).

    With `cv_prior` the output head starts at zero, so the untrained model predicts constant velocity (unit
    sigmas, no correlation) and training learns the corrections."""
    pos = jnp.zeros((num_humans, OBS_LEN, 2))
    params = MODEL.init(key, pos, jnp.ones((num_humans, OBS_LEN), bool))["params"]
    if cv_prior:
        head = jax.tree_util.tree_map(jnp.zeros_like, params["head"])
        params = {**params, "head": head, "cv_prior": jnp.ones((), jnp.float32)}
    return params


def _check_inputs(fn: str, positions, visible, frames: int | None) -> None:
    """Shapes of the public entry points' arrays, named by argument. Users pass these arrays by hand (a batch of
    environments where one is expected, a missing (x, y) axis); chex's messages name neither the argument nor
    what it means, and flax would fail later still on a shape deep inside the network. Shapes are static, so
    this also holds under jit and vmap (where they are the shapes of one element)."""
    shape, vis = tuple(jnp.shape(positions)), tuple(jnp.shape(visible))
    t = "T" if frames is None else str(frames)
    if len(shape) != 3 or shape[-1] != 2 or (frames is not None and shape[1] != frames):
        raise ValueError(
            f"gst.{fn}: positions has shape {shape}; expected (humans, {t}, 2): each human's last "
            f"{'observed' if frames is None else frames} positions (x, y), frame -1 = now (vmap over "
            "environments for a batch)"
        )
    if vis != shape[:2]:
        raise ValueError(
            f"gst.{fn}: visible has shape {vis}; expected {shape[:2]} (humans, {t}), one flag per "
            "human and frame of positions"
        )


def step_gaussians(
    params, positions, visible, *, dropout_key=None, dropout: float = DROPOUT, detach_spreads: bool = False
) -> StepGaussians:
    """Per-step Gaussians; dropout (rate `dropout`) is on only when `dropout_key` is given."""
    _check_inputs("step_gaussians", positions, visible, frames=None)
    rngs = None if dropout_key is None else {"dropout": dropout_key}
    model = GST(dropout=dropout, detach_spreads=detach_spreads)
    return model.apply({"params": params}, positions, visible, dropout_key is None, rngs=rngs)


def accumulate(g: StepGaussians, last_pos) -> Prediction:
    """Absolute means and cumulative sigma / correlation, as the reference wrapper returns them."""
    sx, sy = g.sigma[..., 0], g.sigma[..., 1]
    sx_cum = jnp.sqrt(jnp.cumsum(sx * sx, axis=-1))
    sy_cum = jnp.sqrt(jnp.cumsum(sy * sy, axis=-1))
    rho = jnp.cumsum(g.corr * sx * sy, axis=-1) / (sx_cum * sy_cum)
    means = last_pos[:, None, :] + jnp.cumsum(g.mu, axis=1)
    means = jnp.where(g.out_mask[:, None, None], means, last_pos[:, None, :])
    return Prediction(means=means, sigmas=jnp.stack([sx_cum, sy_cum], -1), rho=rho, out_mask=g.out_mask)


def predict(params, positions, visible) -> Prediction:
    """Predicted absolute positions of N humans over the next 5 steps from their last 5 observed positions.

    positions (N, 5, 2) absolute, frame 4 = now; visible (N, 5) bool. Unseen frames may hold any finite
    filler, but note the reference's quirk: a filler adjacent to a seen frame enters the network (see the
    module docstring). jit- and vmap-able; vmap over environments.
    """
    positions = jnp.asarray(positions, jnp.float32)
    visible = jnp.asarray(visible, bool)
    _check_inputs("predict", positions, visible, frames=OBS_LEN)
    return accumulate(step_gaussians(params, positions, visible), positions[:, -1])
