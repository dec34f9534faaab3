"""PPO learner: GAE and truncation bootstrapping, recurrent resets, determinism, learning without humans, configs."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import tiny_config

from tgrf_jax.config import TrainConfig
from tgrf_jax.evaluate import evaluate
from tgrf_jax.policies.learned import LearnedPolicy
from tgrf_jax.storage.checkpoint import tree_digest as params_digest
from tgrf_jax.train import compute_gae, make_trainer

# ----------------------------------------------------------------------------------------------------- GAE


def _gae_reference(rewards, values, dones, truncs, finals, last_value, gamma, lam):
    """Plain-Python GAE, one env, written independently of the scan version."""
    T = len(rewards)
    adv = np.zeros(T)
    gae = 0.0
    for t in reversed(range(T)):
        next_v = last_value if t == T - 1 else values[t + 1]
        boot = finals[t] if truncs[t] else (0.0 if dones[t] else next_v)
        delta = rewards[t] + gamma * boot - values[t]
        gae = delta + (0.0 if dones[t] else gamma * lam * gae)
        adv[t] = gae
    return adv


def test_gae_truncation_bootstraps_from_final_obs_value():
    # Env 0: a time-limit truncation at t=2 (bootstrap from V(final_obs) = 5, not from V(obs_3) = -100, which
    # belongs to the next episode). Env 1: a termination at t=2 (no bootstrap at all).
    gamma, lam = 0.9, 0.8
    rewards = jnp.array([[1.0, 1.0], [0.0, 0.0], [2.0, 2.0], [1.0, 1.0]])
    values = jnp.array([[0.5, 0.5], [0.4, 0.4], [0.3, 0.3], [-100.0, -100.0]])
    dones = jnp.array([[0, 0], [0, 0], [1, 1], [0, 0]], bool)
    truncs = jnp.array([[0, 0], [0, 0], [1, 0], [0, 0]], bool)
    finals = jnp.array([[0.0, 0.0], [0.0, 0.0], [5.0, 0.0], [0.0, 0.0]])
    last = jnp.array([0.7, 0.7])
    adv, ret = compute_gae(rewards, values, dones, truncs, finals, last, gamma, lam)
    for b in range(2):
        ref = _gae_reference(
            np.asarray(rewards[:, b]),
            np.asarray(values[:, b]),
            np.asarray(dones[:, b]),
            np.asarray(truncs[:, b]),
            np.asarray(finals[:, b]),
            float(last[b]),
            gamma,
            lam,
        )
        np.testing.assert_allclose(np.asarray(adv[:, b]), ref, rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(ret, adv + values, rtol=1e-6)
    # hand values at the episode end: truncated: 2 + 0.9 * 5 - 0.3; terminated: 2 - 0.3
    assert float(adv[2, 0]) == pytest.approx(2.0 + gamma * 5.0 - 0.3)
    assert float(adv[2, 1]) == pytest.approx(2.0 - 0.3)
    # the next episode's value never leaks back across the boundary
    assert float(adv[1, 0]) == pytest.approx(0.0 + gamma * 0.3 - 0.4 + gamma * lam * float(adv[2, 0]))
    # the last step bootstraps from last_value
    assert float(adv[3, 0]) == pytest.approx(1.0 + gamma * 0.7 + 100.0)


def test_gae_random_matches_reference():
    rng = np.random.default_rng(0)
    T, B = 17, 5
    rewards = rng.normal(size=(T, B)).astype(np.float32)
    values = rng.normal(size=(T, B)).astype(np.float32)
    dones = rng.random((T, B)) < 0.2
    truncs = dones & (rng.random((T, B)) < 0.5)
    finals = np.where(truncs, rng.normal(size=(T, B)), 0.0).astype(np.float32)
    last = rng.normal(size=B).astype(np.float32)
    adv, _ = compute_gae(*map(jnp.asarray, (rewards, values, dones, truncs, finals, last)), 0.99, 0.95)
    for b in range(B):
        ref = _gae_reference(rewards[:, b], values[:, b], dones[:, b], truncs[:, b], finals[:, b], last[b], 0.99, 0.95)
        np.testing.assert_allclose(np.asarray(adv[:, b]), ref, rtol=1e-4, atol=1e-4)


# -------------------------------------------------------------------------------------------- recurrence


def test_gru_carry_resets_at_episode_boundaries():
    """A hand-built sequence through the loss's sequence replay: after a reset the outputs equal those of a fresh
    sequence started from a zero carry, and without the reset they differ (the carry matters)."""
    from tgrf_jax.policies.nets import make_network

    net = make_network("hh_attn", "small", obs_human_dim=2, num_humans=3)
    params = jax.jit(net.init)(jax.random.PRNGKey(0))  # one program, not one per initialiser and layer shape
    T, B = 6, 2
    k = jax.random.split(jax.random.PRNGKey(1), 3)
    obs = net.dummy_obs(1)
    obs = jax.tree_util.tree_map(lambda x: jnp.broadcast_to(x, (T, B) + x.shape[1:]), obs)
    obs = obs.replace(
        robot_node=jax.random.normal(k[0], (T, B, 7)),
        robot_vel=jax.random.normal(k[1], (T, B, 2)),
        humans=jax.random.normal(k[2], (T, B, 3, 2)),
        human_mask=jnp.ones((T, B, 3), bool),
    )
    resets = jnp.zeros((T, B), bool).at[3, 0].set(True)
    carry0 = jax.tree_util.tree_map(lambda c: c + 0.5, net.initialize_carry(B))  # a non-zero stored carry

    @jax.jit
    def replay(params, carry0, obs, resets):
        _, pi, values = net.apply_sequence(params, carry0, obs, resets)
        tail = jax.tree_util.tree_map(lambda x: x[3:], obs)
        _, pi_fresh, values_fresh = net.apply_sequence(
            params, net.initialize_carry(B), tail, jnp.zeros((T - 3, B), bool)
        )
        return pi.mean(), values, pi_fresh.mean(), values_fresh

    means, values, means_fresh, values_fresh = replay(params, carry0, obs, resets)
    np.testing.assert_allclose(values[3:, 0], values_fresh[:, 0], rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(means[3:, 0], means_fresh[:, 0], rtol=1e-5, atol=1e-6)
    # env 1 was not reset: it still carries its history
    assert not np.allclose(values[3:, 1], values_fresh[:, 1], atol=1e-4)


def test_rollout_replay_matches_stored_log_probs_and_values():
    """The minibatch replay (stored carry at step 0 + stored resets) reproduces the rollout's own log-probs and
    values exactly, across episode boundaries (short time limit -> several truncations inside the rollout)."""
    cfg = tiny_config(
        env={"num_humans": 2, "human_policy": "social_force", "time_limit": 2.0},
        network={"name": "hh_attn"},
        ppo={"num_steps": 12},
    )
    t = make_trainer(cfg)
    state = t.jit_init(jax.random.PRNGKey(3), t.default_hparams)
    state = state.replace(carry=jax.tree_util.tree_map(lambda c: c + 0.3, state.carry), resets=state.resets & False)

    @jax.jit  # the rollout and its replay in one program (run eagerly, the replay compiles op by op)
    def go(state):
        new_state, traj, carry0, last_value, ep = t.rollout(state, jax.random.PRNGKey(4))
        _, pi, values = t.net.apply_sequence(state.params, carry0, traj.obs, traj.resets)
        return traj, last_value, ep, values, pi.log_prob(traj.action)

    traj, last_value, ep, values, log_prob = go(state)
    assert bool(jnp.any(traj.truncated)) and int(ep["timeouts"]) > 0
    assert bool(jnp.all(traj.resets[1:] == traj.done[:-1]))  # reset = previous step ended the episode
    assert bool(jnp.all(jnp.where(traj.truncated, traj.final_value != 0, traj.final_value == 0)))
    np.testing.assert_allclose(values, traj.value, rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(log_prob, traj.log_prob, rtol=1e-5, atol=1e-4)
    # final values are V(final_obs) computed with the carry after the step (not reset)
    assert np.isfinite(np.asarray(last_value)).all()


# ------------------------------------------------------------------------------------- whole-update checks


def test_a_run_is_a_function_of_its_seed_whatever_its_chunks():
    """The same seed gives the same parameters bit for bit, however the updates are cut into chunks (the update
    count is traced, so every plan runs the one compiled program); another seed gives others."""
    t = make_trainer(tiny_config())

    def run(seed, chunks):
        state = t.jit_init(jax.random.PRNGKey(seed), t.default_hparams)
        for n in chunks:
            state, m = t.jit_run_chunk(state, n)
            assert all(np.isfinite(float(v)) for v in m.values())
        assert int(state.update) == sum(chunks)
        return params_digest(state.params)

    digests = {chunks: run(0, chunks) for chunks in ((2, 2), (4,), (1, 1, 2))}
    assert len(set(digests.values())) == 1, digests
    assert run(1, (2, 2)) != digests[(2, 2)]


def test_gradient_microbatches_give_the_same_update():
    """Accumulating a minibatch's gradient over env slices is the same update, up to float rounding."""
    results = []
    for microbatch_envs in (0, 1):
        cfg = tiny_config(
            env={"num_humans": 3, "predictor": "const_vel"},
            network={"name": "hh_attn"},
            ppo={"microbatch_envs": microbatch_envs},
        )
        assert cfg.ppo.num_microbatches == {0: 1, 1: 4}[microbatch_envs]
        t = make_trainer(cfg)
        state, metrics = t.jit_run_chunk(t.jit_init(jax.random.PRNGKey(0), t.default_hparams), 2)
        results.append((np.concatenate([np.ravel(x) for x in jax.tree_util.tree_leaves(state.params)]), metrics))
    (whole, m_whole), *sliced = results
    for params, metrics in sliced:
        np.testing.assert_allclose(params, whole, rtol=1e-4, atol=1e-6)
        for name in ("loss", "approx_kl", "grad_norm"):
            np.testing.assert_allclose(float(metrics[name]), float(m_whole[name]), rtol=1e-4, atol=1e-7)
    initial = t.jit_init(jax.random.PRNGKey(0), t.default_hparams).params
    moved = whole - np.concatenate([np.ravel(x) for x in jax.tree_util.tree_leaves(initial)])
    assert np.abs(moved).max() > 1e-4  # the updates did something, so the comparison means something


