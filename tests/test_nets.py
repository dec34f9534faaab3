"""Policy networks: shapes, masking, parameter counts, recurrent resets, sequence form, gradients."""

import functools
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from tgrf_jax.env.obstacles import Obstacles
from tgrf_jax.env.types import Obs
from tgrf_jax.policies.nets import (
    NETWORK_NAMES,
    NETWORK_SIZES,
    count_params,
    make_network,
    masked_softmax,
)
from tgrf_jax.policies.nets.common import LidarEncoderSize, TorchGRUCell
from tgrf_jax.policies.nets.dsrnn import DSRNN_SIZES
from tgrf_jax.policies.nets.hh_attn import HH_ATTN_SIZES
from tgrf_jax.policies.nets.mlp import MLP_SIZES

B, N = 3, 20
RECURRENT = ("hh_attn", "dsrnn")


def random_obs(key, batch_shape, num_humans, dim, num_visible=None, lidar_rays=0):
    """Random observation batch laid out like the env's: visible rows first, zeros in invisible rows; a scan of
    `lidar_rays` ranges in [0, 6] m (beyond the default 5 m sensor range, to exercise the clipping)."""
    batch_shape = tuple(batch_shape)
    k = jax.random.split(key, 6)
    if num_visible is None:
        num_visible = jax.random.randint(k[0], batch_shape, 0, num_humans + 1)
    mask = jnp.arange(num_humans) < jnp.asarray(num_visible)[..., None]
    mask = jnp.broadcast_to(mask, batch_shape + (num_humans,))
    humans = jax.random.normal(k[1], batch_shape + (num_humans, dim)) * 3.0
    humans = jnp.where(mask[..., None], humans, 0.0)
    return Obs(
        robot_node=jax.random.normal(k[2], batch_shape + (7,)) * 3.0,
        robot_vel=jax.random.normal(k[3], batch_shape + (2,)),
        humans=humans,
        human_mask=mask,
        human_vel=jnp.zeros(batch_shape + (num_humans, 2)),
        human_radius=jnp.zeros(batch_shape + (num_humans,)),
        lidar=jax.random.uniform(k[5], batch_shape + (lidar_rays,), maxval=6.0),
        obstacles=Obstacles(jnp.zeros(batch_shape + (0, 2, 2)), jnp.zeros(batch_shape + (0,), jnp.int32)),
    )


@functools.cache
def built(name, size, dim, num_humans=N, lidar_rays=0):
    net = make_network(name, size, obs_human_dim=dim, num_humans=num_humans, lidar_rays=lidar_rays)
    # an "rbg" key compiles the random initialisers faster than threefry; `PRNGKey` keys are tested below. Jitted:
    # run eagerly, every initialiser of every distinct layer shape is a program of its own (hundreds for hh_attn).
    params = jax.jit(net.init)(jax.random.key(0, impl="rbg"))

    @jax.jit
    def step(p, carry, obs, resets):  # -> (carry, mean, std, value)
        carry, pi, value = net.apply(p, carry, obs, resets)
        return carry, pi.mean(), pi.stddev(), value

    return net, params, step


def assert_tree_equal(a, b):
    for x, y in zip(jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b)):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))


def all_finite(tree):
    return all(bool(jnp.all(jnp.isfinite(x))) for x in jax.tree_util.tree_leaves(tree))


# ------------------------------------------------------------------------------------------------------- building


def test_make_network_rejects_unknown_names():
    with pytest.raises(ValueError, match="hh_attn, dsrnn, mlp"):
        make_network("transformer", "paper", 12, 20)
    with pytest.raises(ValueError, match="paper, small"):
        make_network("hh_attn", "huge", 12, 20)


def n_params(name, size, dim, num_humans=N, lidar_rays=0):
    net = make_network(name, size, obs_human_dim=dim, num_humans=num_humans, lidar_rays=lidar_rays)
    return count_params(jax.eval_shape(net.init, jax.random.PRNGKey(0)))


def linear(n_in, n_out):
    return n_in * n_out + n_out


def gru(n_in, hidden):  # PyTorch's nn.GRU: three gates, an input and a hidden bias each
    return 3 * hidden * (n_in + hidden) + 6 * hidden


