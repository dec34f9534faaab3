"""tgrf-jax: socially aware crowd navigation in JAX with the transformable Gaussian reward function."""

from tgrf_jax import reward
from tgrf_jax.config import ConfigError, EnvConfig, RewardConfig
from tgrf_jax.env import CrowdNavEnv, EnvParams, EnvState, Info, Obs

__version__ = "0.1.0"

__all__ = ["CrowdNavEnv", "ConfigError", "EnvConfig", "EnvParams", "EnvState", "Info", "Obs", "RewardConfig", "reward"]
