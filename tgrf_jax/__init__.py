"""tgrf-jax: socially aware crowd navigation in JAX with the transformable Gaussian reward function.

Importing the package changes no process state; for the CPU settings the command-line tools use (512-bit
vectors on AVX-512, one CPU device per env shard) call `tgrf_jax.configure_cpu(...)` before any JAX computation.
"""

import importlib.metadata

from tgrf_jax import reward
from tgrf_jax.config import ConfigError, EnvConfig, RewardConfig
from tgrf_jax.env import CrowdNavEnv, EnvParams, EnvState, Info, Obs
from tgrf_jax.runtime.cpu import configure_cpu

try:  # the version is declared once, in pyproject.toml
    __version__ = importlib.metadata.version("tgrf-jax")
except importlib.metadata.PackageNotFoundError:  # a source tree on sys.path that was never installed
    __version__ = "unknown"

__all__ = [
    "CrowdNavEnv",
    "ConfigError",
    "EnvConfig",
    "EnvParams",
    "EnvState",
    "Info",
    "Obs",
    "RewardConfig",
    "configure_cpu",
    "reward",
]