# The layers of CrowdNav++'s networks at the paper's sizes, less the layers they build but never use, which the port
# leaves out (514 parameters in HH Attn, 16,968 in DS-RNN; with them the totals are the reference's "about 2.50 M"
# and "about 0.97 M"). Actor and critic: two 256-wide tanh layers each; then the value, the action mean and the
# state-independent log-std.
HEADS = 2 * 2 * linear(256, 256) + linear(256, 1) + linear(256, 2) + 2
# `rl/networks/selfAttn_srnn_temp_node.py` with 12 features per human (positions + 5 predicted steps): robot
# embedding; human embedding, q/k/v and 8-head self-attention over humans, its output layer; robot-human attention
# (q, k); the node GRU's two input embeddings, the GRU and its output layer.
HH_ATTN_REFERENCE = (
    linear(9, 256)
    + linear(12, 128)
    + linear(128, 512)
    + 3 * linear(512, 512)
    + linear(512, 3 * 512)
    + linear(512, 512)
    + linear(512, 256)
    + 2 * linear(256, 64)
    + 2 * linear(256, 64)
    + gru(128, 128)
    + linear(128, 256)
    + HEADS
)
# `rl/networks/srnn_model.py` with 2 features per human: robot node and its encoder; temporal and spatial edge
# embeddings and GRUs; attention (q, k); the node RNN's input layer, GRU and output layer.
DSRNN_REFERENCE = (
    linear(7, 3)
    + linear(3, 64)
    + 2 * (linear(2, 64) + gru(64, 256))
    + 2 * linear(256, 64)
    + linear(512, 64)
    + gru(128, 128)
    + linear(128, 256)
    + HEADS
)


def test_param_counts_match_reference():
    assert n_params("hh_attn", "paper", 12) == HH_ATTN_REFERENCE
    assert n_params("dsrnn", "paper", 2) == DSRNN_REFERENCE
    for name in NETWORK_NAMES:
        for dim in (2, 12):
            assert n_params(name, "small", dim) < n_params(name, "paper", dim)
    # the real initialisation (with a raw uint32 PRNGKey) has the same structure
    net = make_network("mlp", "small", obs_human_dim=12, num_humans=N)
    assert count_params(jax.jit(net.init)(jax.random.PRNGKey(0))) == n_params("mlp", "small", 12)


@pytest.mark.parametrize("rays", [1, 36, 360, 1001])
def test_lidar_param_counts(rays):
    """The scan adds exactly its encoder and the wider GRU input (MLP: the wider first layers); without a scan the
    networks are the reference's (see above), with no LiDAR parameter at all."""
    for name, sizes in (("hh_attn", HH_ATTN_SIZES), ("dsrnn", DSRNN_SIZES)):
        for size in NETWORK_SIZES:
            s = sizes[size]
            gru_width = s.gru if name == "hh_attn" else s.node_rnn
            encoder = LidarEncoderSize.num_params(s.lidar, rays)
            # hand count of the encoder: two circular convolutions of width 5 and stride 2, then the dense layer
            c1, c2 = s.lidar.channels
            length = math.ceil(math.ceil(rays / 2) / 2)
            assert encoder == (5 * c1 + c1) + (c1 * 5 * c2 + c2) + (length * c2 + 1) * s.lidar.embed
            extra = n_params(name, size, 12, lidar_rays=rays) - n_params(name, size, 12)
            assert extra == encoder + 3 * gru_width * s.lidar.embed, (name, size)
    hidden = MLP_SIZES["small"]
    assert n_params("mlp", "small", 12, lidar_rays=rays) - n_params("mlp", "small", 12) == 2 * rays * hidden
    without = jax.eval_shape(make_network("dsrnn", "small", 12, N, lidar_rays=0).init, jax.random.PRNGKey(0))
    assert "lidar_encoder" not in without["params"]
    with_scan = jax.eval_shape(make_network("dsrnn", "small", 12, N, lidar_rays=rays).init, jax.random.PRNGKey(0))
    assert "lidar_encoder" in with_scan["params"]


def test_make_network_rejects_bad_lidar_settings():
    with pytest.raises(ValueError, match="lidar_rays = -1 must be a whole number"):
        make_network("hh_attn", "small", 2, 3, lidar_rays=-1)
    with pytest.raises(ValueError, match="lidar_range = 0.0 must be > 0"):
        make_network("hh_attn", "small", 2, 3, lidar_rays=8, lidar_range=0.0)


