"""Everything that drives the robot, behind one interface: `initialize_carry(batch_size)` and
`act(carry, obs, resets, key) -> (carry, action)` on a batch of observations.

`nets` holds the trainable actor-critics (HH Attn, DS-RNN, MLP), `learned` wraps a trained one as a
deterministic policy, `baselines` the hand-written robots (straight to goal, ORCA).
"""

from tgrf_jax.policies.baselines import (
    BASELINES,
    OrcaPolicy,
    Policy,
    StraightPolicy,
    baseline,
)
from tgrf_jax.policies.learned import LearnedPolicy, make_network_for

__all__ = ["BASELINES", "LearnedPolicy", "OrcaPolicy", "Policy", "StraightPolicy", "baseline", "make_network_for"]
