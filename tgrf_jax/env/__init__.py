"""The functional crowd-navigation environment."""

from tgrf_jax.env.crowd import CrowdNavEnv
from tgrf_jax.env.types import (
    COLLISION,
    OBSTACLE_COLLISION,
    OUTCOME_NAMES,
    RUNNING,
    SUCCESS,
    TIMEOUT,
    EnvParams,
    EnvState,
    Humans,
    Info,
    Obs,
    Robot,
)

__all__ = [
    "CrowdNavEnv",
    "EnvParams",
    "EnvState",
    "Humans",
    "Info",
    "Obs",
    "Robot",
    "RUNNING",
    "SUCCESS",
    "COLLISION",
    "TIMEOUT",
    "OBSTACLE_COLLISION",
    "OUTCOME_NAMES",
]