def test_wrong_obs_shape_raises():
    net, params, _ = built("hh_attn", "small", 12)
    obs = random_obs(jax.random.PRNGKey(0), (B,), N, 2)
    with pytest.raises(ValueError, match="obs.humans"):
        net.apply(params, net.initialize_carry(B), obs, jnp.zeros(B, bool))
    # a scan for a network without one, and a scan of the wrong ray count, are named
    obs = random_obs(jax.random.PRNGKey(0), (B,), N, 12, lidar_rays=8)
    with pytest.raises(ValueError, match=r"expects no LiDAR scan \(env.lidar_rays = 0\).*got \(3, 8\)"):
        net.apply(params, net.initialize_carry(B), obs, jnp.zeros(B, bool))
    scan_net = make_network("mlp", "small", obs_human_dim=12, num_humans=N, lidar_rays=16)
    with pytest.raises(ValueError, match=r"expects a 16-ray LiDAR scan.*got \(3, 8\)"):
        scan_net.init(jax.random.PRNGKey(0), obs)


# --------------------------------------------------------------------------------------------------------- shapes


@pytest.mark.parametrize("dim", [2, 12])
@pytest.mark.parametrize("size", NETWORK_SIZES)
@pytest.mark.parametrize("name", NETWORK_NAMES)
def test_output_shapes(name, size, dim):
    net, params, step = built(name, size, dim)
    carry = net.initialize_carry(B)
    obs = random_obs(jax.random.PRNGKey(1), (B,), N, dim)
    new_carry, mean, std, value = step(params, carry, obs, jnp.zeros(B, bool))
    assert jax.tree_util.tree_structure(new_carry) == jax.tree_util.tree_structure(carry)
    for c, nc in zip(jax.tree_util.tree_leaves(carry), jax.tree_util.tree_leaves(new_carry)):
        assert c.shape == nc.shape and c.shape[0] == B
    assert mean.shape == (B, 2) and std.shape == (B, 2) and value.shape == (B,)
    np.testing.assert_allclose(std, 1.0)  # log-std initialised to 0
    assert all_finite((new_carry, mean, value))

    @jax.jit  # one program rather than one per operation of the network
    def sample_and_log_prob(params, carry, obs):
        _, pi, _ = net.apply(params, carry, obs, jnp.zeros(B, bool))
        return pi.sample(seed=jax.random.PRNGKey(0)), pi.log_prob(jnp.zeros((B, 2)))

    sample, log_prob = sample_and_log_prob(params, carry, obs)
    assert sample.shape == (B, 2) and log_prob.shape == (B,)


@pytest.mark.parametrize("name", NETWORK_NAMES)
def test_zero_humans(name):
    net, params, step = built(name, "small", 12, num_humans=0)
    obs = random_obs(jax.random.PRNGKey(2), (B,), 0, 12)
    carry, mean, _, value = step(params, net.initialize_carry(B), obs, jnp.zeros(B, bool))
    assert mean.shape == (B, 2) and value.shape == (B,)
    assert all_finite((carry, mean, value))


# -------------------------------------------------------------------------------------------------------- masking


def test_masked_softmax():
    s = jnp.array([[1.0, 2.0, 3.0], [1.0, 2.0, 3.0], [5.0, -1e30, 0.0]])
    m = jnp.array([[True, True, False], [False, False, False], [True, True, True]])
    w = masked_softmax(s, m)
    np.testing.assert_allclose(w[0], [1 / (1 + np.e), np.e / (1 + np.e), 0.0], rtol=1e-6)
    np.testing.assert_array_equal(w[1], 0.0)
    np.testing.assert_allclose(w[2].sum(), 1.0, rtol=1e-6)
    g = jax.grad(lambda s: jnp.sum(masked_softmax(s, m) * jnp.arange(3.0)))(s)
    assert all_finite(g)
    assert masked_softmax(jnp.zeros((2, 0)), jnp.zeros((2, 0), bool)).shape == (2, 0)


@pytest.mark.parametrize("size", NETWORK_SIZES)
@pytest.mark.parametrize("name", NETWORK_NAMES)
def test_all_humans_masked_is_finite(name, size):
    net, params, step = built(name, size, 12)
    obs = random_obs(jax.random.PRNGKey(3), (B,), N, 12, num_visible=jnp.zeros(B, int))
    # even garbage in the invisible rows must not leak in
    obs = obs.replace(humans=jax.random.normal(jax.random.PRNGKey(4), obs.humans.shape) * 100.0)
    carry, mean, _, value = step(params, net.initialize_carry(B), obs, jnp.zeros(B, bool))
    assert all_finite((carry, mean, value))
    ref_obs = obs.replace(humans=jnp.zeros_like(obs.humans))
    assert_tree_equal(step(params, net.initialize_carry(B), ref_obs, jnp.zeros(B, bool)), (carry, mean, _, value))