def test_microbatch_slices_are_the_fewest_equal_ones_within_the_limit():
    def slices(envs, minibatches, microbatch_envs):
        return tiny_config(
            ppo={
                "num_envs": envs,
                "num_minibatches": minibatches,
                "total_steps": envs * 8,
                "microbatch_envs": microbatch_envs,
            }
        ).ppo.num_microbatches

    assert slices(128, 4, 8) == 4  # 32 envs per minibatch -> 4 slices of 8
    assert slices(128, 4, 0) == 1
    assert slices(24, 4, 4) == 2  # 6 envs -> 2 slices of 3
    assert slices(12, 4, 8) == 1  # 3 envs fit in one slice
    assert slices(14, 1, 4) == 7  # 14 envs -> 7 slices of 2 (14 has no divisor in 3..4)


def test_train_is_vmappable_over_seeds_and_hparams():
    """Seeds x numeric hparams (lr, a reward parameter) as a vmap: vmapped init, then vmapped chunks.

    (jit(vmap(train)) with init and updates fused in ONE program hangs in XLA:CPU on this machine (jax 0.10.2);
    the two-program form below is equivalent and is what sweeps should use.)"""
    cfg = tiny_config()  # the config of the tests above: the unbatched 2-update chunk below is compiled already
    t = make_trainer(cfg)
    hp = t.default_hparams
    hps = jax.tree_util.tree_map(lambda x: jnp.broadcast_to(x, (2,) + x.shape), hp)
    hps = hps.replace(
        lr=jnp.array([1e-3, 3e-4]), env=hps.env.replace(reward=hps.env.reward.replace(h_disc=jnp.array([2.5, 1.0])))
    )
    keys = jax.random.split(jax.random.PRNGKey(0), 2)
    states = jax.jit(jax.vmap(t.init))(keys, hps)
    states, metrics = jax.jit(jax.vmap(lambda s: t.run_chunk(s, 2)))(states)
    assert states.update.shape == (2,) and metrics["loss"].shape == (2,)
    assert np.isfinite(np.asarray(metrics["loss"])).all()
    # each vmapped member equals its own unbatched run
    single = t.jit_init(keys[1], jax.tree_util.tree_map(lambda x: x[1], hps))
    single, _ = t.jit_run_chunk(single, 2)
    np.testing.assert_allclose(
        jax.tree_util.tree_leaves(states.params)[0][1],
        jax.tree_util.tree_leaves(single.params)[0],
        rtol=1e-5,
        atol=1e-6,
    )


