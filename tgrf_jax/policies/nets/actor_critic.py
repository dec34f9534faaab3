"""Common recurrent actor-critic interface over the three policy torsos, and `make_network`.

Every policy is a linen module whose `__call__(carry, obs)` processes ONE time step of a batch and returns
`(new_carry, (mean, log_std, value))`. `ActorCritic` wraps it with the PPO-facing API:

    net = make_network("hh_attn", "paper", obs_human_dim=12, num_humans=20)
    params = net.init(key)                                   # or net.init(key, obs)
    carry = net.initialize_carry(B)
    carry, pi, value = net.apply(params, carry, obs, resets)            # obs (B, ...), resets (B,) bool
    carry_T, pi, values = net.apply_sequence(params, carry0, obs_seq, resets_seq)   # time-major (T, B, ...)

`resets[b]` True zeroes row b of the carry *before* the step (the observation is the first of a new episode).
`apply_sequence` is a `jax.lax.scan` of exactly the single-step function, so the two forms agree exactly and resets
inside a sequence restart the recurrent state as during the rollout. `pi` is a `distrax.MultivariateNormalDiag`
(batch shape (B,) or (T, B), event shape (action_dim,)) with a state-independent std exp(log_std).
"""

from __future__ import annotations

import distrax
import jax
import jax.numpy as jnp
from flax import linen as nn

from tgrf_jax.env.obstacles import Obstacles
from tgrf_jax.env.types import Obs
from tgrf_jax.policies.nets.common import count_params, reset_carry
from tgrf_jax.policies.nets.dsrnn import DSRNN_SIZES, DSRNNNet
from tgrf_jax.policies.nets.frames import FRAMES, action_to_world, to_goal_frame, to_world_frame
from tgrf_jax.policies.nets.hh_attn import HH_ATTN_SIZES, HHAttnNet
from tgrf_jax.policies.nets.mlp import MLP_SIZES, MLPNet

NETWORK_NAMES = ("hh_attn", "dsrnn", "mlp")
NETWORK_SIZES = ("paper", "small")


def dummy_obs(batch_shape, num_humans: int, obs_human_dim: int, lidar_rays: int = 0) -> Obs:
    """All-zeros observation batch (no human visible, no obstacle) with the given leading shape."""
    batch_shape = tuple(batch_shape) if isinstance(batch_shape, (tuple, list)) else (int(batch_shape),)
    z = lambda *s: jnp.zeros(batch_shape + s, jnp.float32)
    return Obs(
        robot_node=z(7),
        robot_vel=z(2),
        humans=z(num_humans, obs_human_dim),
        human_mask=jnp.zeros(batch_shape + (num_humans,), bool),
        human_vel=z(num_humans, 2),
        human_radius=z(num_humans),
        lidar=z(lidar_rays),
        obstacles=Obstacles(z(0, 2, 2), jnp.zeros(batch_shape + (0,), jnp.int32)),
    )