@pytest.mark.parametrize("size", NETWORK_SIZES)
@pytest.mark.parametrize("name", NETWORK_NAMES)
def test_invisible_rows_do_not_influence(name, size):
    net, params, step = built(name, size, 12)
    num_visible = jnp.array([0, 5, 19])
    keys = jax.random.split(jax.random.PRNGKey(5), 4)
    carry_a = carry_b = net.initialize_carry(B)
    for t in range(2):  # two steps, so recurrent state built from perturbed rows would show up
        obs = random_obs(keys[2 * t], (B,), N, 12, num_visible=num_visible)
        noise = jax.random.normal(keys[2 * t + 1], obs.humans.shape) * 50.0
        perturbed = obs.replace(humans=jnp.where(obs.human_mask[..., None], obs.humans, noise))
        out_a = step(params, carry_a, obs, jnp.zeros(B, bool))
        out_b = step(params, carry_b, perturbed, jnp.zeros(B, bool))
        assert_tree_equal(out_a, out_b)
        carry_a, carry_b = out_a[0], out_b[0]
    # and visible rows do matter
    obs2 = obs.replace(humans=obs.humans.at[1, 0, :2].add(1.0))
    out_c = step(params, carry_a, obs2, jnp.zeros(B, bool))
    out_a = step(params, carry_a, obs, jnp.zeros(B, bool))
    assert not np.allclose(out_a[1][1], out_c[1][1])
    np.testing.assert_array_equal(out_a[1][0], out_c[1][0])  # other batch rows untouched


@pytest.mark.parametrize("size", NETWORK_SIZES)
def test_hh_attn_attends_to_the_nearest_max_humans(size):
    """`small` reads only the first (nearest visible) `max_humans` rows; `paper` reads all of them."""
    net, params, step = built("hh_attn", size, 12)
    max_humans = net.module.size.max_humans
    assert max_humans == {"paper": 0, "small": 16}[size]
    obs = random_obs(jax.random.PRNGKey(6), (B,), N, 12, num_visible=jnp.array([N, N, N]))
    carry = net.initialize_carry(B)
    base = step(params, carry, obs, jnp.zeros(B, bool))[1]
    for row in (0, 15, 16, 19):
        moved = obs.replace(humans=obs.humans.at[:, row, :2].add(2.0))
        out = step(params, carry, moved, jnp.zeros(B, bool))[1]
        read = max_humans == 0 or row < max_humans
        assert np.allclose(out, base) != read, (size, row)


def test_dsrnn_ignores_predictions():
    net, params, step = built("dsrnn", "small", 12)
    obs = random_obs(jax.random.PRNGKey(6), (B,), N, 12)
    other = obs.replace(humans=obs.humans.at[..., 2:].set(7.0))
    assert_tree_equal(
        step(params, net.initialize_carry(B), obs, jnp.zeros(B, bool)),
        step(params, net.initialize_carry(B), other, jnp.zeros(B, bool)),
    )


# -------------------------------------------------------------------------------------------------- recurrence


def test_gru_cell_matches_torch_equations():
    cell = TorchGRUCell(4)
    x, h = jax.random.normal(jax.random.PRNGKey(7), (2, 3)), jax.random.normal(jax.random.PRNGKey(8), (2, 4))
    p = cell.init(jax.random.PRNGKey(9), h, x)
    rng = np.random.default_rng(0)
    p = jax.tree_util.tree_map(lambda a: a + 0.1 * rng.standard_normal(a.shape).astype(np.float32), p)
    q = {k: np.asarray(v, np.float64) for k, v in p["params"].items()}
    wi, wh = np.split(q["w_i"], 3, 1), np.split(q["w_h"], 3, 1)
    bi, bh = np.split(q["b_i"], 3), np.split(q["b_h"], 3)
    sig = lambda a: 1 / (1 + np.exp(-a))
    xn, hn = np.asarray(x, np.float64), np.asarray(h, np.float64)
    r = sig(xn @ wi[0] + bi[0] + hn @ wh[0] + bh[0])
    z = sig(xn @ wi[1] + bi[1] + hn @ wh[1] + bh[1])
    n = np.tanh(xn @ wi[2] + bi[2] + r * (hn @ wh[2] + bh[2]))
    np.testing.assert_allclose(cell.apply(p, h, x), (1 - z) * n + z * hn, rtol=1e-5, atol=1e-6)
    assert count_params(p) == 3 * 4 * (3 + 4) + 6 * 4  # PyTorch nn.GRU(3, 4)


