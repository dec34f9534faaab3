"""tgrf-jax: socially aware crowd navigation in JAX with the transformable Gaussian reward function."""

from tgrf_jax import cpu_codegen

cpu_codegen.prefer_wide_vectors()  # before anything touches JAX's backend (see tgrf_jax.cpu_codegen)

from tgrf_jax import reward  # noqa: E402
from tgrf_jax.config import ConfigError, EnvConfig, RewardConfig  # noqa: E402
from tgrf_jax.env import CrowdNavEnv, EnvParams, EnvState, Info, Obs  # noqa: E402

__version__ = "0.1.0"

__all__ = ["CrowdNavEnv", "ConfigError", "EnvConfig", "EnvParams", "EnvState", "Info", "Obs", "RewardConfig", "reward"]