def test_learns_to_reach_goal_without_humans():
    """No humans: the success rate of the training episodes starts low and rises above 90 % within 58 updates
    (59k steps); the deterministic policy then reaches the goal in >= 70 % of 64 evaluation episodes. About 30 s on
    2 cores."""
    cfg = tiny_config(
        ppo={"num_envs": 32, "num_steps": 32, "total_steps": 32 * 32 * 60, "update_epochs": 4, "lr": 1e-3}
    )
    t = make_trainer(cfg)
    state = t.jit_init(jax.random.PRNGKey(0), t.default_hparams)
    state, first = t.jit_run_chunk(state, 2)
    rates = []
    for _ in range(14):
        state, m = t.jit_run_chunk(state, 4)
        assert all(np.isfinite(float(v)) for v in m.values()), m
        rates.append(float(m["successes"]) / max(float(m["episodes"]), 1.0))
    first_rate = float(first["successes"]) / max(float(first["episodes"]), 1.0)
    assert first_rate < 0.5, first_rate
    assert max(rates[-2:]) > 0.9, rates
    # The deterministic (mean) action is slower than the clipped high-entropy samples this early in training, so
    # some evaluation episodes still time out: a looser bar than for the training episodes.
    result = evaluate(t.env, LearnedPolicy(t.net, state.params), jax.random.key(7), 64)
    assert result.success_rate >= 0.7 and result.collision_rate == 0.0, result


