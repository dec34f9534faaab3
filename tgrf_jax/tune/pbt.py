"""Population-based training's exploit-and-explore step, as one pure function over the population axis.

Truncation selection (Jaderberg et al. 2017): the worst `fraction` of the members by score take the network
parameters, optimiser state, return statistics and hyper-parameters of members drawn uniformly from the best
`fraction`, then perturb the copied hyper-parameters of the searched fields: each is multiplied by 0.8 or 1.25
(equal odds) or, with probability `resample_prob`, drawn afresh within its bounds (log-uniformly on a log
scale), and clipped to its bounds. Everything runs under `jit` on the arrays where they live (a member's
parameters never pass through the host); the random draws come from the key handed in, so a resumed tune
repeats them exactly.

What a member keeps of its own: its environments (states, observations, running episodes), recurrent carry,
PRNG key and update count, so copied members explore different episodes from the moment they are copied.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import jax
import jax.numpy as jnp
from flax import struct

from tgrf_jax.tune.space import SearchDim, hparams_path

__all__ = [
    "COPIED_FIELDS",
    "PERTURB_FACTORS",
    "Exploit",
    "exploit_explore",
    "get_values",
    "num_replaced",
    "select_donors",
    "set_values",
]

PERTURB_FACTORS = (0.8, 1.25)
COPIED_FIELDS = ("params", "opt_state", "return_stats", "hparams")


@struct.dataclass
class Exploit:
    """What one exploit-and-explore step did, per member: `donor` (the member copied, itself when kept) and the
    searched fields' values after the step, (P, D) in the order of the search dimensions."""

    donor: jnp.ndarray
    values: jnp.ndarray


def num_replaced(population: int, fraction: float) -> int:
    """How many members are replaced per step; at least one, at most half of the population."""
    return max(1, min(population // 2, int(math.floor(population * fraction + 1e-9))))


def _get(tree, path):
    for name in path:
        tree = getattr(tree, name)
    return tree


def _set(tree, path, value):
    if len(path) == 1:
        return tree.replace(**{path[0]: value})
    return tree.replace(**{path[0]: _set(getattr(tree, path[0]), path[1:], value)})


def get_values(hparams, dims: Sequence[SearchDim]) -> jnp.ndarray:
    """The searched fields of a batched `HParams`, (P, D) float32."""
    return jnp.stack([jnp.asarray(_get(hparams, hparams_path(d.name)), jnp.float32) for d in dims], axis=-1)


def set_values(hparams, dims: Sequence[SearchDim], values: jnp.ndarray):
    """A batched `HParams` with the searched fields set from `values` (P, D)."""
    for i, d in enumerate(dims):
        path = hparams_path(d.name)
        hparams = _set(hparams, path, values[:, i].astype(_get(hparams, path).dtype))
    return hparams


def select_donors(scores: jnp.ndarray, key: jnp.ndarray, n_replaced: int) -> jnp.ndarray:
    """Each member's donor: itself, or for the `n_replaced` lowest scores a member drawn from the `n_replaced`
    highest. Ties rank by member index (a stable sort), so equal scores never make the draw depend on order."""
    population = scores.shape[0]
    order = jnp.argsort(scores, stable=True)  # ascending: worst first
    worst, best = order[:n_replaced], order[population - n_replaced :]
    picks = best[jax.random.randint(key, (n_replaced,), 0, n_replaced)]
    return jnp.arange(population).at[worst].set(picks)


def _explore(key, values, replaced, dims: Sequence[SearchDim], resample_prob: float) -> jnp.ndarray:
    low = jnp.array([d.low for d in dims], jnp.float32)
    high = jnp.array([d.high for d in dims], jnp.float32)
    log = jnp.array([d.log for d in dims])
    k_factor, k_resample, k_fresh = jax.random.split(key, 3)
    factors = jnp.asarray(PERTURB_FACTORS, jnp.float32)[jax.random.randint(k_factor, values.shape, 0, 2)]
    u = jax.random.uniform(k_fresh, values.shape)
    fresh = jnp.where(
        log,
        jnp.exp(jnp.log(low) + u * (jnp.log(high) - jnp.log(low))),
        low + u * (high - low),
    )
    resample = jax.random.uniform(k_resample, values.shape) < resample_prob
    moved = jnp.clip(jnp.where(resample, fresh, values * factors), low, high)
    return jnp.where(replaced[:, None], moved, values)


def exploit_explore(state, scores, key, dims: Sequence[SearchDim], fraction: float, resample_prob: float):
    """One PBT step over a population-batched `TrainState` (leading axis P on every leaf).

    Returns the new state and an `Exploit` record. `dims`, `fraction` and `resample_prob` are static: jit with
    them closed over (`functools.partial`) and the state donated."""
    population = scores.shape[0]
    k_select, k_explore = jax.random.split(key)
    donor = select_donors(scores, k_select, num_replaced(population, fraction))
    copied = {name: jax.tree.map(lambda x: x[donor], getattr(state, name)) for name in COPIED_FIELDS}
    state = state.replace(**copied)
    replaced = donor != jnp.arange(population)
    values = _explore(k_explore, get_values(state.hparams, dims), replaced, dims, resample_prob)
    state = state.replace(hparams=set_values(state.hparams, dims, values))
    return state, Exploit(donor=donor, values=values)