@pytest.mark.parametrize("name", NETWORK_NAMES)
def test_reset_restarts_the_carry(name):
    net, params, step = built(name, "small", 12)
    k0, k1 = jax.random.split(jax.random.PRNGKey(11))
    obs0 = random_obs(k0, (B,), N, 12, num_visible=jnp.array([3, 10, 20]))
    obs1 = random_obs(k1, (B,), N, 12, num_visible=jnp.array([4, 0, 20]))
    fresh = net.initialize_carry(B)
    carry1, *_ = step(params, fresh, obs0, jnp.zeros(B, bool))
    with_reset = step(params, carry1, obs1, jnp.ones(B, bool))
    from_fresh = step(params, fresh, obs1, jnp.zeros(B, bool))
    assert_tree_equal(with_reset, from_fresh)
    # partial reset only touches the reset rows
    partial = step(params, carry1, obs1, jnp.array([True, False, False]))
    np.testing.assert_array_equal(partial[1][0], from_fresh[1][0])
    no_reset = step(params, carry1, obs1, jnp.zeros(B, bool))
    if name in RECURRENT:
        assert not np.allclose(no_reset[1], from_fresh[1])
        assert not np.allclose(partial[1][1:], from_fresh[1][1:])
    else:
        assert_tree_equal(no_reset, from_fresh)


@pytest.mark.parametrize("name", NETWORK_NAMES)
def test_apply_sequence_equals_stepwise_and_has_finite_gradients(name):
    net, params, step = built(name, "small", 12)
    T = 5
    obs_seq = random_obs(jax.random.PRNGKey(12), (T, B), N, 12)
    # an all-invisible step and episode starts inside the sequence
    obs_seq = obs_seq.replace(human_mask=obs_seq.human_mask.at[1].set(False), humans=obs_seq.humans.at[1].set(0.0))
    resets = jax.random.bernoulli(jax.random.PRNGKey(13), 0.3, (T, B)).at[0].set(True).at[3, 1].set(True)
    carry0 = jax.tree_util.tree_map(lambda c: c + 0.5, net.initialize_carry(B))  # non-trivial start state
    actions = jax.random.normal(jax.random.PRNGKey(15), (T, B, 2))

    def loss(p):  # PPO-like: log-prob of stored actions, value, entropy, all through the scanned sequence form
        carry_T, pi, values = net.apply_sequence(p, carry0, obs_seq, resets)
        assert pi.batch_shape == (T, B) and pi.event_shape == (2,)
        loss = -pi.log_prob(actions).mean() + jnp.square(values).mean() - pi.entropy().mean()
        return loss, (carry_T, pi.mean(), pi.stddev(), values)

    grads, (carry_T, means, stds, values) = jax.jit(jax.grad(loss, has_aux=True))(params)
    assert means.shape == (T, B, 2) and values.shape == (T, B)
    assert all_finite(grads)
    assert float(jnp.abs(grads["params"]["heads"]["log_std"]).sum()) > 0
    assert sum(float(jnp.abs(g).sum()) for g in jax.tree_util.tree_leaves(grads)) > 0

    carry = carry0
    for t in range(T):
        obs_t = jax.tree_util.tree_map(lambda x, t=t: x[t], obs_seq)
        carry, mean, std, value = step(params, carry, obs_t, resets[t])
        np.testing.assert_allclose(means[t], mean, rtol=1e-5, atol=1e-6)
        np.testing.assert_allclose(stds[t], std, rtol=1e-6)
        np.testing.assert_allclose(values[t], value, rtol=1e-5, atol=1e-6)
    for a, b in zip(jax.tree_util.tree_leaves(carry_T), jax.tree_util.tree_leaves(carry)):
        np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("name", NETWORK_NAMES)
