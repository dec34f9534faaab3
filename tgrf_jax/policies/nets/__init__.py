"""Policy networks (flax.linen): HH Attn, DS-RNN and an MLP baseline behind one recurrent actor-critic API.

See `tgrf_jax.policies.nets.actor_critic` for the interface and each module's docstring for the architecture and
presets.
"""

from tgrf_jax.policies.nets.actor_critic import (
    NETWORK_NAMES,
    NETWORK_SIZES,
    ActorCritic,
    dummy_obs,
    make_network,
)
from tgrf_jax.policies.nets.common import count_params, masked_softmax
from tgrf_jax.policies.nets.dsrnn import DSRNN_SIZES, DSRNNNet
from tgrf_jax.policies.nets.hh_attn import HH_ATTN_SIZES, HHAttnNet
from tgrf_jax.policies.nets.mlp import MLP_SIZES, MLPNet

__all__ = [
    "ActorCritic",
    "DSRNNNet",
    "DSRNN_SIZES",
    "HHAttnNet",
    "HH_ATTN_SIZES",
    "MLPNet",
    "MLP_SIZES",
    "NETWORK_NAMES",
    "NETWORK_SIZES",
    "count_params",
    "dummy_obs",
    "make_network",
    "masked_softmax",
]