class ActorCritic:
    """A policy module plus the recurrent PPO interface. Stateless: parameters are passed explicitly."""

    def __init__(
        self,
        name: str,
        size: str,
        module: nn.Module,
        obs_human_dim: int,
        num_humans: int,
        action_dim: int,
        frame: str = "world",
        rotate_action: bool = False,
        init_log_std: float = 0.0,
        lidar_rays: int = 0,
        lidar_range: float = 5.0,
    ):
        self.name = name
        self.size = size
        self.module = module
        self.obs_human_dim = obs_human_dim
        self.num_humans = num_humans
        self.action_dim = action_dim
        self.frame = frame
        self.rotate_action = rotate_action
        self.init_log_std = init_log_std
        self.lidar_rays = lidar_rays
        self.lidar_range = lidar_range

    def __repr__(self):
        lidar = f", lidar_rays={self.lidar_rays}" if self.lidar_rays else ""
        return (
            f"ActorCritic(name={self.name!r}, size={self.size!r}, obs_human_dim={self.obs_human_dim}, "
            f"num_humans={self.num_humans}, action_dim={self.action_dim}, frame={self.frame!r}{lidar})"
        )

    # ------------------------------------------------------------------------------------------------ state

    def dummy_obs(self, batch_size: int = 1) -> Obs:
        return dummy_obs(batch_size, self.num_humans, self.obs_human_dim, self.lidar_rays)

    def initialize_carry(self, batch_size: int):
        """Zero recurrent state for `batch_size` environments (a dict of arrays with leading axis B)."""
        return self.module.initialize_carry(batch_size)

    def init(self, key: jax.Array, obs: Obs | None = None):
        """Parameters (batch-size independent). `obs`: an optional example batch (B, ...) to check shapes."""
        if obs is None:
            obs = self.dummy_obs(1)
        self._check_obs(obs, batch_ndim=1)
        batch = obs.robot_node.shape[0]
        params = self.module.init(key, self.initialize_carry(batch), obs)
        log_std = params["params"]["heads"]["log_std"]
        params["params"]["heads"]["log_std"] = jnp.full_like(log_std, self.init_log_std)
        return params

    def num_params(self, params) -> int:
        return count_params(params)

    # ---------------------------------------------------------------------------------------------- forward

    def _check_obs(self, obs: Obs, batch_ndim: int):
        hs = obs.humans.shape
        if len(hs) != batch_ndim + 2 or hs[-1] != self.obs_human_dim or hs[-2] != self.num_humans:
            raise ValueError(
                f"{self}: expected obs.humans of shape {('...',) * batch_ndim + (self.num_humans, self.obs_human_dim)}"
                f" with {batch_ndim} batch axes, got {hs}"
            )
        ls = obs.lidar.shape
        if len(ls) != batch_ndim + 1 or ls[-1] != self.lidar_rays:
            what = f"a {self.lidar_rays}-ray LiDAR scan" if self.lidar_rays else "no LiDAR scan (env.lidar_rays = 0)"
            raise ValueError(
                f"{self}: expects {what}: obs.lidar of shape {('...',) * batch_ndim + (self.lidar_rays,)} with "
                f"{batch_ndim} batch axes, got {ls}"
            )

    def _step(self, params, carry, obs: Obs, resets):
        if resets is not None:
            carry = reset_carry(carry, jnp.asarray(resets, bool))
        obs, axes = self._to_frame(obs)
        carry, (mean, log_std, value) = self.module.apply(params, carry, obs)
        return carry, (self._action_to_world(mean, axes), log_std, value)

    def _to_frame(self, obs: Obs):
        if self.lidar_rays:
            # clipped before the frame's rotation interpolates between rays: a range beyond the sensor's (a real
            # scanner's) reads exactly as the sensor range, as in the env
            obs = obs.replace(lidar=jnp.clip(obs.lidar.astype(jnp.float32), 0.0, self.lidar_range))
        return (to_world_frame(obs), None) if self.frame == "world" else to_goal_frame(obs)

    def _action_to_world(self, mean, axes):
        return action_to_world(mean, axes) if self.rotate_action else mean

    def _dist(self, mean, log_std):
        return distrax.MultivariateNormalDiag(mean, jnp.broadcast_to(jnp.exp(log_std), mean.shape))

    def apply(self, params, carry, obs: Obs, resets):
        """One step. obs batched (B, ...), resets (B,) bool (or None). Returns (new_carry, pi, value (B,))."""
        self._check_obs(obs, batch_ndim=1)
        carry, (mean, log_std, value) = self._step(params, carry, obs, resets)
        return carry, self._dist(mean, log_std), value

    def apply_sequence(self, params, carry0, obs_seq: Obs, resets_seq):
        """Time-major sequence: obs (T, B, ...), resets (T, B) bool. Returns (carry_T, pi [(T, B)], values (T, B)).

        Modules split into encode / recur / decode (HH Attn, MLP) run the encoder and decoder once over all T x B
        inputs and scan only the recurrent cell; others (DS-RNN, whose attention reads recurrent edge states) scan
        the whole step. Both equal the step-by-step `apply` up to float rounding."""
        self._check_obs(obs_seq, batch_ndim=2)
        resets_seq = jnp.asarray(resets_seq, bool)
        if hasattr(self.module, "encode"):
            obs_seq, axes = self._to_frame(obs_seq)
            x = self.module.apply(params, obs_seq, method="encode")

            def recur(carry, xs):
                x_t, resets = xs
                return self.module.apply(params, reset_carry(carry, resets), x_t, method="recur")

            carry_T, y = jax.lax.scan(recur, carry0, (x, resets_seq))
            means, log_std, values = self.module.apply(params, y, method="decode")
            means = self._action_to_world(means, axes)
        else:

            def body(carry, xs):
                obs, resets = xs
                carry, (mean, _, value) = self._step(params, carry, obs, resets)
                return carry, (mean, value)

            carry_T, (means, values) = jax.lax.scan(body, carry0, (obs_seq, resets_seq))
            log_std = params["params"]["heads"]["log_std"]  # state-independent: the same at every step
        return carry_T, self._dist(means, log_std), values


