"""Reward and hyper-parameter tuning: population-based training over a sweep's population axis."""

from tgrf_jax.tune.objective import METRICS, Objective, parse_objective
from tgrf_jax.tune.pbt import Exploit, exploit_explore, num_replaced
from tgrf_jax.tune.space import SearchDim, parse_space, searchable_fields

__all__ = [
    "METRICS",
    "Exploit",
    "Objective",
    "SearchDim",
    "exploit_explore",
    "num_replaced",
    "parse_objective",
    "parse_space",
    "searchable_fields",
]
