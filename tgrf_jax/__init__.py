"""tgrf-jax: socially aware crowd navigation in JAX with the transformable Gaussian reward function.

Importing the package changes no process state; for the CPU settings the command-line tools use (512-bit
vectors on AVX-512, one CPU device per env shard) call `tgrf_jax.configure_cpu(...)` before any JAX computation.
"""

from tgrf_jax import reward
from tgrf_jax.config import ConfigError, EnvConfig, RewardConfig
from tgrf_jax.cpu import configure_cpu
from tgrf_jax.env import CrowdNavEnv, EnvParams, EnvState, Info, Obs

__version__ = "0.1.0"

__all__ = [
    "CrowdNavEnv", "ConfigError", "EnvConfig", "EnvParams", "EnvState", "Info", "Obs", "RewardConfig",
    "configure_cpu", "reward",
]