def make_network(
    name: str,
    size: str,
    obs_human_dim: int,
    num_humans: int,
    action_dim: int = 2,
    *,
    frame: str = "world",
    rotate_action: bool = False,
    init_log_std: float = 0.0,
    lidar_rays: int = 0,
    lidar_range: float = 5.0,
) -> ActorCritic:
    """Build a policy: name in ("hh_attn", "dsrnn", "mlp"), size in ("paper", "small").

    obs_human_dim: D, features per human row (2 without predictions, 2 (K + 1) with K predicted positions).
    num_humans: N, rows of obs.humans (N = 0 is allowed).
    frame: "world" (the reference's inputs) or "goal" (inputs re-expressed in the robot-centred, goal-aligned frame;
    see `tgrf_jax.policies.nets.frames`). rotate_action: the action is a planar velocity to rotate back to the world
    frame (holonomic robots; a unicycle's (dv, dtheta) is frame-free). init_log_std: initial value of the log-std.
    lidar_rays: R, rays of the 2-D LiDAR scan the policy reads (`Obs.lidar`, body frame; 0: none, the reference
    networks with exactly their parameters). HH Attn and DS-RNN encode it with a `LidarEncoder` (1-D circular
    convolutions, then a dense layer) whose output joins the robot's GRU input; the MLP appends the scaled ranges
    to its input. lidar_range: metres that scale the ranges to [0, 1] (the env's sensor range).
    """
    if frame not in FRAMES:
        raise ValueError(f"unknown frame {frame!r}; valid frames: {', '.join(FRAMES)}")
    if name not in NETWORK_NAMES:
        raise ValueError(f"unknown network {name!r}; valid names: {', '.join(NETWORK_NAMES)}")
    if size not in NETWORK_SIZES:
        raise ValueError(f"unknown network size {size!r}; valid sizes: {', '.join(NETWORK_SIZES)}")
    if isinstance(lidar_rays, bool) or int(lidar_rays) != lidar_rays or lidar_rays < 0:
        raise ValueError(f"lidar_rays = {lidar_rays!r} must be a whole number >= 0 (0: no LiDAR)")
    lidar_rays = int(lidar_rays)
    if lidar_rays and not lidar_range > 0:
        raise ValueError(f"lidar_range = {lidar_range!r} must be > 0 m (the range that scales the scan to [0, 1])")
    lidar_range = float(lidar_range)
    if obs_human_dim < 2 or num_humans < 0 or action_dim < 1:
        raise ValueError(
            "need obs_human_dim >= 2, num_humans >= 0, action_dim >= 1; "
            f"got {obs_human_dim}, {num_humans}, {action_dim}"
        )
    if name == "hh_attn":
        module = HHAttnNet(
            HH_ATTN_SIZES[size],
            obs_human_dim=obs_human_dim,
            action_dim=action_dim,
            lidar_rays=lidar_rays,
            lidar_range=lidar_range,
        )
    elif name == "dsrnn":
        module = DSRNNNet(
            DSRNN_SIZES[size],
            num_humans=num_humans,
            action_dim=action_dim,
            lidar_rays=lidar_rays,
            lidar_range=lidar_range,
        )
    else:
        module = MLPNet(MLP_SIZES[size], action_dim=action_dim, lidar_range=lidar_range)
    return ActorCritic(
        name,
        size,
        module,
        obs_human_dim,
        num_humans,
        action_dim,
        frame=frame,
        rotate_action=rotate_action and frame == "goal",
        init_log_std=init_log_std,
        lidar_rays=lidar_rays,
        lidar_range=lidar_range,
    )