def test_lidar_networks_read_the_scan(name):
    """With a scan: it changes the outputs, ranges beyond the sensor range read as the range, and the sequence form
    (HH Attn and MLP encode all steps at once) equals the step-by-step one."""
    rays, n = 16, 3
    net, params, step = built(name, "small", 2, num_humans=n, lidar_rays=rays)
    assert net.lidar_rays == rays and net.dummy_obs(2).lidar.shape == (2, rays)
    T = 3
    obs_seq = random_obs(jax.random.PRNGKey(20), (T, B), n, 2, lidar_rays=rays)
    obs = jax.tree_util.tree_map(lambda x: x[0], obs_seq)
    carry = net.initialize_carry(B)
    base = step(params, carry, obs, jnp.zeros(B, bool))
    assert all_finite(base)
    nearer = obs.replace(lidar=obs.lidar.at[1, 3].set(0.4))
    out = step(params, carry, nearer, jnp.zeros(B, bool))
    assert not np.allclose(out[1][1], base[1][1]) and not np.allclose(out[3][1], base[3][1])
    np.testing.assert_array_equal(out[1][0], base[1][0])  # other batch rows untouched
    clipped = obs.replace(lidar=jnp.minimum(obs.lidar, 5.0))  # the default sensor range
    assert bool(jnp.any(obs.lidar > 5.0))
    assert_tree_equal(step(params, carry, clipped, jnp.zeros(B, bool)), base)

    resets = jnp.zeros((T, B), bool).at[2, 1].set(True)
    _, pi, values = jax.jit(net.apply_sequence)(params, carry, obs_seq, resets)
    for t in range(T):
        obs_t = jax.tree_util.tree_map(lambda x, t=t: x[t], obs_seq)
        carry, mean, _, value = step(params, carry, obs_t, resets[t])
        np.testing.assert_allclose(pi.mean()[t], mean, rtol=1e-5, atol=1e-6)
        np.testing.assert_allclose(values[t], value, rtol=1e-5, atol=1e-6)


# ------------------------------------------------------------------------------------------- attention algebra


def test_key_into_query_equals_the_reference_key_layer():
    """HH Attn scores humans with (W q) . hum instead of q . (W^T hum + b): the same attention weights, and the
    unused bias gets an exactly zero gradient (softmax is shift-invariant)."""
    from tgrf_jax.policies.nets.common import robot_human_attention
    from tgrf_jax.policies.nets.hh_attn import KeyIntoQuery

    F, a = 6, 4
    k = jax.random.split(jax.random.PRNGKey(21), 4)
    layer = KeyIntoQuery(a, F)
    params = layer.init(k[0], jnp.zeros((1, a)))
    params = jax.tree_util.tree_map(lambda x: x + jax.random.normal(k[1], x.shape), params)  # bias non-zero
    query = jax.random.normal(k[2], (B, a))
    hum = jax.random.normal(k[3], (B, 5, F))
    mask = jnp.array([[True] * 5, [True, True, False, False, False], [False] * 5])

    def folded(p):
        return robot_human_attention(layer.apply(p, query), hum, hum, mask, scale=2.5)

    def explicit(p):
        keys = hum @ p["params"]["kernel"] + p["params"]["bias"]
        return robot_human_attention(query, keys, hum, mask, scale=2.5)

    np.testing.assert_allclose(folded(params), explicit(params), rtol=1e-5, atol=1e-6)
    assert not np.allclose(folded(params)[0], 0.0)
    grads = jax.grad(lambda p: jnp.sum(jnp.sin(explicit(p))))(params)
    np.testing.assert_allclose(grads["params"]["bias"], 0.0, atol=1e-6)
    assert float(jnp.abs(grads["params"]["kernel"]).sum()) > 0


def test_multi_head_attention_options():
    """The packed one-matmul path for self-attention equals separate projections; narrower query/key heads and
    the unprojected output have the documented shapes and algebra."""
    from tgrf_jax.policies.nets.common import MultiHeadAttention

    x = jax.random.normal(jax.random.PRNGKey(31), (B, 5, 8))
    mask = jnp.arange(5) < jnp.array([5, 2, 0])[:, None]
    for qk in (0, 2):
        full = MultiHeadAttention(8, 2, qk_head_dim=qk)
        params = full.init(jax.random.PRNGKey(32), x, x, x, mask)
        assert params["params"]["in_proj_kernel"].shape == (8, 2 * 2 * (qk or 4) + 8)
        packed = full.apply(params, x, x, x, mask)  # q is k is v: one matmul
        separate = full.apply(params, x, x + 0.0, x * 1.0, mask)
        np.testing.assert_allclose(packed, separate, rtol=1e-5, atol=1e-6)
        bare = MultiHeadAttention(8, 2, qk_head_dim=qk, out_projection=False)
        heads = bare.apply({"params": {k: v for k, v in params["params"].items() if k != "out_proj"}}, x, x, x, mask)
        out = params["params"]["out_proj"]
        np.testing.assert_allclose(heads @ out["kernel"] + out["bias"], packed, rtol=1e-5, atol=1e-5)
        np.testing.assert_array_equal(heads[2], 0.0)  # no visible key: zero attention vector