@pytest.mark.slow
def test_hh_attn_learns_to_reach_goal_without_humans():
    cfg = tiny_config(
        network={"name": "hh_attn", "size": "small"},
        ppo={"num_envs": 32, "num_steps": 32, "total_steps": 32 * 32 * 40, "update_epochs": 4, "lr": 1e-3},
    )
    t = make_trainer(cfg)
    state = t.jit_init(jax.random.PRNGKey(0), t.default_hparams)
    state, _ = t.jit_run_chunk(state, 40)
    result = evaluate(t.env, LearnedPolicy(t.net, state.params), jax.random.key(7), 100)
    assert result.success_rate >= 0.9, result


# ----------------------------------------------------------------------------------------------- configs


def test_default_yaml_matches_embedded_default():
    import pathlib

    root = pathlib.Path(__file__).resolve().parents[1]
    assert TrainConfig.from_yaml(root / "configs" / "default.yaml") == TrainConfig()
    paper = TrainConfig.from_yaml(root / "configs" / "paper_hh_attn.yaml")
    p = paper.ppo
    assert (p.num_envs, p.num_steps, p.update_epochs, p.num_minibatches) == (16, 30, 5, 2)
    assert (p.clip_eps, p.clip_value, p.gamma, p.gae_lambda, p.lr, p.adam_eps) == (0.2, True, 0.99, 0.95, 4e-5, 1e-5)
    assert (p.ent_coef, p.vf_coef, p.max_grad_norm, p.total_steps, p.anneal_lr) == (0.0, 0.5, 0.5, 10_000_000, False)
    assert (p.norm_value, p.reset_ratio, p.reset_slots) == (False, 1, 16)  # raw returns, one reset per env
    assert (paper.network.name, paper.network.size) == ("hh_attn", "paper")
    assert TrainConfig.from_dict(TrainConfig().to_dict()) == TrainConfig()
